"""The camera's radiometric response: the quadratic fit of an exposure series and its inverse.

A frame value v (offset removed, white = 1) of linear signal x follows v = x (1 - beta x) (the radiometry step's
model, :mod:`rig.calibration.radiometry`); :func:`fit_linearity` fits it per channel, :func:`linearize` inverts it,
x = (1 - sqrt(1 - 4 beta v)) / (2 beta). Kept apart from the step so that the calibration store can linearize
frames without importing the step that measures the response.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["linearize", "fit_linearity"]


def linearize(values: npt.ArrayLike, result: Mapping[str, Any]) -> FloatArray:
    """Frame values (H, W, 3) from ``load_linear`` -> black-corrected, linear values (white level = 1), with the
    ``black_offset_dn``, ``span_dn`` and ``nonlinearity`` of a radiometry ``result``."""
    v = np.asarray(values, float) - np.asarray(result["black_offset_dn"], float) / float(result["span_dn"])
    beta = np.asarray(result["nonlinearity"], float)
    with np.errstate(invalid="ignore"):
        safe = np.where(np.abs(beta) > 1e-12, beta, 1.0)
        x = (1.0 - np.sqrt(np.maximum(1.0 - 4.0 * safe * v, 0.0))) / (2.0 * safe)
    return np.where(np.abs(beta) > 1e-12, x, v)


def fit_linearity(exposure_s: npt.ArrayLike, values: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Fit v = a t - c t^2 per channel (least squares, through the origin). Returns a (3,), beta = c / a^2 (3,)
    and the largest relative deviation of the data from the linear part a t (3,)."""
    t = np.asarray(exposure_s, float)
    V = np.asarray(values, float)
    A = np.stack([t, -t * t], axis=1)
    coef, *_ = np.linalg.lstsq(A, V, rcond=None)
    a, c = coef
    dev = np.max(np.abs(V - np.outer(t, a)) / np.outer(t, a), axis=0)
    return a, c / (a * a), dev
