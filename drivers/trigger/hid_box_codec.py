"""Sans-IO codec of the USB HID trigger box (``docs/protocols/trigger-boxes.md``): the 16-byte output (command) and
input (status) reports, packed and checked byte by byte. Never touches a device; shared by the driver
(:mod:`drivers.trigger.hid_box`) and ``simulators.trigger``.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

from ..errors import ProtocolError

REPORT_SIZE = 16
OUT_REPORT_ID = 0x01
IN_REPORT_ID = 0x02

CMD_FIRE = 0x01
CMD_SET_BULB = 0x02
CMD_ENABLE = 0x03
CMD_GET_STATUS = 0x04
COMMAND_NAMES = {CMD_FIRE: "FIRE", CMD_SET_BULB: "SET_BULB", CMD_ENABLE: "ENABLE", CMD_GET_STATUS: "GET_STATUS"}

RESULT_OK = 0
RESULT_UNKNOWN_COMMAND = 1
RESULT_BAD_ARGUMENT = 2
RESULT_BUSY = 3
RESULT_NO_BULB = 4
RESULT_NAMES = {RESULT_OK: "OK", RESULT_UNKNOWN_COMMAND: "UNKNOWN_COMMAND", RESULT_BAD_ARGUMENT: "BAD_ARGUMENT",
                RESULT_BUSY: "BUSY", RESULT_NO_BULB: "NO_BULB"}

FLAG_BUSY = 0x01
OUTPUT_COUNT = 6
ALL_OUTPUTS = (1 << OUTPUT_COUNT) - 1
U32_MAX = 0xFFFF_FFFF

_OUT = struct.Struct("<BBBI9x")          # id, command, seq, arg, reserved
_IN = struct.Struct("<BBBIBBIBBx")       # id, seq, result, shots, flags, mask, bulb_ms, fw major, fw minor
assert _OUT.size == REPORT_SIZE and _IN.size == REPORT_SIZE


@dataclass(frozen=True)
class OutputReport:
    command: int
    seq: int
    arg: int = 0


@dataclass(frozen=True)
class StatusReport:
    """The box's input report: the answer to any command, and its status."""

    seq: int
    result: int
    shot_count: int
    busy: bool
    enabled_mask: int
    bulb_ms: int
    firmware: tuple[int, int]

    @property
    def result_name(self) -> str:
        return RESULT_NAMES.get(self.result, "UNKNOWN")


def encode_output(report: OutputReport) -> bytes:
    """The 16 bytes the host writes for ``report``."""
    if report.command not in COMMAND_NAMES:
        raise ValueError(f"unknown HID trigger command 0x{report.command:02x}")
    if not 0 <= report.seq <= 0xFF:
        raise ValueError(f"sequence number must be 0..255, got {report.seq}")
    if not 0 <= report.arg <= U32_MAX:
        raise ValueError(f"argument must fit in u32, got {report.arg}")
    return _OUT.pack(OUT_REPORT_ID, report.command, report.seq, report.arg)


def _check_size(data: bytes, what: str) -> bytes:
    data = bytes(data)
    if len(data) != REPORT_SIZE:
        raise ProtocolError(f"{what} must be {REPORT_SIZE} bytes, got {len(data)}: {data[:16].hex(' ')}")
    return data


def decode_output(data: bytes) -> OutputReport:
    """Parse an output report (the box's side). Unknown commands are *not* a framing error: the box answers
    them with ``UNKNOWN_COMMAND``; bad framing (size, report id, reserved bytes) raises :class:`ProtocolError`."""
    data = _check_size(data, "output report")
    if data[0] != OUT_REPORT_ID:
        raise ProtocolError(f"output report id 0x{data[0]:02x}, expected 0x{OUT_REPORT_ID:02x}")
    if any(data[7:]):
        raise ProtocolError(f"output report reserved bytes not zero: {data.hex(' ')}")
    _, command, seq, arg = _OUT.unpack(data)
    return OutputReport(command, seq, arg)


def encode_status(status: StatusReport) -> bytes:
    """The 16 bytes the box sends for ``status``."""
    if not 0 <= status.enabled_mask <= ALL_OUTPUTS:
        raise ValueError(f"enabled mask must use bits 0..{OUTPUT_COUNT - 1}, got 0x{status.enabled_mask:x}")
    return _IN.pack(IN_REPORT_ID, status.seq, status.result, status.shot_count,
                    FLAG_BUSY if status.busy else 0, status.enabled_mask, status.bulb_ms, *status.firmware)


def decode_status(data: bytes) -> StatusReport:
    """Parse an input report; :class:`ProtocolError` for a wrong size, report id or non-zero reserved bits."""
    data = _check_size(data, "input report")
    if data[0] != IN_REPORT_ID:
        raise ProtocolError(f"input report id 0x{data[0]:02x}, expected 0x{IN_REPORT_ID:02x}")
    _, seq, result, shots, flags, mask, bulb_ms, fw_major, fw_minor = _IN.unpack(data)
    if flags & ~FLAG_BUSY or mask & ~ALL_OUTPUTS or data[15]:
        raise ProtocolError(f"input report reserved bits set: {data.hex(' ')}")
    return StatusReport(seq, result, shots, bool(flags & FLAG_BUSY), mask, bulb_ms, (fw_major, fw_minor))
