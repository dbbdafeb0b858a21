"""Run the estimators on a session folder (read only through docs/session-format.md)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable


def estimate_session(root: str | Path, *, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    return {"rows": [], "notes": ["estimators not wired yet"]}
