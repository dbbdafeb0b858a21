"""The per-window l' search of :func:`estimation.relief.fit_relief_windows`, batched over windows and channels.

For each job (one window and one channel) the cost of :mod:`estimation.relief` is

    cost(l') = sum over the two tangential components of sum_px (w (d - (p - mean p)))^2,
    p = crop(IFFT(M(|k| l') FFT(pad(t))))

on a shared log grid of l' (48 values), then refined by a parabola in log l' and thresholded for the
profile-likelihood interval (module docstring of :mod:`estimation.relief`). The arithmetic is the per-window one,
arranged for throughput (issue 16, the 24-megapixel line):

- the true normals' spectra are real-input FFTs (``scipy.fft.rfft2``), computed once per window and shared by its
  three channels; the prediction is the inverse real FFT (``irfft2``) of the Hermitian product, i.e. the real part
  of the complex inverse the per-window fit took (equal to rounding);
- M(|k| l') is interpolated only at the distinct values of |k| on the half-spectrum grid (1800 of 8320 for a
  64-px window) and gathered, for all 48 l' at once; every window has the same grid;
- the inverse FFTs of many (job, l') pairs run as one batched call, in blocks bounded by ``block_bytes``;
- alpha' of the window's R_d (and its interval ends) is inverted for all jobs of a band at once by a 64-step
  bisection in s = sqrt(3 (1 - alpha')) (R_d(s) strictly decreasing; double precision, as
  :func:`estimation.dipole.reduced_albedo_from_total_reflectance` does for large inputs);
- the minimum, the parabola, the threshold and the derived intervals are array operations over jobs.

References: Ma et al. 2007 sec. 5; Jensen et al. 2001 (R^(k)); ``docs/gradients.md`` sec. 9.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy import fft as sfft
from scipy import stats

from .dipole import hankel_transform, total_diffuse_reflectance

Array = NDArray[np.float64]

__all__ = ["alpha_from_rd_many", "mtf_tables", "window_weight", "true_spectra", "search_l_prime"]

_X_TABLE = np.concatenate([[0.0], np.logspace(-4, 4, 1200)])


def alpha_from_rd_many(R_d: Array, eta: float, fdr: str, model: str) -> Array:
    """alpha' of half-spaces of total diffuse reflectance ``R_d`` (any shape, values in (0, 1)): the Jensen
    dipole's by a vectorized bisection in s = sqrt(3 (1 - alpha')) to double precision, or the Monte Carlo table's
    (:meth:`estimation.mc_table.McProfileTable.invert_albedo`)."""
    r = np.asarray(R_d, dtype=np.float64)
    if model == "mc-table":
        from .mc_table import default_table
        tab = default_table()
        return np.array([float(tab.invert_albedo(float(v), eta, out_of_range="clip")) for v in r.ravel()]
                        ).reshape(r.shape)
    lo = np.zeros(r.shape)
    hi = np.full(r.shape, np.sqrt(3.0))
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        sa = mid * mid / 3.0
        above = total_diffuse_reflectance(np.clip(1.0 - sa, 0.0, None), sa, eta, fdr=fdr) > r
        lo = np.where(above, mid, lo)
        hi = np.where(above, hi, mid)
    s = 0.5 * (lo + hi)
    return 1.0 - s * s / 3.0


def _mtf_table(alpha_prime: float, eta: float, fdr: str, model: str = "dipole-jensen") -> tuple[Array, Array]:
    """M as a function of x = k l' for sigma_t' = 1 (x log-spaced; M(0) = 1): the Jensen dipole's closed form
    (:func:`estimation.dipole.hankel_transform`) or, ``model="mc-table"``, the zeroth-order Hankel transform of the
    Monte Carlo table's profile (:mod:`estimation.mc_table`), M(x) = int J0(x rho) dC(rho) / C(inf), summed over the
    table's cumulative C on 2400 log-spaced radii from 1e-3 to 1e4 transport mean free paths (the mass inside
    1e-3 counted with J0 = 1)."""
    x = np.concatenate([[0.0], np.logspace(-4, 4, 1200)])
    if model == "mc-table":
        from scipy.special import j0

        from .mc_table import default_table
        rho = np.logspace(-3, 4, 2400)
        C = default_table().cumulative(rho, alpha_prime, 1.0 - alpha_prime, eta, out_of_range="clip")
        dC = np.diff(C)
        mid = np.sqrt(rho[1:] * rho[:-1])
        M = (C[0] + j0(x[:, None] * mid[None, :]) @ dC) / C[-1]
        return x, np.asarray(M, dtype=np.float64)
    R = hankel_transform(x, alpha_prime, 1.0 - alpha_prime, eta, fdr=fdr)
    return x, np.asarray(R / R[0], dtype=np.float64)


def mtf_tables(alphas: Array, eta: float, fdr: str, model: str) -> tuple[Array, Array]:
    """(x, M) with M (n, len(x)) the modulation transfer of each alpha' as a function of x = k l' (sigma_t' = 1),
    the table of :func:`_mtf_table` for every alpha' at once (Jensen: closed form, vectorized;
    ``mc-table``: one Hankel sum per alpha')."""
    a = np.asarray(alphas, dtype=np.float64).reshape(-1, 1)
    if model == "mc-table":
        return _X_TABLE, np.stack([_mtf_table(float(v), eta, fdr, model)[1] for v in a[:, 0]]) if a.size else \
            np.empty((0, _X_TABLE.size))
    R = hankel_transform(_X_TABLE[None, :], a, 1.0 - a, eta, fdr=fdr)
    return _X_TABLE, np.asarray(R / R[:, :1], dtype=np.float64)


def window_weight(h: int, w: int, margin_px: int) -> Array:
    """The Hann weight inside ``margin_px`` of the window's edge (zero in the margin)."""
    win = np.zeros((h, w))
    win[margin_px:h - margin_px, margin_px:w - margin_px] = np.outer(np.hanning(h - 2 * margin_px),
                                                                      np.hanning(w - 2 * margin_px))
    return win


def true_spectra(t: Array, comps: NDArray[np.int64], workers: int = 1) -> Array:
    """Half-spectra (n, 2, H2, W2 // 2 + 1) of the reflect-padded, mean-removed components ``comps`` (n, 2) of
    true-normal windows ``t`` (n, h, w, 3) (padding h // 2 and w // 2 on each side)."""
    n, h, w = t.shape[:3]
    sel = np.take_along_axis(t, comps[:, None, None, :], axis=-1)            # (n, h, w, 2)
    sel = np.moveaxis(sel, -1, 1)                                              # (n, 2, h, w)
    sel = sel - sel.mean(axis=(-2, -1), keepdims=True)
    ph, pw = h // 2, w // 2
    padded = np.pad(sel, ((0, 0), (0, 0), (ph, ph), (pw, pw)), mode="reflect")
    return sfft.rfft2(padded, axes=(-2, -1), workers=workers)


@njit(cache=True)
def _modulated_spectra(spectra: Array, wins: NDArray[np.int64], Mu: Array, inv: NDArray[np.int64]) -> Array:
    """Z[p, c] = M_p(|k|) x spectra[wins[p], c] with M_p given at the distinct |k| (``Mu`` (P, K), ``inv`` the
    index of each half-spectrum cell's |k|): one pass, no gathered copies."""
    P = wins.shape[0]
    _, C, H2, W2r = spectra.shape
    out = np.empty((P, C, H2, W2r), dtype=np.complex128)
    for p in range(P):
        w = wins[p]
        for c in range(C):
            for i in range(H2):
                for j in range(W2r):
                    out[p, c, i, j] = spectra[w, c, i, j] * Mu[p, inv[i, j]]
    return out


@njit(cache=True)
def _window_cost_weighted(pred: Array, pw: int, data: Array, jobs: NDArray[np.int64], w2: Array) -> Array:
    """The windowed cost with a squared weight per job and pixel: sum_c sum_px w2[jobs[p]] (data - (q - mean q))^2
    (the mean of q over the window, unweighted; without per-pixel weights w2 is the window's squared taper for
    every job)."""
    P, C, h, _ = pred.shape
    w = data.shape[3]
    out = np.zeros(P)
    for p in range(P):
        jd = jobs[p]
        tot = 0.0
        for c in range(C):
            mean = 0.0
            for i in range(h):
                for j in range(w):
                    mean += pred[p, c, i, pw + j]
            mean /= h * w
            for i in range(h):
                for j in range(w):
                    r = data[jd, c, i, j] - (pred[p, c, i, pw + j] - mean)
                    tot += w2[jd, i, j] * r * r
        out[p] = tot
    return out


def search_l_prime(spectra: Array, data: Array, alphas: Array, pixel_mm: float, eta: float, l_grid: Array,
                   margin_px: int, fdr: str, confidence: float, model: str = "dipole-jensen", *,
                   job_window: NDArray[np.int64] | None = None, coarse_step: int = 3, block_bytes: int = 16 << 20,
                   workers: int = 1, job_inv_var: Array | None = None
                   ) -> tuple[Array, Array, Array, NDArray[np.bool_], NDArray[np.bool_], Array]:
    """The l' search for n jobs: ``spectra`` (m, 2, H2, W2r) of the true normals of m windows
    (:func:`true_spectra`), ``job_window`` (n,) the window of each job (default: job i is window i), ``data``
    (n, 2, h, w) the diffuse normals' two tangential components with their window means removed, ``alphas``
    (n,). Returns (best, lo, hi, lo_at_bound, hi_at_bound, cost) with cost (n, len(l_grid)).

    Search (``coarse_step`` > 1): the cost on every ``coarse_step``-th grid point (and the last), then every grid
    point within ``coarse_step`` of the coarse minimum, then the neighbours of the fine minimum until both are
    known, then -- for the interval -- every grid point between the outermost known points under the threshold
    and the nearest known points beyond them. Where the cost is unimodal on the scale of ``coarse_step`` grid
    steps this is the exhaustive search's result exactly (the same grid points, the same arithmetic);
    ``coarse_step=1`` evaluates the whole grid. Unknown costs are NaN in the returned ``cost``.

    ``block_bytes`` bounds the inverse-FFT work arrays (about 4 x 2 H2 W2 x 8 bytes per (job, l') pair).

    ``job_inv_var`` (n, h, w): the residual's inverse variance per pixel (1 / (sigma_diffuse^2 + sigma_true^2) from
    the frames' noise, :mod:`estimation.gradients.uncertainty`; 0 for unusable pixels). The cost's weight is then
    win^2 / sigma^2 and the interval's threshold chi^2_1 x phi x 2 sum(win^4/sigma^2) / sum(win^2/sigma^2) above
    the minimum, phi = max(1, cost_min / (2 sum win^2)) (the stated noise, or the residual where it is larger --
    model error, unstated noise). Without it: the Hann weight and the residual's own variance (as before)."""
    n, _, h, w = data.shape
    jw = np.arange(n) if job_window is None else np.asarray(job_window, dtype=np.int64)
    nl = l_grid.size
    if n == 0:
        e = np.empty(0)
        return e, e, e, np.zeros(0, bool), np.zeros(0, bool), np.empty((0, nl))
    H2, W2 = h + 2 * (h // 2), w + 2 * (w // 2)
    ph, pw = h // 2, w // 2
    ky = 2 * np.pi * np.fft.fftfreq(H2, d=pixel_mm)
    kx = 2 * np.pi * np.fft.rfftfreq(W2, d=pixel_mm)
    kk = np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    uk, inv = np.unique(kk, return_inverse=True)
    inv = inv.reshape(kk.shape).astype(np.int64)
    xs, ms = mtf_tables(alphas, eta, fdr, model)
    win = window_weight(h, w, margin_px)
    w2 = None
    if job_inv_var is not None:
        iv = np.asarray(job_inv_var, dtype=np.float64)
        if iv.shape != (n, h, w):
            raise ValueError(f"job_inv_var must have shape {(n, h, w)}, got {iv.shape}")
        w2 = np.ascontiguousarray(np.where(np.isfinite(iv) & (iv > 0), iv, 0.0) * (win * win)[None])
    # the cost's squared weights: the stated noise's, else the taper's for every job (a view, no copy)
    cost_w2 = w2 if w2 is not None else np.broadcast_to(win * win, (n, h, w))
    per_pair = 2 * H2 * W2 * 8 * 4
    block = max(1, int(block_bytes) // per_pair)
    cost = np.full((n, nl), np.nan)
    arg = uk[None, :] * l_grid[:, None]                                       # (nl, K): the products k l'

    def evaluate(todo: NDArray[np.bool_]) -> None:
        """cost[j, l] for every (j, l) with ``todo`` set and cost not yet known, in blocks of pairs. The inverse
        real FFT is pruned to the rows of the window: the inverse along the rows (complex), then only the window's
        h rows through the inverse real FFT along the columns."""
        jobs, ls = np.nonzero(todo & np.isnan(cost))
        for s0 in range(0, jobs.size, block):
            jb, lb = jobs[s0:s0 + block], ls[s0:s0 + block]
            Mu = np.stack([np.interp(arg[l], xs, ms[j]) for j, l in zip(jb, lb)])   # (P, K)
            Z = _modulated_spectra(spectra, jw[jb], Mu, inv)                           # (P, 2, H2, W2r)
            Z = sfft.ifft(Z, axis=-2, overwrite_x=True, workers=workers)[..., ph:ph + h, :]
            pred = sfft.irfft(Z, n=W2, axis=-1, workers=workers)                   # (P, 2, h, W2)
            cost[jb, lb] = _window_cost_weighted(pred, pw, data, jb, cost_w2)

    rows = np.arange(n)
    grid = np.arange(nl)
    step = max(1, int(coarse_step))
    coarse = (grid % step == 0) | (grid == nl - 1)
    evaluate(np.broadcast_to(coarse, (n, nl)))
    if step > 1:      # the fine grid around the coarse minimum, then around the fine one until both neighbours
        kc = np.nanargmin(cost, axis=1)
        evaluate(np.abs(grid[None, :] - kc[:, None]) <= step)
        while True:
            k = np.nanargmin(cost, axis=1)
            need = (np.abs(grid[None, :] - k[:, None]) <= 1) & np.isnan(cost)
            if not need.any():
                break
            evaluate(need)
    k = np.nanargmin(cost, axis=1)
    ll = np.log(l_grid)
    best = ll[k].copy()
    cmin = cost[rows, k].copy()
    inner = (k > 0) & (k < nl - 1)
    km, kp = np.clip(k - 1, 0, nl - 1), np.clip(k + 1, 0, nl - 1)
    y0, y1, y2 = cost[rows, km], cost[rows, k], cost[rows, kp]
    den = y0 - 2 * y1 + y2
    par = inner & (den > 0)                    # parabola through the three grid points around the minimum
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(par, 0.5 * (y0 - y2) / np.where(par, den, 1.0), 0.0)
    best = np.where(par, ll[k] + off * (ll[1] - ll[0]), best)
    cmin = np.where(par, y1 - 0.25 * (y0 - y2) * off, cmin)
    W2s, W4s = float(np.sum(win ** 2)), float(np.sum(win ** 4))
    if w2 is None:
        s2 = np.maximum(cmin, 0.0) / (2 * W2s)     # residual variance per pixel and component
        thr = np.maximum(cmin + stats.chi2.ppf(confidence, 1) * s2 * W4s / W2s * 2, cost[rows, k])
    else:                                      # the stated noise, widened where the residual exceeds it
        phi = np.maximum(1.0, np.maximum(cmin, 0.0) / (2 * W2s))
        u2 = w2.sum(axis=(1, 2))
        u4 = (w2 * (win * win)[None]).sum(axis=(1, 2))
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(u2 > 0, u4 / u2, np.inf)
        thr = np.maximum(cmin + stats.chi2.ppf(confidence, 1) * phi * ratio * 2, cost[rows, k])
    if step > 1:      # the fine grid between the outermost known points inside and the known points beyond
        while True:
            known = ~np.isnan(cost)
            inside = cost <= thr[:, None]
            i0 = np.argmax(inside, axis=1)
            i1 = nl - 1 - np.argmax(inside[:, ::-1], axis=1)
            before = np.where(known & (grid[None, :] < i0[:, None]), grid[None, :], -1).max(axis=1)
            after = np.where(known & (grid[None, :] > i1[:, None]), grid[None, :], nl).min(axis=1)
            need = ~known & (((grid[None, :] > before[:, None]) & (grid[None, :] < i0[:, None]))
                             | ((grid[None, :] > i1[:, None]) & (grid[None, :] < after[:, None])))
            if not need.any():
                break
            evaluate(need)
    inside = cost <= thr[:, None]
    i0 = np.argmax(inside, axis=1)
    i1 = nl - 1 - np.argmax(inside[:, ::-1], axis=1)
    lo = np.where(i0 > 0, l_grid[np.maximum(i0 - 1, 0)], l_grid[0])   # the next grid point out: conservative
    hi = l_grid[np.minimum(i1 + 1, nl - 1)]
    return np.exp(best), lo, hi, i0 == 0, i1 == nl - 1, cost
