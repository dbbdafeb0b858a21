"""Small helpers every writer of provenance shares: file hashes, JSON from numpy values, and the one JSON file writer."""
from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["sha256_file", "jsonable", "json_default", "write_json"]


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


def write_json(path: str | os.PathLike[str], obj: Any, *, strict: bool = False, indent: int = 2) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (``drivers.atomic``): the one JSON file writer of the rig and the
    benchmarks. ``strict=False`` keeps numbers as they are (:func:`json_default`; NaN / Infinity as Python's json
    writes them); ``strict=True`` writes :func:`jsonable` (non-finite floats as null) and refuses NaN."""
    from drivers.atomic import atomic_write_bytes

    text = (json.dumps(jsonable(obj), indent=indent, allow_nan=False) if strict
            else json.dumps(obj, indent=indent, default=json_default))
    return atomic_write_bytes(path, (text + "\n").encode())
