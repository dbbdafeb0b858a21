"""Region summaries of diffusion maps (median and its interval per parameter) and the known-sphere convenience
path (:func:`estimate_sphere`) (``estimation.diffusion``).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from ..gradients import GradientMaps
from .maps import DiffusionMaps, _derived, estimate_diffusion
from .models import _PARAMS, Array, _alpha_from_rd, _G_model, _model_rd, check_grounded_model, grounded_model_bias
from .sphere import invert_sphere, invert_sphere_scalar


# --------------------------------------------------------------------------------------------------------------
# region summaries
# --------------------------------------------------------------------------------------------------------------
def _median_ci(x: Array, confidence: float) -> tuple[float, float, float]:
    """Median and distribution-free order-statistic interval (binomial) for the median of i.i.d. samples.

    O(n): the three order statistics come from one ``np.partition`` in the maps' own precision (no full sort and
    no float64 copy of a 24-megapixel region).
    """
    x = np.asarray(x)
    fin = np.isfinite(x)
    if not fin.all():
        x = x[fin]
    n = x.size
    if n == 0:
        return float("nan"), float("nan"), float("nan")
    if n < 6:
        x = np.sort(x.astype(np.float64))
        return float(np.median(x)), float(x[0]), float(x[-1])
    lo_k = max(int(stats.binom.ppf((1 - confidence) / 2, n, 0.5)) - 1, 0)
    hi_k = min(int(stats.binom.isf((1 - confidence) / 2, n, 0.5)), n - 1)
    mid = sorted({(n - 1) // 2, n // 2})
    part = np.partition(x, sorted({lo_k, hi_k, *mid}))
    med = 0.5 * (float(part[(n - 1) // 2]) + float(part[n // 2]))
    return med, float(part[lo_k]), float(part[hi_k])


@dataclass(frozen=True)
class ParameterSummary:
    """Per-channel value (3,) and interval (3, 2) of one parameter over a region."""

    value: Array
    interval: Array


@dataclass(frozen=True)
class DiffusionSummary:
    """Region summary. ``params[name]`` for name in albedo, shortening, R_d, alpha_prime, l_prime_mm,
    sigma_t_prime_per_mm, sigma_s_prime_per_mm, sigma_a_per_mm, D_mm, l_d_mm, r2_mm2.

    ``status`` per channel: "ok", "censored" (a model bound was hit: the interval is one-sided) or
    "unknown" (no usable pixels; values NaN). ``n_pixels`` per channel. ``spread``: (3, 2) 25/75 %
    quantiles of the per-pixel D_mm (a dispersion diagnostic, not an interval).
    """

    params: dict[str, ParameterSummary]
    status: tuple[str, str, str]
    n_pixels: NDArray[np.int64]
    confidence: float
    method: str
    spread_D_mm: Array
    provenance: dict[str, Any] = field(default_factory=dict)

    def value(self, name: str) -> Array:
        return self.params[name].value

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"status": list(self.status), "n_pixels": self.n_pixels.tolist(),
                               "confidence": self.confidence, "method": self.method}
        for k, p in self.params.items():
            out[k] = {"value": p.value.tolist(), "interval": p.interval.tolist()}
        out["model"] = self.provenance.get("model", "dipole-jensen")
        if "model_bias" in self.provenance:
            out["model_bias"] = self.provenance["model_bias"]
        if "pixel_noise" in self.provenance:
            out["pixel_noise"] = self.provenance["pixel_noise"]
        return out


def summarize(dmaps: DiffusionMaps, region: ArrayLike | None = None, *, confidence: float = 0.95,
              systematic_shortening: float = 5e-4, systematic_albedo_rel: float = 2e-3,
              fdr: str = "fit", model: str | None = None, model_bias: bool = True,
              pixel_stderr: Mapping[str, ArrayLike] | None = None, invert: bool = True) -> DiffusionSummary:
    """Robust per-channel summary over ``region`` (default: every known pixel).

    ``model``: the profile model of the maps (default: the one recorded in ``dmaps.provenance``, else
    "dipole-jensen"); ``model_bias``: also report the model's bias against the Monte Carlo table at the summary's
    parameters (:func:`grounded_model_bias`) in ``provenance["model_bias"]`` (and :meth:`DiffusionSummary.as_dict`).

    When the radius is uniform over the region (a known sphere) the *observables* are pooled: median albedo and
    median shortening with order-statistic intervals for the median (i.i.d. pixel noise), widened by the
    systematic allowances (``systematic_shortening`` absolute, ``systematic_albedo_rel`` relative: residuals of
    the discrete-LED correction, docs/gradients.md), then inverted once with :func:`invert_sphere_scalar` (or
    the first-order formula for ``method="small_blur"``); the interval of every parameter is the range over the
    four corners of the (albedo, shortening) box, which is exact for these monotone maps. Otherwise (varying
    curvature) the parameters' own per-pixel medians and order-statistic intervals are reported.

    ``pixel_stderr``: {"albedo": (H, W, 3), "shortening": (H, W, 3)} per-pixel standard errors propagated from the
    frames' noise (:mod:`estimation.gradients.uncertainty`), optionally "albedo_rel_common" (3,): a relative
    standard error shared by every pixel (the albedo scale's, e.g. from a noisy reference target). The
    observables' intervals are then also at least median +- z sqrt(pi/2) sqrt(mean sigma^2 / n) (the median's
    standard error under the stated Gaussian noise; the common part added in quadrature to the albedo's),
    so a region whose pixels are noisier than their scatter shows (correlated noise, a smoothed demosaic) still
    gets the width its noise implies; pixels with an infinite standard error are left out of the summary.
    ``invert=False`` (a known sphere): the pooled observables only - albedo and shortening with their intervals,
    every other parameter NaN, no model bias - for callers that need nothing else (the Monte Carlo reference of
    :mod:`estimation.gradient_correction`, whose observables are these two; issue 19: the parameter inversions
    were ~1.8 s of a ~7 s reference call in its profile).
    """
    H, W = dmaps.albedo.shape[:2]
    if model is None:
        model = str(dmaps.provenance.get("model", "dipole-jensen"))
    check_grounded_model(model, dmaps.method, dmaps.eta)
    reg = np.ones((H, W), bool) if region is None else np.asarray(region, dtype=bool)
    eta = dmaps.eta
    vals = {k: np.full(3, np.nan) for k in _PARAMS}
    ints = {k: np.full((3, 2), np.nan) for k in _PARAMS}
    status: list[str] = []
    npix = np.zeros(3, np.int64)
    spread = np.full((3, 2), np.nan)
    for c in range(3):
        m = reg & ~dmaps.unknown[..., c]
        npix[c] = int(m.sum())
        if npix[c] == 0:
            status.append("unknown")
            continue
        d_c = dmaps.D_mm[..., c][m]
        spread[c] = np.percentile(d_c[np.isfinite(d_c)], [25, 75]) if np.isfinite(d_c).any() else np.nan
        radii = dmaps.radius_mm[m]
        uniform = np.ptp(radii) <= 1e-6 * float(np.max(radii))
        if pixel_stderr is not None:    # pixels without a first-order standard error carry no usable value
            for key in ("albedo", "shortening"):
                m = m & np.isfinite(np.asarray(pixel_stderr[key])[..., c])
            npix[c] = int(m.sum())
            if npix[c] == 0:
                status.append("unknown")
                continue
        A_med, A_lo, A_hi = _median_ci(dmaps.albedo[..., c][m], confidence)
        S_med, S_lo, S_hi = _median_ci(dmaps.shortening[..., c][m], confidence)
        if pixel_stderr is not None:
            z = float(stats.norm.ppf(0.5 + confidence / 2))
            hw = {key: z * np.sqrt(np.pi / 2 * np.mean(np.asarray(pixel_stderr[key], dtype=np.float64)[..., c][m] ** 2)
                                   / npix[c]) for key in ("albedo", "shortening")}
            if "albedo_rel_common" in pixel_stderr:     # e.g. the albedo scale's, shared by every pixel
                rel = float(np.asarray(pixel_stderr["albedo_rel_common"], dtype=np.float64).reshape(-1)[c])
                hw["albedo"] = float(np.hypot(hw["albedo"], z * rel * A_med))
            A_lo, A_hi = min(A_lo, A_med - hw["albedo"]), max(A_hi, A_med + hw["albedo"])
            S_lo, S_hi = min(S_lo, S_med - hw["shortening"]), max(S_hi, S_med + hw["shortening"])
        vals["albedo"][c], ints["albedo"][c] = A_med, (A_lo * (1 - systematic_albedo_rel),
                                                      A_hi * (1 + systematic_albedo_rel))
        vals["shortening"][c], ints["shortening"][c] = S_med, (S_lo - systematic_shortening,
                                                              S_hi + systematic_shortening)
        if uniform and not invert:
            status.append("ok")
        elif uniform:
            rho = float(radii[0])

            def solve(a: float, s: float) -> tuple[dict[str, float], bool]:
                if dmaps.method == "sphere":
                    al, ll, cens = invert_sphere_scalar(a, s, rho, eta, fdr=fdr)
                else:
                    al, c_a = _alpha_from_rd(a, eta, fdr, model)
                    r2 = 4.0 * (1.0 - s) * rho * rho / 2.0
                    G = _G_model(al, eta, fdr, model)
                    cens = r2 <= 0 or c_a
                    ll = float(np.sqrt(max(r2, 0.0) / G)) if G > 0 else float("nan")
                    ll = max(ll, 1e-4 * rho)
                d = _derived(np.array(al), np.array(ll), eta, fdr)
                if model != "dipole-jensen":
                    d["R_d"] = np.asarray(_model_rd(al, eta, fdr, model))
                    d["r2_mm2"] = np.asarray(ll * ll * G)
                return {k: float(v) for k, v in d.items()}, cens

            if dmaps.method == "sphere" and model == "dipole-jensen":    # point and four corners in one vectorized inversion (invert_sphere
                # agrees with the scalar reference to < 1e-9 relative; 5 x 28 ms -> ~10 ms)
                a5 = np.array([A_med] + [a for a in ints["albedo"][c] for _ in (0, 1)], dtype=np.float64)
                s5 = np.array([S_med] + list(ints["shortening"][c]) * 2, dtype=np.float64)
                al5, ll5, ce5 = invert_sphere(a5, s5, rho, eta, fdr=fdr)
                d5 = _derived(al5, ll5, eta, fdr)
                point, cens = {k: float(v[0]) for k, v in d5.items()}, bool(ce5[0])
                corners = [{k: float(v[i]) for k, v in d5.items()} for i in range(1, 5)]
            else:
                point, cens = solve(A_med, S_med)
                corners = [solve(a, s)[0] for a in ints["albedo"][c] for s in ints["shortening"][c]]
            for k, v in point.items():
                vals[k][c] = v
                cv = np.array([cn[k] for cn in corners] + [v])
                ints[k][c] = (np.nanmin(cv), np.nanmax(cv))
            status.append("censored" if cens else "ok")
        else:
            cens = bool(np.mean(dmaps.censored[..., c][m]) > 0.5)
            for k in ("R_d", "alpha_prime", "l_prime_mm", "sigma_t_prime_per_mm", "sigma_s_prime_per_mm",
                      "sigma_a_per_mm", "D_mm", "l_d_mm", "r2_mm2"):
                med, lo, hi = _median_ci(getattr(dmaps, k)[..., c][m], confidence)
                vals[k][c], ints[k][c] = med, (lo, hi)
            status.append("censored" if cens else "ok")
    params = {k: ParameterSummary(vals[k], ints[k]) for k in _PARAMS}
    prov = {"confidence": confidence, "systematic_shortening": systematic_shortening,
            "systematic_albedo_rel": systematic_albedo_rel, "maps": dmaps.provenance, "model": model,
            "pixel_noise": "frames' noise propagated (at least the median's standard error under it)"
            if pixel_stderr is not None else "order statistics of the pixels' scatter"}
    if model_bias and invert:
        try:
            prov["model_bias"] = grounded_model_bias(vals["sigma_s_prime_per_mm"], vals["sigma_a_per_mm"], eta,
                                                     model, fdr=fdr)
        except (ValueError, FileNotFoundError) as exc:  # e.g. eta outside the table: say so, do not fail
            prov["model_bias"] = {"available": False, "reason": str(exc)}
    st3 = (status[0], status[1], status[2])
    return DiffusionSummary(params, st3, npix, confidence, dmaps.method, spread, prov)


# --------------------------------------------------------------------------------------------------------------
# sphere convenience (the end-to-end demo path)
# --------------------------------------------------------------------------------------------------------------
def sphere_geometry(camera: Any, center_mm: ArrayLike, radius_mm: float) -> tuple[Array, Array, NDArray[np.bool_]]:
    """(normals (H, W, 3) NaN off the sphere, view directions (H, W, 3) towards the camera, hit mask (H, W))
    for a :class:`estimation.camera.PinholeCamera` and a sphere in the rig frame."""
    from ..camera import intersect_sphere

    origins, dirs = camera.pixel_rays()
    pts, hit = intersect_sphere(origins, dirs, center_mm, radius_mm)
    n = (pts - np.asarray(center_mm, dtype=np.float64)) / float(radius_mm)
    view = -dirs
    return n, view, hit


@dataclass(frozen=True)
class SphereEstimate:
    """Per-pixel grounded maps and their region summary for a known sphere."""

    maps: DiffusionMaps
    summary: DiffusionSummary


def estimate_sphere(maps: GradientMaps, *, radius_mm: float, true_normals: ArrayLike | None = None,
                    camera: Any = None, center_mm: ArrayLike | None = None, region: ArrayLike | None = None,
                    method: str = "sphere", erode_px: int = 2, confidence: float = 0.95,
                    fdr: str = "fit", inversion: str = "table", tile_rows: int = 256,
                    out_dir: str | Path | None = None, workers: int | None = None,
                    model: str = "dipole-jensen", pixel_stderr: Mapping[str, ArrayLike] | None = None,
                    invert_summary: bool = True) -> SphereEstimate:
    """Grounded estimate on a known sphere: per-pixel maps plus the region summary (median + interval).

    The true normals come from ``true_normals`` (H, W, 3) or from ``camera`` + ``center_mm`` via
    :func:`sphere_geometry`. ``region`` defaults to the pixels on the sphere, eroded by ``erode_px`` so that
    silhouette pixels (partly background) are not used; masked / grazing / dark pixels of ``maps`` are excluded.
    ``inversion``, ``tile_rows``, ``out_dir``: see :func:`estimate_diffusion` (the summary always inverts exactly;
    ``invert_summary=False``: the summary's observables only, :func:`summarize`'s ``invert``).
    ``pixel_stderr``: the frames' noise propagated to the albedo and shortening maps (:func:`summarize`).
    """
    from scipy import ndimage

    if true_normals is None:
        if camera is None or center_mm is None:
            raise ValueError("give true_normals, or camera and center_mm")
        true_normals = sphere_geometry(camera, center_mm, radius_mm)[0]
    H, W = maps.shape
    if np.shape(true_normals) != (H, W, 3):
        raise ValueError(f"true_normals must be (H, W, 3) = {(H, W, 3)}, got {np.shape(true_normals)}")
    if region is None:
        reg = np.empty((H, W), bool)
        for r0 in range(0, H, tile_rows):
            t = np.asarray(true_normals[r0:r0 + tile_rows])
            reg[r0:r0 + tile_rows] = np.isfinite(t[..., 0] + t[..., 1] + t[..., 2])
    else:
        reg = np.asarray(region, dtype=bool)
    if erode_px > 0:
        reg = ndimage.binary_erosion(reg, iterations=int(erode_px))
    dm = estimate_diffusion(maps, true_normals, sphere_radius_mm=radius_mm, method=method, region=reg, fdr=fdr,
                            inversion=inversion, tile_rows=tile_rows, out_dir=out_dir, workers=workers,
                            model=model)
    return SphereEstimate(dm, summarize(dm, reg, confidence=confidence, fdr=fdr, model=model,
                                        pixel_stderr=pixel_stderr, invert=invert_summary))
