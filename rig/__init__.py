"""sssrig's rig layer: config, devices, plans, runner, sessions, estimates, CLI (docs/architecture.md)."""
from __future__ import annotations


def __getattr__(name: str) -> str:
    """``rig.__version__``, read on first use (importlib.metadata takes ~0.4 s to import, and the command line
    must speak within 2 s of its start)."""
    if name != "__version__":
        raise AttributeError(f"module 'rig' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("sssrig")
    except PackageNotFoundError:  # pragma: no cover - a source tree without install
        return "0+unknown"

# POSIX only (Linux, macOS): the transports use termios/fcntl (ptys, pyserial's posix backend) and the
# simulators serve on ptys. `rig` says so in one line instead of failing on an import elsewhere.
POSIX_ONLY = "sssrig needs a POSIX system (Linux or macOS): its serial transports and simulators use termios and ptys"
