"""Small helpers every writer of provenance shares: file hashes and strict JSON from numpy values."""
from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["sha256_file", "jsonable", "json_default"]


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks (frames can be hundreds of MB)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def jsonable(o: Any) -> Any:
    """Plain JSON from numpy values, paths and tuples; NaN/inf become null (strict JSON); anything else
    unknown becomes its ``str``."""
    if isinstance(o, Mapping):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist())
    if isinstance(o, (np.bool_, bool)):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, (float, np.floating)):
        f = float(o)
        return f if math.isfinite(f) else None
    if isinstance(o, Path):
        return str(o)
    if o is None or isinstance(o, (str, int)):
        return o
    return str(o)


def json_default(o: Any) -> Any:
    """The ``json.dumps(default=...)`` hook of every JSON writer that keeps numbers as they are (sessions,
    calibration files, the CLI's --json): numpy arrays and scalars as lists and numbers, paths as strings;
    anything else is an error. Non-finite floats stay JSON's NaN / Infinity extension there (Python's json does
    so for its own floats); :func:`jsonable` is the strict form (null) for maps, scene results and reports."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
