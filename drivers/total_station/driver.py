"""Leica total station as a :class:`~drivers.contracts.PositionFeed`, over geocompy's ``GeoCom``.

``measure(target)`` aims the instrument at a named target's approximate rig-frame position
(``AUT_MakePositioning`` 9027, ATR fine-pointing by default), starts a distance measurement
(``TMC_DoMeasure`` 2008), reads the coordinates (``TMC_GetCoordinate`` 2082, E/N/H in metres) and converts
them to rig-frame millimetres.

Frame convention (also in ``docs/protocols/geocom.md``). Let T be the instrument's tilting-axis centre,
``station_xyz_mm`` its rig-frame position and psi = ``station_yaw_deg``. The instrument's E axis points
along rig (cos psi, sin psi, 0), its N axis along rig (-sin psi, cos psi, 0), its H axis along rig +z
(psi is measured counter-clockwise, seen from +z, from rig +x to instrument E; psi = 0 means E = x,
N = y, H = z). The instrument reports a target at E, N, H = (E0, N0, H0 + hi - ht) + delta, where
(E0, N0, H0, hi) is its station setup (``TMC_GetStation`` 2009) and ht its reflector height
(``TMC_GetHeight`` 2011); both are read once per feed and removed, so any station setup works. Then::

    rig_mm = station_xyz_mm + 1000 * Rz(psi) @ delta_m

geocompy never raises on I/O: every response is classified here (``codec.classify``): warnings
(1283 TMC_NO_FULL_CORRECTION, 1284 TMC_ACCURACY_GUARANTEE) set ``SurveyedPoint.warning``; busy codes raise
:class:`DeviceBusy`; other errors :class:`DeviceRejected` with the GeoCOM code; COM_TIMEDOUT
:class:`DeviceTimeout`; undecodable / wrong-CRC / wrong-transaction-id replies :class:`ProtocolError`;
send failures :class:`ConnectionLost`.
"""
from __future__ import annotations

import contextlib
import logging
import math
import threading
from typing import Any, Iterator, Mapping

from geocompy.communication import SerialConnection
from geocompy.geo import GeoCom
from geocompy.geo.gcdata import ATR, Inclination, Measurement, Position

from ..contracts import DeviceIdentity, SurveyedPoint
from ..errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, ProtocolError
from ..transport import open_transport
from . import codec

# geocompy logs every timeout with a traceback; without a handler configured by the application it is dropped
# here instead of reaching Python's last-resort handler (rig -v / --log-level shows it)
logging.getLogger("geocompy").addHandler(logging.NullHandler())

__all__ = ["SurveyImplausible", "TotalStationFeed", "open_total_station", "rig_to_instrument", "instrument_to_rig"]

Xyz = tuple[float, float, float]

# COM_SRVR_RX_CHECKSUM_ERROR: the instrument received our request garbled. COM_FAILED is geocompy's code for
# any other exception in an exchange: a reply it could not decode as ASCII (a corrupted byte >= 0x80; a
# ProtocolError) or a port that failed (ConnectionLost); _Connection tells which.
_PROTOCOL_CODES = frozenset({codec.COM_CANT_DECODE, codec.COM_CLNT_RX_CHECKSUM_ERROR, codec.COM_TR_ID_MISMATCH,
                             codec.COM_SRVR_RX_CHECKSUM_ERROR})
_LINK_CODES = frozenset({codec.COM_CANT_SEND, codec.COM_FAILED})


class _Connection(SerialConnection):
    """geocompy's ``SerialConnection`` that remembers whether the last exchange failed on an undecodable reply
    (``garbled``): geocompy turns every exception into COM_FAILED, and a garbled reply is not a lost link."""

    garbled = False

    def exchange(self, cmd: str) -> str:
        self.garbled = False
        try:
            return super().exchange(cmd)
        except UnicodeDecodeError:
            self.garbled = True
            raise


class SurveyImplausible(ProtocolError):
    """A surveyed point lies farther from its target's expected position than ``max_error_mm``: a reply
    corrupted in a way no check caught, or the instrument locked onto another reflector. Never journalled."""


def _xyz(value: Any, what: str) -> Xyz:
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: expected three numbers (x, y, z), got {value!r}") from exc
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise ValueError(f"{what}: coordinates must be finite, got {value!r}")
    return x, y, z


def rig_to_instrument(point_mm: Xyz, *, station_xyz_mm: Xyz, station_yaw_deg: float) -> Xyz:
    """(dE, dN, dH) in metres from the tilting axis to a rig-frame point (inverse of :func:`instrument_to_rig`)."""
    psi = math.radians(station_yaw_deg)
    dx, dy, dz = (p - s for p, s in zip(point_mm, station_xyz_mm))
    c, s = math.cos(psi), math.sin(psi)
    return (c * dx + s * dy) / 1000.0, (-s * dx + c * dy) / 1000.0, dz / 1000.0


def instrument_to_rig(delta_enh_m: Xyz, *, station_xyz_mm: Xyz, station_yaw_deg: float) -> Xyz:
    """Rig-frame mm of a point at (dE, dN, dH) metres from the tilting axis: station + 1000 Rz(yaw) delta."""
    psi = math.radians(station_yaw_deg)
    d_e, d_n, d_h = delta_enh_m
    c, s = math.cos(psi), math.sin(psi)
    return (station_xyz_mm[0] + 1000.0 * (c * d_e - s * d_n),
            station_xyz_mm[1] + 1000.0 * (s * d_e + c * d_n),
            station_xyz_mm[2] + 1000.0 * d_h)


class TotalStationFeed:
    """A GeoCOM total station measuring named reflectors, in rig-frame millimetres.

    ``geocom`` is an already-connected geocompy ``GeoCom`` (the constructor does no I/O). ``targets`` maps
    names to approximate rig-frame positions (mm) used only to aim; with ``use_atr`` the instrument's
    automatic target recognition fine-points onto the reflector, so a few mm of error are fine.
    ``timeout_s`` bounds every reply (it must cover a full turn of the telescope); ``TMC_GetCoordinate``
    additionally lets the instrument wait ``edm_wait_s`` for the distance. ``connection`` is the geocompy
    connection under ``geocom`` (taken from it when omitted); it is reset after a timeout or a garbled reply
    and closed by :meth:`close`. All calls are serialized by a lock, so threads may share one feed.

    ``checksum``: the feed talks GeoCOM with CRC-16 (``geocom`` made with ``checksum=True``); every reply must
    then carry a CRC field that matches (checked here again with :func:`codec.decode_reply`, since geocompy
    skips a reply whose CRC field was lost), else :class:`ProtocolError`. ``max_error_mm``: plausibility check
    of every survey against the target's expected position (:class:`SurveyImplausible`; None = off).
    """

    kind = "total_station"

    def __init__(self, geocom: GeoCom, *, station_xyz_mm: Xyz, station_yaw_deg: float = 0.0,
                 targets: Mapping[str, Xyz], timeout_s: float = 5.0, edm_wait_s: float = 3.0,
                 use_atr: bool = True, connection: Any | None = None, checksum: bool = False,
                 max_error_mm: float | None = None) -> None:
        if not targets:
            raise ValueError("targets: at least one named target position is needed")
        if not (timeout_s > 0 and math.isfinite(timeout_s)):
            raise ValueError(f"timeout_s must be a positive number, got {timeout_s!r}")
        if not (edm_wait_s >= 0 and math.isfinite(edm_wait_s)):
            raise ValueError(f"edm_wait_s must be >= 0, got {edm_wait_s!r}")
        if not math.isfinite(float(station_yaw_deg)):
            raise ValueError(f"station_yaw_deg must be finite, got {station_yaw_deg!r}")
        self._geocom = geocom
        self._conn = connection if connection is not None else getattr(geocom, "_conn", None)
        self.station_xyz_mm: Xyz = _xyz(station_xyz_mm, "station_xyz_mm")
        self.station_yaw_deg = float(station_yaw_deg)
        self._targets: dict[str, Xyz] = {str(k): _xyz(v, f"targets[{k!r}]") for k, v in targets.items()}
        self.timeout_s = float(timeout_s)
        self.edm_wait_s = float(edm_wait_s)
        self.use_atr = bool(use_atr)
        self.checksum = bool(checksum)
        if max_error_mm is not None and not (max_error_mm > 0 and math.isfinite(max_error_mm)):
            raise ValueError(f"max_error_mm must be a positive number or None, got {max_error_mm!r}")
        self.max_error_mm = max_error_mm
        self._lock = threading.Lock()
        self._origin_enh_m: Xyz | None = None
        self._closed = False

    # ---------------------------------------------------------------- pure helpers (no I/O)
    @property
    def targets(self) -> dict[str, Xyz]:
        """The approximate rig-frame target positions (a copy)."""
        return dict(self._targets)

    @property
    def geocom(self) -> GeoCom:
        """The wrapped geocompy ``GeoCom`` for RPCs the feed does not cover; hold :attr:`lock` while using it
        and classify its responses yourself (geocompy returns error codes, it does not raise)."""
        return self._geocom

    @property
    def lock(self) -> threading.Lock:
        """The lock that serializes traffic on the connection."""
        return self._lock

    @property
    def instrument_origin_enh_m(self) -> Xyz | None:
        """(E0, N0, H0 + hi - ht) as read from the instrument, or None before the first measurement."""
        return self._origin_enh_m

    def aim_angles(self, target: str) -> tuple[float, float]:
        """(Hz, V) in radians the instrument turns to for ``target`` (Hz clockwise from N, V zenith angle)."""
        delta = rig_to_instrument(self._target(target), station_xyz_mm=self.station_xyz_mm,
                                  station_yaw_deg=self.station_yaw_deg)
        hz, v, distance = codec.polar_from_delta(*delta)
        if distance < 1e-6:
            raise ValueError(f"target {target!r} coincides with the station position")
        return hz, v

    def _target(self, target: str) -> Xyz:
        try:
            return self._targets[target]
        except KeyError:
            known = ", ".join(sorted(self._targets))
            raise ValueError(f"unknown target {target!r}; known targets: {known}") from None

    # ---------------------------------------------------------------- PositionFeed
    def identify(self) -> DeviceIdentity:
        """Instrument name, serial number, firmware and GeoCOM versions (4 RPCs)."""
        with self._session():
            warnings: list[str] = []
            name = self._check(self._geocom.csv.get_instrument_name(), "CSV_GetInstrumentName", warnings)
            serial = self._check(self._geocom.csv.get_serial_number(), "CSV_GetInstrumentNo", warnings)
            firmware = self._check(self._geocom.csv.get_firmware_version(), "CSV_GetSWVersion", warnings)
            geocom = self._check(self._geocom.com.get_geocom_version(), "COM_GetSWVersion", warnings)
        return DeviceIdentity(
            kind=self.kind,
            model=str(name),
            firmware=".".join(str(v) for v in firmware),
            serial_number=str(serial),
            extra={"protocol": "GeoCOM", "geocom_version": ".".join(str(v) for v in geocom)},
        )

    def measure(self, target: str) -> SurveyedPoint:
        """Aim at ``target``, measure, return its rig-frame position (mm). Unknown name -> ValueError."""
        hz, v = self.aim_angles(target)
        warnings: list[str] = []
        with self._session():
            origin = self._read_origin(warnings)
            atr = ATR.TARGET if self.use_atr else ATR.POSITION
            self._check(self._geocom.aut.turn_to(hz, v, Position.NORMAL, atr), "AUT_MakePositioning", warnings,
                        values=False)
            self._check(self._geocom.tmc.do_measurement(Measurement.DISTANCE, Inclination.AUTO),
                        "TMC_DoMeasure", warnings, values=False)
            with self._timeout(self.timeout_s + self.edm_wait_s):
                resp = self._geocom.tmc.get_coordinate(wait=self.edm_wait_s, mode=Inclination.AUTO)
            params = self._check(resp, "TMC_GetCoordinate", warnings)
        try:
            coord = params[0]
            enh = (float(coord.x), float(coord.y), float(coord.z))
        except (TypeError, IndexError, AttributeError, ValueError) as exc:
            raise ProtocolError(f"TMC_GetCoordinate reply carried no coordinates: {resp.response!r}") from exc
        delta = (enh[0] - origin[0], enh[1] - origin[1], enh[2] - origin[2])
        xyz = instrument_to_rig(delta, station_xyz_mm=self.station_xyz_mm, station_yaw_deg=self.station_yaw_deg)
        if self.max_error_mm is not None:
            expected = self._targets[target]
            off = math.dist(xyz, expected)
            if not off <= self.max_error_mm:
                raise SurveyImplausible(f"total station: {target!r} surveyed at {tuple(round(v, 2) for v in xyz)} mm, "
                                        f"{off:.1f} mm from its expected position (max_survey_error_mm = "
                                        f"{self.max_error_mm:g}); not used")
        return SurveyedPoint(name=target, xyz_mm=xyz, warning=", ".join(dict.fromkeys(warnings)) or None)

    def close(self) -> None:
        """Close the connection (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._conn is not None:
                with contextlib.suppress(Exception):
                    self._conn.close()

    def __enter__(self) -> "TotalStationFeed":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- internals
    def _read_origin(self, warnings: list[str]) -> Xyz:
        if self._origin_enh_m is None:
            station, hi = self._check(self._geocom.tmc.get_station(), "TMC_GetStation", warnings)
            ht = self._check(self._geocom.tmc.get_target_height(), "TMC_GetHeight", warnings)
            self._origin_enh_m = (float(station.x), float(station.y), float(station.z) + float(hi) - float(ht))
        return self._origin_enh_m

    @contextlib.contextmanager
    def _session(self) -> Iterator[None]:
        with self._lock:
            if self._closed:
                raise ConnectionLost("total station feed is closed")
            with self._timeout(self.timeout_s):
                yield

    @contextlib.contextmanager
    def _timeout(self, timeout_s: float) -> Iterator[None]:
        override = getattr(self._conn, "timeout_override", None)
        if override is None:
            yield
        else:
            with override(timeout_s):
                yield

    def _resync(self) -> None:
        """Drop stale input after a timeout or a garbled reply so the next exchange starts clean."""
        reset = getattr(self._conn, "reset", None)
        if reset is not None:
            with contextlib.suppress(Exception):
                reset()

    @staticmethod
    def _code_of(resp: Any) -> int:
        code = int(resp.error)
        if code == codec.UNDEFINED:
            # geocompy maps codes it does not know to UNDEFINED; recover the number from the raw reply.
            with contextlib.suppress(codec.ProtocolError):
                code = codec.decode_reply(resp.response).code or code
        return code

    def _check(self, resp: Any, what: str, warnings: list[str], *, values: bool = True) -> Any:
        """Classify a geocompy response; return its params (required when ``values``) or raise the
        matching typed error. Warning names are appended to ``warnings``."""
        code = self._code_of(resp)
        severity = codec.classify(code)
        if self.checksum and severity is not codec.Severity.ERROR:
            try:
                codec.decode_reply(resp.response, require_crc=True)
            except codec.ProtocolError as exc:
                self._resync()
                raise ProtocolError(f"total station: reply to {what} failed its CRC check ({exc})") from None
        if severity is codec.Severity.OK:
            if values and resp.params is None:
                raise ProtocolError(f"total station: {what} reply could not be parsed: {resp.response!r}")
            return resp.params
        name = codec.code_name(code)
        if severity is codec.Severity.WARNING:
            warnings.append(name)
            if values and resp.params is None:
                raise ProtocolError(f"total station: {what} returned {name} without values: {resp.response!r}")
            return resp.params
        if code == codec.COM_TIMEDOUT:
            self._resync()
            raise DeviceTimeout(f"total station did not answer {what} within {self.timeout_s:.3g} s")
        if code in _PROTOCOL_CODES or (code == codec.COM_FAILED and getattr(self._conn, "garbled", False)):
            self._resync()
            raise ProtocolError(f"total station: bad reply to {what} ({name}): {resp.response!r}")
        if code in _LINK_CODES:
            raise ConnectionLost(f"total station link failed during {what} ({name})")
        if code in codec.BUSY_CODES:
            raise DeviceBusy(f"total station busy, {what} refused", code, name=name)
        raise DeviceRejected(f"total station refused {what}", code, name=name)


def open_total_station(url: str, *, station_xyz_mm: Xyz, station_yaw_deg: float = 0.0,
                       targets: Mapping[str, Xyz], checksum: bool = False, timeout_s: float = 5.0,
                       baudrate: int = 9600, edm_wait_s: float = 3.0, use_atr: bool = True,
                       connect_attempts: int = 2, logger: logging.Logger | None = None,
                       max_error_mm: float | None = None) -> TotalStationFeed:
    """Open ``url`` with pyserial (device path, pty path, ``socket://host:port``...), connect geocompy's
    ``GeoCom`` (which probes the instrument and sleeps about 1 s) and return the feed.

    Raises :class:`ConnectionLost` if the port cannot be opened and :class:`DeviceTimeout` if no GeoCOM
    instrument answers on it."""
    port = open_transport(url, baudrate=baudrate, timeout_s=timeout_s)
    try:
        connection = _Connection(port, logger=logger)
        geocom = GeoCom(connection, logger=logger, checksum=checksum, attempts=connect_attempts)
    except ConnectionRefusedError as exc:
        port.close()
        raise DeviceTimeout(f"no GeoCOM instrument answered on {url!r} within {timeout_s:.3g} s") from exc
    except BaseException:
        port.close()
        raise
    return TotalStationFeed(geocom, station_xyz_mm=station_xyz_mm, station_yaw_deg=station_yaw_deg,
                            targets=targets, timeout_s=timeout_s, edm_wait_s=edm_wait_s, use_atr=use_atr,
                            connection=connection, checksum=checksum, max_error_mm=max_error_mm)
