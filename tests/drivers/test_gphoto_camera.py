"""gphoto2 camera driver, tested through real libgphoto2 (python-gphoto2 wheel, optional extra ``gphoto``).

Two virtual cameras that ship inside libgphoto2 stand in for hardware:

* "Directory Browse" (camlib ``directory``, port ``disk:<folder>``) exposes a local folder as a camera. It has
  no events and cannot capture: it covers open/identify, the listing fallback of the external mode (a DNG put
  into the folder after ``arm()`` is found by listing and downloaded through libgphoto2), timeouts, and the
  typed error for an unsupported capture.
* The virtual PTP camera of libgphoto2's ``vusb`` port library (``IOLIBS=<wheel>/libgphoto2/vusb``,
  ``VCAMERADIR=<folder>``) is a full PTP stack (autodetected as a Nikon): it covers autodetection, the
  event path of the external mode (``GP_EVENT_FILE_ADDED`` for a file the driver did not ask for), and the
  capture mode (``capture()``). It "captures" by re-serving the first file whose name contains ``.jpg``, so
  the DNG it serves is named ``frame.jpg.dng`` (rawpy and tifffile read the content, not the name).

Without python-gphoto2 these tests are skipped (CI installs only ``.[test]``); the import-error test runs
everywhere.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.camera.gphoto import (GP_ERROR_CAMERA_BUSY, GP_ERROR_IO,
                                   GP_ERROR_NOT_SUPPORTED, GP_ERROR_TIMEOUT, GphotoBusy, GphotoCamera,
                                   GphotoConnectionLost, GphotoError, GphotoTimeout, gphoto_error,
                                   open_gphoto_camera, parse_shutter_speed)
from drivers.camera.raw import RawFileError
from drivers.contracts import Camera, RawFrame
from drivers.errors import ConnectionLost, DeviceBusy, DeviceError, DeviceTimeout
from simulators.dng import write_dng

try:
    import gphoto2 as gp
except ImportError:  # the optional extra is not installed
    gp = None

ROOT = Path(__file__).resolve().parents[2]
needs_gphoto2 = pytest.mark.skipif(
    gp is None, reason="python-gphoto2 is not installed (optional extra: pip install 'sssrig[gphoto]')")
WHITE, BLACK = 16383, 512
LSB = 1.0 / (WHITE - BLACK)          # one DN in linear units: the quantization step of write_dng


def rendering(value: float, h: int = 12, w: int = 12) -> np.ndarray:
    rgb = np.full((h, w, 3), value)
    rgb[0, 0] = (0.25, 0.5, 0.75)
    return rgb


# ------------------------------------------------------------------------------ without the hardware
def test_module_imports_without_gphoto2_and_open_names_the_extra():
    code = ("import sys; sys.modules['gphoto2'] = None\n"
            "import drivers.camera.gphoto as g\n"
            "try:\n    g.open_gphoto_camera()\nexcept ImportError as e:\n    print('ImportError:', e)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "ImportError:" in proc.stdout and "pip install 'sssrig[gphoto]'" in proc.stdout


@pytest.mark.parametrize("text, seconds", [
    ("1/125", 1 / 125), ("0.0100s", 0.01), ("30", 30.0), ('2.5"', 2.5), ("1/4000s", 1 / 4000),
    ("bulb", None), ("Bulb", None), ("auto", None), ("", None), (None, None), ("1/0", None), ("0", None),
])
def test_parse_shutter_speed(text, seconds):
    got = parse_shutter_speed(text)
    assert got == pytest.approx(seconds) if seconds is not None else got is None


class _Err(Exception):
    def __init__(self, code: int, string: str) -> None:
        super().__init__(f"[{code}] {string}")
        self.code, self.string = code, string


@pytest.mark.parametrize("code, cls, builtin", [
    (GP_ERROR_TIMEOUT, GphotoTimeout, TimeoutError),
    (GP_ERROR_IO, GphotoConnectionLost, ConnectionError),
    (-52, GphotoConnectionLost, ConnectionError),          # GP_ERROR_IO_USB_FIND: camera unplugged
    (GP_ERROR_NOT_SUPPORTED, GphotoError, Exception),
    (-113, GphotoError, Exception),                         # GP_ERROR_CAMERA_ERROR
])
def test_gphoto2_result_codes_become_typed_errors_with_the_code(code, cls, builtin):
    err = gphoto_error(_Err(code, "some text"), "cam: do it")
    assert type(err) is cls and isinstance(err, builtin) and isinstance(err, DeviceError)
    assert err.code == code and f"gphoto2 error {code}" in str(err) and "some text" in str(err)


def test_busy_camera_is_device_busy_with_the_code():
    err = gphoto_error(_Err(GP_ERROR_CAMERA_BUSY, "Camera busy"), "cam: capture")
    assert isinstance(err, GphotoBusy) and isinstance(err, DeviceBusy) and err.code == GP_ERROR_CAMERA_BUSY


# --------------------------------------------------------------------- "Directory Browse" virtual camera
@pytest.fixture
def browse(tmp_path):
    """A "Directory Browse" camera on an empty folder; frames download into tmp_path/dl."""
    card = tmp_path / "card"
    card.mkdir()
    cam = open_gphoto_camera(port=f"disk:{card}", model="Directory Browse", download_dir=tmp_path / "dl",
                             poll_s=0.02)
    try:
        yield cam, card
    finally:
        cam.close()


@needs_gphoto2
def test_directory_browse_identifies_and_satisfies_the_camera_contract(browse):
    cam, card = browse
    assert isinstance(cam, Camera)
    ident = cam.identify()
    assert ident.kind == "camera" and ident.model == "Directory Browse"
    assert ident.extra["port"] == f"disk:{card}" and ident.extra["camlib"] == "directory"
    assert ident.extra["capture_mode"] == "external"


@needs_gphoto2
def test_directory_browse_delivers_a_dng_written_after_arm(browse, tmp_path):
    cam, card = browse
    write_dng(card / "old.dng", rendering(0.9), exposure_s=0.5)       # present at arm(): not a frame
    cam.arm()

    def camera_writes_frame():
        time.sleep(0.2)
        write_dng(card / "DSC_0001.dng", rendering(0.5), exposure_s=0.02)

    writer = threading.Thread(target=camera_writes_frame)
    writer.start()
    try:
        frame = cam.fetch(5.0)
    finally:
        writer.join()
    assert isinstance(frame, RawFrame)
    np.testing.assert_allclose(frame.rgb, rendering(0.5), atol=LSB)
    assert frame.exposure_s == pytest.approx(0.02)
    assert frame.metadata["file_name"] == "DSC_0001.dng" and frame.metadata["camera_folder"] == "/"
    assert frame.metadata["camera_model"] == "Directory Browse"
    assert frame.metadata["camera_port"] == f"disk:{card}" and frame.metadata["capture_mode"] == "external"
    assert frame.metadata["shutterspeed"] is None        # this camlib has no settings
    # downloaded through libgphoto2 into the download folder, byte for byte
    assert Path(frame.path) == tmp_path / "dl" / "DSC_0001.dng"
    assert Path(frame.path).read_bytes() == (card / "DSC_0001.dng").read_bytes()
    # the old file never comes, the new one only once
    with pytest.raises(DeviceTimeout):
        cam.fetch(0.3)


@needs_gphoto2
def test_directory_browse_finds_frames_in_subfolders_oldest_name_first(browse):
    cam, card = browse
    cam.arm()
    (card / "DCIM" / "100NIKON").mkdir(parents=True)
    write_dng(card / "DCIM" / "100NIKON" / "b.dng", rendering(0.25), exposure_s=0.01)
    write_dng(card / "a.dng", rendering(0.75), exposure_s=0.01)
    first, second = cam.fetch(5.0), cam.fetch(5.0)
    assert {first.metadata["file_name"], second.metadata["file_name"]} == {"a.dng", "b.dng"}
    by_name = {f.metadata["file_name"]: f for f in (first, second)}
    assert by_name["b.dng"].metadata["camera_folder"] == "/DCIM/100NIKON"
    np.testing.assert_allclose(by_name["b.dng"].rgb, rendering(0.25), atol=LSB)


@needs_gphoto2
def test_directory_browse_times_out_without_a_new_file(browse):
    cam, _ = browse
    cam.arm()
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="no new file in the camera's listing"):
        cam.fetch(0.3)
    assert 0.3 <= time.monotonic() - t0 < 3.0


@needs_gphoto2
def test_pattern_ignores_other_files(browse):
    cam, card = browse
    cam.pattern = "*.dng"
    cam.arm()
    (card / "DSC_0001.JPG").write_bytes(b"\xff\xd8\xff\xe0 not a raw")
    with pytest.raises(DeviceTimeout):
        cam.fetch(0.3)


@needs_gphoto2
def test_undecodable_download_is_a_raw_file_error_naming_the_local_copy(browse, tmp_path):
    cam, card = browse
    cam.arm()
    (card / "broken.dng").write_bytes(b"II*\x00" + b"\x00" * 64)
    with pytest.raises(RawFileError) as err:
        cam.fetch(5.0)
    assert str(tmp_path / "dl" / "broken.dng") in str(err.value)


@needs_gphoto2
def test_directory_browse_cannot_capture_typed_error_with_code(browse):
    cam, _ = browse
    cam.capture_mode = "capture"
    cam.arm()
    with pytest.raises(GphotoError) as err:
        cam.fetch(1.0)
    assert err.value.code == GP_ERROR_NOT_SUPPORTED and isinstance(err.value, DeviceError)


@needs_gphoto2
def test_fetch_before_arm_and_after_close(browse):
    cam, _ = browse
    with pytest.raises(RuntimeError, match="before arm"):
        cam.fetch(0.1)
    cam.close()
    cam.close()                      # idempotent
    with pytest.raises(ConnectionLost):
        cam.arm()


@needs_gphoto2
def test_opening_a_missing_folder_or_an_absent_camera_is_connection_lost(tmp_path):
    with pytest.raises(GphotoConnectionLost) as err:
        open_gphoto_camera(port=f"disk:{tmp_path / 'absent'}", model="Directory Browse")
    assert isinstance(err.value, ConnectionError) and isinstance(err.value.code, int)
    with pytest.raises(GphotoConnectionLost, match="no camera for model 'No Such Camera'"):
        open_gphoto_camera(model="No Such Camera")


def test_capture_mode_is_validated():
    with pytest.raises(ValueError, match="capture_mode"):
        GphotoCamera(object(), sys, capture_mode="sometimes")


# ----------------------------------------------------------------------- libgphoto2's virtual PTP camera
@pytest.fixture
def vcam_dir(tmp_path, monkeypatch):
    """A virtual PTP camera serving tmp_path/vcam: write files into the returned DCIM folder before opening."""
    if gp is None:
        pytest.skip("python-gphoto2 is not installed (optional extra: pip install 'sssrig[gphoto]')")
    vusb = Path(gp.__file__).parent / "libgphoto2" / "vusb"
    if not vusb.is_dir():
        pytest.skip(f"this python-gphoto2 build has no virtual USB camera ({vusb} missing)")
    root = tmp_path / "vcam"
    dcim = root / "DCIM" / "100SSSRG"       # the virtual camera needs a DCIM folder to "capture" into
    dcim.mkdir(parents=True)
    monkeypatch.setenv("VCAMERADIR", str(root))
    monkeypatch.setenv("IOLIBS", str(vusb))    # read by libgphoto2 each time it loads the port list
    return dcim


def _camera_reports_new_file(cam: GphotoCamera) -> None:
    """What a camera fired by our trigger box does: it reports a new object that gphoto2 did not ask for.
    The virtual camera's PTP opcode 0x9999 (sent through ptp2's ``opcode`` setting) queues ObjectAdded."""
    widget = cam.gp_camera.get_single_config("opcode")
    widget.set_value("0x9999,0x0,0x0")
    cam.gp_camera.set_single_config("opcode", widget)


def _gphoto2_trigger_capture(cam: GphotoCamera) -> None:
    cam.gp_camera.trigger_capture()


@needs_gphoto2
def test_virtual_ptp_camera_is_autodetected_and_identified(vcam_dir, tmp_path):
    write_dng(vcam_dir / "frame.jpg.dng", rendering(0.5), exposure_s=0.02)
    detected = gp.Camera.autodetect()
    assert detected.count() == 1
    with open_gphoto_camera(download_dir=tmp_path / "dl") as cam:
        ident = cam.identify()
    assert ident.model == detected.get_name(0) and ident.extra["port"] == detected.get_value(0)
    assert ident.extra["camlib"] == "ptp2" and ident.extra["manufacturer"] == "GP"
    assert ident.serial_number and ident.firmware


@needs_gphoto2
@pytest.mark.parametrize("shutter", [_camera_reports_new_file, _gphoto2_trigger_capture],
                         ids=["camera-reports-object", "gphoto2-trigger-capture"])
def test_external_mode_waits_for_file_added_and_downloads_it(vcam_dir, tmp_path, shutter):
    write_dng(vcam_dir / "frame.jpg.dng", rendering(0.5), exposure_s=0.02)
    with open_gphoto_camera(download_dir=tmp_path / "dl") as cam:
        cam.arm()
        shutter(cam)
        frame = cam.fetch(5.0)
        np.testing.assert_allclose(frame.rgb, rendering(0.5), atol=LSB)
        assert frame.exposure_s == pytest.approx(0.02)               # the file's EXIF wins
        assert re.fullmatch(r"GPH_\d{4}\.JPG", frame.metadata["file_name"])
        assert frame.metadata["camera_folder"].startswith("/store_00010001/DCIM/")
        assert frame.metadata["shutterspeed"] == "0.0100s"           # the camera's setting at arm()
        assert frame.metadata["camera_serial"] == cam.identify().serial_number
        assert Path(frame.path).read_bytes() == (vcam_dir / "frame.jpg.dng").read_bytes()
        with pytest.raises(DeviceTimeout, match="no event"):          # one shot, one frame
            cam.fetch(0.3)


@needs_gphoto2
def test_external_mode_discards_files_reported_before_arm(vcam_dir, tmp_path):
    write_dng(vcam_dir / "frame.jpg.dng", rendering(0.5), exposure_s=0.02)
    with open_gphoto_camera(download_dir=tmp_path / "dl") as cam:
        _camera_reports_new_file(cam)
        time.sleep(0.2)
        cam.arm()
        with pytest.raises(DeviceTimeout):
            cam.fetch(0.5)
        assert not (tmp_path / "dl").exists() or not any((tmp_path / "dl").iterdir())


@needs_gphoto2
def test_external_mode_ignores_files_not_matching_the_pattern(vcam_dir, tmp_path):
    write_dng(vcam_dir / "frame.jpg.dng", rendering(0.5), exposure_s=0.02)
    with open_gphoto_camera(download_dir=tmp_path / "dl", pattern="*.nef") as cam:
        cam.arm()
        _camera_reports_new_file(cam)       # the virtual camera names it GPH_nnnn.JPG
        with pytest.raises(DeviceTimeout):
            cam.fetch(0.5)


@needs_gphoto2
def test_capture_mode_captures_downloads_and_can_delete_from_the_card(vcam_dir, tmp_path):
    write_dng(vcam_dir / "frame.jpg.dng", rendering(0.25), exposure_s=0.03)
    with open_gphoto_camera(capture_mode="capture", download_dir=tmp_path / "dl",
                            delete_after_download=True) as cam:
        cam.arm()
        first = cam.fetch(10.0)
        second = cam.fetch(10.0)
        for frame in (first, second):
            np.testing.assert_allclose(frame.rgb, rendering(0.25), atol=LSB)
            assert frame.exposure_s == pytest.approx(0.03) and frame.metadata["capture_mode"] == "capture"
        assert first.metadata["file_name"] != second.metadata["file_name"]
        assert Path(first.path).parent == Path(second.path).parent == tmp_path / "dl"
        folder = first.metadata["camera_folder"]
        listed = cam.gp_camera.folder_list_files(folder)
        names = {listed.get_name(i) for i in range(listed.count())}
        assert first.metadata["file_name"] not in names               # deleted after download


@needs_gphoto2
def test_same_name_twice_gets_a_suffix_not_overwritten(browse, tmp_path):
    cam, card = browse
    cam.arm()
    for sub, value in (("100NIKON", 0.25), ("101NIKON", 0.75)):   # camera counters restart per folder
        (card / sub).mkdir()
        write_dng(card / sub / "DSC_0001.dng", rendering(value), exposure_s=0.01)
    frames = sorted((cam.fetch(5.0) for _ in range(2)), key=lambda f: f.metadata["camera_folder"])
    assert sorted(Path(f.path).name for f in frames) == ["DSC_0001-1.dng", "DSC_0001.dng"]
    for frame, value in zip(frames, (0.25, 0.75)):
        assert Path(frame.path).read_bytes() == (card / frame.metadata["camera_folder"].lstrip("/")
                                                 / "DSC_0001.dng").read_bytes()
        np.testing.assert_allclose(frame.rgb, rendering(value), atol=LSB)
