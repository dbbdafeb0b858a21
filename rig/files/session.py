"""The on-disk session (docs/session-format.md): one folder per session, written so nothing is lost.

- ``manifest.json``: format version, name, creation time, software version, config snapshot, device
  identities, the plan, (simulated sessions only) the scene's ground truth, and (``rig capture --calibration``)
  the calibration file with its revision and SHA-256. Written atomically once.
- ``events.jsonl``: append-only journal, one JSON object per line, fsynced per event: ``start``, ``frame``,
  ``survey``, ``stop`` and the runner's ``retry``, ``busy``, ``fault``, ``hold``, ``release``, ``lost``,
  ``reconnected``, ``pause``, ``resume``, ``restart``, ``recovered``. A line cut short by a crash is ignored on read.
- one writer at a time: :meth:`Session.lock` holds an exclusive ``flock`` on ``.lock`` (released by the
  kernel even after ``kill -9``); :meth:`Session.recover` moves frames a crash left unjournalled to
  ``frames/orphans/`` (never deleted) so that a resumed run re-captures those steps.
- ``frames/``: RAW frames (DNG), each written atomically (temporary file, fsync, rename) and never
  overwritten; the journal records each frame's pattern, polarization, exposure, timestamps and SHA-256.
- ``estimates/``: one JSON file per estimator run.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from drivers.atomic import atomic_write_bytes as _atomic_write_bytes
from drivers.atomic import fsync_dir
from drivers.errors import RigError

from rig.files.provenance import json_default

FORMAT_VERSION = 1
STOP_STATUSES = ("complete", "paused", "aborted")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


class SessionError(RigError, ValueError):
    """A session folder is missing, malformed, or would be clobbered."""


class SessionBusy(SessionError):
    """Another process holds the session's lock (a capture or resume is running on it)."""


def software_version() -> str:
    try:
        from importlib.metadata import version
        return version("sssrig")
    except Exception:  # pragma: no cover - running from a source tree without install
        return "0+unknown"


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")


def validate_session_name(name: str) -> str:
    """Accept ``[A-Za-z0-9][A-Za-z0-9._-]{0,63}`` without '..': no path traversal, no hidden folders."""
    if not isinstance(name, str) or not _NAME_RE.match(name) or ".." in name:
        raise SessionError(f"session name {name!r}: expected 1-64 characters of letters, digits, '.', '_' "
                           "or '-', starting with a letter or digit, without '..'")
    return name


def atomic_write_bytes(path: Path, data: bytes, *, overwrite: bool = False) -> None:
    """drivers.atomic.atomic_write_bytes, refusing to clobber by default (a session's files are written once)."""
    try:
        _atomic_write_bytes(path, data, overwrite=overwrite)
    except FileExistsError as exc:
        raise SessionError(str(exc)) from None


def atomic_copy(src: Path, dst: Path) -> str:
    """Copy ``src`` to ``dst`` atomically; return the SHA-256 of the bytes written."""
    data = Path(src).read_bytes()
    atomic_write_bytes(dst, data)
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class FrameRecord:
    step: int
    pattern: str
    polarization: str
    exposure_s: float
    file: str
    sha256: str
    t_trigger: str
    t_written: str


class Session:
    """A session folder. Create with :meth:`create`, reopen with :meth:`open`."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    # --- writing -----------------------------------------------------------------------------
    @classmethod
    def create(cls, parent: str | Path, name: str, *, config: dict[str, Any],
               devices: dict[str, Any], plan: list[dict[str, Any]],
               geometry: dict[str, Any] | None = None,
               truth: dict[str, Any] | None = None,
               request: dict[str, Any] | None = None,
               calibration: dict[str, Any] | None = None) -> "Session":
        """``calibration``: the calibration file the session is captured with (``file``, ``rig``, ``revision``,
        ``sha256``; ``rig.acquire.capture.calibration_record``), written to the manifest only when given."""
        validate_session_name(name)
        parent = Path(parent)
        parent.mkdir(parents=True, exist_ok=True)
        root = parent / name
        try:
            root.mkdir()
        except FileExistsError:
            raise SessionError(f"{root}: a session with this name exists; choose another name or "
                               "resume it") from None
        (root / "frames").mkdir()
        (root / "estimates").mkdir()
        manifest = {"format": "sssrig-session", "format_version": FORMAT_VERSION, "name": name,
                    "created": now_iso(), "software_version": software_version(),
                    "config": config, "devices": devices, "request": request, "plan": plan,
                    "geometry": geometry, "truth": truth}
        if calibration is not None:
            manifest["calibration"] = calibration
        atomic_write_bytes(root / "manifest.json",
                           json.dumps(manifest, indent=2, default=json_default).encode())
        s = cls(root)
        s.append_event({"type": "start"})
        return s

    def append_event(self, event: dict[str, Any]) -> None:
        """Append one event to the journal and fsync it (a crash loses at most the line being written)."""
        record = {"t": now_iso(), **event}
        line = (json.dumps(record, separators=(",", ":")) + "\n").encode()
        fd = os.open(self.root / "events.jsonl", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)

    def add_frame(self, step: int, source: Path, *, pattern: str, polarization: str,
                  exposure_s: float, t_trigger: str) -> FrameRecord:
        """Copy ``source`` into ``frames/`` atomically, then journal it. A journalled frame is never
        overwritten (:class:`SessionError`); an unjournalled file in the way (a crash between the copy and the
        journal line) is moved to ``frames/orphans/`` first."""
        rel = f"frames/{step:04d}_{pattern}_{polarization}{Path(source).suffix.lower() or '.dng'}"
        if (self.root / rel).exists() and rel not in {f.file for f in self.frames()}:
            self.recover()
        digest = atomic_copy(Path(source), self.root / rel)
        rec = FrameRecord(step, pattern, polarization, float(exposure_s), rel, digest, t_trigger,
                          now_iso())
        self.append_event({"type": "frame", **rec.__dict__})
        return rec

    def add_survey(self, step: int, target: str, xyz_mm: tuple[float, float, float],
                   warning: str | None) -> None:
        self.append_event({"type": "survey", "step": step, "target": target,
                           "xyz_mm": [float(v) for v in xyz_mm], "warning": warning})

    def write_estimate(self, name: str, payload: dict[str, Any]) -> Path:
        validate_session_name(name)
        path = self.root / "estimates" / f"{name}.json"
        atomic_write_bytes(path, json.dumps(payload, indent=2, default=json_default).encode(),
                           overwrite=True)
        return path

    def stop(self, status: str, reason: str | None = None) -> None:
        if status not in STOP_STATUSES:
            raise ValueError(f"stop status {status!r}: expected one of {', '.join(STOP_STATUSES)}")
        self.append_event({"type": "stop", "status": status, "reason": reason})

    @contextlib.contextmanager
    def lock(self) -> Iterator["Session"]:
        """Hold the session's writer lock; :class:`SessionBusy` if another process holds it."""
        fd = os.open(self.root / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise SessionBusy(f"{self.root}: another process is writing this session "
                                  "(a capture or resume is running)") from None
            yield self
        finally:
            os.close(fd)    # releases the lock

    def recover(self) -> list[str]:
        """Move files in ``frames/`` that the journal does not reference (a frame copied just before a
        crash, a temporary file of an interrupted copy) to ``frames/orphans/``; journal a ``recovered``
        event. Nothing is deleted. Returns the moved names."""
        frames_dir = self.root / "frames"
        journalled = {Path(f.file).name for f in self.frames()}
        stray = sorted(p for p in frames_dir.iterdir() if p.is_file() and p.name not in journalled)
        if not stray:
            return []
        orphans = frames_dir / "orphans"
        orphans.mkdir(exist_ok=True)
        moved = []
        for p in stray:
            dst = orphans / p.name.lstrip(".")
            n = 1
            while dst.exists():
                dst = orphans / f"{p.name.lstrip('.')}.{n}"
                n += 1
            os.rename(p, dst)
            moved.append(f"{p.name} -> {dst.relative_to(self.root)}")
        fsync_dir(orphans)
        fsync_dir(frames_dir)
        self.append_event({"type": "recovered", "moved": moved})
        return moved

    # --- reading -----------------------------------------------------------------------------
    @classmethod
    def open(cls, root: str | Path) -> "Session":
        root = Path(root)
        if not (root / "manifest.json").is_file():
            raise SessionError(f"{root}: not a session folder (no manifest.json)")
        s = cls(root)
        m = s.manifest
        if m.get("format") != "sssrig-session" or m.get("format_version") != FORMAT_VERSION:
            raise SessionError(f"{root / 'manifest.json'}: field 'format_version': expected "
                               f"sssrig-session version {FORMAT_VERSION}, got {m.get('format_version')!r}")
        return s

    @property
    def manifest(self) -> dict[str, Any]:
        path = self.root / "manifest.json"
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise SessionError(f"{path}: not valid JSON ({exc})") from exc

    def events(self) -> Iterator[dict[str, Any]]:
        path = self.root / "events.jsonl"
        if not path.exists():
            return
        for line in path.read_text().splitlines():
            if not line.strip():
                continue
            try:
                yield json.loads(line)
            except json.JSONDecodeError:
                # a line torn by a crash mid-write carries no committed event: skip it
                continue

    def frames(self) -> list[FrameRecord]:
        out = []
        for e in self.events():
            if e.get("type") == "frame":
                out.append(FrameRecord(**{k: e[k] for k in FrameRecord.__dataclass_fields__}))
        return out

    def frame(self, pattern: str, polarization: str) -> FrameRecord:
        for rec in reversed(self.frames()):
            if rec.pattern == pattern and rec.polarization == polarization:
                return rec
        raise SessionError(f"{self.root}: no frame with pattern {pattern!r} and polarization "
                           f"{polarization!r}")

    def surveys(self) -> dict[str, dict[str, Any]]:
        return {e["target"]: e for e in self.events() if e.get("type") == "survey"}

    def completed_steps(self) -> set[int]:
        """Plan steps whose ``frame`` or ``survey`` event is in the journal (done; a resume skips them)."""
        done = set()
        for e in self.events():
            if e.get("type") in ("frame", "survey") and "step" in e:
                done.add(int(e["step"]))
        return done

    def status(self) -> str:
        """``complete``, ``paused`` or ``aborted`` (the last ``stop`` event after the last (re)start), or
        ``interrupted`` (started, no stop: killed or crashed)."""
        status = "interrupted"
        for e in self.events():
            if e.get("type") in ("start", "restart"):
                status = "interrupted"
            elif e.get("type") == "stop":
                status = e.get("status", "interrupted")
        return status

    def verify(self) -> list[str]:
        """Check every journalled frame exists with its recorded SHA-256; return the problems found."""
        problems = []
        for rec in self.frames():
            p = self.root / rec.file
            if not p.is_file():
                problems.append(f"{rec.file}: missing")
            elif hashlib.sha256(p.read_bytes()).hexdigest() != rec.sha256:
                problems.append(f"{rec.file}: SHA-256 differs from the journal")
        return problems

    def estimates(self) -> dict[str, Any]:
        out = {}
        for p in sorted((self.root / "estimates").glob("*.json")):
            out[p.stem] = json.loads(p.read_text())
        return out
