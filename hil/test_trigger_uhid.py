"""HidTrigger through real hidapi (hidraw backend) and the Linux HID stack, against a virtual trigger box.

``/dev/uhid`` lets user space create a real HID device: the kernel parses our report descriptor (the report
layout of ``docs/protocols/trigger-boxes.md``, section "USB HID box"), makes a ``/dev/hidrawN`` node, passes
every output report the host writes to us as ``UHID_OUTPUT`` and delivers the input reports we write
(``UHID_INPUT2``) to the hidraw reader. The box's behaviour is ``simulators.trigger.FakeHidTriggerBox``: here
it sits behind the kernel instead of at the driver's ``HidTransport`` seam, so the driver's bytes really cross
hidapi, hidraw, HID core and uhid.

The wheel's ``hid`` module uses libusb, which cannot see a virtual device; these tests open the node with the
wheel's ``hidraw`` module and hand the opened device to ``HidapiTransport``.

Skipped (with the reason) when ``/dev/uhid`` is absent (kernel without uhid, module not loaded - try
``modprobe uhid`` - or a container without the device), not writable (needs root or a udev rule), when the
kernel refuses the device, no hidraw node appears, or hidapi cannot open it.
"""
from __future__ import annotations

import errno
import glob
import os
import select
import struct
import threading
import time
from pathlib import Path

import pytest

from drivers.errors import ConnectionLost, DeviceRejected, DeviceTimeout
from drivers.trigger import hid_box as hc
from drivers.trigger.hid_box import HidapiTransport, HidTrigger
from simulators.trigger import FakeHidTriggerBox

UHID_PATH = "/dev/uhid"

# <linux/uhid.h> event types and sizes (all structs are packed, little-endian on x86/arm)
UHID_DESTROY, UHID_START, UHID_STOP, UHID_OPEN, UHID_CLOSE, UHID_OUTPUT = 1, 2, 3, 4, 5, 6
UHID_GET_REPORT, UHID_GET_REPORT_REPLY, UHID_CREATE2, UHID_INPUT2 = 9, 10, 11, 12
UHID_SET_REPORT, UHID_SET_REPORT_REPLY = 13, 14
UHID_FEATURE_REPORT, UHID_OUTPUT_REPORT, UHID_INPUT_REPORT = 0, 1, 2
UHID_DATA_MAX = 4096
HID_MAX_DESCRIPTOR_SIZE = 4096
BUS_USB = 0x03
_CREATE2 = struct.Struct(f"<I128s64s64sHHIIII{HID_MAX_DESCRIPTOR_SIZE}s")   # type + uhid_create2_req
_INPUT2 = struct.Struct(f"<IH{UHID_DATA_MAX}s")                            # type + uhid_input2_req
_OUTPUT = struct.Struct(f"<I{UHID_DATA_MAX}sHB")                           # type + uhid_output_req
_GET_REPORT = struct.Struct("<IIBB")                                       # type + uhid_get_report_req
_GET_REPORT_REPLY = struct.Struct(f"<IIHH{UHID_DATA_MAX}s")
_SET_REPORT = struct.Struct(f"<IIBBH{UHID_DATA_MAX}s")
_SET_REPORT_REPLY = struct.Struct("<IIH")
assert _CREATE2.size == 4 + 4372 and _OUTPUT.size == 4 + 4099 and _INPUT2.size == 4 + 4098

# Report descriptor of the trigger box (docs/protocols/trigger-boxes.md): vendor page, 8-bit fields,
# output report 0x01 and input report 0x02 of 15 data bytes each (16 with the report id).
REPORT_DESCRIPTOR = bytes([
    0x06, 0x00, 0xFF,        # Usage Page (Vendor Defined 0xFF00)
    0x09, 0x01,              # Usage (0x01: trigger box)
    0xA1, 0x01,              # Collection (Application)
    0x15, 0x00,              #   Logical Minimum (0)
    0x26, 0xFF, 0x00,        #   Logical Maximum (255)
    0x75, 0x08,              #   Report Size (8)
    0x85, hc.OUT_REPORT_ID,  #   Report ID (0x01): host -> box
    0x95, hc.REPORT_SIZE - 1,  # Report Count (15)
    0x09, 0x02,              #   Usage (0x02: command)
    0x91, 0x02,              #   Output (Data, Var, Abs)
    0x85, hc.IN_REPORT_ID,   #   Report ID (0x02): box -> host
    0x95, hc.REPORT_SIZE - 1,  # Report Count (15)
    0x09, 0x03,              #   Usage (0x03: status)
    0x81, 0x02,              #   Input (Data, Var, Abs)
    0xC0,                    # End Collection
])

NAME = "sssrig uhid trigger box"
VENDOR_ID, PRODUCT_ID = 0x1209, 0x5353          # pid.codes test range


class UhidTriggerBox:
    """The device side of a virtual HID trigger box on an open ``/dev/uhid`` file descriptor.

    A thread answers the kernel's events: each ``UHID_OUTPUT`` report goes to ``model`` (a
    :class:`FakeHidTriggerBox`), whose queued answers are written back as ``UHID_INPUT2`` input reports.
    The box has no feature reports: ``UHID_GET_REPORT`` / ``UHID_SET_REPORT`` are answered at once with EIO
    (a USB device would stall), so the kernel never waits for its 5 s timeout. ``outputs`` keeps the raw
    output reports, ``events`` the other event types seen.
    """

    def __init__(self, fd: int, model: FakeHidTriggerBox, *, uniq: str) -> None:
        self.fd = fd
        self.model = model
        self.uniq = uniq
        self.outputs: list[bytes] = []
        self.events: list[int] = []
        self.errors: list[BaseException] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="uhid-box", daemon=True)
        self._destroyed = False
        self.hid_device: object = None          # the host side's opened hidraw device (set by the fixture)

    def create(self) -> None:
        os.write(self.fd, _CREATE2.pack(UHID_CREATE2, NAME.encode(), b"sssrig-uhid", self.uniq.encode(),
                                        len(REPORT_DESCRIPTOR), BUS_USB, VENDOR_ID, PRODUCT_ID, 0x0100, 0,
                                        REPORT_DESCRIPTOR))
        self._thread.start()

    def _send_input(self, report: bytes) -> None:
        os.write(self.fd, _INPUT2.pack(UHID_INPUT2, len(report), report))

    def _handle(self, event: bytes) -> None:
        (kind,) = struct.unpack_from("<I", event)
        if kind == UHID_OUTPUT:
            _, data, size, rtype = _OUTPUT.unpack_from(event.ljust(_OUTPUT.size, b"\0"))
            report = data[:size]
            self.outputs.append(report)
            if rtype == UHID_OUTPUT_REPORT:
                self.model.write(report)
                while answer := self.model.read(hc.REPORT_SIZE, 0):
                    self._send_input(answer)
        elif kind == UHID_GET_REPORT:
            _, req_id, _rnum, _rtype = _GET_REPORT.unpack_from(event)
            os.write(self.fd, _GET_REPORT_REPLY.pack(UHID_GET_REPORT_REPLY, req_id, errno.EIO, 0, b""))
        elif kind == UHID_SET_REPORT:
            req_id = struct.unpack_from("<I", event, 4)[0]
            os.write(self.fd, _SET_REPORT_REPLY.pack(UHID_SET_REPORT_REPLY, req_id, errno.EIO))
        else:
            self.events.append(kind)

    def _serve(self) -> None:
        poller = select.poll()
        poller.register(self.fd, select.POLLIN)
        while not self._stop.is_set():
            if not poller.poll(50):
                continue
            try:
                event = os.read(self.fd, 2 * UHID_DATA_MAX + 512)
            except BlockingIOError:
                continue
            except OSError as exc:
                self.errors.append(exc)
                return
            if not event:
                return
            try:
                self._handle(event)
            except Exception as exc:  # noqa: BLE001 - reported by the fixture
                self.errors.append(exc)

    def destroy(self) -> None:
        """Unplug the virtual box (the hidraw node goes away)."""
        if not self._destroyed:
            self._destroyed = True
            os.write(self.fd, struct.pack("<I", UHID_DESTROY))

    def close(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=2)
        try:
            self.destroy()
        except OSError:
            pass


def _hidraw_node(uniq: str, timeout_s: float = 5.0) -> str | None:
    """The /dev/hidrawN whose HID device carries ``uniq`` (HID_UNIQ in its uevent), once it exists."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for uevent in glob.glob("/sys/class/hidraw/hidraw*/device/uevent"):
            try:
                text = Path(uevent).read_text()
            except OSError:
                continue
            if f"HID_UNIQ={uniq}\n" in text + "\n":
                node = "/dev/" + Path(uevent).parents[1].name
                if os.path.exists(node):
                    return node
        time.sleep(0.02)
    return None


@pytest.fixture
def uhid_box():
    """(trigger, box): a HidTrigger on real hidapi/hidraw, talking to a fresh virtual box."""
    if not os.path.exists(UHID_PATH):
        pytest.skip(f"{UHID_PATH} is absent: kernel without uhid or module not loaded (try `modprobe uhid`), "
                    "or a container without the device")
    try:
        fd = os.open(UHID_PATH, os.O_RDWR | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError as exc:
        pytest.skip(f"{UHID_PATH} is not writable here ({exc}); run as root or add a udev rule")
    try:
        import hidraw  # hidapi's hidraw backend (the wheel's `hid` module is libusb and cannot see uhid)
    except ImportError as exc:
        os.close(fd)
        pytest.skip(f"hidapi's hidraw backend is not importable: {exc}")
    uniq = f"UHID-{os.getpid()}-{time.monotonic_ns() % 10**9}"
    box = UhidTriggerBox(fd, FakeHidTriggerBox(manufacturer="", product=NAME, serial=uniq), uniq=uniq)
    try:
        try:
            box.create()
        except OSError as exc:
            pytest.skip(f"the kernel refused UHID_CREATE2: {exc}")
        node = _hidraw_node(uniq)
        if node is None:
            pytest.skip("uhid device created but no /dev/hidraw node appeared (kernel without hidraw?)")
        dev = hidraw.device()
        try:
            dev.open_path(node.encode())
        except (OSError, ValueError) as exc:
            pytest.skip(f"hidapi (hidraw) cannot open {node}: {exc}")
        box.hid_device = dev
        transport = HidapiTransport(dev, description=f"uhid {node}")
        trigger = HidTrigger(transport, timeout_s=1.0, name=f"hid-trigger {node}")
        try:
            yield trigger, box
        finally:
            trigger.close()
        assert box.errors == [], box.errors
    finally:
        box.close()
        os.close(fd)


def test_identify_reads_the_usb_strings_and_firmware_through_hidraw(uhid_box):
    trigger, box = uhid_box
    ident = trigger.identify()
    assert NAME in ident.model and ident.serial_number == box.uniq
    assert ident.firmware == "1.0" and ident.extra["protocol"] == "sssrig-hid-trigger"
    assert box.outputs == [hc.encode_output(hc.OutputReport(hc.CMD_GET_STATUS, 1))]


def test_fire_sends_the_documented_reports_and_fires_once(uhid_box):
    trigger, box = uhid_box
    t0 = time.monotonic()
    trigger.fire(0.25)
    assert time.monotonic() - t0 >= 0.25
    assert box.model.fired == [0.25] and box.model.shots == 1
    # the golden example of the protocol document, byte for byte, as the kernel handed it to the device
    pad = bytes(9)
    assert box.outputs[:3] == [bytes.fromhex("01 03 01 3f 00 00 00") + pad,
                               bytes.fromhex("01 02 02 fa 00 00 00") + pad,
                               bytes.fromhex("01 01 03 00 00 00 00") + pad]
    assert all(r[:2] == b"\x01\x04" for r in box.outputs[3:])      # then GET_STATUS until not busy
    assert [r.command for r in box.model.received[:3]] == [hc.CMD_ENABLE, hc.CMD_SET_BULB, hc.CMD_FIRE]


def test_refusal_carries_the_box_code(uhid_box):
    trigger, box = uhid_box
    box.model.error_next = hc.RESULT_BAD_ARGUMENT
    with pytest.raises(DeviceRejected) as err:
        trigger.fire(0.01)
    assert err.value.code == hc.RESULT_BAD_ARGUMENT and err.value.name == "BAD_ARGUMENT"
    assert box.model.fired == []


def test_silent_box_times_out_and_stale_reports_are_skipped(uhid_box):
    trigger, box = uhid_box
    box.model.mute = True
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        trigger.identify()
    assert 1.0 <= time.monotonic() - t0 < 3.0
    box.model.mute = False
    box.model.stale_next = 2                     # two input reports with old sequence numbers come first
    assert trigger.status().seq == 2


def test_feature_report_requests_are_answered_not_left_to_time_out(uhid_box):
    trigger, box = uhid_box
    dev = box.hid_device
    t0 = time.monotonic()
    try:
        dev.get_feature_report(hc.OUT_REPORT_ID, hc.REPORT_SIZE)
    except (OSError, ValueError):
        pass                                     # the box has no feature reports: EIO, as a stall would
    assert time.monotonic() - t0 < 2.0           # the kernel's own timeout would be 5 s
    assert trigger.status().result == hc.RESULT_OK


def test_unplugged_box_is_connection_lost(uhid_box):
    trigger, box = uhid_box
    trigger.identify()
    box.destroy()
    time.sleep(0.2)
    with pytest.raises(ConnectionLost):          # hidraw refuses the write with ENODEV
        trigger.fire(0.01)
    assert box.model.fired == []
