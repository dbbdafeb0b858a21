"""Diffusion parameters of surfaces with relief, per window and per region, with intervals and a status.

The diffuse (cross-polarized) normal field of a translucent surface is its true (specular) normal field blurred
by the subsurface transport: in the linear regime of small slopes the tangential components are filtered by the
modulation transfer M(k) = R^(k) / R^(0) of the diffusion profile (Ma et al. 2007, sec. 5; Zhu et al., the seed;
Jensen et al. 2001 for R^(k): :func:`estimation.dipole.hankel_transform`). :func:`estimation.diffusion.fit_relief`
fits one length per channel to a whole map; this module fits it per window of a stated size and over a region and
says how much the data constrain it:

- the reduced albedo alpha' comes from the window's median R_d (``albedo``, exit Fresnel divided out) times the
  exit normalization c(eta) = 1 - 2 FM1_ext(eta) (0.939 at eta 1.3; :func:`exit_normalization`), the reduced
  mean free path l' = 1/sigma_t' from the blur; then sigma_s' = alpha'/l', sigma_a = (1 - alpha')/l',
  sigma_tr = sqrt(3 sigma_a sigma_t'), l_d = 1/sigma_tr, D = l'/3 (science.md sec. 1);
- M depends on k only through k l' for a given alpha' (the profile scales with l'), so it is tabulated once per
  window and channel on a grid of k l' and the cost is evaluated on a grid of l' (log-spaced between
  ``pixel_mm/4`` and twice the window's extent) and refined by a parabola in log l';
- the interval is the profile-likelihood one: every l' whose cost exceeds the minimum by less than
  chi^2_1(confidence) times the residual variance (weighted least squares, the residual's per-pixel variance
  estimated from the fit; its spatial correlation and the linear model's error are *not* in it), then widened by
  the model's known relative bias ``model_bias_rel`` (the relief fit on Monte Carlo frames reads l' up to ~25-35 %
  off: tests/simulators/test_mc_frames_gradients.py, issue 16) and by the albedo's systematic uncertainty;
- status per window and channel: "unknown" (no usable albedo -- dark or NaN --, too few valid pixels, or a relief
  whose normal-field variance is not above its noise: a flat region carries no information about a length),
  "weak" (the profile interval reaches a bound of the l' grid -- only a one-sided bound -- or spans more than a
  factor ``weak_ratio``), "ok". Unknown windows report NaN values and the whole grid range as their interval.

**Exit normalization.** The map's convention divides the cross-polarized value by F_t(eta, n.v)/pi and the
transmitted irradiance E_t. By reciprocity a half-space under uniform radiance L, seen from v, sends
L_o = L F_t(eta, v) R_d(v) (R_d(v): the total diffuse reflectance per unit power entering for collimated light from
v; the dipole's and the Monte Carlo table's R_d at normal incidence), while E_t = c pi L. So the map reads
R_d(v) / c, not R_d: 6.5 % high at eta 1.3, which at alpha' ~ 0.999 moves 1 - alpha' by a factor ~3 and l_d by
~1.7. Measured with the project's Monte Carlo renderer (simulators.mc, 200k photons per channel, cosine-weighted
incidence, exit cos >= 0.9; docs/model-error.md "Issue 16 acceptance, measured"): pi L_o / (F_t E_t) over the
table's R_d = 1.060-1.064 (+-0.005) for marble, apple, skimmilk and skin1, every channel. The fit therefore
inverts alpha' from c x the map's R_d (``exit_normalization``; 1.0 restores the old behaviour).

The noise of a normal field is estimated from its second differences (robust MAD; a smooth relief contributes
little to them): sigma^2 = (1.4826 MAD)^2 / 6 per component.

References: Ma et al. 2007; Zhu, Peers, Debevec, Ghosh (the seed); Jensen et al. 2001; ``docs/gradients.md``
sec. 9; ``shared/reference/science.md`` sec. 1, 3-4.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .dipole import reduced_albedo_from_total_reflectance

__all__ = ["RELIEF_PARAMS", "STATUS_CODES", "ReliefFit", "ReliefRegion", "SeedComparison", "compare_seed",
           "exit_normalization", "fit_relief_windows", "summarize_relief", "normal_noise_rad", "parameters_from_l_prime", "normals_from_height"]

Array = NDArray[np.float64]
RELIEF_PARAMS: tuple[str, ...] = ("l_prime_mm", "l_d_mm", "D_mm", "sigma_s_prime_per_mm", "sigma_a_per_mm",
                                  "alpha_prime")
STATUS_CODES = {"unknown": 0, "weak": 1, "ok": 2}
_N_GRID = 48


def normal_noise_rad(normals: ArrayLike, comps: tuple[int, int] | None = None) -> float:
    """Per-pixel noise standard deviation (radians, small angles) of a normal field (h, w, 3), from the robust
    MAD of its second differences along both image axes: a smooth relief contributes ~(2 pi px / lambda)^2 of its
    amplitude to them, white noise sqrt(6) sigma."""
    n = np.asarray(normals, dtype=np.float64)
    cs = comps if comps is not None else tuple(np.argsort(np.nanvar(n.reshape(-1, 3), axis=0))[-2:])
    d2 = []
    for c in cs:
        a = n[..., c]
        if a.shape[0] >= 3:
            d2.append((a[2:] - 2 * a[1:-1] + a[:-2]).ravel())
        if a.shape[1] >= 3:
            d2.append((a[:, 2:] - 2 * a[:, 1:-1] + a[:, :-2]).ravel())
    v = np.concatenate(d2) if d2 else np.array([np.nan])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    mad = float(np.median(np.abs(v - np.median(v))))
    return 1.4826 * mad / np.sqrt(6.0)


def exit_normalization(eta: float) -> float:
    """c(eta) = 1 - 2 FM1_ext(eta) = int F_t(eta, mu) 2 mu dmu (0.9389 at eta 1.3, 0.9082 at 1.5): the fraction of
    uniform radiance a smooth dielectric transmits (E_t / E) and the normalization of the exit radiance F_t/(pi c)
    (pbrt's SeparableBSSRDF::Sw; :func:`estimation.mc_table.exit_radiance_factor`). The R_d map of
    :func:`estimation.gradients.compute_maps` reads R_d / c on a half-space (module docstring)."""
    from .fresnel import fresnel_moment
    return float(1.0 - 2.0 * fresnel_moment(eta, 1, side="external"))


def parameters_from_l_prime(alpha_prime: ArrayLike, l_prime_mm: ArrayLike) -> dict[str, Array]:
    """sigma_t' = 1/l', sigma_s' = alpha' sigma_t', sigma_a = (1 - alpha') sigma_t', l_d = 1/sqrt(3 sigma_a sigma_t'),
    D = l'/3 (science.md sec. 1)."""
    a = np.asarray(alpha_prime, dtype=np.float64)
    lp = np.asarray(l_prime_mm, dtype=np.float64)
    st = 1.0 / lp
    sa = (1.0 - a) * st
    with np.errstate(divide="ignore", invalid="ignore"):
        l_d = 1.0 / np.sqrt(3.0 * sa * st)
    return {"l_prime_mm": lp, "l_d_mm": l_d, "D_mm": lp / 3.0, "sigma_s_prime_per_mm": a * st,
            "sigma_a_per_mm": sa, "alpha_prime": a + 0.0 * lp}


def normals_from_height(height_mm: ArrayLike, pixel_mm: float, rotation: ArrayLike) -> Array:
    """Rig-frame unit normals (h, w, 3) of a height field ``height_mm`` (h, w) sampled on an orthographic camera's
    pixel grid (height towards the camera), for the camera ``rotation`` (rows: right, down, forward in the rig
    frame): in camera coordinates n = (-dh/dx, -dh/dy, -1) / norm (x right, y down, z away from the camera)."""
    h = np.asarray(height_mm, dtype=np.float64)
    gy, gx = np.gradient(h, pixel_mm)
    n_cam = np.stack([-gx, -gy, -np.ones_like(h)], axis=-1)
    n_cam /= np.linalg.norm(n_cam, axis=-1, keepdims=True)
    return n_cam @ np.asarray(rotation, dtype=np.float64)          # R^T n per pixel


@dataclass(frozen=True)
class ReliefFit:
    """Per-window results. Window (i, j) covers rows ``origins_px[i, j, 0] + [0, window_px)`` and columns
    ``origins_px[i, j, 1] + [0, window_px)``. ``values[name]`` (ny, nx, 3), ``intervals[name]`` (ny, nx, 3, 2) for
    name in :data:`RELIEF_PARAMS`; ``status`` (ny, nx, 3) of "ok" | "weak" | "unknown"; ``relief_rms_rad`` and
    ``relief_noise_rad`` (ny, nx): RMS tangential tilt of the true normals in the window and its estimated
    per-pixel noise; ``diffuse_noise_rad`` (ny, nx, 3); ``l_grid_mm``: the (min, max) searched."""

    window_px: int
    stride_px: int
    pixel_mm: float
    origins_px: NDArray[np.int64]
    values: dict[str, Array]
    intervals: dict[str, Array]
    status: NDArray[np.str_]
    relief_rms_rad: Array
    relief_noise_rad: Array
    diffuse_noise_rad: Array
    l_grid_mm: tuple[float, float]
    provenance: dict[str, Any] = field(default_factory=dict)

    def pixel_map(self, name: str, shape: tuple[int, int], which: str = "value") -> NDArray[np.float32]:
        """A full-resolution (H, W, 3) map: each pixel takes the value (or interval ``"lo"`` / ``"hi"``, or the
        status code of :data:`STATUS_CODES` for ``name = "status"``) of the last window covering it; NaN where no
        window does."""
        if name == "status":
            v = np.vectorize(STATUS_CODES.__getitem__, otypes=[np.float32])(self.status)
        elif which == "value":
            v = self.values[name]
        else:
            v = self.intervals[name][..., 0 if which == "lo" else 1]
        return self.window_map(v, shape)

    def window_map(self, per_window: ArrayLike, shape: tuple[int, int]) -> NDArray[np.float32]:
        """A full-resolution (H, W, 3) float32 map of per-window values (ny, nx, 3): each pixel takes the value of
        the last window covering it; NaN where no window does."""
        v = np.asarray(per_window, dtype=np.float32)
        out = np.full(shape + (3,), np.nan, np.float32)
        ny, nx = self.origins_px.shape[:2]
        for i in range(ny):
            for j in range(nx):
                r0, c0 = self.origins_px[i, j]
                out[r0:r0 + self.window_px, c0:c0 + self.window_px] = v[i, j]
        return out


@dataclass(frozen=True)
class SeedComparison:
    """The seed's D = k R_d / |n_z| against the relief fit, per window: ``ratio`` (ny, nx, 3) the window's median
    seed D over its fitted D; ``disagree`` (ny, nx, 3) where the seed's median lies outside the fit's interval
    (windows whose fit is not "unknown" and whose seed D is known); per channel the median ratio and the fraction
    of compared windows that disagree (NaN without any)."""

    ratio: Array
    disagree: NDArray[np.bool_]
    compared: NDArray[np.bool_]
    median_ratio: Array
    fraction_disagree: Array

    def as_dict(self) -> dict[str, Any]:
        return {"median_ratio": self.median_ratio.tolist(), "fraction_disagree": self.fraction_disagree.tolist(),
                "windows_compared": self.compared.sum(axis=(0, 1)).tolist(),
                "rule": "disagree: the window's median seed D outside the relief fit's D interval"}


def compare_seed(seed_D_mm: ArrayLike, fit: ReliefFit, *, min_known_fraction: float = 0.5) -> SeedComparison:
    """Compare the seed's D map (H, W, 3; NaN where unknown) with the relief fit window by window (issue 16: "the
    seed's D = k R_d / |n_z| with its calibrated k beside it, and where the two disagree, a map of that").

    A window is compared in a channel when its fit is "ok" or "weak" and at least ``min_known_fraction`` of its
    pixels have a finite seed D; the two disagree when the seed's median over the window lies outside the fit's
    interval (which already carries the relief model's bias): k is an empirical length calibrated on one reference,
    so a disagreement says the seed's proportionality does not hold here, not which of the two is right."""
    sd = np.asarray(seed_D_mm)
    ny, nx = fit.origins_px.shape[:2]
    ratio = np.full((ny, nx, 3), np.nan)
    disagree = np.zeros((ny, nx, 3), bool)
    compared = np.zeros((ny, nx, 3), bool)
    w = fit.window_px
    for i in range(ny):
        for j in range(nx):
            r0, c0 = fit.origins_px[i, j]
            block = np.asarray(sd[r0:r0 + w, c0:c0 + w], dtype=np.float64)
            for c in range(3):
                if fit.status[i, j, c] == "unknown":
                    continue
                v = block[..., c]
                ok = np.isfinite(v) & (v > 0)
                if ok.mean() < min_known_fraction:
                    continue
                med = float(np.median(v[ok]))
                lo, hi = fit.intervals["D_mm"][i, j, c]
                compared[i, j, c] = True
                ratio[i, j, c] = med / fit.values["D_mm"][i, j, c]
                disagree[i, j, c] = not (lo <= med <= hi)
    n = compared.sum(axis=(0, 1))
    med_ratio = np.array([np.median(ratio[..., c][compared[..., c]]) if n[c] else np.nan for c in range(3)])
    frac = np.array([disagree[..., c].sum() / n[c] if n[c] else np.nan for c in range(3)])
    return SeedComparison(ratio, disagree, compared, med_ratio, frac)


@dataclass(frozen=True)
class ReliefRegion:
    """Region summary: ``values[name]`` (3,), ``intervals[name]`` (3, 2), ``status`` per channel, the number of
    windows used per channel and how the interval was made (``method``)."""

    values: dict[str, Array]
    intervals: dict[str, Array]
    status: tuple[str, str, str]
    n_windows: NDArray[np.int64]
    method: str
    confidence: float
    provenance: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"status": list(self.status), "n_windows": self.n_windows.tolist(),
                               "method": self.method, "confidence": self.confidence}
        for k in RELIEF_PARAMS:
            out[k] = {"value": self.values[k].tolist(), "interval": self.intervals[k].tolist()}
        out.update(self.provenance)
        return out


# --------------------------------------------------------------------------------------------------------------
# one window
# --------------------------------------------------------------------------------------------------------------
def _alpha_from_rd(R_d: float, eta: float, fdr: str, model: str) -> float:
    """alpha' of a half-space of total diffuse reflectance R_d: the Jensen dipole's (science.md sec. 1) or the Monte
    Carlo table's (:meth:`estimation.mc_table.McProfileTable.invert_albedo`)."""
    if model == "mc-table":
        from .mc_table import default_table
        return float(default_table().invert_albedo(R_d, eta, out_of_range="clip"))
    return float(reduced_albedo_from_total_reflectance(R_d, eta, fdr=fdr))


def _window_origins(n: int, window: int, stride: int) -> list[int]:
    if n < window:
        return []
    o = list(range(0, n - window + 1, stride))
    if o[-1] != n - window:
        o.append(n - window)
    return o


def _derived_interval(alpha: float, alpha_lo: float, alpha_hi: float, l_lo: float, l_hi: float
                      ) -> dict[str, tuple[float, float]]:
    corners = [parameters_from_l_prime(a, lp) for a in (alpha_lo, alpha_hi) for lp in (l_lo, l_hi)]
    out = {}
    for k in RELIEF_PARAMS:
        v = np.array([float(c[k]) for c in corners])
        out[k] = (float(np.nanmin(v)), float(np.nanmax(v))) if np.isfinite(v).any() else (0.0, float("inf"))
    return out


def _derived_intervals(alpha_lo: Array, alpha_hi: Array, l_lo: Array, l_hi: Array) -> dict[str, Array]:
    """:func:`_derived_interval` for arrays of jobs: {name: (n, 2)} (0, inf) where no corner is finite."""
    corners = [parameters_from_l_prime(a, lp) for a in (alpha_lo, alpha_hi) for lp in (l_lo, l_hi)]
    out = {}
    for k in RELIEF_PARAMS:
        v = np.stack([np.broadcast_to(c[k], np.shape(l_lo)) for c in corners])
        fin = np.isfinite(v).any(axis=0)
        with warnings.catch_warnings():           # all-NaN columns: replaced below
            warnings.simplefilter("ignore", RuntimeWarning)
            lo = np.where(fin, np.nanmin(v, axis=0), 0.0)
            hi = np.where(fin, np.nanmax(v, axis=0), np.inf)
        out[k] = np.stack([lo, hi], axis=-1)
    return out


def _band(a: Any, rows: slice, dtype: Any = np.float64) -> NDArray[Any]:
    """Rows ``rows`` of an array-like (ndarray, memory map or a derived map computing a slice on access)."""
    return np.asarray(a[rows], dtype=dtype)


def fit_relief_windows(diffuse_normals: ArrayLike, true_normals: ArrayLike, albedo: ArrayLike, pixel_mm: float,
                       eta: float, *, window_px: int = 64, stride_px: int | None = None,
                       valid: ArrayLike | None = None, region: ArrayLike | None = None,
                       min_valid_fraction: float = 0.9,
                       margin_px: int | None = None, confidence: float = 0.95, model_bias_rel: float = 0.3,
                       albedo_rel_uncertainty: float = 0.1, weak_ratio: float = 4.0, min_relief_snr: float = 2.0,
                       min_relief_rad: float = 2e-3, fdr: str = "fit", exit_norm: float | None = None,
                       model: str = "dipole-jensen", search_step: int = 3, workers: int = 1,
                       block_bytes: int = 16 << 20, residual_stderr_rad: ArrayLike | None = None,
                       min_stderr_rad: float = 1e-4) -> ReliefFit:
    """Fit l' per window and channel from the blur of ``diffuse_normals`` (H, W, 3 channels, 3 xyz) against
    ``true_normals`` (H, W, 3) (known geometry, or the specular normals of the same capture); ``albedo``
    (H, W, 3) is R_d (exit Fresnel divided out, as :func:`estimation.gradients.compute_maps` reports it);
    ``pixel_mm`` the pixel footprint on the surface; ``exit_norm``: the factor applied to the map's R_d before
    inverting alpha' (default :func:`exit_normalization` (eta); 1.0: the map's R_d as is); ``valid`` (H, W) or
    (H, W, 3) usable pixels (NaN pixels are never used; a window needs ``min_valid_fraction`` of them, the rest are
    filled with the window mean); ``region`` (H, W): true normals outside it count as unknown (as NaN would).

    Windows of ``window_px`` (>= 16) every ``stride_px`` (default: ``window_px``, non-overlapping) with a Hann
    weight inside ``margin_px`` (default window/4) of the edge: a diffuse normal depends on the relief within a few
    l_d, which the window must contain (margin >~ 2 l_d). See the module docstring for the interval and status.

    Streaming: the inputs are read one band of ``window_px`` rows at a time and cast to float64 there (they may be
    float32 memory maps or derived maps), so a 24 MP capture never holds a full-frame float64 copy; the l' search
    of all windows and channels of a band is batched (:func:`estimation.relief_windows.search_l_prime`: real FFTs,
    ``workers`` threads, inverse-FFT work arrays bounded by ``block_bytes``); ``search_step`` > 1 evaluates the
    cost on a coarse grid first and refines only where the result depends on it (the minimum and the interval's
    ends; exact where the cost is unimodal on that scale), ``search_step=1`` on the whole grid -- equal to the
    one-window-at-a-time fit to rounding (tests/estimation/test_relief.py).

    ``residual_stderr_rad`` (H, W, 3): the per-pixel standard error (radians, per tangential component) of the
    residual diffuse - blurred true normal, from the frames' noise (sqrt(sigma_diffuse^2 + sigma_true^2),
    :mod:`estimation.gradients.uncertainty`; floored at ``min_stderr_rad``; NaN / inf: not used). The fit then
    weights each pixel by win^2 / sigma^2 and the profile interval uses the stated noise, or the residual where
    it is larger (:func:`estimation.relief_windows.search_l_prime`): a window whose pixels are noisy gets a wide
    interval (and "weak") even where its residual happens to be small.
    """
    from .relief_windows import alpha_from_rd_many, search_l_prime, true_spectra

    t_wall, t_cpu = time.perf_counter(), time.process_time()
    def lazy(a: Any) -> Any:
        return a if hasattr(a, "__getitem__") and hasattr(a, "shape") else np.asarray(a)

    Dn, Tn, alb = lazy(diffuse_normals), lazy(true_normals), lazy(albedo)
    H, W = Tn.shape[:2]
    se_all = None if residual_stderr_rad is None else lazy(residual_stderr_rad)
    if se_all is not None and tuple(se_all.shape) != (H, W, 3):
        raise ValueError(f"residual_stderr_rad must have shape ({H}, {W}, 3), got {tuple(se_all.shape)}")
    if tuple(Tn.shape) != (H, W, 3) or tuple(Dn.shape) != (H, W, 3, 3) or tuple(alb.shape) != (H, W, 3):
        raise ValueError("need diffuse_normals (H, W, 3, 3), true_normals (H, W, 3) and albedo (H, W, 3)")
    if int(window_px) < 16:
        raise ValueError(f"window_px must be >= 16, got {window_px}")
    if not pixel_mm > 0 or not np.isfinite(pixel_mm):
        raise ValueError(f"pixel_mm must be a finite number > 0, got {pixel_mm}")
    win_px = int(window_px)
    stride = win_px if stride_px is None else int(stride_px)
    if stride < 1:
        raise ValueError(f"stride_px must be >= 1, got {stride_px}")
    margin = win_px // 4 if margin_px is None else int(margin_px)
    if not 0 <= 2 * margin < win_px - 2:
        raise ValueError("margin_px leaves no pixels")
    v_all = None if valid is None else lazy(valid)
    if v_all is not None and tuple(v_all.shape) not in ((H, W), (H, W, 3)):
        raise ValueError(f"valid must have shape ({H}, {W}) or ({H}, {W}, 3), got {tuple(v_all.shape)}")
    reg_all = None if region is None else lazy(region)
    if reg_all is not None and tuple(reg_all.shape) != (H, W):
        raise ValueError(f"region must have shape ({H}, {W}), got {tuple(reg_all.shape)}")
    c_exit = exit_normalization(eta) if exit_norm is None else float(exit_norm)
    l_grid = np.exp(np.linspace(np.log(pixel_mm / 4.0), np.log(2.0 * win_px * pixel_mm), _N_GRID))
    rows, cols = _window_origins(H, win_px, stride), _window_origins(W, win_px, stride)
    ny, nx = len(rows), len(cols)
    if ny == 0 or nx == 0:
        raise ValueError(f"window_px {win_px} is larger than the map ({W} x {H} px)")
    vals = {k: np.full((ny, nx, 3), np.nan) for k in RELIEF_PARAMS}
    ints = {k: np.full((ny, nx, 3, 2), np.nan) for k in RELIEF_PARAMS}
    status = np.full((ny, nx, 3), "unknown", dtype="<U7")
    rms = np.full((ny, nx), np.nan)
    noise = np.full((ny, nx), np.nan)
    dnoise = np.full((ny, nx, 3), np.nan)
    full_lo, full_hi = l_grid[0], l_grid[-1]
    n_jobs = 0
    for i, r0 in enumerate(rows):
        band = slice(r0, r0 + win_px)
        T_b = _band(Tn, band)
        if reg_all is not None:
            T_b = np.where(_band(reg_all, band, bool)[..., None], T_b, np.nan)
        fin_b = np.isfinite(T_b).all(-1)
        D_b, A_b = _band(Dn, band), _band(alb, band)
        S_b = None if se_all is None else _band(se_all, band)
        V_b = np.ones(T_b.shape, bool) if v_all is None else _band(v_all, band, bool)
        if V_b.ndim == 2:
            V_b = np.repeat(V_b[..., None], 3, axis=-1)
        t_win: list[Array] = []                 # per fitted window: filled true normals and components
        comps_win: list[tuple[int, int]] = []
        job_w: list[int] = []                   # per job: index into t_win, column j, channel c
        job_jc: list[tuple[int, int]] = []
        job_data: list[Array] = []
        job_a: list[float] = []
        job_iv: list[Array] = []                # per job: inverse residual variance (with residual_stderr_rad)
        unk_jc: list[tuple[int, int]] = []      # unknown window-channels and their albedo
        unk_a: list[float] = []
        for j, c0 in enumerate(cols):
            cs = slice(c0, c0 + win_px)
            t = T_b[:, cs]
            ok_t = fin_b[:, cs]
            if ok_t.mean() < min_valid_fraction:
                continue
            t = np.where(ok_t[..., None], t, np.nanmean(t[ok_t], axis=0))
            comps = tuple(int(c) for c in np.argsort(t.reshape(-1, 3).var(axis=0))[-2:])
            sig_n = normal_noise_rad(t, comps)
            tot_var = sum(float(np.var(t[..., c])) for c in comps)
            rel_rms = float(np.sqrt(max(tot_var - 2 * sig_n ** 2, 0.0)))
            rms[i, j], noise[i, j] = rel_rms, sig_n
            relief_ok = rel_rms >= max(min_relief_snr * np.sqrt(2.0) * sig_n, min_relief_rad)
            w_index = -1
            for c in range(3):
                d = D_b[:, cs, c, :]
                a_w = A_b[:, cs, c]
                ok = ok_t & V_b[:, cs, c] & np.isfinite(d).all(-1) & np.isfinite(a_w)
                a_med = c_exit * float(np.median(a_w[ok])) if ok.any() else float("nan")
                if ok.mean() < min_valid_fraction or not (0 < a_med < 1):
                    unk_jc.append((j, c))
                    unk_a.append(a_med)
                    continue
                dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
                dn = np.where(ok[..., None], dn, np.nanmean(dn[ok], axis=0))
                dnoise[i, j, c] = normal_noise_rad(dn, comps)
                if not relief_ok:
                    unk_jc.append((j, c))
                    unk_a.append(a_med)
                    continue
                if w_index < 0:
                    w_index = len(t_win)
                    t_win.append(t)
                    comps_win.append(comps)
                job_w.append(w_index)
                job_jc.append((j, c))
                job_a.append(a_med)
                job_data.append(np.stack([dn[..., k] - dn[..., k].mean() for k in comps]))
                if S_b is not None:
                    sg = np.maximum(S_b[:, cs, c], min_stderr_rad)
                    job_iv.append(np.where(ok & np.isfinite(sg), 1.0 / (sg * sg), 0.0))
        if unk_jc:
            _put_unknown_many(ints, i, unk_jc, np.array(unk_a), full_lo, full_hi, eta, fdr)
        if not job_jc:
            continue
        n_jobs += len(job_jc)
        a_med_j = np.array(job_a)
        al3 = alpha_from_rd_many(np.concatenate([a_med_j, a_med_j / (1 + albedo_rel_uncertainty),
                                                 np.minimum(a_med_j * (1 + albedo_rel_uncertainty), 0.999)]),
                                 eta, fdr, model)
        alpha, a_lo, a_hi = np.split(al3, 3)
        spectra = true_spectra(np.stack(t_win), np.array(comps_win, dtype=np.int64), workers=workers)
        best, lo, hi, lo_b, hi_b, _ = search_l_prime(spectra, np.stack(job_data), alpha, pixel_mm, eta, l_grid,
                                                     margin, fdr, confidence, model, job_window=np.array(job_w),
                                                     coarse_step=search_step, block_bytes=block_bytes,
                                                     workers=workers,
                                                     job_inv_var=np.stack(job_iv) if job_iv else None)
        lo_w, hi_w = lo / (1.0 + model_bias_rel), hi * (1.0 + model_bias_rel)
        point = parameters_from_l_prime(alpha, best)
        iv = _derived_intervals(a_lo, a_hi, lo_w, hi_w)
        jj, cc = np.array(job_jc).T
        for k in RELIEF_PARAMS:
            vals[k][i, jj, cc] = point[k]
            ints[k][i, jj, cc] = iv[k]
        weak = lo_b | hi_b | (hi / lo > weak_ratio)
        status[i, jj, cc] = np.where(weak, "weak", "ok")
    origins = np.array([[(r, c) for c in cols] for r in rows], dtype=np.int64).reshape(ny, nx, 2)
    prov = {"window_px": win_px, "stride_px": stride, "margin_px": margin, "pixel_mm": float(pixel_mm),
            "confidence": confidence, "model_bias_rel": model_bias_rel,
            "albedo_rel_uncertainty": albedo_rel_uncertainty, "weak_ratio": weak_ratio,
            "min_relief_snr": min_relief_snr, "min_relief_rad": min_relief_rad, "eta": eta, "fdr": fdr,
            "exit_normalization": c_exit, "fitted_window_channels": n_jobs,
            "residual_weights": "Hann x 1/sigma^2 from the frames' noise" if se_all is not None else "Hann", "search_step": int(search_step),
            "seconds": time.perf_counter() - t_wall, "cpu_seconds": time.process_time() - t_cpu,
            "method": "relief blur, profile likelihood per window (estimation.relief), batched per band of rows "
                      "(estimation.relief_windows)"}
    return ReliefFit(win_px, stride, float(pixel_mm), origins, vals, ints, status, rms, noise, dnoise,
                     (float(full_lo), float(full_hi)), prov)


def _put_unknown_many(ints: dict[str, Array], i: int, jc: list[tuple[int, int]], a_med: Array, l_lo: float,
                      l_hi: float, eta: float, fdr: str) -> None:
    """Unknown window-channels (row ``i``, columns and channels ``jc``): NaN value, interval = the whole searched
    l' range at the window's alpha' (the Jensen dipole's inversion), or (0, inf) where the albedo is unusable."""
    from .relief_windows import alpha_from_rd_many

    jj, cc = np.array(jc).T
    usable = (a_med > 0) & (a_med < 1)
    al = np.full(a_med.shape, np.nan)
    if usable.any():
        al[usable] = alpha_from_rd_many(a_med[usable], eta, fdr, "dipole-jensen")
    iv = _derived_intervals(al, al, np.full(al.shape, l_lo), np.full(al.shape, l_hi))
    for k in RELIEF_PARAMS:
        ints[k][i, jj, cc] = np.where(usable[:, None], iv[k], np.array([0.0, np.inf]))


# --------------------------------------------------------------------------------------------------------------
# region summary
# --------------------------------------------------------------------------------------------------------------
def summarize_relief(fit: ReliefFit, region: ArrayLike | None = None, *, min_in_region: float = 0.5,
                     n_boot: int = 400, seed: int = 0) -> ReliefRegion:
    """Per-channel summary over the windows of ``fit`` that lie mostly (``min_in_region``) inside ``region``
    (H, W) (default: all windows).

    Value: the median of log l' over the "ok" windows (over the "weak" ones when none is ok); derived parameters
    from it and the median alpha'. Interval (``method``): with >= 5 ok windows the bootstrap percentile interval of
    that median (``n_boot`` resamples, seeded) widened by the fit's ``model_bias_rel`` -- and never narrower than
    the narrowest single-window interval's relative width; with 1-4 ok windows the hull of their intervals.
    Status: "ok" when ok windows are at least half of the usable ones, "weak" when only weak windows exist or ok
    windows are a minority, "unknown" without any (values NaN, interval the whole searched range).
    """
    ny, nx = fit.origins_px.shape[:2]
    wmask = np.ones((ny, nx), bool)
    if region is not None:
        reg = np.asarray(region, dtype=bool)
        for i in range(ny):
            for j in range(nx):
                r0, c0 = fit.origins_px[i, j]
                wmask[i, j] = reg[r0:r0 + fit.window_px, c0:c0 + fit.window_px].mean() >= min_in_region
    bias = float(fit.provenance.get("model_bias_rel", 0.3))
    conf = float(fit.provenance.get("confidence", 0.95))
    vals = {k: np.full(3, np.nan) for k in RELIEF_PARAMS}
    ints = {k: np.full((3, 2), np.nan) for k in RELIEF_PARAMS}
    status: list[str] = []
    nwin = np.zeros(3, np.int64)
    methods = []
    rng = np.random.default_rng(seed)
    for c in range(3):
        st = fit.status[..., c][wmask]
        lp = fit.values["l_prime_mm"][..., c][wmask]
        al = fit.values["alpha_prime"][..., c][wmask]
        okw, weakw = st == "ok", st == "weak"
        use = okw if okw.any() else weakw
        nwin[c] = int(use.sum())
        if not use.any():
            status.append("unknown")
            methods.append("none")
            unk = fit.intervals["l_prime_mm"][..., c, :][wmask]
            for k in RELIEF_PARAMS:
                ints[k][c] = (0.0, float("inf"))
            if unk.size:
                ints["l_prime_mm"][c] = (float(np.nanmin(unk[:, 0])), float(np.nanmax(unk[:, 1])))
                ints["D_mm"][c] = ints["l_prime_mm"][c] / 3.0
            continue
        logl = np.log(lp[use])
        a_med = float(np.median(al[use]))
        best = float(np.exp(np.median(logl)))
        point = parameters_from_l_prime(a_med, best)
        wint = {k: fit.intervals[k][..., c, :][wmask][use] for k in RELIEF_PARAMS}
        if use.sum() >= 5 and okw.any():
            boots = np.median(rng.choice(logl, size=(n_boot, logl.size), replace=True), axis=1)
            q = np.quantile(boots, [(1 - conf) / 2, (1 + conf) / 2])
            rel_single = float(np.min(wint["l_prime_mm"][:, 1] / wint["l_prime_mm"][:, 0]))
            lo, hi = float(np.exp(q[0])) / (1 + bias), float(np.exp(q[1])) * (1 + bias)
            if hi / lo < rel_single:       # never narrower than the best single window's own interval
                f = np.sqrt(rel_single / (hi / lo))
                lo, hi = lo / f, hi * f
            a_iv = (float(np.min(al[use])), float(np.max(al[use])))
            iv = _derived_interval(a_med, a_iv[0], a_iv[1], lo, hi)
            methods.append("bootstrap over windows, widened by the model bias")
        else:
            iv = {k: (float(np.nanmin(wint[k][:, 0])), float(np.nanmax(wint[k][:, 1]))) for k in RELIEF_PARAMS}
            methods.append("hull of the window intervals")
        for k in RELIEF_PARAMS:
            vals[k][c] = float(point[k])
            ints[k][c] = iv[k]
        n_usable = int((okw | weakw).sum())
        status.append("ok" if okw.any() and okw.sum() * 2 >= n_usable else "weak")
    prov = {"windows_in_region": int(wmask.sum()), "window_px": fit.window_px, "model_bias_rel": bias}
    return ReliefRegion(vals, ints, (status[0], status[1], status[2]), nwin, "; ".join(sorted(set(methods))),
                        conf, prov)
