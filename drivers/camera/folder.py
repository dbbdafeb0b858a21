"""A camera seen through a folder: tethering software (or the simulated camera) drops RAW files there.

``FolderCamera`` satisfies ``drivers.contracts.Camera``: :meth:`~FolderCamera.arm` records the files already
present; :meth:`~FolderCamera.fetch` waits for a new file, waits until it is complete (size and mtime unchanged
for ``settle_s``), loads it with :func:`drivers.camera.raw.load_linear` and returns a ``RawFrame``.
"""
from __future__ import annotations

import fnmatch
import math
import os
import time
from pathlib import Path

from ..contracts import DeviceIdentity, RawFrame
from ..errors import DeviceTimeout
from .raw import RawFileError, load_linear

_Stamp = tuple[int, int, int]          # (inode, mtime_ns, size)


class FolderCamera:
    """Frames from RAW files appearing in ``folder``.

    ``pattern`` is a glob matched case-insensitively against file names (cameras write ``.DNG``); hidden
    files (``.name``, e.g. an atomic writer's temporary file) are ignored. A file counts as new if its name
    was not present at :meth:`arm` or it was replaced since (other inode or mtime). Several new files are
    returned oldest first, one per :meth:`fetch`. The constructor does no I/O.
    """

    def __init__(self, folder: str | os.PathLike[str], pattern: str = "*.dng", settle_s: float = 0.05, *,
                 poll_s: float = 0.01) -> None:
        if settle_s < 0 or poll_s <= 0:
            raise ValueError(f"need settle_s >= 0 and poll_s > 0, got {settle_s}, {poll_s}")
        self.folder = Path(folder)
        self.pattern = pattern
        self.settle_s = settle_s
        self.poll_s = poll_s
        self._seen: dict[str, _Stamp] | None = None
        self._closed = False

    def identify(self) -> DeviceIdentity:
        return DeviceIdentity(kind="camera", model="FolderCamera", firmware="",
                              extra={"folder": os.fspath(self.folder), "pattern": self.pattern,
                                     "settle_s": self.settle_s})

    def _scan(self) -> dict[str, _Stamp]:
        pat = self.pattern.lower()
        found: dict[str, _Stamp] = {}
        try:
            entries = list(os.scandir(self.folder))
        except FileNotFoundError:
            raise FileNotFoundError(2, "camera drop folder does not exist", os.fspath(self.folder)) from None
        for entry in entries:
            name = entry.name
            if name.startswith(".") or not fnmatch.fnmatchcase(name.lower(), pat):
                continue
            try:
                if not entry.is_file():
                    continue
                st = entry.stat()
            except FileNotFoundError:      # vanished between listing and stat
                continue
            found[name] = (st.st_ino, st.st_mtime_ns, st.st_size)
        return found

    def arm(self) -> None:
        """Remember the files present now; only files appearing after this count as frames."""
        self._seen = self._scan()

    def _new_files(self) -> list[tuple[str, _Stamp]]:
        assert self._seen is not None
        new = [(name, stamp) for name, stamp in self._scan().items() if self._seen.get(name) != stamp]
        new.sort(key=lambda item: (item[1][1], item[0]))
        return new

    def _stat(self, name: str) -> _Stamp | None:
        try:
            st = (self.folder / name).stat()
        except FileNotFoundError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def fetch(self, timeout_s: float) -> RawFrame:
        """Wait up to ``timeout_s`` for a new complete file and load it; :class:`DeviceTimeout` if none.

        A complete file that cannot be decoded raises :class:`~drivers.camera.raw.RawFileError`.
        """
        if self._closed:
            raise RuntimeError("FolderCamera is closed")
        if self._seen is None:
            raise RuntimeError("FolderCamera.fetch() called before arm()")
        deadline = time.monotonic() + timeout_s
        pending: dict[str, tuple[_Stamp, float]] = {}   # name -> (stamp, monotonic time first seen so)
        while True:
            now = time.monotonic()
            new = self._new_files()
            if new:                           # strictly oldest first: wait for it to settle
                name, stamp = new[0]
                first = pending.get(name)
                if first is None or first[0] != stamp:
                    pending[name] = (stamp, now)
                elif stamp[2] > 0 and now - first[1] >= self.settle_s:
                    frame = self._load(name, stamp)
                    if frame is not None:
                        return frame
                    pending.pop(name, None)
            if now >= deadline:
                waiting = f"; {len(pending)} file(s) still growing" if pending else ""
                raise DeviceTimeout(f"no new file matching {self.pattern!r} in {self.folder} "
                                    f"within {timeout_s:.3g} s{waiting}")
            time.sleep(min(self.poll_s, max(self.settle_s, 0.001)))

    def _load(self, name: str, stamp: _Stamp) -> RawFrame | None:
        """Load a settled file; None if it changed meanwhile (still being written)."""
        path = self.folder / name
        try:
            rgb, meta = load_linear(path)
        except (RawFileError, FileNotFoundError):
            if self._stat(name) != stamp:      # it changed under us: not complete after all
                return None
            raise
        if self._stat(name) != stamp:
            return None
        assert self._seen is not None
        self._seen[name] = stamp
        exposure = meta.get("exposure_s")
        return RawFrame(rgb=rgb, exposure_s=float(exposure) if exposure is not None else math.nan,
                        path=os.fspath(path), metadata=meta)

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> "FolderCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
