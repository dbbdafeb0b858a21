"""The LED rig's response LUT, built once per LED layout (issue 19): in this process and on disk, keyed by content.

:func:`estimation.gradients.build_response_lut` costs ~0.25-0.3 CPU s for a 343-LED rig (65 x 65 nodes x 64 stencil
normals x 343 LEDs, near field; the 5 mm sphere capture of ``benchmarks/reference_speed.py``, load ~4; numba since
branch lut19, it was 1.6-2.6 s at load ~4 and 4.5-5.3 s at load 7-12 in numpy), its solve table for four patterns
~0.1 s (was 0.3-0.4 s): with both the first capture on a rig is now within the run-to-run noise of a cached one
(docs/model-error.md, issue 19 line 2). The table depends only on the LED calibration (directions,
gains, distances, displayed drive values), eta, the reference normal, the surface model (centre, radius), the table
size and smoothing, and the code that builds it. :func:`response_lut` keys the table by the SHA-256 of all of these
(the code as the source text of :mod:`estimation.gradients.response`) and returns

1. the same :class:`~estimation.gradients.ResponseLUT` object again within a process (its per-pattern solve tables,
   :func:`estimation.gradients.response._solve_table`, ~0.1 s, come along), else
2. the table stored under ``$SSSRIG_LUT_CACHE`` (default ``$XDG_CACHE_HOME/sssrig/response-lut``, ``~/.cache``
   when unset) as ``<key>.npz`` (float64 arrays, so the loaded table is bit-identical to a fresh build), else
3. a fresh build, then stored (atomically; an unwritable cache folder only costs the next process a rebuild).

``SSSRIG_LUT_CACHE=off`` (or ``0``, ``none``) disables the disk cache (the in-process one stays). A studio's sessions
share one LED layout, so every capture after the first pays ~0.01-0.05 s instead of the build.
"""
from __future__ import annotations

import hashlib
import inspect
import json
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from drivers.atomic import atomic_write
from estimation.gradients import GRADIENT_PATTERNS, LedRig, ResponseLUT, build_response_lut

__all__ = ["response_lut", "lut_cache_dir", "lut_key", "clear_memory_cache"]

_MEMORY: dict[str, ResponseLUT] = {}
_MEMORY_MAX = 8
_CODE_HASH: str | None = None


def _code_hash() -> str:
    global _CODE_HASH
    if _CODE_HASH is None:
        from estimation.gradients import response

        _CODE_HASH = hashlib.sha256(inspect.getsource(response).encode()).hexdigest()
    return _CODE_HASH


def lut_cache_dir() -> Path | None:
    """The disk cache folder (``$SSSRIG_LUT_CACHE``, else ``$XDG_CACHE_HOME/sssrig/response-lut``), None when off."""
    env = os.environ.get("SSSRIG_LUT_CACHE")
    if env is not None and env.strip().lower() in ("", "0", "off", "none", "no", "false"):
        return None
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "sssrig" / "response-lut"


def lut_key(leds: LedRig, *, eta: float, size: int, smoothing_rad: float | None, reference_normal: ArrayLike,
            surface_center_mm: ArrayLike, surface_radius_mm: float) -> str:
    """SHA-256 (hex) of everything :func:`build_response_lut` reads, and of its module's source."""
    h = hashlib.sha256()
    h.update(_code_hash().encode())
    for a in (leds.directions, leds.gains, np.zeros(0) if leds.distances_mm is None else leds.distances_mm,
              *(leds.pattern_values(p) for p in GRADIENT_PATTERNS),
              np.asarray(reference_normal, dtype=np.float64).reshape(-1),
              np.asarray(surface_center_mm, dtype=np.float64).reshape(-1)):
        arr = np.ascontiguousarray(a, dtype=np.float64)
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    h.update(json.dumps([float(eta), int(size), None if smoothing_rad is None else float(smoothing_rad),
                         float(surface_radius_mm), leds.distances_mm is None]).encode())
    return h.hexdigest()


def _load(path: Path) -> ResponseLUT | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return ResponseLUT(int(meta["size"]), tuple(meta["patterns"]), np.array(z["coeffs"]),
                               np.array(z["reference_full"]), float(meta["smoothing_rad"]), float(meta["eta"]),
                               np.array(z["fit_residual"]), dict(meta["provenance"]))
    except (OSError, ValueError, KeyError, TypeError):     # missing, partial or foreign file: rebuild
        return None


def _store(path: Path, lut: ResponseLUT) -> None:
    meta = json.dumps({"size": lut.size, "patterns": list(lut.patterns), "smoothing_rad": lut.smoothing_rad,
                       "eta": lut.eta, "provenance": lut.provenance})

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, coeffs=lut.coeffs, reference_full=lut.reference_full, fit_residual=lut.fit_residual,
                     meta=np.array(meta))
    try:
        atomic_write(path, write)
    except OSError:
        pass


def response_lut(leds: LedRig, *, eta: float = 1.3, size: int = 65, smoothing_rad: float | None = None,
                 reference_normal: ArrayLike = (0.0, -1.0, 0.0), surface_center_mm: ArrayLike = (0.0, 0.0, 0.0),
                 surface_radius_mm: float = 0.0) -> ResponseLUT:
    """:func:`estimation.gradients.build_response_lut` with the same arguments, cached (module docstring)."""
    key = lut_key(leds, eta=eta, size=size, smoothing_rad=smoothing_rad, reference_normal=reference_normal,
                  surface_center_mm=surface_center_mm, surface_radius_mm=surface_radius_mm)
    lut = _MEMORY.get(key)
    if lut is not None:
        return lut
    folder = lut_cache_dir()
    path = None if folder is None else folder / f"{key[:32]}.npz"
    lut = None if path is None or not path.exists() else _load(path)
    if lut is None:
        lut = build_response_lut(leds, eta=eta, size=size, smoothing_rad=smoothing_rad,
                                 reference_normal=reference_normal, surface_center_mm=surface_center_mm,
                                 surface_radius_mm=surface_radius_mm)
        if path is not None:
            _store(path, lut)
    if len(_MEMORY) >= _MEMORY_MAX:
        _MEMORY.pop(next(iter(_MEMORY)))
    _MEMORY[key] = lut
    return lut


def clear_memory_cache() -> None:
    """Forget the in-process tables (tests; the disk cache stays)."""
    _MEMORY.clear()

