"""Driver for the LED sphere's Modbus interface (Modbus TCP or Modbus RTU) over a pymodbus 3.16 sync client.

The register map and the upload sequence are in ``docs/protocols/led-sphere-modbus.md``; addresses come
from :mod:`.registers`. The driver satisfies :class:`drivers.contracts.LightSource`.

Errors at this boundary:

* Modbus exception response -> :class:`DeviceRejected` with ``code`` = the exception code (2 illegal
  address, 3 illegal value, 4 device failure) and ``name`` = its name; code 6 -> :class:`DeviceBusy`.
* no answer within ``timeout_s`` -> :class:`DeviceTimeout` (the connection is then dropped, so a late
  answer cannot be taken for the answer to the next request; the next call reconnects).
* cannot connect / socket or port gone -> :class:`ConnectionLost`.
* a reply that does not match the request (wrong transaction or device id) -> :class:`ProtocolError`.
* a pattern over ``max_total_current_a`` or ``max_mean_duty``, a slot out of range -> :class:`LimitError`,
  raised before anything is sent.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np
import numpy.typing as npt
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

from ..contracts import DeviceIdentity, LightStatus, Polarization
from ..errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError, ProtocolError
from . import registers as rm

try:  # pyserial raises its own exception type for ports that vanish
    from serial import SerialException
except ImportError:  # pragma: no cover
    SerialException = OSError  # type: ignore[misc,assignment]

DEFAULT_TCP_PORT = 502
DEFAULT_BAUDRATE = 115200


class LedSphereModbus:
    """LED sphere over Modbus. Constructing it does no I/O; the first call that needs the identity
    (``identify``, ``led_count``, ``upload_pattern``, ``select_slot``) reads it once.

    ``client``: a pymodbus sync client (``ModbusTcpClient`` or ``ModbusSerialClient`` with the RTU framer),
    connected or not (pymodbus connects on the first request). ``timeout_s`` is applied to the client's
    response timeout. Limits: the summed LED current ``sum(rgb16 / 65535) * led_current_a_per_channel``
    must not exceed ``max_total_current_a`` and the mean duty ``mean(rgb16 / 65535)`` must not exceed
    ``max_mean_duty``.
    """

    def __init__(self, client: ModbusTcpClient | ModbusSerialClient, *, device_id: int = 1,
                 max_total_current_a: float, max_mean_duty: float,
                 led_current_a_per_channel: float = 0.02, timeout_s: float = 1.0) -> None:
        if not 0 <= device_id <= 247:
            raise ValueError(f"device_id must be 0..247, got {device_id}")
        if not (max_total_current_a > 0 and 0 < max_mean_duty <= 1 and led_current_a_per_channel > 0
                and timeout_s > 0):
            raise ValueError("limits and timeout_s must be positive (max_mean_duty in (0, 1])")
        self.client = client
        self.device_id = device_id
        self.max_total_current_a = float(max_total_current_a)
        self.max_mean_duty = float(max_mean_duty)
        self.led_current_a_per_channel = float(led_current_a_per_channel)
        self.timeout_s = float(timeout_s)
        comm = getattr(client, "comm_params", None)
        if comm is not None:
            comm.timeout_connect = self.timeout_s
        self._identity: DeviceIdentity | None = None
        self._lock = threading.RLock()     # one request (and one multi-request upload) at a time

    # -- low level: one Modbus request, errors mapped ---------------------------------------------------

    def _execute(self, call: Callable[..., Any], what: str, *args: Any, **kwargs: Any) -> Any:
        try:
            with self._lock:
                response = call(*args, device_id=self.device_id, **kwargs)
        except ConnectionException as exc:
            raise ConnectionLost(f"Modbus connection lost during {what}: {exc}") from exc
        except ModbusIOException as exc:
            if "No response" in str(exc):
                self._drop_connection()
                raise DeviceTimeout(f"no answer to {what} within {self.timeout_s:.3g} s "
                                    f"(device id {self.device_id})") from exc
            self._drop_connection()
            raise ProtocolError(f"unexpected reply to {what}: {exc}") from exc
        except (SerialException, OSError) as exc:
            raise ConnectionLost(f"Modbus port lost during {what}: {exc}") from exc
        except ModbusException as exc:
            raise ProtocolError(f"Modbus error during {what}: {exc}") from exc
        if response is None:
            raise ProtocolError(f"no response object for {what}")
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            try:
                name: str | None = rm.ExceptionCode(code).name
            except ValueError:
                name = None
            cls = DeviceBusy if code == rm.ExceptionCode.SERVER_DEVICE_BUSY else DeviceRejected
            raise cls(f"LED sphere refused {what}", code, name=name)
        return response

    def _drop_connection(self) -> None:
        try:
            self.client.close()
        except Exception:  # noqa: BLE001 - best effort; the original error is what matters
            pass

    def read_registers(self, address: int, count: int = 1) -> list[int]:
        """Read ``count`` registers from ``address`` (FC03), errors mapped as for every call."""
        if not 1 <= count <= rm.MAX_READ_REGISTERS:
            raise LimitError(f"a read covers 1..{rm.MAX_READ_REGISTERS} registers, asked {count}")
        rr = self._execute(self.client.read_holding_registers, f"read of {count} register(s) at {address}",
                           address, count=count)
        regs = list(rr.registers)
        if len(regs) != count:
            raise ProtocolError(f"asked {count} registers at {address}, got {len(regs)}")
        return regs

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        """Write ``values`` from ``address``: FC06 for one register, FC16 for more."""
        values = [int(v) for v in values]
        if not 1 <= len(values) <= rm.MAX_WRITE_REGISTERS:
            raise LimitError(f"a write covers 1..{rm.MAX_WRITE_REGISTERS} registers, asked {len(values)}")
        if any(not 0 <= v <= 0xFFFF for v in values):
            raise LimitError("register values must be in 0..65535")
        what = f"write of {len(values)} register(s) at {address}"
        if len(values) == 1:
            self._execute(self.client.write_register, what, address, values[0])
        else:
            self._execute(self.client.write_registers, what, address, values)

    def _read_block(self, block: str) -> dict[str, list[int]]:
        first, count = rm.block_span(block)
        regs = self.read_registers(first, count)
        return {r.name: regs[r.address - first:r.end - first] for r in rm.REGISTERS if r.block == block}

    def _write(self, name: str, value: int) -> None:
        self.write_registers(rm.reg(name).address, [value])

    # -- LightSource ------------------------------------------------------------------------------------

    def identify(self) -> DeviceIdentity:
        """Read the identity block (one FC03 of registers 0-18)."""
        v = self._read_block("identity")
        version = v["PROTOCOL_VERSION"][0]
        if version != rm.PROTOCOL_VERSION:
            raise ProtocolError(f"device speaks register-map version {version}, this driver "
                                f"version {rm.PROTOCOL_VERSION}")
        if v["CHANNELS"][0] != rm.CHANNELS:
            raise ProtocolError(f"device reports {v['CHANNELS'][0]} channels per LED, expected {rm.CHANNELS}")
        window = v["WINDOW_REGISTERS"][0]
        if not (rm.CHANNELS <= window <= rm.MAX_WRITE_REGISTERS - 2 and window % rm.CHANNELS == 0):
            raise ProtocolError(f"device reports an unusable upload window of {window} registers")
        self._identity = DeviceIdentity(
            kind="led_sphere",
            model=rm.decode_ascii(v["MODEL"]),
            firmware=f"{v['FIRMWARE_MAJOR'][0]}.{v['FIRMWARE_MINOR'][0]}",
            serial_number=rm.decode_ascii(v["SERIAL_NUMBER"]),
            extra={"led_count": v["LED_COUNT"][0], "slot_count": v["SLOT_COUNT"][0],
                   "channels": v["CHANNELS"][0], "window_registers": window,
                   "protocol_version": version, "interface": "modbus"},
        )
        return self._identity

    def _ident(self) -> DeviceIdentity:
        return self._identity if self._identity is not None else self.identify()

    @property
    def led_count(self) -> int:
        return int(self._ident().extra["led_count"])

    @property
    def slot_count(self) -> int:
        return int(self._ident().extra["slot_count"])

    def check_pattern(self, rgb16: npt.ArrayLike) -> PatternLoad:
        """Coerce ``rgb16`` to an (M, 3) uint16 array and check it against the limits (no I/O).

        Raises :class:`LimitError` naming the limit. The LED count is checked in ``upload_pattern``.
        """
        arr = np.asarray(rgb16)
        if arr.ndim != 2 or arr.shape[1] != rm.CHANNELS:
            raise ValueError(f"pattern must be (led_count, 3), got shape {arr.shape}")
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"pattern must hold integers (uint16), got {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() > 0xFFFF):
            raise LimitError("pattern values must be in 0..65535")
        duty = arr.astype(np.float64) / 65535.0
        load = PatternLoad(total_current_a=float(duty.sum()) * self.led_current_a_per_channel,
                           mean_duty=float(duty.mean()) if duty.size else 0.0)
        if load.total_current_a > self.max_total_current_a:
            raise LimitError(f"pattern draws {load.total_current_a:.3f} A, over the limit "
                             f"max_total_current_a = {self.max_total_current_a:.3f} A; nothing was sent")
        if load.mean_duty > self.max_mean_duty:
            raise LimitError(f"pattern mean duty {load.mean_duty:.4f} is over the limit "
                             f"max_mean_duty = {self.max_mean_duty:.4f}; nothing was sent")
        return load

    def upload_pattern(self, slot: int, rgb16: npt.NDArray[np.uint16]) -> None:
        """Store ``rgb16`` ((led_count, 3) uint16) in ``slot``; check the limits before sending anything.

        Sequence (see the protocol document): FC16 at UPLOAD_SLOT with [slot, offset 0, first window];
        FC16 at UPLOAD_OFFSET with [offset, next window] for every further window that is not all zero
        (the buffer starts all zero, so dark LEDs need not be sent); FC06 UPLOAD_COMMIT = 1.
        """
        self.check_pattern(rgb16)          # before any I/O, including the identity read
        arr = np.asarray(rgb16).astype(np.uint16)
        ident = self._ident()
        n, slots = int(ident.extra["led_count"]), int(ident.extra["slot_count"])
        if arr.shape[0] != n:
            raise ValueError(f"pattern has {arr.shape[0]} LEDs, the sphere has {n}")
        self._check_slot(slot, slots)
        window_leds = int(ident.extra["window_registers"]) // rm.CHANNELS
        with self._lock:                   # another thread's upload must not interleave with this one
            for offset in range(0, n, window_leds):
                chunk = arr[offset:offset + window_leds].reshape(-1).tolist()
                if offset == 0:
                    self.write_registers(rm.reg("UPLOAD_SLOT").address, [slot, offset, *chunk])
                elif any(chunk):
                    self.write_registers(rm.reg("UPLOAD_OFFSET").address, [offset, *chunk])
            self._write("UPLOAD_COMMIT", rm.COMMIT_COMMAND)

    @staticmethod
    def _check_slot(slot: int, slot_count: int) -> None:
        if not (isinstance(slot, (int, np.integer)) and 0 <= slot < slot_count):
            raise LimitError(f"slot must be in 0..{slot_count - 1}, got {slot!r}; nothing was sent")

    def select_slot(self, slot: int) -> None:
        """Show the pattern stored in ``slot`` (FC06 SELECT_SLOT)."""
        self._check_slot(slot, self.slot_count)
        self._write("SELECT_SLOT", int(slot))

    def set_polarization(self, state: Polarization) -> None:
        """Switch the polarizer banks (FC06 POLARIZATION)."""
        try:
            value = Polarization(state)
        except ValueError as exc:
            raise LimitError(f"unknown polarization {state!r}; nothing was sent") from exc
        self._write("POLARIZATION", int(value))

    def all_off(self) -> None:
        """Darken every LED (FC06 ALL_OFF = 1; the device accepts it even when busy). Idempotent."""
        self._write("ALL_OFF", rm.ALL_OFF_COMMAND)

    def status(self) -> LightStatus:
        """Read the status block (one FC03 of registers 100-107)."""
        v = self._read_block("status")
        active = v["ACTIVE_SLOT"][0]
        try:
            pol = Polarization(v["POLARIZATION_STATE"][0])
        except ValueError as exc:
            raise ProtocolError(f"device reports polarization {v['POLARIZATION_STATE'][0]}") from exc
        return LightStatus(
            temperature_c=rm.to_i16(v["TEMPERATURE"][0]) * rm.reg("TEMPERATURE").scale,
            current_a=v["CURRENT"][0] / 1000.0,
            fault_flags=v["FAULT_FLAGS"][0],
            active_slot=None if active == rm.DARK else active,
            polarization=pol,
            lit=bool(v["LIT"][0]),
        )

    def close(self) -> None:
        self.client.close()

    # -- extras ---------------------------------------------------------------------------------------

    def set_watchdog(self, timeout_s: float) -> None:
        """Darken the LEDs if no request arrives for ``timeout_s`` (0 disables; ms resolution, max 60 s)."""
        ms = int(math.ceil(timeout_s * 1000))
        if not 0 <= ms <= rm.MAX_WATCHDOG_MS:
            raise LimitError(f"watchdog timeout must be 0..{rm.MAX_WATCHDOG_MS / 1000:g} s, got {timeout_s}")
        self._write("WATCHDOG_MS", ms)

    def clear_faults(self, mask: int = 0xFFFF) -> None:
        """Clear latched fault bits (watchdog, LED fault); over-temperature clears itself when cool."""
        self._write("CLEAR_FAULTS", mask & 0xFFFF)

    def __enter__(self) -> LedSphereModbus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class PatternLoad:
    total_current_a: float
    mean_duty: float


# -- factory ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ModbusUrl:
    kind: str                 # "tcp" | "rtu"
    host: str = ""
    port: int = DEFAULT_TCP_PORT
    device: str = ""
    baudrate: int = DEFAULT_BAUDRATE
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8


def parse_modbus_url(url: str) -> ModbusUrl:
    """``modbus-tcp://host[:port]`` (port 502 by default) or
    ``modbus-rtu:///dev/ttyUSB0[?baudrate=115200&parity=N&stopbits=1&bytesize=8]``."""
    parts = urlsplit(url)
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    if parts.scheme == "modbus-tcp":
        if query or parts.path not in ("", "/"):
            raise ValueError(f"{url!r}: modbus-tcp URLs take no path or options")
        if not parts.hostname:
            raise ValueError(f"{url!r}: expected modbus-tcp://host:port")
        try:
            port = parts.port or DEFAULT_TCP_PORT
        except ValueError as exc:
            raise ValueError(f"{url!r}: bad port") from exc
        return ModbusUrl("tcp", host=parts.hostname, port=port)
    if parts.scheme == "modbus-rtu":
        if parts.netloc or not parts.path:
            raise ValueError(f"{url!r}: expected modbus-rtu:///dev/ttyX (three slashes, absolute path)")
        unknown = set(query) - {"baudrate", "parity", "stopbits", "bytesize"}
        if unknown:
            raise ValueError(f"{url!r}: unknown option(s) {sorted(unknown)}; "
                             "known: baudrate, parity, stopbits, bytesize")
        try:
            parsed = ModbusUrl("rtu", device=parts.path,
                               baudrate=int(query.get("baudrate", DEFAULT_BAUDRATE)),
                               parity=query.get("parity", "N").upper(),
                               stopbits=int(query.get("stopbits", 1)), bytesize=int(query.get("bytesize", 8)))
        except ValueError as exc:
            raise ValueError(f"{url!r}: baudrate, stopbits and bytesize must be integers") from exc
        if parsed.parity not in ("N", "E", "O") or parsed.stopbits not in (1, 2) or parsed.bytesize not in (7, 8):
            raise ValueError(f"{url!r}: parity must be N/E/O, stopbits 1/2, bytesize 7/8")
        return parsed
    raise ValueError(f"{url!r}: scheme must be modbus-tcp:// or modbus-rtu://")


def open_led_sphere_modbus(url: str, *, device_id: int = 1, timeout_s: float = 1.0,
                           **limits: float) -> LedSphereModbus:
    """Open a pymodbus client for ``url`` (no retries: a request is sent once), connect it and wrap it.

    ``limits``: ``max_total_current_a``, ``max_mean_duty`` (required), ``led_current_a_per_channel``.
    Raises :class:`ConnectionLost` naming the URL if it cannot connect.
    """
    u = parse_modbus_url(url)
    client: ModbusTcpClient | ModbusSerialClient
    if u.kind == "tcp":
        client = ModbusTcpClient(u.host, port=u.port, timeout=timeout_s, retries=0, reconnect_delay=0)
    else:
        client = ModbusSerialClient(u.device, framer=FramerType.RTU, baudrate=u.baudrate, parity=u.parity,
                                    stopbits=u.stopbits, bytesize=u.bytesize, timeout=timeout_s, retries=0,
                                    reconnect_delay=0)
    driver = LedSphereModbus(client, device_id=device_id, timeout_s=timeout_s, **limits)
    try:
        connected = client.connect()
    except Exception as exc:  # noqa: BLE001 - pyserial/termios raise many types
        raise ConnectionLost(f"cannot open Modbus device {url!r}: {exc}") from exc
    if not connected:
        client.close()
        raise ConnectionLost(f"cannot open Modbus device {url!r}")
    return driver
