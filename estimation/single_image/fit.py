"""The per-channel fit of (log sigma_s', log sigma_a): QR-reduced problems, lockstep multistart Levenberg-Marquardt,
Wald covariance, the profile likelihood of sigma_a, and the Tikhonov solve of the binned methods."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, optimize
from scipy.linalg import lapack


Array = NDArray[np.float64]
_LOG_SSP_BOUNDS = (np.log(1e-3), np.log(1e3))
_LOG_SA_MAX = np.log(50.0)
#: the narrowest search box (log) a trust region is given
_MIN_BOX_LOG = 1e-3
_CHI2_1_95 = 3.841458820694124
_Z95 = 1.959963984540054
_JAC_STEP = 6e-6  # central-difference step of the fit Jacobians (~eps^(1/3), relative to max(1, |theta|))
_GOLDEN_ITERS = 12  # profile scan: bracket 10 x 0.618^12 ~ 3e-3 in log sigma_s', then one parabolic step
_LM_MAX_ITER = 100  # lockstep multistart iterations (:func:`_lm_multistart`); measured 5-20
_LM_RTOL = 1e-14  # multistart stop: Gauss-Newton predicted decrease <= _LM_RTOL x cost
_LM_DAMPING = (0.1, 1.0, 10.0)  # damping values tried per start and iteration (x lambda), in the same batch
#: a warm refit (``local``: inside a trust box, from the previous solution): start grid points per parameter over the
#: box (instead of 21 x 21 over the whole range) and the sigma_a profile's local grid (points, half-width in Wald
#: standard errors); the whole-range profile grid is used whenever the interval reaches the local grid's end
_LOCAL_GRID = 5
_LOCAL_PROFILE_POINTS, _LOCAL_PROFILE_SE = 17, 4.0


# ---------------------------------------------------------------------------------------------- fitting core
def _reduce(a: Array, b: Array) -> tuple[Array, Array, float]:
    """QR reduction of min ||a x - b||: (R, Q^T b, ||b - Q Q^T b||^2), or (a, b, 0) when a is not tall.

    ||a x - b||^2 = ||R x - Q^T b||^2 + offset for every x, so fits, Jacobians (J^T J) and profile scans on the
    n x n system are those of the full one at O(n^2) instead of O(m n) per evaluation. One Householder QR of
    [a | b] without forming Q: its last column holds Q^T b and the residual norm. LAPACK ``dgeqrt`` (the compact-WY
    blocked QR, block 32) rather than numpy's ``dgeqrf``: the same reflectors, but the tall-skinny panels run as
    matrix products. Measured single-threaded (OpenBLAS): 4.3 vs 5.6 ms on the benchmark sphere's direct system
    (3148 x 122, twice per channel), on random matrices 4.2 vs 8.7 ms at 3148 x 123, 11 vs 19 ms at 8000 x 130,
    0.7 vs 1.3 ms at 800 x 100, equal at 300 x 60 and 3000 x 400. The reduced SSR equals the unreduced one to
    3e-13 (as numpy's did to 4e-13); the direct method's fitted parameters move by <= 3e-9.
    """
    m, n = a.shape
    if m <= n:
        return a, b, 0.0
    ab = np.empty((m, n + 1), order="F")
    ab[:, :n] = a
    ab[:, n] = b
    r = lapack.dgeqrt(min(32, n + 1), ab, overwrite_a=1)[0][:n + 1]
    return np.ascontiguousarray(np.triu(r[:n, :n])), r[:n, n].copy(), float(r[n, n] ** 2)


#: the data correction of :meth:`_Problem.weighted` (``slope``) is linear in theta - theta_ref up to about this
#: distance in log parameters and saturates beyond it (phi = r tanh((theta - theta_ref) / r)): a first-order
#: correction learnt at one point is not extrapolated over decades (e.g. by the sigma_a profile scan)
CORRECTION_SATURATION_LOG = 1.0


def _reduce_affine(a: Array, b: Array, c: Array) -> tuple[Array, Array, Array]:
    """QR reduction of ||a v - b + c phi|| over (v, phi): (R_a, r_b, R_c) with ||a v - b + c phi|| =
    ||R_a v - r_b + R_c phi|| for every v and phi (one Householder QR of [a | b | c], as :func:`_reduce`)."""
    m, n = a.shape
    k = c.shape[1]
    x = np.empty((m, n + 1 + k), order="F")
    x[:, :n] = a
    x[:, n] = b
    x[:, n + 1:] = c
    if m <= n + 1 + k:
        return a, b, c
    r = np.triu(lapack.dgeqrt(min(32, n + 1 + k), x, overwrite_a=1)[0][:n + 1 + k])
    return np.ascontiguousarray(r[:, :n]), r[:, n].copy(), np.ascontiguousarray(r[:, n + 1:])


class _Problem:
    """SSR(theta) = ||a v(theta) - b + lin phi(theta)||^2 + offset for a batch of log parameters theta (T, 2).

    ``vector_fn(theta) -> (n, T)`` gives the model's unknowns (profile or disk-integral values at nodes); ``a``
    (None = identity) and ``b`` are the weighted system, usually its QR reduction (:func:`_reduce`).
    ``n_data`` counts the data (degrees of freedom) and ``weighted_data`` holds w * data (the model-error floor).
    ``lin`` (n, 2), optional: a data term linear in phi(theta) = r tanh((theta - theta_ref) / r) (r =
    :data:`CORRECTION_SATURATION_LOG`), i.e. data that move with the parameters to first order near theta_ref
    (the reference-corrected fit's defect correction, :mod:`estimation.model_correction`).
    """

    def __init__(self, vector_fn: Any, a: Array | None, b: Array, n_data: int, weighted_data: Array,
                 offset: float = 0.0, lin: Array | None = None, theta_ref: Array | None = None) -> None:
        self.vector_fn = vector_fn
        self.a = a
        self.b = b
        self.n_data = int(n_data)
        self.weighted_data = weighted_data
        self.offset = float(offset)
        self.lin = lin
        self.theta_ref = None if theta_ref is None else np.asarray(theta_ref, dtype=np.float64).reshape(2)
        self.nfev = 0

    @classmethod
    def weighted(cls, vector_fn: Any, matrix: Array, data: Array, weights: Array, slope: Array | None = None,
                 theta_ref: Array | None = None) -> "_Problem":
        """min || w (matrix v(theta) - (data - slope phi(theta))) ||, reduced by QR; ``slope`` (m, 2) is the
        derivative of the data with respect to phi (None: fixed data)."""
        wd = data * weights
        if slope is None:
            a, b, off = _reduce(matrix * weights[:, None], wd)
            return cls(vector_fn, a, b, data.size, wd, off)
        if theta_ref is None:
            raise ValueError("a data slope needs its reference point theta_ref")
        a, b, lin = _reduce_affine(matrix * weights[:, None], wd, np.asarray(slope) * weights[:, None])
        return cls(vector_fn, a, b, data.size, wd, 0.0, lin, theta_ref)

    def phi(self, t: Array) -> Array:
        """phi(theta) (T, 2) of :class:`_Problem` (0 without a data slope)."""
        if self.theta_ref is None:
            return np.zeros_like(t)
        r = CORRECTION_SATURATION_LOG
        return r * np.tanh((t - self.theta_ref[None, :]) / r)

    def resid(self, theta: Array) -> Array:
        t = np.atleast_2d(theta)
        self.nfev += t.shape[0]
        v = self.vector_fn(t)
        out = (v if self.a is None else self.a @ v) - self.b[:, None]
        if self.lin is not None:
            out = out + self.lin @ self.phi(t).T
        return out

    def jacobian(self, theta: Array) -> Array:
        """d resid / d theta (n, 2) by central differences, all four points in one batched evaluation."""
        t = np.asarray(theta, dtype=np.float64)
        h = _JAC_STEP * np.maximum(1.0, np.abs(t))
        pts = np.repeat(t[None, :], 4, axis=0)
        pts[0, 0] += h[0]
        pts[1, 0] -= h[0]
        pts[2, 1] += h[1]
        pts[3, 1] -= h[1]
        r = self.resid(pts)
        return np.stack([(r[:, 0] - r[:, 1]) / (2 * h[0]), (r[:, 2] - r[:, 3]) / (2 * h[1])], axis=1)

    def ssr(self, theta: Array) -> Array:
        r = self.resid(theta)
        return np.einsum("nt,nt->t", r, r) + self.offset


def _golden_batch(f: Any, lo: Array, hi: Array, iters: int = 32) -> tuple[Array, Array]:
    """Vectorized golden-section minimization of f(x (T,)) -> (T,) on [lo, hi] per element, finished by one
    parabolic step. Returns the best point evaluated and its value.

    After ``iters`` golden iterations (bracket [a, b] with interior points c < d) a third point is evaluated: the
    bracket's midpoint, or the end lo / hi when the bracket still touches it (a monotone f never moves that end,
    and its minimum is the end itself, which golden section approaches only geometrically). The vertex of the
    parabola through the three points (clipped to [a, b]; the best of the three when they are not convex) is the
    last evaluation; the best of c, d, the third point and the vertex is returned.

    The finish replaces 12 golden iterations: measured on the benchmark sphere's sigma_a profile (42 elements,
    bracket 10 in log sigma_s'), 12 iterations + parabola leave the values within 1e-6 s^2 of 40 golden
    iterations wherever the minimum is interior, as 24 plain iterations did, and exact at a bracket end (24 plain
    iterations: off by slope x 5e-5), at 16 batched calls instead of 27 (2.8 instead of 4.6 ms).
    """
    g = (np.sqrt(5) - 1) / 2
    a, b = lo.copy(), hi.copy()
    c = b - g * (b - a)
    d = a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iters):
        left = fc < fd  # the minimum lies in [a, d]
        a_new = np.where(left, a, c)
        b_new = np.where(left, d, b)
        c_new = np.where(left, b_new - g * (b_new - a_new), d)
        d_new = np.where(left, c, a_new + g * (b_new - a_new))
        f_eval = f(np.where(left, c_new, d_new))
        fc, fd = np.where(left, f_eval, fd), np.where(left, fc, f_eval)
        a, b, c, d = a_new, b_new, c_new, d_new
    at_lo, at_hi = (a == lo) & (fc < fd), (b == hi) & (fd <= fc)
    e = np.where(at_lo, lo, np.where(at_hi, hi, 0.5 * (a + b)))
    fe = f(e)
    # the three points in increasing order: (lo, c, d), (c, d, hi) or (c, midpoint, d)
    x1, x2, x3 = np.where(at_lo, e, c), np.where(at_lo, c, np.where(at_hi, d, e)), np.where(at_hi, e, d)
    f1, f2, f3 = np.where(at_lo, fe, fc), np.where(at_lo, fc, np.where(at_hi, fd, fe)), np.where(at_hi, fe, fd)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s12, s23 = (f2 - f1) / (x2 - x1), (f3 - f2) / (x3 - x2)
        u = 0.5 * (x1 + x2) - 0.5 * s12 * (x3 - x1) / (s23 - s12)  # (vertex: where the secant slopes' line is 0)
    xs3, fs3 = np.stack([x1, x2, x3]), np.stack([f1, f2, f3])
    cols = np.arange(lo.size)
    best3 = xs3[np.argmin(np.where(np.isnan(fs3), np.inf, fs3), axis=0), cols]
    u = np.where((s23 > s12) & np.isfinite(u), np.clip(u, a, b), best3)
    xs = np.stack([c, d, e, u])
    fs = np.stack([fc, fd, fe, f(u)])
    k = np.argmin(np.where(np.isnan(fs), np.inf, fs), axis=0)
    return xs[k, cols], fs[k, cols]


def _box_qp_2d(g: Array, a: Array, lo: Array, hi: Array) -> Array:
    """Exact minimizer d of g.d + d^T a d / 2 over the box lo <= d <= hi, for a batch: g (S, 2), a (S, 2, 2)
    symmetric positive definite, lo <= 0 <= hi (S, 2). Returns d (S, 2).

    A strictly convex quadratic attains its minimum over a rectangle either at its unconstrained minimizer (when
    that lies inside) or on an edge, where it is the edge's 1-D minimizer clamped to the edge (corners included).
    So the five candidates (unconstrained, four clamped edge minimizers) contain the answer: the feasible one with
    the lowest model value wins. No active-set iteration, no Python loop over the batch (~30 us for S = 8).
    """
    s = g.shape[0]
    a00, a01, a11 = a[:, 0, 0], a[:, 0, 1], a[:, 1, 1]
    g0, g1 = g[:, 0], g[:, 1]
    d0 = np.empty((5, s))
    d1 = np.empty((5, s))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        det = a00 * a11 - a01 * a01
        d0[0] = (a01 * g1 - a11 * g0) / det
        d1[0] = (a01 * g0 - a00 * g1) / det
        d0[1], d0[2] = lo[:, 0], hi[:, 0]  # edges d0 = lo0, hi0
        d1[1:3] = np.clip(-(g1 + a01 * d0[1:3]) / a11, lo[:, 1], hi[:, 1])
        d1[3], d1[4] = lo[:, 1], hi[:, 1]  # edges d1 = lo1, hi1
        d0[3:5] = np.clip(-(g0 + a01 * d1[3:5]) / a00, lo[:, 0], hi[:, 0])
        q = g0 * d0 + g1 * d1 + 0.5 * (a00 * d0 * d0 + 2.0 * a01 * d0 * d1 + a11 * d1 * d1)
    inside = (d0[0] >= lo[:, 0]) & (d0[0] <= hi[:, 0]) & (d1[0] >= lo[:, 1]) & (d1[0] <= hi[:, 1])
    q[0, ~inside] = np.inf  # (NaN compares False: a singular a never picks the unconstrained candidate)
    q[np.isnan(q)] = np.inf
    k = np.argmin(q, axis=0)
    cols = np.arange(s)
    return np.stack([d0[k, cols], d1[k, cols]], axis=1)


def _stencil(problem: _Problem, x: Array) -> tuple[Array, Array]:
    """Residuals (n, S) and central-difference Jacobians (S, n, 2) at S points in ONE batched evaluation of 5 S
    points; the steps and differences are those of :meth:`_Problem.jacobian`, so J equals its value at each point."""
    s = x.shape[0]
    h = _JAC_STEP * np.maximum(1.0, np.abs(x))
    pts = np.tile(x, (5, 1))
    pts[s:2 * s, 0] += h[:, 0]
    pts[2 * s:3 * s, 0] -= h[:, 0]
    pts[3 * s:4 * s, 1] += h[:, 1]
    pts[4 * s:, 1] -= h[:, 1]
    r = problem.resid(pts)
    jac = np.stack([(r[:, s:2 * s] - r[:, 2 * s:3 * s]) / (2 * h[:, 0]),
                    (r[:, 3 * s:4 * s] - r[:, 4 * s:]) / (2 * h[:, 1])], axis=2)  # (n, S, 2)
    return r[:, :s], np.ascontiguousarray(jac.transpose(1, 0, 2))


@dataclass
class _Multistart:
    """Result of :func:`_lm_multistart` per start: the end point x (S, 2), cost 0.5 ||r||^2 (S,) (as least_squares
    reports it), the Jacobian there (S, n, 2), whether the start converged, and the lockstep loop's iterations."""
    x: Array
    cost: Array
    jac: Array
    converged: NDArray[np.bool_]
    iterations: int


def _lm_multistart(problem: _Problem, starts: Array, lb: Array, ub: Array, max_iter: int = _LM_MAX_ITER,
                   rtol: float = _LM_RTOL, ftol: float = 1e-12, damping: tuple[float, ...] = _LM_DAMPING
                   ) -> _Multistart:
    """Bounded Levenberg-Marquardt from every start at once, in lockstep; returns every start's end point.

    ``problem.resid`` costs about the same for one parameter vector as for ~50 (measured on the benchmark sphere,
    10k patches, n = 122 reduced rows: 0.08 ms + 1.7 us per vector), while one ``least_squares`` call costs ~2 ms
    of Python overhead. So every iteration is ONE batched evaluation: for each start still running, the trial
    points of ``len(damping)`` damping values (lambda x ``damping``) together with their four central-difference
    points (:func:`_stencil`: 15 vectors per start), so the accepted trial already carries its Jacobian and a
    rejected one costs no extra call. The best trial of a start is accepted when it lowers the cost; lambda then
    follows Nielsen's update (x max(1/3, 1 - (2 rho - 1)^3) on success, x nu, nu doubling, on failure), the damping
    matrix being lambda diag(D), D the running max of diag(J^T J) (Marquardt-More scaling: a direction that barely
    matters, log sigma_a -> its floor, is not frozen by the damping of the stiff one).

    The step minimizes the damped Gauss-Newton model exactly over the box [lb, ub] (:func:`_box_qp_2d`): a
    parameter at a bound (sigma_a at its floor, a legitimate optimum when sigma_a is not identified) stays there
    while the other one moves along the edge. A start stops (``converged``) when the barely damped Gauss-Newton
    step within the box promises at most ``rtol`` x cost of further decrease or moves less than 1e-12, when a good
    step (rho > 1/4) gains less than ``ftol`` x cost (least_squares' ftol test), or when lambda exceeds 1e16; else
    after ``max_iter`` iterations. Starts whose residuals or Jacobian are not finite are dropped (cost inf).

    Measured on 23 multistarts (3-7 starts) from benchmark scenes (10k sphere direct and pinv, 4k spheres, three
    channels, LED and sky): 256 iterations and 86 ms in all with damping (0.1, 1, 10), 509 iterations and 136 ms
    with a single lambda; 5-8 iterations for starts near the optimum, 10-20 for far ones.
    """
    x = np.clip(np.asarray(starts, dtype=np.float64), lb, ub)
    s = x.shape[0]
    mult = np.asarray(damping, dtype=np.float64)
    n_var = mult.size
    r, jac = _stencil(problem, x)
    cost = 0.5 * np.einsum("ns,ns->s", r, r)
    live = np.isfinite(cost) & np.all(np.isfinite(jac), axis=(1, 2))
    cost = np.where(live, cost, np.inf)
    converged = np.zeros(s, dtype=bool)
    lam = np.full(s, 1e-3)
    nu = np.full(s, 2.0)
    dsc = np.zeros((s, 2))  # Marquardt-More scaling: running max of diag(J^T J) per start
    eye = np.eye(2)
    it = 0
    while it < max_iter and np.any(live):
        it += 1
        idx = np.flatnonzero(live)
        k = idx.size
        xs, js = x[idx], jac[idx]
        g = np.einsum("snk,ns->sk", js, r[:, idx])
        hess = js.transpose(0, 2, 1) @ js
        diag_h = np.einsum("sii->si", hess)
        dsc[idx] = np.maximum(dsc[idx], diag_h)
        ds = np.maximum(dsc[idx], 1e-12 * np.max(dsc[idx], axis=1, keepdims=True) + np.finfo(np.float64).tiny)
        lam_i = np.maximum(lam[idx], 1e-12)
        # one box-QP batch: the barely damped Gauss-Newton step (the convergence test: it promises at most
        # rtol x cost of further decrease) and the Levenberg-Marquardt steps at every damping variant
        damp = np.concatenate([np.full(k, 1e-12), (mult[:, None] * lam_i).ravel()])
        rep = np.tile(np.arange(k), n_var + 1)
        d_all = _box_qp_2d(g[rep], hess[rep] + (damp[:, None] * ds[rep])[:, :, None] * eye, lb - xs[rep],
                           ub - xs[rep])
        x_all = np.clip(xs[rep] + d_all, lb, ub)  # (round-off off the box)
        d_all = x_all - xs[rep]
        pred_all = -np.einsum("sk,sk->s", d_all, g[rep] + 0.5 * np.einsum("sij,sj->si", hess[rep], d_all))
        pred_gn = pred_all[:k]
        done = ((pred_gn <= rtol * cost[idx])
                | (np.max(np.abs(d_all[:k]), axis=1) <= 1e-12 * (1.0 + np.max(np.abs(xs), axis=1))))
        converged[idx[done]] = True
        live[idx[done]] = False
        keep = np.flatnonzero(~done)
        if keep.size == 0:
            break
        x_var = x_all[k:].reshape(n_var, k, 2)[:, keep].reshape(-1, 2)  # (variant-major: row j * k' + start)
        pred_var = pred_all[k:].reshape(n_var, k)[:, keep]
        idx, lam_i = idx[keep], lam_i[keep]
        k = idx.size
        r_new, jac_new = _stencil(problem, x_var)
        cost_new = 0.5 * np.einsum("ns,ns->s", r_new, r_new)
        cost_new = np.where(np.isfinite(cost_new) & np.all(np.isfinite(jac_new), axis=(1, 2)), cost_new, np.inf)
        j_best = np.argmin(cost_new.reshape(n_var, k), axis=0)
        flat = j_best * k + np.arange(k)
        c_best = cost_new[flat]
        acc = c_best < cost[idx]
        decrease = np.where(acc, cost[idx] - np.where(acc, c_best, 0.0), 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.where(acc, decrease / pred_var[j_best, np.arange(k)], 0.0)
        # least_squares' ftol test: a good step (rho > 1/4) that gains less than ftol x cost ends the start
        flat_cost = acc & (rho > 0.25) & (decrease <= ftol * cost[idx])
        ia, fa = idx[acc], flat[acc]
        x[ia], cost[ia], r[:, ia], jac[ia] = x_var[fa], c_best[acc], r_new[:, fa], jac_new[fa]
        lam_c = lam_i * mult[j_best]
        lam[idx] = np.where(acc, lam_c * np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3),
                            lam_i * mult[-1] * nu[idx])
        nu[idx] = np.where(acc, 2.0, 2.0 * nu[idx])
        # damping beyond 1e16 (relative to diag(J^T J)): steps below round-off of the cost, nothing left to gain
        stuck = (lam[idx] > 1e16) | flat_cost
        converged[idx[stuck]] = True
        live[idx[stuck]] = False
    return _Multistart(x, cost, jac, converged, it)


@dataclass
class _ChannelFit:
    theta: Array
    cov: Array
    ssr: float
    s2: float
    nfev: int
    jac_cond: float
    sa_profile_ci: tuple[float, float]
    one_sided: bool
    ok: bool
    message: str


def _fit_channel(problem: _Problem, sa_floor: float, n_params_dof: int = 2, known_noise: bool = False,
                 profile: bool = True, model_error: float = 0.0, start_hint: Array | None = None,
                 polish: bool = True, box: tuple[Array, Array] | None = None, local: bool = False) -> _ChannelFit:
    """Grid start + bounded least squares in (log sigma_s', log sigma_a); Wald covariance and sigma_a profile.

    Every start (best grid point, +-2 in log sigma_a, up to 4 other local minima of the grid, ``start_hint``) runs
    at once in :func:`_lm_multistart`; the best end point is then polished by one ``least_squares("trf")`` call with
    the settings every start used to get on its own (``polish``; False skips it), and the polished point, cost and
    Jacobian are returned. Measured on the benchmark sphere (10k patches, sky map): ~3.9 ms for the direct method's
    first fit (no polish, no profile; ~9.5 ms with one least_squares per start) and ~7.6 ms for the final one
    (~14.5 ms; the profile scan 2.8 of it, was 4.7); parameters equal to 1e-9 relative, sigma_a interval ends to
    1e-7 (<= 7e-6 over 1- and 3-channel sky / LED scenes with 0-20 % noise).

    The residual scale is s^2 = SSR/dof; for known noise max(1, SSR/dof) (the stated noise, or more when the
    residuals say the model or the noise figure is off: never narrower than the misfit warrants), floored so
    that the 95 % thresholds are never tighter than a relative model error ``model_error`` on every datum:
    Delta SSR >= sum (model_error * data * weight)^2, i.e. parameters whose best-fit predictions differ by less
    than that rms are not distinguished.

    ``box`` (lo, hi) in log parameters, optional: the minimum is searched inside it only (a trust region of the
    reference-corrected fit); the covariance and the sigma_a profile are those of the whole parameter range.

    ``local`` (with ``box`` and a finite ``start_hint``: a refit near a known solution, issue 19): the start grid is
    :data:`_LOCAL_GRID` x :data:`_LOCAL_GRID` points over the box instead of 21 x 21 over the whole range (the box is
    the trust region about the previous solution; the hint is a start as always), and the sigma_a profile is scanned
    on :data:`_LOCAL_PROFILE_POINTS` points within +- :data:`_LOCAL_PROFILE_SE` Wald standard errors of the estimate,
    falling back to the whole-range scan when the interval reaches that grid's end (:func:`_profile_sigma_a`).
    """
    lb_all = np.array([_LOG_SSP_BOUNDS[0], np.log(sa_floor)])
    ub_all = np.array([_LOG_SSP_BOUNDS[1], _LOG_SA_MAX])
    lb, ub = lb_all, ub_all
    if box is not None:
        lb = np.clip(np.maximum(lb_all, np.asarray(box[0], dtype=np.float64)), lb_all, ub_all)
        ub = np.clip(np.minimum(ub_all, np.asarray(box[1], dtype=np.float64)), lb, ub_all)
        # a box wholly beyond a range's end collapses onto it: keep a sliver inside (least_squares needs lb < ub;
        # measured: a 5 mm skimmilk pyramid's trust region above sigma_s' = 1e3 /mm failed the reference loop)
        thin = ub - lb < _MIN_BOX_LOG
        lb = np.where(thin & (ub >= ub_all), ub_all - _MIN_BOX_LOG, lb)
        ub = np.where(thin & (ub < ub_all), lb + _MIN_BOX_LOG, ub)
    # coarse grid (one batched evaluation), then trust-region least squares with bounds
    near = bool(local and box is not None and start_hint is not None and np.all(np.isfinite(start_hint)))
    if near:
        g_s, g_a = np.linspace(lb[0], ub[0], _LOCAL_GRID), np.linspace(lb[1], ub[1], _LOCAL_GRID)
    else:
        g_s = np.linspace(np.log(0.01), np.log(100.0), 21)
        g_a = np.linspace(max(np.log(1e-6), lb_all[1]), np.log(10.0), 21)
    grid = np.array(np.meshgrid(g_s, g_a, indexing="ij")).reshape(2, -1).T
    ssr_grid = problem.ssr(grid)
    if not np.any(np.isfinite(ssr_grid)):
        return _ChannelFit(np.full(2, np.nan), np.full((2, 2), np.nan), np.nan, np.nan, problem.nfev, np.nan,
                           (np.nan, np.nan), False, False, "model evaluation is not finite on the start grid")
    x0 = np.clip(grid[int(np.nanargmin(ssr_grid))], lb, ub)
    # (a refit near a known solution: the box's best grid point and the hint only; the lockstep multistart runs until
    # its slowest start ends, and starts on the box's faces and corners only prolong it)
    starts = [x0] if near else [x0, np.clip(x0 + np.array([0.0, 2.0]), lb, ub),
                                np.clip(x0 - np.array([0.0, 2.0]), lb, ub)]
    # other basins: every local minimum of the grid (8-neighbourhood), best first, up to 4 more starts (measured: on
    # a 14 mm pyramid of skin1-R under an environment map the best grid point leads to a minimum with sigma_a at
    # its floor and a 2.2 % rms residual; the truth, which leaves none, lies in another basin)
    finite = np.where(np.isfinite(ssr_grid), ssr_grid, np.inf).reshape(g_s.size, g_a.size)
    local = (finite <= ndimage.minimum_filter(finite, size=3, mode="nearest")) & np.isfinite(finite)
    cand = np.flatnonzero(local.ravel())
    cand = cand[np.argsort(finite.ravel()[cand])]
    starts += [grid[i] for i in cand if np.max(np.abs(grid[i] - x0)) > 0][:0 if near else 4]
    if start_hint is not None and np.all(np.isfinite(start_hint)):
        starts.append(np.clip(np.asarray(start_hint, dtype=np.float64), lb, ub))
    # every start at once (one batched evaluation per iteration), then one trust-region polish of the best. The
    # multistart's box is the one least_squares("trf") works in: its iterates stay strictly inside [lb, ub] (x0 is
    # moved 1e-10 x max(1, |bound|) off an active bound), so the polish starts where TRF would, never ends worse
    # than the multistart's point, and sigma_a at its floor is reported >= the floor, as before.
    shrink = 1e-10 * np.maximum(1.0, np.abs(lb)), 1e-10 * np.maximum(1.0, np.abs(ub))
    lb_in, ub_in = lb + shrink[0], ub - shrink[1]
    start_arr = np.clip(np.array(starts), lb_in, ub_in)
    _, first = np.unique(start_arr, axis=0, return_index=True)  # (x0 - 2 clipped to the floor repeats x0)
    start_arr = start_arr[np.sort(first)]
    ms = _lm_multistart(problem, start_arr, lb_in, ub_in)
    i_best = int(np.argmin(ms.cost))
    if not np.isfinite(ms.cost[i_best]):
        return _ChannelFit(np.full(2, np.nan), np.full((2, 2), np.nan), np.nan, np.nan, problem.nfev, np.nan,
                           (np.nan, np.nan), False, False, "model evaluation is not finite at every start")
    theta, cost, J = ms.x[i_best].copy(), float(ms.cost[i_best]), ms.jac[i_best]
    ok = bool(ms.converged[i_best])
    msg = "ok" if ok else f"batched Levenberg-Marquardt: no convergence in {ms.iterations} iterations"
    if polish:
        res = optimize.least_squares(lambda t: problem.resid(t[None, :])[:, 0], theta, jac=problem.jacobian,
                                     bounds=(lb, ub), method="trf", x_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-12,
                                     max_nfev=400)
        ok = bool(res.status > 0)
        msg = "ok" if res.success else f"least_squares: {res.message}"
        if res.cost <= cost:  # (else keep the multistart's point, whose J is the same central difference)
            theta, cost, J = res.x, float(res.cost), res.jac
    ssr_min = 2.0 * cost + problem.offset
    dof = max(problem.n_data - n_params_dof, 1)
    s2 = max(ssr_min / dof, 1.0 if known_noise else 1e-300)
    if model_error > 0:
        s2 = max(s2, float(np.sum((model_error * problem.weighted_data) ** 2)) / _CHI2_1_95)
    try:
        sv = np.linalg.svd(J, compute_uv=False)
        jac_cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
        cov = s2 * np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        jac_cond, cov = np.inf, np.full((2, 2), np.inf)
    ci = (np.nan, np.nan)
    one_sided = False
    if profile:
        se_a = float(np.sqrt(cov[1, 1])) if np.isfinite(cov[1, 1]) and cov[1, 1] >= 0 else np.inf
        ci, one_sided = _profile_sigma_a(problem, theta, ssr_min, s2, lb_all, ub_all,
                                         local_se=se_a if near else None, cov=cov if near else None)
    return _ChannelFit(theta, cov, ssr_min, s2, problem.nfev, jac_cond, ci, one_sided, ok, msg)


def _profile_sigma_a(problem: _Problem, theta: Array, ssr_min: float, s2: float, lb: Array, ub: Array,
                     local_se: float | None = None, cov: Array | None = None) -> tuple[tuple[float, float], bool]:
    """95 % profile-likelihood interval for sigma_a: {sigma_a : min_ssp SSR <= SSR_min + 3.84 s^2}.

    The profile is scanned on 41 points over sigma_a's whole range (and the estimate), the interval's ends
    interpolated linearly between the last point inside and the first outside. ``local_se`` (log sigma_a's Wald
    standard error, finite and positive): first on :data:`_LOCAL_PROFILE_POINTS` points within +-
    :data:`_LOCAL_PROFILE_SE` of them (a refit near a known solution: a finer grid where the ends lie), each point's
    minimum over sigma_s' by Gauss-Newton from the Wald covariance ``cov``'s conditional line (:func:`_profile_gn`: 5
    batched evaluations instead of golden section's 16); when the interval reaches that grid's end short of the
    range's, the whole-range scan as above. (The whole-range grid's spacing, ~0.5 in log sigma_a, is coarse against
    a well-determined sigma_a: linear interpolation of the quadratic profile between the estimate and its outside
    neighbour then puts the ends ~1.96 se^2 / 0.25 from the estimate instead of 1.96 se: measured on z10's refits,
    +-0.65 % against the Wald interval's +-4 %; the local grid gives the Wald interval's width there.)"""
    if local_se is not None and np.isfinite(local_se) and local_se > 0:
        half = _LOCAL_PROFILE_SE * local_se
        g_lo, g_hi = max(lb[1], theta[1] - half), min(ub[1], theta[1] + half)
        if g_hi > g_lo:
            grid = np.unique(np.concatenate([np.linspace(g_lo, g_hi, _LOCAL_PROFILE_POINTS), [theta[1]]]))
            out = _profile_on(problem, theta, ssr_min, s2, lb, ub, grid, cov=cov)
            if out is not None:
                return out
    grid = np.unique(np.concatenate([np.linspace(lb[1], ub[1], 41), [theta[1]]]))
    out = _profile_on(problem, theta, ssr_min, s2, lb, ub, grid, whole=True)
    assert out is not None
    return out


def _profile_gn(problem: _Problem, theta: Array, grid: Array, cov: Array, lo: float, hi: float, iters: int = 4
                ) -> Array:
    """min over log sigma_s' of the SSR at each log sigma_a of ``grid``, by batched Gauss-Newton in one variable:
    from the Wald conditional line theta_0 + cov_01 / cov_11 (a - theta_1), ``iters`` steps (each one evaluation of
    3 points per grid point: x and x +- the central-difference step), kept within [lo, hi]; the lowest SSR seen per
    point is returned (an upper bound of the profile, equal to it once the steps converge)."""
    slope = cov[0, 1] / cov[1, 1] if np.all(np.isfinite(cov)) and cov[1, 1] > 0 else 0.0
    x = np.clip(theta[0] + slope * (grid - theta[1]), lo, hi)
    t = grid.size
    best = np.full(t, np.inf)
    for _ in range(iters + 1):
        h = _JAC_STEP * np.maximum(1.0, np.abs(x))
        pts = np.stack([np.concatenate([x, x + h, x - h]), np.tile(grid, 3)], axis=1)
        r = problem.resid(pts)
        r0 = r[:, :t]
        ssr = np.einsum("nt,nt->t", r0, r0) + problem.offset
        best = np.minimum(best, np.where(np.isfinite(ssr), ssr, np.inf))
        j = (r[:, t:2 * t] - r[:, 2 * t:]) / (2 * h)
        jj = np.einsum("nt,nt->t", j, j)
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = np.where(jj > 0, -np.einsum("nt,nt->t", j, r0) / jj, 0.0)
        dx = np.where(np.isfinite(dx), np.clip(dx, -1.0, 1.0), 0.0)
        if np.max(np.abs(dx)) < 1e-6:
            break
        x = np.clip(x + dx, lo, hi)
    return best


def _profile_on(problem: _Problem, theta: Array, ssr_min: float, s2: float, lb: Array, ub: Array, grid: Array,
                whole: bool = False, cov: Array | None = None) -> tuple[tuple[float, float], bool] | None:
    """:func:`_profile_sigma_a` on ``grid`` (sorted log sigma_a, holding theta[1]); None when not ``whole`` and the
    interval reaches an end of the grid that is not the end of sigma_a's range [lb[1], ub[1]]. With ``cov`` the
    profile's minima over sigma_s' by :func:`_profile_gn`, else by golden section over +- 5 in log sigma_s'."""
    lo_s = np.full(grid.size, max(lb[0], theta[0] - 5.0))
    hi_s = np.full(grid.size, min(_LOG_SSP_BOUNDS[1], theta[0] + 5.0))

    def f(x: Array) -> Array:
        return problem.ssr(np.stack([x, grid], axis=1))

    if cov is not None:
        prof = _profile_gn(problem, theta, grid, cov, float(lo_s[0]), float(hi_s[0]))
    else:
        _, prof = _golden_batch(f, lo_s, hi_s, iters=_GOLDEN_ITERS)
    prof = np.minimum(prof, np.where(grid == theta[1], ssr_min, np.inf))
    thresh = ssr_min + _CHI2_1_95 * s2
    inside = prof <= thresh
    i0 = int(np.argmin(np.abs(grid - theta[1])))
    inside[i0] = True
    # connected run around the optimum
    lo_i = i0
    while lo_i > 0 and inside[lo_i - 1]:
        lo_i -= 1
    hi_i = i0
    while hi_i < grid.size - 1 and inside[hi_i + 1]:
        hi_i += 1

    def cross(i_in: int, i_out: int) -> float:
        a, b = prof[i_in], prof[i_out]
        if not np.isfinite(b) or b == a:
            return float(grid[i_in])
        t = (thresh - a) / (b - a)
        return float(grid[i_in] + np.clip(t, 0, 1) * (grid[i_out] - grid[i_in]))

    if not whole and ((lo_i == 0 and grid[0] > lb[1]) or (hi_i == grid.size - 1 and grid[-1] < ub[1])):
        return None
    one_sided = lo_i == 0
    lower = 0.0 if one_sided else float(np.exp(cross(lo_i, lo_i - 1)))
    upper = float(np.exp(grid[-1])) if hi_i == grid.size - 1 else float(np.exp(cross(hi_i, hi_i + 1)))
    return (lower, upper), one_sided



def _tikhonov(w: Array, l: Array, lam: float | None, monotone: bool, *, n_data: int | None = None,
              offset: float = 0.0) -> tuple[Array, float]:
    """min ||W r - l||^2 + lam ||L2 r||^2, r >= 0 (monotone: r non-increasing); lam by GCV when None.

    ``w``, ``l`` may be the QR reduction of the weighted system (:func:`_reduce`): ``n_data`` is then the number
    of data and ``offset`` the residual no r can fit (both enter the GCV score only).
    """
    n = w.shape[1]
    m = w.shape[0] if n_data is None else int(n_data)
    L = np.diff(np.eye(n), 2, axis=0)
    # scale columns so lambda is dimensionless
    colscale = np.linalg.norm(w, axis=0)
    colscale = np.where(colscale > 0, colscale, 1.0)
    ws = w / colscale
    Ls = L / colscale  # penalty on r = r_s / colscale
    gtg = ws.T @ ws
    ltl = Ls.T @ Ls
    scale_l = np.trace(gtg) / max(np.trace(ltl), 1e-300)
    if lam is None:
        best = (np.inf, 1e-6)
        for lg in np.linspace(-10, 2, 25):
            lam_t = 10.0**lg * scale_l
            a = gtg + lam_t * ltl
            try:
                rs = np.linalg.solve(a, ws.T @ l)
                infl = np.trace(np.linalg.solve(a, gtg))
            except np.linalg.LinAlgError:
                continue
            res = ws @ rs - l
            gcv = m * (float(res @ res) + offset) / max(m - infl, 1e-9) ** 2
            if gcv < best[0]:
                best = (gcv, lam_t)
        lam_used = best[1]
    else:
        lam_used = float(lam) * scale_l
    a_aug = np.vstack([ws, np.sqrt(lam_used) * Ls])
    b_aug = np.concatenate([l, np.zeros(Ls.shape[0])])
    if monotone:
        # r = T u with u >= 0, r_i = sum_{t >= i} u_t: non-negative and non-increasing. The objective is the
        # same as in the scaled variables: ||W r - l||^2 + lam ||L r||^2 (ws r_s = W r, Ls r_s = L r).
        T = np.triu(np.ones((n, n)))
        a_aug = np.vstack([w @ T, np.sqrt(lam_used) * (L @ T)])
        u, _ = optimize.nnls(a_aug, b_aug, maxiter=50 * n)
        return T @ u, lam_used
    rs, _ = optimize.nnls(a_aug, b_aug, maxiter=50 * n)
    return rs / colscale, lam_used
