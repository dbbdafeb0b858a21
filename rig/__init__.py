"""sssrig's rig layer: config, devices, plans, runner, sessions, estimates, CLI (docs/architecture.md)."""
from __future__ import annotations

try:
    from importlib.metadata import PackageNotFoundError, version

    __version__ = version("sssrig")
except PackageNotFoundError:  # pragma: no cover - a source tree without install
    __version__ = "0+unknown"

# POSIX only (Linux, macOS): the transports use termios/fcntl (ptys, pyserial's posix backend) and the
# simulators serve on ptys. `rig` says so in one line instead of failing on an import elsewhere.
POSIX_ONLY = "sssrig needs a POSIX system (Linux or macOS): its serial transports and simulators use termios and ptys"
