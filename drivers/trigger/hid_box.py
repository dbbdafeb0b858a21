"""USB HID trigger box: a ``HidTransport`` seam over hidapi and the driver (its sans-IO report codec:
:mod:`drivers.trigger.hid_box_codec`, re-exported here).

Report layout (``docs/protocols/trigger-boxes.md``): both directions use fixed 16-byte reports, the first byte
being the report id (hidapi's convention). Multi-byte fields are little-endian; reserved bytes are zero.

Output report (host -> box), report id ``0x01``::

    0  u8   report id 0x01
    1  u8   command: FIRE 0x01, SET_BULB 0x02, ENABLE 0x03, GET_STATUS 0x04
    2  u8   sequence number (echoed in the answer)
    3  u32  argument: SET_BULB milliseconds (1..2**32-1), ENABLE output mask (bits 0..5), else 0
    7  9 B  reserved, zero

Input report (box -> host), report id ``0x02``, one per output report::

    0  u8   report id 0x02
    1  u8   sequence number of the command answered
    2  u8   result: OK 0, UNKNOWN_COMMAND 1, BAD_ARGUMENT 2, BUSY 3, NO_BULB 4
    3  u32  shot counter (shots fired since power-up)
    7  u8   flags: bit 0 = busy (an exposure is running); bits 1..7 zero
    8  u8   enabled output mask (bits 0..5; bits 6, 7 zero)
    9  u32  bulb time in ms (0 = never set)
    13 u8   firmware major
    14 u8   firmware minor
    15 u8   reserved, zero

The driver talks to a :class:`HidTransport` (``write(bytes)``, ``read(n, timeout_ms)``, ``close()``):
:class:`HidapiTransport` wraps ``hid.device()`` for real boxes; tests use the fake device model in
``simulators.trigger`` at the same seam.
"""
from __future__ import annotations

import math
import threading
import time
from typing import Any, Protocol, runtime_checkable

from ..contracts import DeviceIdentity
from ..errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError, ProtocolError
from .exposure import check_exposure_range, exposure_ms
from .hid_box_codec import (ALL_OUTPUTS, CMD_ENABLE, CMD_FIRE, CMD_GET_STATUS, CMD_SET_BULB, COMMAND_NAMES,
                            FLAG_BUSY, IN_REPORT_ID, OUTPUT_COUNT, OUT_REPORT_ID, OutputReport, REPORT_SIZE,
                            RESULT_BAD_ARGUMENT, RESULT_BUSY, RESULT_NAMES, RESULT_NO_BULB, RESULT_OK,
                            RESULT_UNKNOWN_COMMAND, StatusReport, U32_MAX, decode_output, decode_status,
                            encode_output, encode_status)

__all__ = ['ALL_OUTPUTS', 'CMD_ENABLE', 'CMD_FIRE', 'CMD_GET_STATUS', 'CMD_SET_BULB', 'COMMAND_NAMES', 'FLAG_BUSY',
           'HidTransport', 'HidTrigger', 'HidapiTransport', 'IN_REPORT_ID', 'OUTPUT_COUNT', 'OUT_REPORT_ID',
           'OutputReport', 'REPORT_SIZE', 'RESULT_BAD_ARGUMENT', 'RESULT_BUSY', 'RESULT_NAMES', 'RESULT_NO_BULB',
           'RESULT_OK', 'RESULT_UNKNOWN_COMMAND', 'StatusReport', 'U32_MAX', 'decode_output', 'decode_status',
           'encode_output', 'encode_status', 'open_hid_trigger']


# ------------------------------------------------------------------------------------------- transport
@runtime_checkable
class HidTransport(Protocol):
    """The seam between the driver and a HID device: hidapi for real boxes, a fake model in tests.

    Implementations raise :class:`~drivers.errors.ConnectionLost` when the device is gone.
    """

    def write(self, data: bytes) -> int:
        """Write one report (first byte = report id); return the number of bytes written."""

    def read(self, n: int, timeout_ms: int) -> bytes:
        """Return one input report of at most ``n`` bytes, or ``b""`` when none came within ``timeout_ms``."""

    def close(self) -> None: ...


class HidapiTransport:
    """Thin :class:`HidTransport` over ``hid.device()`` (hidapi 0.15). Open with :meth:`open`."""

    def __init__(self, device: Any, *, description: str = "hid") -> None:
        self._dev = device
        self.description = description
        self.manufacturer = self._string("get_manufacturer_string")
        self.product = self._string("get_product_string")
        self.serial = self._string("get_serial_number_string")

    def _string(self, getter: str) -> str:
        try:
            return str(getattr(self._dev, getter)() or "")
        except (OSError, ValueError, AttributeError):
            return ""

    @classmethod
    def open(cls, vendor_id: int | None = None, product_id: int | None = None, *, serial: str | None = None,
             path: bytes | None = None) -> "HidapiTransport":
        """Open by ``path`` (from ``hid.enumerate``) or by vendor/product id (+ serial number)."""
        import hid  # imported here so the codec and the fakes work without the hidapi wheel

        dev = hid.device()
        what = f"HID device path={path!r}" if path is not None else (
            f"HID device {vendor_id or 0:04x}:{product_id or 0:04x}" + (f" serial {serial}" if serial else ""))
        try:
            if path is not None:
                dev.open_path(path)
            else:
                dev.open(vendor_id or 0, product_id or 0, serial)
        except (OSError, ValueError) as exc:
            raise ConnectionLost(f"cannot open {what}: {exc}") from exc
        return cls(dev, description=what)

    def write(self, data: bytes) -> int:
        try:
            n = self._dev.write(bytes(data))
        except (OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.description}: write failed: {exc}") from exc
        if n < 0:
            raise ConnectionLost(f"{self.description}: write failed: {self._error()}")
        return int(n)

    def read(self, n: int, timeout_ms: int) -> bytes:
        try:
            data = self._dev.read(n, timeout_ms)
        except (OSError, ValueError) as exc:
            raise ConnectionLost(f"{self.description}: read failed: {exc}") from exc
        return bytes(data)

    def _error(self) -> str:
        try:
            return str(self._dev.error())
        except (OSError, ValueError, AttributeError):
            return "unknown error"

    def close(self) -> None:
        try:
            self._dev.close()
        except (OSError, ValueError):
            pass


# ---------------------------------------------------------------------------------------------- driver
class HidTrigger:
    """Driver for the HID trigger box on an injected :class:`HidTransport`; the constructor does no I/O.

    Every command carries a sequence number; input reports with another number (stale answers) are
    skipped. The first :meth:`fire` enables ``outputs_mask`` once. :meth:`fire` sends SET_BULB and FIRE,
    waits for the exposure, then polls GET_STATUS until the box is no longer busy
    (``wait_for_exposure=True``).
    """

    def __init__(self, transport: HidTransport, *, timeout_s: float = 1.0, min_exposure_s: float = 0.001,
                 max_exposure_s: float = 60.0, outputs_mask: int = ALL_OUTPUTS, wait_for_exposure: bool = True,
                 poll_interval_s: float = 0.005, name: str = "hid-trigger") -> None:
        if not 0 <= outputs_mask <= ALL_OUTPUTS:
            raise ValueError(f"outputs_mask must use bits 0..{OUTPUT_COUNT - 1}, got 0x{outputs_mask:x}")
        check_exposure_range(min_exposure_s, max_exposure_s)
        self._t = transport
        self.timeout_s = timeout_s
        self.min_exposure_s = min_exposure_s
        self.max_exposure_s = max_exposure_s
        self.outputs_mask = outputs_mask
        self.wait_for_exposure = wait_for_exposure
        self.poll_interval_s = poll_interval_s
        self.name = name
        self._seq = 0
        self._configured = False
        self._closed = False
        self._lock = threading.RLock()

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _transact(self, command: int, arg: int = 0) -> StatusReport:
        if self._closed:
            raise ConnectionLost(f"{self.name}: trigger is closed")
        seq = self._next_seq()
        what = f"{COMMAND_NAMES[command]}(seq {seq})"
        frame = encode_output(OutputReport(command, seq, arg))
        n = self._t.write(frame)
        if n != len(frame):
            raise ConnectionLost(f"{self.name}: wrote {n} of {len(frame)} bytes of {what}")
        deadline = time.monotonic() + self.timeout_s
        skipped = 0
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"{self.name}: no answer to {what} within {self.timeout_s:.3g} s"
                                    f" ({skipped} stale reports skipped)")
            data = self._t.read(REPORT_SIZE, max(1, math.ceil(remaining * 1000)))
            if not data:
                continue
            try:
                status = decode_status(data)
            except ProtocolError as exc:
                raise ProtocolError(f"{self.name}: garbled answer to {what}: {exc}") from None
            if status.seq != seq:
                skipped += 1
                continue
            if status.result != RESULT_OK:
                cls = DeviceBusy if status.result == RESULT_BUSY else DeviceRejected
                raise cls(f"{self.name}: box refused {what}", status.result, name=status.result_name)
            return status

    def status(self) -> StatusReport:
        with self._lock:
            return self._transact(CMD_GET_STATUS)

    def identify(self) -> DeviceIdentity:
        st = self.status()
        product = getattr(self._t, "product", "") or "HID trigger box"
        maker = getattr(self._t, "manufacturer", "") or ""
        return DeviceIdentity(kind="trigger", model=f"{maker} {product}".strip(),
                              firmware=f"{st.firmware[0]}.{st.firmware[1]}",
                              serial_number=getattr(self._t, "serial", "") or "",
                              extra={"protocol": "sssrig-hid-trigger", "outputs": OUTPUT_COUNT})

    def enable(self, mask: int) -> None:
        if not 0 <= mask <= ALL_OUTPUTS:
            raise LimitError(f"output mask must use bits 0..{OUTPUT_COUNT - 1}, got 0x{mask:x}")
        with self._lock:
            self._transact(CMD_ENABLE, mask)
            self.outputs_mask = mask
            self._configured = True

    def fire(self, exposure_s: float) -> None:
        """Open the shutter for ``exposure_s`` (whole ms); return once the box reports the exposure over."""
        ms = exposure_ms(exposure_s, min_exposure_s=self.min_exposure_s, max_exposure_s=self.max_exposure_s)
        if ms > U32_MAX:
            raise LimitError(f"exposure {exposure_s:g} s is {ms} ms, beyond the box's u32 bulb field")
        with self._lock:
            if not self._configured:
                self.enable(self.outputs_mask)
            self._transact(CMD_SET_BULB, ms)
            t_fire = time.monotonic()
            self._transact(CMD_FIRE)
            if not self.wait_for_exposure:
                return
            end = t_fire + ms / 1000.0
            deadline = end + self.timeout_s
            while True:
                now = time.monotonic()
                if now < end:
                    time.sleep(end - now)
                if not self._transact(CMD_GET_STATUS).busy:
                    return
                if time.monotonic() >= deadline:
                    raise DeviceTimeout(f"{self.name}: still busy {self.timeout_s:.3g} s after a "
                                        f"{ms} ms exposure should have ended")
                time.sleep(self.poll_interval_s)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._t.close()

    def __enter__(self) -> "HidTrigger":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_hid_trigger(vendor_id: int | None = None, product_id: int | None = None, *, serial: str | None = None,
                     path: bytes | None = None, timeout_s: float = 1.0, **kwargs: Any) -> HidTrigger:
    """Open a HID trigger box through hidapi and wrap it in a :class:`HidTrigger` (no command sent yet)."""
    transport = HidapiTransport.open(vendor_id, product_id, serial=serial, path=path)
    return HidTrigger(transport, timeout_s=timeout_s, name=f"hid-trigger {transport.description}", **kwargs)
