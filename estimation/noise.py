"""Pixel noise from the image itself: a signal-dependent (Poisson-Gaussian) variance model var = a * value + b.

Raw photographs follow it (a: the inverse gain, values per electron; b: the read-noise variance), and so, roughly,
do Monte Carlo renders at a fixed sample count (a path's contribution scales with the pixel's radiance). When a
capture states no noise figure, the single-image method uses this estimate instead of relative weights, so that dim
and zero pixels are data with their variance, never infinite-weight points (issue 15).

Method (after Foi, Trimeche, Katkovnik, Egiazarian 2008, "Practical Poissonian-Gaussian noise modeling and fitting
for single-image raw-data", IEEE TIP 17(10), simplified): on the usable pixels whose 3 x 3 neighbourhood is usable
too, the local mean (3 x 3) and a high-pass residual r = (4 I - sum of the 4 neighbours) / sqrt(20), which removes
a locally linear signal and has the pixel variance for independent noise (Immerkaer 1996, "Fast noise variance
estimation", CVIU 64(2), uses the same idea); pixels are grouped into up to :data:`N_BINS` quantile bins of the
local mean; each bin's variance is the squared normalized median absolute deviation of r (robust against edges
between faces, fireflies and hot pixels); a, b >= 0 by weighted least squares on the bins (weights: bin count /
variance^2, the inverse variance of a variance estimate). Curvature of the signal leaks into r (it estimates the
noise high where the image bends sharply within a pixel or two): the estimate is conservative there.

Pure numpy / scipy; ``rig.files.scene_file`` applies it to scene images without a ``[noise]`` section.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage, optimize

__all__ = ["NoiseFit", "estimate_signal_dependent_noise", "N_BINS"]

Array = NDArray[np.float64]
N_BINS = 16
_MIN_PIXELS = 50


@dataclass(frozen=True)
class NoiseFit:
    """var = a * max(value, 0) + b per channel; ``pixels`` used per channel; ``floor`` the variance floor applied
    (a noise-free image still gets a finite weight per pixel: (1e-3 x its 99th percentile)^2)."""

    a: Array
    b: Array
    floor: Array
    pixels: NDArray[np.int64]

    def variance(self, image: ArrayLike) -> Array:
        """Per-pixel variance (H, W, C) of ``image`` under this model."""
        img = np.asarray(image, dtype=np.float64)
        var = self.a[None, None, :] * np.maximum(img, 0.0) + self.b[None, None, :]
        return np.maximum(np.nan_to_num(var, nan=np.inf), self.floor[None, None, :])

    def as_dict(self) -> dict[str, list[float] | list[int]]:
        return {"a": self.a.tolist(), "b": self.b.tolist(), "floor": self.floor.tolist(), "pixels": self.pixels.tolist()}


def _channel(img: Array, usable: NDArray[np.bool_]) -> tuple[float, float, int]:
    k = np.array([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]]) / np.sqrt(20.0)
    filled = np.where(usable, img, 0.0)
    r = ndimage.convolve(filled, k, mode="constant")
    mean = ndimage.uniform_filter(filled, 3, mode="constant")
    inner = ndimage.binary_erosion(usable, structure=np.ones((3, 3), bool), border_value=0)
    r, mean = r[inner], mean[inner]
    n = r.size
    if n < _MIN_PIXELS:
        return 0.0, 0.0, n
    n_bins = int(min(N_BINS, max(2, n // 50)))
    edges = np.quantile(mean, np.linspace(0.0, 1.0, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, mean, side="right") - 1, 0, n_bins - 1)
    mu, var, cnt = [], [], []
    for b in range(n_bins):
        sel = idx == b
        if sel.sum() < 10:
            continue
        rb = r[sel]
        mad = 1.4826 * float(np.median(np.abs(rb - np.median(rb))))
        mu.append(float(np.mean(mean[sel])))
        var.append(mad * mad)
        cnt.append(int(sel.sum()))
    if not mu:
        return 0.0, 0.0, n
    mu_a, var_a, cnt_a = np.array(mu), np.array(var), np.array(cnt, float)
    w = np.sqrt(cnt_a) / np.maximum(var_a, np.max(var_a) * 1e-6 + 1e-300)  # 1 / sd of a variance estimate
    design = np.stack([np.maximum(mu_a, 0.0), np.ones_like(mu_a)], axis=1) * w[:, None]
    sol = optimize.nnls(design, var_a * w)[0]
    return float(sol[0]), float(sol[1]), n


def estimate_signal_dependent_noise(image: ArrayLike, usable: ArrayLike | None = None) -> NoiseFit:
    """Fit var = a * value + b per channel of ``image`` (H, W) or (H, W, C) on the ``usable`` pixels (H, W) bool
    (default: all finite pixels); module docstring. Channels with fewer than 50 usable interior pixels get a = b = 0
    (then only the floor)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3:
        raise ValueError(f"image must be (H, W) or (H, W, C); got shape {np.shape(image)}")
    fin = np.all(np.isfinite(img), axis=2)
    use = fin if usable is None else np.asarray(usable, bool) & fin
    if use.shape != img.shape[:2]:
        raise ValueError(f"usable has shape {use.shape}; expected {img.shape[:2]}")
    a, b, floor, pix = [], [], [], []
    for c in range(img.shape[2]):
        ac, bc, n = _channel(img[..., c], use)
        vals = img[..., c][use]
        scale = float(np.percentile(np.abs(vals), 99)) if vals.size else 0.0
        a.append(ac)
        b.append(bc)
        floor.append((1e-3 * scale) ** 2 if scale > 0 else 1e-300)
        pix.append(n)
    return NoiseFit(np.array(a), np.array(b), np.array(floor), np.array(pix, dtype=np.int64))
