"""A camera controlled through libgphoto2 (python-gphoto2, the optional extra ``sssrig[gphoto]``).

:class:`GphotoCamera` satisfies ``drivers.contracts.Camera`` in one of two capture modes:

``"external"``
    Something else opens the shutter - our trigger box, wired to the camera's remote socket, with the camera
    in bulb mode. :meth:`~GphotoCamera.arm` discards the events already queued; :meth:`~GphotoCamera.fetch`
    waits (``wait_for_event``) for a ``GP_EVENT_FILE_ADDED`` whose name matches ``pattern``, downloads that
    file and loads it. Cameras whose camlib has no events (libgphoto2's "Directory Browse", mass-storage
    cameras) are handled by listing the camera's folders instead: files absent at :meth:`arm` are new.
``"capture"``
    gphoto2 takes the picture itself: :meth:`fetch` calls ``capture()`` (the camera times the exposure from
    its own shutter-speed setting, so a trigger box must not also be wired to it) and downloads the result.

The downloaded file is written atomically into ``download_dir`` under the camera's file name (a ``-1``,
``-2`` ... suffix when the name is taken) and decoded with :func:`drivers.camera.raw.load_linear`. The
frame's metadata adds ``file_name``, ``camera_folder``, ``camera_model``, ``camera_serial``, ``camera_port``,
``capture_mode``, the camera's ``shutterspeed``/``iso``/``aperture`` settings read at :meth:`arm` (``None``
when the camera has no such setting) and ``iso`` (the file's EXIF ISO, else the setting). ``exposure_s`` is
the file's EXIF ExposureTime, else the camera's shutter-speed setting, else NaN.

Errors are typed at this boundary: :class:`GphotoError` (a :class:`~drivers.errors.DeviceError` carrying
libgphoto2's result ``code``), :class:`GphotoTimeout` (also a :class:`~drivers.errors.DeviceTimeout`),
:class:`GphotoConnectionLost` (also :class:`~drivers.errors.ConnectionLost`, for port and USB errors),
:class:`GphotoBusy` (a :class:`~drivers.errors.DeviceBusy`); no frame within ``timeout_s`` is a plain
:class:`~drivers.errors.DeviceTimeout`. This module imports without python-gphoto2; opening a camera without
it raises :class:`ImportError` naming ``pip install 'sssrig[gphoto]'``.
"""
from __future__ import annotations

import collections
import fnmatch
import math
import os
import posixpath
import tempfile
import threading
import time
from pathlib import Path
from types import ModuleType
from typing import Any, Iterator

from ..atomic import atomic_write
from ..contracts import DeviceIdentity, RawFrame
from ..errors import ConnectionLost, DeviceBusy, DeviceError, DeviceTimeout
from .raw import load_linear

INSTALL_HINT = "pip install 'sssrig[gphoto]'"
CAPTURE_MODES = ("external", "capture")

# libgphoto2 result codes (gphoto2-result.h, gphoto2-port-result.h); here so errors map without the module.
GP_ERROR = -1
GP_ERROR_BAD_PARAMETERS = -2
GP_ERROR_UNKNOWN_PORT = -5
GP_ERROR_NOT_SUPPORTED = -6
GP_ERROR_IO = -7
GP_ERROR_TIMEOUT = -10
GP_ERROR_MODEL_NOT_FOUND = -105
GP_ERROR_FILE_NOT_FOUND = -108
GP_ERROR_CAMERA_BUSY = -110
#: port / USB failures: the camera is unreachable (cable, power, another program holding the USB interface)
CONNECTION_CODES = frozenset({GP_ERROR_UNKNOWN_PORT, GP_ERROR_IO, -20, -21, -31, -34, -35, -37, -41, -51, -52,
                              -53, -60, -70, GP_ERROR_MODEL_NOT_FOUND})

# wait_for_event types (gphoto2-camera.h CameraEventType)
GP_EVENT_UNKNOWN, GP_EVENT_TIMEOUT, GP_EVENT_FILE_ADDED, GP_EVENT_FOLDER_ADDED = 0, 1, 2, 3
GP_EVENT_CAPTURE_COMPLETE, GP_EVENT_FILE_CHANGED = 4, 5

_SETTINGS = ("shutterspeed", "iso", "aperture")
_IDENTITY_WIDGETS = ("manufacturer", "cameramodel", "serialnumber", "deviceversion")
_TAG_ISO = 34855            # EXIF ISOSpeedRatings


def import_gphoto2() -> ModuleType:
    """Import python-gphoto2, or raise :class:`ImportError` that says how to install the extra."""
    try:
        import gphoto2
    except ImportError as exc:
        raise ImportError(f"the gphoto2 camera driver needs python-gphoto2 (libgphoto2 bindings): "
                          f"{INSTALL_HINT}") from exc
    return gphoto2


class GphotoError(DeviceError):
    """libgphoto2 returned an error; ``code`` is its result code (``GP_ERROR_*``), ``text`` its message."""

    def __init__(self, message: str, code: int, text: str = "") -> None:
        super().__init__(f"{message}: gphoto2 error {code}" + (f" ({text})" if text else ""))
        self.code = code
        self.text = text


class GphotoTimeout(GphotoError, DeviceTimeout):
    """libgphoto2 itself timed out (``GP_ERROR_TIMEOUT``)."""


class GphotoConnectionLost(GphotoError, ConnectionLost):
    """The camera cannot be reached: a port or USB error, or no camera where one was expected."""


class GphotoBusy(DeviceBusy):
    """The camera refused because it is busy (``GP_ERROR_CAMERA_BUSY``); ``code`` is -110."""


def gphoto_error(exc: BaseException, what: str) -> DeviceError:
    """Translate a ``gphoto2.GPhoto2Error`` raised while doing ``what`` into our typed errors."""
    code = int(getattr(exc, "code", GP_ERROR))
    text = str(getattr(exc, "string", "") or exc)
    if code == GP_ERROR_TIMEOUT:
        return GphotoTimeout(what, code, text)
    if code == GP_ERROR_CAMERA_BUSY:
        return GphotoBusy(f"{what}: camera busy", code, name=text)
    if code in CONNECTION_CODES:
        return GphotoConnectionLost(what, code, text)
    return GphotoError(what, code, text)


def parse_shutter_speed(text: str | None) -> float | None:
    """Seconds from a gphoto2 shutter-speed value (``"1/125"``, ``"0.0100s"``, ``"30"``, ``'2.5"'``);
    ``None`` for ``"bulb"``, ``"auto"`` or anything else that is not a duration."""
    if not text:
        return None
    s = str(text).strip().lower().rstrip('s"').strip()
    try:
        if "/" in s:
            num, den = s.split("/", 1)
            value = float(num) / float(den)
        else:
            value = float(s)
    except (ValueError, ZeroDivisionError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _file_iso(path: Path) -> int | None:
    """EXIF ISOSpeedRatings of a TIFF-based RAW (DNG, NEF, ...); None if absent or not TIFF."""
    try:
        import tifffile

        with tifffile.TiffFile(path) as tf:
            tags = tf.pages[0].tags
            if _TAG_ISO in tags:
                value = tags[_TAG_ISO].value
                return int(value[0] if isinstance(value, (tuple, list)) else value)
            exif = tags.get("ExifTag")
            if exif is not None and isinstance(exif.value, dict) and "ISOSpeedRatings" in exif.value:
                value = exif.value["ISOSpeedRatings"]
                return int(value[0] if isinstance(value, (tuple, list)) else value)
    except Exception:  # noqa: BLE001 - metadata is best effort; the pixels came from rawpy
        return None
    return None


class GphotoCamera:
    """Frames from a camera opened with libgphoto2 (see the module docstring for the two capture modes).

    ``camera`` is an initialised ``gphoto2.Camera`` and ``gp`` the ``gphoto2`` module (use
    :func:`open_gphoto_camera`); the constructor does no I/O. ``pattern`` is a glob matched
    case-insensitively against the camera's file names (``"*.nef"`` when shooting RAW+JPEG); other new files
    are left on the camera. ``delete_after_download`` removes each downloaded frame from the camera's card.
    ``poll_s`` bounds each ``wait_for_event`` call (and is the polling period of the listing fallback).
    """

    def __init__(self, camera: Any, gp: ModuleType, *, capture_mode: str = "external",
                 download_dir: str | os.PathLike[str] | None = None, pattern: str = "*",
                 delete_after_download: bool = False, poll_s: float = 0.1, name: str = "gphoto2") -> None:
        if capture_mode not in CAPTURE_MODES:
            raise ValueError(f"capture_mode must be one of {', '.join(CAPTURE_MODES)}, got {capture_mode!r}")
        if poll_s <= 0:
            raise ValueError(f"poll_s must be > 0, got {poll_s}")
        self._camera = camera
        self._gp = gp
        self.capture_mode = capture_mode
        self.download_dir = Path(download_dir) if download_dir is not None else None
        self.pattern = pattern
        self.delete_after_download = delete_after_download
        self.poll_s = poll_s
        self.name = name
        self._lock = threading.RLock()
        self._armed = False
        self._closed = False
        self._events: bool | None = None               # None: not yet known whether the camlib has events
        self._pending: collections.deque[tuple[str, str]] = collections.deque()
        self._listing: set[tuple[str, str]] = set()    # listing fallback: files present at arm()
        self._growing: dict[tuple[str, str], int] = {}  # listing fallback: size seen at the previous poll
        self._settings: dict[str, str | None] = {}
        self._ident: DeviceIdentity | None = None

    # ------------------------------------------------------------------------------------------ helpers
    @property
    def gp_camera(self) -> Any:
        """The underlying ``gphoto2.Camera`` (for camera settings this driver does not wrap)."""
        return self._camera

    def _call(self, what: str, fn: Any, *args: Any) -> Any:
        if self._closed:
            raise ConnectionLost(f"{self.name}: camera is closed")
        try:
            return fn(*args)
        except self._gp.GPhoto2Error as exc:
            raise gphoto_error(exc, f"{self.name}: {what}") from exc

    def _widget_value(self, key: str) -> str | None:
        """A configuration value as text; None when the camera has no such widget (or no config at all)."""
        try:
            return str(self._camera.get_single_config(key).get_value())
        except self._gp.GPhoto2Error as exc:
            err = gphoto_error(exc, f"{self.name}: read setting {key!r}")
            if isinstance(err, (GphotoConnectionLost, GphotoTimeout, GphotoBusy)):
                raise err from exc
            return None

    def _matches(self, file_name: str) -> bool:
        return not file_name.startswith(".") and fnmatch.fnmatchcase(file_name.lower(), self.pattern.lower())

    # --------------------------------------------------------------------------------------- identity
    def identify(self) -> DeviceIdentity:
        """Model from the camlib's abilities (or the camera's own ``cameramodel``), serial number,
        firmware (``deviceversion``) and the port, read once and cached."""
        with self._lock:
            if self._ident is None:
                abilities = self._call("read abilities", self._camera.get_abilities)
                port = self._call("read port", self._camera.get_port_info).get_path()
                widgets = {key: self._widget_value(key) for key in _IDENTITY_WIDGETS}
                model = str(abilities.model or widgets["cameramodel"] or "gphoto2 camera")
                self._ident = DeviceIdentity(
                    kind="camera", model=model, firmware=widgets["deviceversion"] or "",
                    serial_number=widgets["serialnumber"] or "",
                    extra={"driver": "gphoto2", "port": port, "manufacturer": widgets["manufacturer"] or "",
                           "camera_model": widgets["cameramodel"] or "", "capture_mode": self.capture_mode,
                           "pattern": self.pattern, "camlib": posixpath.basename(str(abilities.library))})
            return self._ident

    # ------------------------------------------------------------------------------------------ arming
    def _next_event(self, timeout_ms: int) -> tuple[int, Any]:
        """One ``wait_for_event``; switches to the listing fallback when the camlib has no events."""
        if self._events is False:
            return GP_EVENT_TIMEOUT, None
        try:
            event, data = self._camera.wait_for_event(max(0, int(timeout_ms)))
        except self._gp.GPhoto2Error as exc:
            if getattr(exc, "code", None) == GP_ERROR_NOT_SUPPORTED and self._events is None:
                self._events = False
                return GP_EVENT_TIMEOUT, None
            raise gphoto_error(exc, f"{self.name}: wait for camera event") from exc
        self._events = True
        return int(event), data

    def _drain(self) -> int:
        """Discard queued events (files the camera wrote before arm() are not this frame's)."""
        n = 0
        for _ in range(1000):                        # a camera flooding events must not hang arm()
            event, _data = self._next_event(0)
            if event == GP_EVENT_TIMEOUT:
                break
            n += 1
        return n

    def _walk(self, folder: str = "/") -> Iterator[tuple[str, str]]:
        files = self._call(f"list files in {folder}", self._camera.folder_list_files, folder)
        for i in range(files.count()):
            yield folder, files.get_name(i)
        folders = self._call(f"list folders in {folder}", self._camera.folder_list_folders, folder)
        for i in range(folders.count()):
            yield from self._walk(posixpath.join(folder, folders.get_name(i)))

    def _list_now(self) -> set[tuple[str, str]]:
        # libgphoto2 caches folder listings per session; ending the session empties the cache and the next
        # call reopens it (cheap for "Directory Browse"; slow on USB cameras, which have events anyway).
        self._call("refresh file listing", self._camera.exit)
        return set(self._walk("/"))

    def _read_settings(self) -> dict[str, str | None]:
        return {key: self._widget_value(key) for key in _SETTINGS}

    def arm(self) -> None:
        """Forget queued events and pending files, note the camera's exposure settings; with a camlib that
        has no events, remember the files present now (only files appearing later count as frames)."""
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"{self.name}: camera is closed")
            self._pending.clear()
            self._growing.clear()
            self._drain()
            if self._events is False:
                self._listing = self._list_now()
            self._settings = self._read_settings()
            self._armed = True

    # ------------------------------------------------------------------------------------------ fetching
    def fetch(self, timeout_s: float) -> RawFrame:
        """The next frame (see the capture modes); :class:`~drivers.errors.DeviceTimeout` if no matching
        file arrives within ``timeout_s``. A downloaded file that cannot be decoded raises
        :class:`~drivers.camera.raw.RawFileError` naming the local copy."""
        with self._lock:
            if self._closed:
                raise ConnectionLost(f"{self.name}: camera is closed")
            if not self._armed:
                raise RuntimeError(f"{self.name}: fetch() called before arm()")
            deadline = time.monotonic() + timeout_s
            if self.capture_mode == "capture" and not self._pending:
                path = self._call("capture", self._camera.capture, self._gp.GP_CAPTURE_IMAGE)
                if self._matches(path.name):
                    return self._download(path.folder, path.name)
                # RAW+JPEG: capture() reports one file, the other arrives as a FILE_ADDED event
            while not self._pending:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    how = "event" if self._events is not False else "new file in the camera's listing"
                    raise DeviceTimeout(f"{self.name}: no {how} matching {self.pattern!r} within "
                                        f"{timeout_s:.3g} s ({self.capture_mode} mode)")
                if self._events is False:
                    self._poll_listing()
                    if not self._pending:
                        time.sleep(min(self.poll_s, max(0.0, deadline - time.monotonic())))
                    continue
                event, data = self._next_event(math.ceil(min(remaining, self.poll_s) * 1000))
                if event == GP_EVENT_FILE_ADDED and self._matches(data.name):
                    self._pending.append((data.folder, data.name))
            folder, file_name = self._pending.popleft()
            return self._download(folder, file_name)

    def _poll_listing(self) -> None:
        """Listing fallback: queue new files whose size did not change since the previous poll."""
        now = self._list_now()
        fresh = sorted(key for key in now - self._listing if self._matches(key[1]))
        for key in fresh:
            info = self._call(f"read info of {key[1]}", self._camera.file_get_info, *key)
            size = int(info.file.size)
            if size > 0 and self._growing.get(key) == size:
                self._pending.append(key)
                self._listing.add(key)
                self._growing.pop(key, None)
            else:
                self._growing[key] = size

    def _target(self, file_name: str) -> Path:
        if self.download_dir is None:
            self.download_dir = Path(tempfile.mkdtemp(prefix="sssrig-gphoto2-"))
        self.download_dir.mkdir(parents=True, exist_ok=True)
        stem, ext = os.path.splitext(file_name)
        target, k = self.download_dir / file_name, 0
        while target.exists():
            k += 1
            target = self.download_dir / f"{stem}-{k}{ext}"
        return target

    def _download(self, folder: str, file_name: str) -> RawFrame:
        what = f"download {posixpath.join(folder, file_name)}"
        camera_file = self._call(what, self._camera.file_get, folder, file_name, self._gp.GP_FILE_TYPE_NORMAL)
        target = self._target(file_name)
        atomic_write(target, lambda tmp: self._call(what, camera_file.save, os.fspath(tmp)))
        if self.delete_after_download:
            self._call(f"delete {file_name} from the camera", self._camera.file_delete, folder, file_name)
        rgb, meta = load_linear(target)
        ident = self.identify()
        shutter = self._settings.get("shutterspeed")
        exposure = meta.get("exposure_s")
        if exposure is None:
            exposure = parse_shutter_speed(shutter)
        iso = _file_iso(target)
        meta.update({
            "file_name": file_name, "camera_folder": folder, "camera_model": ident.model,
            "camera_serial": ident.serial_number, "camera_port": ident.extra.get("port", ""),
            "capture_mode": self.capture_mode, "shutterspeed": shutter, "aperture": self._settings.get("aperture"),
            "iso_setting": self._settings.get("iso"),
            "iso": iso if iso is not None else self._settings.get("iso"),
            "exposure_s": exposure})
        return RawFrame(rgb=rgb, exposure_s=float(exposure) if exposure is not None else math.nan,
                        path=os.fspath(target), metadata=meta)

    # ---------------------------------------------------------------------------------------------- close
    def close(self) -> None:
        """End the gphoto2 session (releases the USB interface). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._camera.exit()
            except self._gp.GPhoto2Error:
                pass

    def __enter__(self) -> "GphotoCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _autodetected(gp: ModuleType) -> list[tuple[str, str]]:
    found = gp.Camera.autodetect()
    return [(found.get_name(i), found.get_value(i)) for i in range(found.count())]


def open_gphoto_camera(port: str = "", model: str = "", **kwargs: Any) -> GphotoCamera:
    """Open a camera with libgphoto2 and wrap it in a :class:`GphotoCamera`.

    ``port`` is a gphoto2 port (``"usb:001,004"``, ``"ptpip:192.168.1.10"``, ``"disk:/some/folder"``) or
    ``""`` for the first camera found; ``model`` a camlib model name (``"Nikon DSC D750"``, ``"Directory
    Browse"``) or ``""`` to take the autodetected one. ``"disk:"`` ports are not autodetected: give
    ``model="Directory Browse"``. Keyword arguments go to :class:`GphotoCamera`.

    Raises :class:`ImportError` without python-gphoto2, :class:`GphotoConnectionLost` when no camera is
    found or it cannot be opened, :class:`GphotoError` for other libgphoto2 errors.
    """
    gp = import_gphoto2()
    if port.startswith("disk:") and not os.path.isdir(port[len("disk:"):]):
        # the "directory" camlib opens any path and fails only on the first listing: say so up front
        raise GphotoConnectionLost(f"gphoto2: cannot open port {port!r}: no such folder", GP_ERROR_UNKNOWN_PORT)
    where = " ".join(x for x in (f"port {port!r}" if port else "", f"model {model!r}" if model else "") if x)
    where = where or "the first autodetected camera"
    camera = gp.Camera()
    try:
        if port or model:
            if not model or not port:
                cameras = _autodetected(gp)
                match = [(m, p) for m, p in cameras if (not model or m == model) and (not port or p == port)]
                if not match:
                    seen = ", ".join(f"{m} on {p}" for m, p in cameras) or "none"
                    hint = '; disk: ports are not autodetected, give model="Directory Browse"' if (
                        port.startswith("disk:")) else ""
                    raise GphotoConnectionLost(f"gphoto2: no camera for {where} (autodetected: {seen}){hint}",
                                               GP_ERROR_MODEL_NOT_FOUND)
                model, port = match[0]
            abilities = gp.CameraAbilitiesList()
            abilities.load()
            camera.set_abilities(abilities[abilities.lookup_model(model)])
            ports = gp.PortInfoList()
            ports.load()
            camera.set_port_info(ports[ports.lookup_path(port)])
        camera.init()
    except gp.GPhoto2Error as exc:
        err = gphoto_error(exc, f"gphoto2: cannot open {where}")
        if not isinstance(err, GphotoConnectionLost):      # any failure to open means no usable camera
            err = GphotoConnectionLost(f"gphoto2: cannot open {where}", getattr(err, "code", GP_ERROR),
                                       str(getattr(exc, "string", "")))
        raise err from exc
    kwargs.setdefault("name", f"gphoto2 {port or 'auto'}")
    return GphotoCamera(camera, gp, **kwargs)
