"""Simulated Leica total station speaking GeoCOM ASCII (sans-IO; serve it with ``simulators.serve``).

The model answers geocompy's connect sequence (a bare line end, COM_NullProc 0, COM_GetDoublePrecision 108,
CSV_GetInstrumentName 5004, CSV_GetInstrumentNo 5003, COM_GetSWVersion 110, CSV_GetSWVersion 5034) and the
measuring RPCs: AUT_MakePositioning 9027, TMC_DoMeasure 2008, TMC_GetCoordinate 2082, TMC_GetSimpleMea 2108,
TMC_GetAngle1 2003, TMC_GetAngle5 2107, TMC_GetStation/SetStation 2009/2010, TMC_GetHeight/SetHeight
2011/2012, TMC_GetFace 2026, COM_SetDoublePrecision 107. ``c`` is answered ``?``; an unknown RPC gets
COM_PROC_UNAVAIL (3081) in the COM field, a malformed line COM_CANT_DECODE_REQ (3080), a wrong CRC
COM_SRVR_RX_CHECKSUM_ERROR (3101), bad parameters IVPARAM (2).

Physics: the reflectors sit at ``targets_mm`` in the rig frame; the instrument's tilting axis at
``station_xyz_mm`` with its E axis turned ``station_yaw_deg`` counter-clockwise from rig +x (N = E turned a
further 90 degrees, H = +z). Positioning with ATR snaps the aim onto the reflector nearest the requested
direction if it lies within ``acceptance_rad``, else answers AUT_NO_TARGET. TMC_DoMeasure measures the
reflector nearest the aim direction within ``acceptance_rad`` (angles + ``angle_noise_rad``, slope distance +
``noise_mm``, seeded); without one, the result RPCs answer TMC_DIST_ERROR (1292). Reported E/N/H include the
instrument's station setup (E0, N0, H0), instrument height hi and reflector height ht. The geometry here is
written independently of the driver's so that the two cannot share a sign error.

Run alone: ``python -m simulators.total_station --url pty`` (or ``--url tcp://127.0.0.1:0``) prints the URL.
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError
from drivers.total_station import codec

Xyz = tuple[float, float, float]

#: A small default rig for ``main``: four reflectors around the sphere, the instrument 3 m away on -y.
DEFAULT_TARGETS: dict[str, Xyz] = {
    "R1": (600.0, 0.0, 0.0),
    "R2": (-600.0, 0.0, 0.0),
    "R3": (0.0, 600.0, 300.0),
    "R4": (0.0, -600.0, -300.0),
}
DEFAULT_STATION_MM: Xyz = (0.0, -3000.0, 200.0)
DEFAULT_STATION_YAW_DEG = 0.0

_TWO_PI = 2.0 * math.pi


@dataclass
class _Fault:
    code: int
    rpc: int | None
    remaining: int


@dataclass(frozen=True)
class _Shot:
    """A stored distance measurement: angles (rad) and slope distance (m) to a reflector."""

    target: str
    hz: float
    v: float
    distance_m: float
    time_ms: int


class GeoComModel:
    """Sans-IO GeoCOM responder: ``receive(bytes) -> bytes``, ``reset()``; fault hook ``next_return_code``."""

    def __init__(self, targets_mm: dict[str, Xyz], station_xyz_mm: Xyz, station_yaw_deg: float = 0.0, *,
                 noise_mm: float = 0.3, angle_noise_rad: float = 2.4e-6, seed: int = 0, name: str = "TS60",
                 serial: str = "123456", firmware: tuple[int, int, int] = (4, 20, 0),
                 geocom_version: tuple[int, int, int] = (1, 50, 0), checksum: bool = False,
                 acceptance_rad: float = 5e-3, instrument_station_enh_m: Xyz = (0.0, 0.0, 0.0),
                 instrument_height_m: float = 0.0, reflector_height_m: float = 0.0) -> None:
        if not serial.isdigit():
            raise ValueError(f"serial must be decimal digits (CSV_GetInstrumentNo is an integer), got {serial!r}")
        codec.format_value(name)  # refuses names that cannot travel as a GeoCOM string
        self.targets_mm = {k: tuple(float(c) for c in v) for k, v in targets_mm.items()}
        self.station_xyz_mm = tuple(float(c) for c in station_xyz_mm)
        self.station_yaw_deg = float(station_yaw_deg)
        self.noise_mm = float(noise_mm)
        self.angle_noise_rad = float(angle_noise_rad)
        self.seed = seed
        self.name = name
        self.serial = serial
        self.firmware = firmware
        self.geocom_version = geocom_version
        self.checksum = checksum
        self.acceptance_rad = float(acceptance_rad)
        self._initial_setup = (tuple(float(c) for c in instrument_station_enh_m), float(instrument_height_m),
                               float(reflector_height_m))
        self._fault_lock = threading.Lock()
        self.requests: list[codec.Request] = []   # every decoded request, for tests
        self._dispatch = self._handlers()
        self.reset()

    # ------------------------------------------------------------------ public
    def reset(self) -> None:
        """Back to power-on state: empty buffer, aim at Hz=0/V=90 deg, no stored distance, no faults."""
        self._buffer = bytearray()
        self._rng = np.random.default_rng(self.seed)
        self.digits = codec.DEFAULT_DIGITS
        self.hz = 0.0
        self.v = math.pi / 2
        self._shot: _Shot | None = None
        (self.instrument_station_enh_m, self.instrument_height_m, self.reflector_height_m) = self._initial_setup
        self._t0 = time.monotonic()
        with self._fault_lock:
            self._faults: list[_Fault] = []
        self.requests.clear()

    def next_return_code(self, code: int, *, rpc: int | None = None, count: int = 1) -> None:
        """Answer the next ``count`` requests (of RPC ``rpc``, or any RPC) with return code ``code``.

        A warning code (1283, 1284) replaces OK but keeps the normal values; any other code is answered
        without values and the request has no effect (the instrument refused it)."""
        with self._fault_lock:
            self._faults.append(_Fault(code, rpc, count))

    def clear_faults(self) -> None:
        with self._fault_lock:
            self._faults.clear()

    def true_angles(self, target: str) -> tuple[float, float, float]:
        """(Hz, V, slope distance m) from the tilting axis to ``target`` (no noise)."""
        return self._polar(self.targets_mm[target])

    def true_enh(self, target: str) -> Xyz:
        """E, N, H (m) the instrument would report for ``target`` without noise."""
        hz, v, d = self.true_angles(target)
        return self._enh(hz, v, d)

    def receive(self, data: bytes) -> bytes:
        self._buffer += data
        out = bytearray()
        while True:
            try:
                used, line = codec.split_line(self._buffer)
            except ProtocolError:
                self._buffer.clear()   # an endless line: drop it, as the instrument's buffer would overflow
                break
            if line is None:
                break
            del self._buffer[:used]
            out += self._handle_line(line)
        return bytes(out)

    # ------------------------------------------------------------------ geometry (independent of the driver)
    def _polar(self, p: Sequence[float]) -> tuple[float, float, float]:
        yaw = math.radians(self.station_yaw_deg)
        rx = (p[0] - self.station_xyz_mm[0]) / 1000.0
        ry = (p[1] - self.station_xyz_mm[1]) / 1000.0
        rz = (p[2] - self.station_xyz_mm[2]) / 1000.0
        # components along the instrument's E = (cos yaw, sin yaw, 0) and N = (-sin yaw, cos yaw, 0) axes
        east = rx * math.cos(yaw) + ry * math.sin(yaw)
        north = -rx * math.sin(yaw) + ry * math.cos(yaw)
        distance = math.sqrt(east ** 2 + north ** 2 + rz ** 2)
        hz = math.atan2(east, north)
        if hz < 0:
            hz += _TWO_PI
        if hz >= _TWO_PI:
            hz = 0.0
        v = math.acos(max(-1.0, min(1.0, rz / distance))) if distance > 0 else 0.0
        return hz, v, distance

    def _enh(self, hz: float, v: float, distance_m: float) -> Xyz:
        e0, n0, h0 = self.instrument_station_enh_m
        horizontal = distance_m * math.sin(v)
        return (e0 + horizontal * math.sin(hz),
                n0 + horizontal * math.cos(hz),
                h0 + self.instrument_height_m + distance_m * math.cos(v) - self.reflector_height_m)

    @staticmethod
    def _separation(hz1: float, v1: float, hz2: float, v2: float) -> float:
        """Angle (rad) between two directions given as (Hz, V)."""
        a = (math.sin(v1) * math.sin(hz1), math.sin(v1) * math.cos(hz1), math.cos(v1))
        b = (math.sin(v2) * math.sin(hz2), math.sin(v2) * math.cos(hz2), math.cos(v2))
        dot = max(-1.0, min(1.0, sum(x * y for x, y in zip(a, b))))
        return math.acos(dot)

    def _nearest_target(self, hz: float, v: float) -> str | None:
        best, best_sep = None, self.acceptance_rad
        for name, p in self.targets_mm.items():
            t_hz, t_v, _ = self._polar(p)
            sep = self._separation(hz, v, t_hz, t_v)
            if sep <= best_sep:
                best, best_sep = name, sep
        return best

    def _now_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000)

    # ------------------------------------------------------------------ protocol
    def _handle_line(self, line: bytes) -> bytes:
        text = line.strip(b" \t\r\n")
        if not text:
            return b""                       # geocompy's buffer-clearing bare line end: no answer
        if text == codec.ABORT_REQUEST:
            return codec.ABORT_REPLY + codec.TERMINATOR
        try:
            request = codec.decode_request(text)
        except codec.ChecksumError as exc:
            return self._reply(codec.OK, trid=exc.trid or 0, com_rc=codec.COM_SRVR_RX_CHECKSUM_ERROR, crc=True)
        except ProtocolError:
            return self._reply(codec.OK, trid=0, com_rc=codec.COM_CANT_DECODE_REQ, crc=self.checksum)
        self.requests.append(request)
        trid = request.trid or 0
        with_crc = self.checksum or request.crc is not None
        if self.checksum and request.crc is None:
            return self._reply(codec.OK, trid=trid, com_rc=codec.COM_NO_CHECKSUM, crc=True)
        handler = self._dispatch.get(request.rpc)
        if handler is None:
            return self._reply(codec.OK, trid=trid, com_rc=codec.COM_PROC_UNAVAIL, crc=with_crc)
        fault = self._take_fault(request.rpc)
        if fault is not None and codec.classify(fault) is not codec.Severity.WARNING:
            return self._reply(fault, trid=trid, crc=with_crc)
        try:
            rc, values = handler(request.params)
        except ProtocolError:
            rc, values = codec.IVPARAM, ()
        if fault is not None and rc == codec.OK:
            rc = fault
        return self._reply(rc, values, trid=trid, crc=with_crc)

    def _reply(self, rc: int, values: Sequence[codec.Value] = (), *, trid: int, com_rc: int = codec.OK,
               crc: bool) -> bytes:
        return codec.encode_reply(rc, values, trid=trid, com_rc=com_rc, checksum=crc, digits=self.digits)

    def _take_fault(self, rpc: int) -> int | None:
        with self._fault_lock:
            for fault in self._faults:
                if fault.rpc is None or fault.rpc == rpc:
                    fault.remaining -= 1
                    if fault.remaining <= 0:
                        self._faults.remove(fault)
                    return fault.code
        return None

    def _handlers(self) -> dict[int, Callable[[tuple[str, ...]], tuple[int, tuple[codec.Value, ...]]]]:
        return {
            0: self._null_proc,
            107: self._set_double_precision,
            108: self._get_double_precision,
            110: self._get_geocom_version,
            5003: self._get_instrument_no,
            5004: self._get_instrument_name,
            5034: self._get_sw_version,
            9027: self._make_positioning,
            2008: self._do_measure,
            2082: self._get_coordinate,
            2108: self._get_simple_mea,
            2003: self._get_angle1,
            2107: self._get_angle5,
            2009: self._get_station,
            2010: self._set_station,
            2011: self._get_height,
            2012: self._set_height,
            2026: self._get_face,
        }

    @staticmethod
    def _args(params: tuple[str, ...], *parsers: Callable[[str], object]) -> list:
        if len(params) != len(parsers):
            raise ProtocolError(f"expected {len(parsers)} parameters, got {len(params)}")
        return [parse(token) for parse, token in zip(parsers, params)]

    # -- COM / CSV
    def _null_proc(self, params):
        self._args(params)
        return codec.OK, ()

    def _get_double_precision(self, params):
        self._args(params)
        return codec.OK, (self.digits,)

    def _set_double_precision(self, params):
        (digits,) = self._args(params, codec.parse_int)
        if not 0 <= digits <= 15:
            return codec.IVPARAM, ()
        self.digits = digits
        return codec.OK, ()

    def _get_geocom_version(self, params):
        self._args(params)
        return codec.OK, tuple(self.geocom_version)

    def _get_instrument_no(self, params):
        self._args(params)
        return codec.OK, (int(self.serial),)

    def _get_instrument_name(self, params):
        self._args(params)
        return codec.OK, (self.name,)

    def _get_sw_version(self, params):
        self._args(params)
        return codec.OK, tuple(self.firmware)

    # -- AUT
    def _make_positioning(self, params):
        hz, v, posmode, atrmode, _dummy = self._args(
            params, codec.parse_float, codec.parse_float, codec.parse_int, codec.parse_int, codec.parse_int)
        if posmode not in (0, 1) or atrmode not in (0, 1) or not 0.0 < v < _TWO_PI:
            return codec.IVPARAM, ()
        hz %= _TWO_PI
        if v > math.pi:                           # face II: same line of sight as (Hz - pi, 2 pi - V)
            hz, v = (hz + math.pi) % _TWO_PI, _TWO_PI - v
        self.hz, self.v = hz, v
        self._shot = None
        if atrmode == 1:                          # ATR: fine-point onto the reflector in the field of view
            target = self._nearest_target(hz, v)
            if target is None:
                return codec.AUT_NO_TARGET, ()
            self.hz, self.v, _ = self._polar(self.targets_mm[target])
        return codec.OK, ()

    # -- TMC
    def _do_measure(self, params):
        command, incline = self._args(params, codec.parse_int, codec.parse_int)
        if incline not in (0, 1, 2):
            return codec.IVPARAM, ()
        if command in (0, 3):                     # STOP, CLEAR
            self._shot = None
            return codec.OK, ()
        if command == 4:                          # SIGNAL
            return codec.OK, ()
        if command not in (1, 2, 6, 8, 10):
            return codec.IVPARAM, ()
        target = self._nearest_target(self.hz, self.v)
        if target is None:
            self._shot = None
            return codec.OK, ()                   # the EDM runs; the result RPCs report the missing return
        _, _, distance = self._polar(self.targets_mm[target])
        noise_d, noise_hz, noise_v = self._rng.standard_normal(3)
        self._shot = _Shot(target=target,
                           hz=(self.hz + self.angle_noise_rad * noise_hz) % _TWO_PI,
                           v=self.v + self.angle_noise_rad * noise_v,
                           distance_m=distance + self.noise_mm * noise_d / 1000.0,
                           time_ms=self._now_ms())
        return codec.OK, ()

    def _get_coordinate(self, params):
        self._args(params, codec.parse_int, codec.parse_int)
        if self._shot is None:
            return codec.TMC_DIST_ERROR, ()
        e, n, h = self._enh(self._shot.hz, self._shot.v, self._shot.distance_m)
        return codec.OK, (e, n, h, self._shot.time_ms, e, n, h, self._shot.time_ms)

    def _get_simple_mea(self, params):
        self._args(params, codec.parse_int, codec.parse_int)
        if self._shot is None:
            return codec.TMC_DIST_ERROR, ()
        return codec.OK, (self._shot.hz, self._shot.v, self._shot.distance_m)

    def _noisy_aim(self) -> tuple[float, float]:
        noise_hz, noise_v = self._rng.standard_normal(2)
        return (self.hz + self.angle_noise_rad * noise_hz) % _TWO_PI, self.v + self.angle_noise_rad * noise_v

    def _get_angle1(self, params):
        (incline,) = self._args(params, codec.parse_int)
        if incline not in (0, 1, 2):
            return codec.IVPARAM, ()
        hz, v = self._noisy_aim()
        t = self._now_ms()
        accuracy = max(self.angle_noise_rad, 1e-7)
        return codec.OK, (hz, v, accuracy, t, 0.0, 0.0, accuracy, t, 0)

    def _get_angle5(self, params):
        (incline,) = self._args(params, codec.parse_int)
        if incline not in (0, 1, 2):
            return codec.IVPARAM, ()
        return codec.OK, self._noisy_aim()

    def _get_station(self, params):
        self._args(params)
        e0, n0, h0 = self.instrument_station_enh_m
        return codec.OK, (e0, n0, h0, self.instrument_height_m)

    def _set_station(self, params):
        e0, n0, h0, hi = self._args(params, *(codec.parse_float,) * 4)
        self.instrument_station_enh_m, self.instrument_height_m = (e0, n0, h0), hi
        return codec.OK, ()

    def _get_height(self, params):
        self._args(params)
        return codec.OK, (self.reflector_height_m,)

    def _set_height(self, params):
        (ht,) = self._args(params, codec.parse_float)
        self.reflector_height_m = ht
        return codec.OK, ()

    def _get_face(self, params):
        self._args(params)
        return codec.OK, (0 if self.v <= math.pi else 1,)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m simulators.total_station --url pty|tcp://127.0.0.1:PORT``: serve a default rig, print the
    URL, run until interrupted (or for ``--duration`` seconds)."""
    from simulators.serve import serve

    parser = argparse.ArgumentParser(prog="python -m simulators.total_station", description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="pty", help="'pty' or 'tcp://127.0.0.1:PORT' (port 0 = any free port)")
    parser.add_argument("--checksum", action="store_true", help="require and send CRC-16 in every frame")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise-mm", type=float, default=0.3)
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    args = parser.parse_args(argv)
    model = GeoComModel(DEFAULT_TARGETS, DEFAULT_STATION_MM, DEFAULT_STATION_YAW_DEG, noise_mm=args.noise_mm,
                        seed=args.seed, checksum=args.checksum)
    server = serve(model, args.url)
    print(server.url, flush=True)
    print(f"targets (rig mm): {DEFAULT_TARGETS}; station {DEFAULT_STATION_MM}, yaw {DEFAULT_STATION_YAW_DEG} deg",
          file=sys.stderr, flush=True)
    deadline = None if args.duration is None else time.monotonic() + args.duration
    try:
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
