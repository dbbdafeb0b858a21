"""What the ``rig`` command line tells the operator while it works: progress on stderr, logging, JSON errors.

- :class:`Feedback`: stage messages on stderr for work that can take longer than 2 s, with the elapsed time.
  On a terminal a tqdm status line shows the current stage and the elapsed time, refreshed twice a second;
  otherwise every stage is a line and a ``still ...`` line follows after ``heartbeat_s`` of silence. stdout is
  never written, so ``--json`` output stays clean.
- :func:`setup_logging`: ``-v`` / ``-vv`` / ``--log-level`` reach our drivers' wire traces (``drivers.*``), the
  simulators, pymodbus and geocompy.
- :func:`numba_notice`: one line before the Monte Carlo kernels compile for the first time (numba caches them
  on disk, ``cache=True``; later runs load them).
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path
from typing import TextIO

__all__ = ["Feedback", "setup_logging", "numba_notice", "LOGGERS"]

LOGGERS = ("rig", "drivers", "simulators", "pymodbus", "geocompy")
_NOTICED = False


class Feedback:
    """Stage messages and elapsed time on ``stream`` (stderr). ``enabled=False`` keeps it silent."""

    def __init__(self, title: str, stream: TextIO | None = None, *, enabled: bool = True, tty: bool | None = None,
                 heartbeat_s: float = 10.0) -> None:
        self.title = title
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = (self.stream.isatty() if tty is None else tty) if enabled else False
        self.heartbeat_s = heartbeat_s
        self.t0 = time.monotonic()
        self.last = title
        self._t_last = self.t0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._suspended = 0
        self._bar = None
        self._thread: threading.Thread | None = None
        if enabled and self.tty:
            from tqdm import tqdm

            self._bar = tqdm(total=None, file=self.stream, bar_format="{desc} [{elapsed}]", desc=title, leave=False)
        if enabled:
            self._thread = threading.Thread(target=self._beat, name="rig-feedback", daemon=True)
            self._thread.start()

    def elapsed_s(self) -> float:
        return time.monotonic() - self.t0

    def __call__(self, message: str) -> None:
        self.stage(message)

    def stage(self, message: str) -> None:
        """Report what is being done now (also usable as a ``say``/``log`` callback)."""
        if not self.enabled:
            return
        with self._lock:
            self.last, self._t_last = message.strip(), time.monotonic()
            line = f"[{self.elapsed_s():6.1f} s] {message}"
            if self._bar is not None:
                self._bar.write(line, file=self.stream)
                self._bar.set_description_str(f"{self.title}: {self.last[:60]}", refresh=True)
            else:
                self.stream.write(line + "\n")
                self.stream.flush()

    def suspend(self) -> "Feedback":
        """Stop the status line while another progress display (the capture bar) owns the terminal line."""
        with self._lock:
            self._suspended += 1
            if self._bar is not None:
                self._bar.clear()
        return self

    def resume(self) -> None:
        with self._lock:
            self._suspended = max(0, self._suspended - 1)
            self._t_last = time.monotonic()

    def _beat(self) -> None:
        while not self._stop.wait(0.5):
            with self._lock:
                if self._suspended:
                    continue
                if self._bar is not None:
                    self._bar.refresh()
                elif time.monotonic() - self._t_last >= self.heartbeat_s:
                    self._t_last = time.monotonic()
                    self.stream.write(f"[{self.elapsed_s():6.1f} s]   still: {self.last}\n")
                    self.stream.flush()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "Feedback":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def setup_logging(verbosity: int = 0, level: str | None = None) -> int:
    """Log to stderr: WARNING by default, INFO with ``-v``, DEBUG (the drivers' byte traces) with ``-vv``;
    ``level`` (a logging level name) wins. geocompy logs every timeout with a traceback: it is shown only when
    asked for (``-v`` or a level), otherwise it stays at CRITICAL."""
    if level is not None:
        value = logging.getLevelName(level.upper())
        if not isinstance(value, int):
            raise ValueError(f"--log-level {level!r}: expected DEBUG, INFO, WARNING, ERROR or CRITICAL")
    else:
        value = {0: logging.WARNING, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    root = logging.getLogger()
    if not any(getattr(h, "_rig_cli", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s"))
        handler._rig_cli = True  # type: ignore[attr-defined]
        root.addHandler(handler)
    root.setLevel(value)
    asked = level is not None or verbosity > 0
    for name in LOGGERS:
        logging.getLogger(name).setLevel(value if asked or name != "geocompy" else logging.CRITICAL)
    return value


def numba_notice(say: object = None) -> bool:
    """Print one line (through ``say``, else stderr) if numba has not yet cached the Monte Carlo kernels, whose
    first compile takes ~20 s. Returns True if it printed."""
    global _NOTICED
    import simulators.mc as mc

    cache = Path(mc.__file__).parent / "__pycache__"
    if _NOTICED or (cache.is_dir() and any(cache.glob("*.nbi"))):
        return False
    _NOTICED = True
    msg = "compiling the Monte Carlo kernels with numba (first run only, ~20 s; cached afterwards)"
    if callable(say):
        say(msg)
    else:
        print(msg, file=sys.stderr, flush=True)
    return True
