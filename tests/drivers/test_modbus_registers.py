"""The LED sphere's Modbus register map: consistency of registers.py and of the protocol document."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymodbus.constants import ExcCodes

from drivers.led_sphere_modbus import registers as rm

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocols" / "led-sphere-modbus.md"


def _section(text: str, name: str) -> list[list[str]]:
    """Rows (cells stripped) of the Markdown table between the section markers, header excluded."""
    body = text.split(f"<!-- {name}:begin -->", 1)[1].split(f"<!-- {name}:end -->", 1)[0]
    lines = [ln.strip() for ln in body.strip().splitlines()]
    assert lines and all(ln.startswith("|") and ln.endswith("|") for ln in lines), body
    rows = [[c.strip() for c in ln[1:-1].split("|")] for ln in lines]
    assert re.fullmatch(r"(-{3,}\|?)+", "|".join(rows[1])), "second line must be the |---| rule"
    return [rows[0]] + rows[2:]


def _span(cell: str) -> tuple[int, int]:
    first, _, last = cell.partition("-")
    return int(first, 0), int(last or first, 0)


# -- the map itself -------------------------------------------------------------------------------------

def test_registers_do_not_overlap_and_names_are_unique() -> None:
    ordered = sorted(rm.REGISTERS, key=lambda r: r.address)
    for a, b in zip(ordered, ordered[1:]):
        assert a.end <= b.address, f"{a.name} ({a.address}..{a.end - 1}) overlaps {b.name} ({b.address})"
    assert len({r.name for r in rm.REGISTERS}) == len(rm.REGISTERS)
    assert all(0 <= r.address and r.end <= 0x10000 and r.count >= 1 for r in rm.REGISTERS)


def test_each_block_is_contiguous_and_fits_one_read() -> None:
    assert {r.block for r in rm.REGISTERS} == set(rm.BLOCKS)
    for block in rm.BLOCKS:
        first, count = rm.block_span(block)
        regs = sorted((r for r in rm.REGISTERS if r.block == block), key=lambda r: r.address)
        assert sum(r.count for r in regs) == count, f"block {block} has holes"
        if block != "upload":
            assert count <= rm.MAX_READ_REGISTERS, f"block {block} needs more than one FC03"
    spans = sorted(rm.block_span(b) for b in rm.BLOCKS)
    for (a, n), (b, _) in zip(spans, spans[1:]):
        assert a + n < b, "blocks must be separated by unmapped gaps (reads across blocks fail with 2)"


def test_upload_registers_allow_slot_offset_and_full_window_in_one_fc16() -> None:
    slot, offset, window, commit = (rm.reg(n) for n in
                                    ("UPLOAD_SLOT", "UPLOAD_OFFSET", "UPLOAD_WINDOW", "UPLOAD_COMMIT"))
    assert offset.address == slot.end and window.address == offset.end and commit.address == window.end
    assert window.count == rm.WINDOW_REGISTERS and rm.WINDOW_REGISTERS % rm.CHANNELS == 0
    assert 2 + window.count <= rm.MAX_WRITE_REGISTERS


def test_access_of_commands_and_status() -> None:
    assert all(r.access is rm.Access.R for r in rm.REGISTERS if r.block in ("identity", "status"))
    for name in ("ALL_OFF", "CLEAR_FAULTS", "UPLOAD_COMMIT"):
        assert rm.reg(name).access is rm.Access.W
    for name in ("SELECT_SLOT", "POLARIZATION", "WATCHDOG_MS", "UPLOAD_SLOT", "UPLOAD_OFFSET", "UPLOAD_WINDOW"):
        assert rm.reg(name).access is rm.Access.RW


def test_exception_codes_equal_pymodbus_codes() -> None:
    assert rm.ExceptionCode.ILLEGAL_DATA_ADDRESS == ExcCodes.ILLEGAL_ADDRESS == 2
    assert rm.ExceptionCode.ILLEGAL_DATA_VALUE == ExcCodes.ILLEGAL_VALUE == 3
    assert rm.ExceptionCode.SERVER_DEVICE_FAILURE == ExcCodes.DEVICE_FAILURE == 4
    assert rm.ExceptionCode.SERVER_DEVICE_BUSY == ExcCodes.DEVICE_BUSY == 6


# -- value coding ---------------------------------------------------------------------------------------

@given(st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=127), max_size=16))
def test_ascii_round_trip(text: str) -> None:
    regs = rm.encode_ascii(text, 8)
    assert len(regs) == 8 and all(0 <= r <= 0xFFFF for r in regs)
    assert rm.decode_ascii(regs) == text


def test_ascii_packs_first_char_in_high_byte() -> None:
    assert rm.encode_ascii("SSS-", 2) == [0x5353, 0x532D]
    assert rm.encode_ascii("A", 2) == [0x4100, 0x0000]
    with pytest.raises(ValueError):
        rm.encode_ascii("too long", 3)


@given(st.integers(-0x8000, 0x7FFF))
def test_i16_round_trip(value: int) -> None:
    raw = rm.from_i16(value)
    assert 0 <= raw <= 0xFFFF and rm.to_i16(raw) == value


def test_i16_known_values() -> None:
    assert rm.from_i16(-1) == 0xFFFF and rm.to_i16(0x8000) == -0x8000 and rm.to_i16(2534) == 2534
    with pytest.raises(ValueError):
        rm.from_i16(0x8000)


# -- the document ----------------------------------------------------------------------------------------

def test_document_tables_are_generated_from_registers_py() -> None:
    text = DOC.read_text(encoding="utf-8")
    assert rm.render_document(text) == text, (
        "docs/protocols/led-sphere-modbus.md is stale: run "
        "python -m drivers.led_sphere_modbus.registers --write docs/protocols/led-sphere-modbus.md")


def test_document_register_table_parses_back_to_the_map() -> None:
    header, *rows = _section(DOC.read_text(encoding="utf-8"), "register-table")
    assert tuple(header) == rm.TABLE_HEADER
    col = {name: i for i, name in enumerate(header)}
    documented = {}
    for row in rows:
        first, last = _span(row[col["Address"]])
        hex_first, hex_last = _span(row[col["Hex"]])
        ref_first, ref_last = _span(row[col["mbpoll -r"]])
        count = int(row[col["Count"]])
        assert (hex_first, hex_last) == (first, last)
        assert (ref_first, ref_last) == (first + 1, last + 1), "mbpoll references are 1-based"
        assert last - first + 1 == count
        unit = row[col["Unit"]]
        documented[row[col["Name"]]] = (first, count, row[col["Type"]], float(row[col["Scale"]]),
                                        "" if unit == "-" else unit, row[col["Access"]])
    expected = {r.name: (r.address, r.count, r.type, r.scale, r.unit, r.access.value) for r in rm.REGISTERS}
    assert documented == expected


def test_document_fault_bits_and_exception_codes_match() -> None:
    text = DOC.read_text(encoding="utf-8")
    _, *bits = _section(text, "fault-bits")
    assert {(int(b), int(m, 16)) for b, m, _ in bits} == {
        (f.bit_length() - 1, int(f)) for f in rm.FAULT_BIT_DESCRIPTIONS}
    assert [int(b) for b, *_ in bits] == [0, 1, 2]     # bit0 over-temp, bit1 watchdog, bit2 LED fault
    assert "over-temperature" in bits[0][2] and "watchdog" in bits[1][2] and "LED fault" in bits[2][2]
    _, *codes = _section(text, "exception-codes")
    assert {int(c) for c, *_ in codes} == {int(c) for c in rm.EXCEPTION_DESCRIPTIONS} >= {2, 3, 4, 6}


def test_document_upload_example_respects_fc16_limit() -> None:
    """The worked example's register counts follow from the map (2 + 3*40, 1 + 3*40, 1 + 3*20)."""
    text = DOC.read_text(encoding="utf-8")
    rows = re.findall(r"^\| (\d) \| (FC\d+) \| (\d+) \| (\d+) \|", text, flags=re.M)
    assert [(fc, int(a), int(n)) for _, fc, a, n in rows] == [
        ("FC16", rm.reg("UPLOAD_SLOT").address, 2 + rm.WINDOW_REGISTERS),
        ("FC16", rm.reg("UPLOAD_OFFSET").address, 1 + rm.WINDOW_REGISTERS),
        ("FC16", rm.reg("UPLOAD_OFFSET").address, 1 + 3 * (100 - 2 * rm.WINDOW_LEDS)),
        ("FC06", rm.reg("UPLOAD_COMMIT").address, 1),
        ("FC06", rm.reg("SELECT_SLOT").address, 1),
    ]
    assert all(int(n) <= rm.MAX_WRITE_REGISTERS for *_, n in rows)
