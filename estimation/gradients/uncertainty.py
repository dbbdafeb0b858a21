"""Per-pixel standard errors of the gradient maps from the frames' noise (issue 16, "intervals that mean something").

Every output of :func:`estimation.gradients.compute_maps` at a pixel is a function of that pixel's frame values
only (the ideal formulas v_a = (I_a - I_a~)/(I_a + I_a~) or 2 I_a / I_full - 1, the LED rig's per-pixel linear
solve at its lookup normal, the albedo's Fresnel and irradiance factors). With independent noise in the frames
(standard error sigma_p per pixel of frame p: shot + read noise, or a renderer's standard-error image) the
first-order (delta-method) variance of an output f is

    var f = sum_p (df/dI_p)^2 sigma_p^2 .

:func:`propagate_frame_noise` evaluates the derivatives through the same per-pixel formulas (the caller's
``maps_fn``, i.e. ``compute_maps`` itself) by a finite difference per frame, for all pixels of a band of rows at
once: f(I + h sigma_p e_pc) - f(I), h = ``step`` (0.25 standard errors: the second-order term of a ratio is
~h sigma/I of the first, < 1 % for a signal 25 x its noise), one extra map computation per frame and colour
channel (the channels' noise is independent; the specular normals sum the channels). Where the
forward step leaves the pixel's domain (a threshold of the masks), the backward step is used; where both do, the
pixel's standard error is inf (no first-order information). The outputs:

- ``albedo`` (H, W, 3): standard error of the R_d map;
- ``diffuse_normal_rad`` (H, W, 3): per tangential component, the standard error of each channel's diffuse normal
  (radians, small angles: sqrt of half the summed squared tangential change);
- ``specular_normal_rad`` (H, W) or None: the same for the specular normals;
- ``shortening`` (H, W, 3) or None (with ``true_normals``): of S = v.n_true / tau_ratio
  (:mod:`estimation.diffusion`).

References: Ma et al. 2007 (the per-pixel formulas); the delta method (e.g. Casella & Berger, Statistical
Inference, sec. 5.5.4); ``docs/gradients.md`` sec. 9 ("Noise images").
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["MapNoise", "shot_read_stderr", "propagate_frame_noise"]

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class MapNoise:
    """Per-pixel standard errors of the gradient maps (float32; NaN where the map is unknown, inf where no
    first-order derivative exists); see the module docstring."""

    albedo: F32
    diffuse_normal_rad: F32
    specular_normal_rad: F32 | None
    shortening: F32 | None
    provenance: dict[str, Any] = field(default_factory=dict)

    def summary(self, region: ArrayLike | None = None) -> dict[str, Any]:
        """Per-channel medians over ``region`` (H, W) of the finite standard errors (JSON-ready)."""
        reg = None if region is None else np.asarray(region, dtype=bool)

        def med(a: Any) -> Any:
            a = np.asarray(a)
            out = []
            for c in range(a.shape[-1]) if a.ndim == 3 else [None]:
                v = a[..., c] if c is not None else a
                v = v[reg] if reg is not None else v.ravel()
                v = v[np.isfinite(v)]
                out.append(float(np.median(v)) if v.size else None)
            return out if a.ndim == 3 else out[0]
        out = {"albedo_stderr_median": med(self.albedo),
               "diffuse_normal_stderr_rad_median": med(self.diffuse_normal_rad)}
        if self.specular_normal_rad is not None:
            out["specular_normal_stderr_rad_median"] = med(self.specular_normal_rad)
        if self.shortening is not None:
            out["shortening_stderr_median"] = med(self.shortening)
        return out


def shot_read_stderr(values: ArrayLike, electrons_per_value: ArrayLike, read_noise_values: ArrayLike = 0.0
                     ) -> F32:
    """Standard error (frame values) of a raw linear frame: sqrt(max(I, 0) / g + r^2) with g electrons per value
    (per channel or scalar) and r the read noise in values (Poisson photo-electrons + Gaussian read noise)."""
    I = np.asarray(values, dtype=np.float64)
    g = np.asarray(electrons_per_value, dtype=np.float64)
    r = np.asarray(read_noise_values, dtype=np.float64)
    if np.any(~(g > 0)):
        raise ValueError(f"electrons_per_value must be > 0, got {g.tolist()}")
    if np.any(~(r >= 0)):
        raise ValueError(f"read_noise must be >= 0, got {r.tolist()}")
    return np.sqrt(np.maximum(I, 0.0) / g + r * r).astype(np.float32)


def _tangential_sq(dn: NDArray[np.float64], n: NDArray[np.float64]) -> NDArray[np.float64]:
    """|dn - (dn.n) n|^2 over the last axis."""
    t = dn - np.sum(dn * n, axis=-1, keepdims=True) * n
    return np.sum(t * t, axis=-1)


def propagate_frame_noise(maps_fn: Callable[[dict[Any, NDArray[np.float32]], slice], Any],
                          frames: Mapping[Any, Any], stderr: Mapping[Any, Any], *,
                          true_normals: Any = None, tau_ratio: float | None = None, step: float = 0.25,
                          rows_per_band: int = 256) -> MapNoise:
    """First-order standard errors of the gradient maps (module docstring).

    ``maps_fn(frames_band, rows)`` computes the maps (an object with ``albedo`` (h, W, 3), ``diffuse_normals``
    (h, W, 3, 3) and ``specular_normals`` (h, W, 3) or None) of the rows ``rows`` from ``frames_band`` (the frames'
    rows, by key); ``frames`` and ``stderr`` map the same keys to (H, W, 3) arrays (frame values; a key missing
    from ``stderr`` or with zero standard errors is noise-free). ``true_normals`` (H, W, 3) with ``tau_ratio``:
    also the shortening's standard error. Bands of ``rows_per_band`` rows bound the memory (1 + frames map
    computations per band)."""
    keys = list(frames)
    if not keys:
        raise ValueError("no frames")
    H, W = np.shape(frames[keys[0]])[:2]
    for k, s in stderr.items():
        if k not in frames:
            raise ValueError(f"stderr for {k!r}, which is not a frame")
        if tuple(np.shape(s)) not in ((H, W, 3), (H, W)):
            raise ValueError(f"stderr {k!r}: expected shape ({H}, {W}, 3) or ({H}, {W}), got {np.shape(s)}")
    if not step > 0:
        raise ValueError(f"step must be > 0, got {step}")
    if true_normals is not None and not (tau_ratio and tau_ratio > 0):
        raise ValueError("true_normals need tau_ratio > 0")
    alb = np.full((H, W, 3), np.nan, np.float32)
    dnr = np.full((H, W, 3), np.nan, np.float32)
    spr: F32 | None = None
    sho = None if true_normals is None else np.full((H, W, 3), np.nan, np.float32)
    n_calls = 0
    for r0 in range(0, H, int(rows_per_band)):
        rows = slice(r0, min(H, r0 + int(rows_per_band)))
        fb = {k: np.asarray(frames[k][rows], dtype=np.float32) for k in keys}
        base = maps_fn(fb, rows)
        n_calls += 1
        a0 = np.asarray(base.albedo, dtype=np.float64)
        n0 = np.asarray(base.diffuse_normals, dtype=np.float64)
        s0 = None if base.specular_normals is None else np.asarray(base.specular_normals, dtype=np.float64)
        tn = None if true_normals is None else np.asarray(true_normals[rows], dtype=np.float64)
        v0 = None if tn is None else np.asarray(base.diffuse_vectors, dtype=np.float64)
        acc_a = np.zeros(a0.shape)
        acc_n = np.zeros(a0.shape)
        acc_s = None if s0 is None else np.zeros(s0.shape[:2])
        acc_S = None if tn is None else np.zeros(a0.shape)
        jobs = []
        for k in keys:
            if k not in stderr:
                continue
            se_k = np.asarray(stderr[k][rows], dtype=np.float32)
            if se_k.ndim == 2:
                se_k = np.repeat(se_k[..., None], 3, axis=-1)
            for ch in range(3):     # channels separately: their noise is independent (the specular sum mixes them)
                if np.any(se_k[..., ch] > 0):
                    jobs.append((k, ch, se_k))
        for k, ch, se_k in jobs:
            se = np.zeros_like(se_k)
            se[..., ch] = np.nan_to_num(se_k[..., ch], posinf=0.0)
            inf_px = ~np.isfinite(se_k[..., ch])        # no information on the frame there: inf at the outputs
            results = []
            for sign in (1.0, -1.0):
                pert = dict(fb)
                pert[k] = fb[k] + np.float32(sign * step) * se
                m = maps_fn(pert, rows)
                n_calls += 1
                da = (np.asarray(m.albedo, dtype=np.float64) - a0) / (sign * step)
                dn = (np.asarray(m.diffuse_normals, dtype=np.float64) - n0) / (sign * step)
                ds = None if s0 is None else (np.asarray(m.specular_normals, dtype=np.float64) - s0) / (sign * step)
                dv = None if v0 is None else (np.asarray(m.diffuse_vectors, dtype=np.float64) - v0) / (sign * step)
                results.append((da, dn, ds, dv))
                lost = ~np.isfinite(da) & np.isfinite(a0)
                if not lost.any():
                    break
            da, dn, ds, dv = results[0]
            if len(results) == 2:       # the backward step where the forward one left the domain
                db, dnb, dsb, dvb = results[1]
                da = np.where(np.isfinite(da), da, db)
                dn = np.where(np.isfinite(dn).all(-1, keepdims=True), dn, dnb)
                if ds is not None and dsb is not None:
                    ds = np.where(np.isfinite(ds).all(-1, keepdims=True), ds, dsb)
                if dv is not None and dvb is not None:
                    dv = np.where(np.isfinite(dv).all(-1, keepdims=True), dv, dvb)
            if inf_px.any():
                da = np.where(inf_px[..., None], np.inf, da)
                dn = np.where(inf_px[..., None, None], np.inf, dn)
                ds = None if ds is None else np.where(inf_px[..., None], np.inf, ds)
                dv = None if dv is None else np.where(inf_px[..., None, None], np.inf, dv)
            acc_a += np.where(np.isfinite(a0), np.nan_to_num(da, nan=np.inf) ** 2, 0.0)
            acc_n += np.where(np.isfinite(n0).all(-1), np.nan_to_num(_tangential_sq(dn, n0), nan=np.inf), 0.0)
            if acc_s is not None and ds is not None and s0 is not None:
                acc_s += np.where(np.isfinite(s0).all(-1), np.nan_to_num(_tangential_sq(ds, s0), nan=np.inf), 0.0)
            if acc_S is not None and tn is not None and dv is not None:
                # S = v.n_true / tau_ratio: the diffuse vectors' change along the true normal
                dS = np.sum(dv * tn[:, :, None, :], axis=-1) / float(tau_ratio)
                acc_S += np.where(np.isfinite(a0), np.nan_to_num(dS, nan=np.inf) ** 2, 0.0)
        alb[rows] = np.where(np.isfinite(a0), np.sqrt(acc_a), np.nan)
        dnr[rows] = np.where(np.isfinite(n0).all(-1), np.sqrt(0.5 * acc_n), np.nan)
        if acc_s is not None and s0 is not None:
            if spr is None:
                spr = np.full((H, W), np.nan, np.float32)
            spr[rows] = np.where(np.isfinite(s0).all(-1), np.sqrt(0.5 * acc_s), np.nan)
        if sho is not None and acc_S is not None:
            sho[rows] = np.where(np.isfinite(a0), np.sqrt(acc_S), np.nan)
    prov = {"method": "first-order propagation of per-frame standard errors through compute_maps' per-pixel "
                      "formulas (finite difference per frame, estimation.gradients.uncertainty)",
            "step_stderr": float(step), "frames_with_noise": sorted(str(k) for k in stderr), "map_calls": n_calls}
    return MapNoise(alb, dnr, spr, sho, prov)
