"""Tabulated Monte Carlo reflectance profiles of a half-space: the ``"mc-table"`` profile model (issue 8 item 3).

The table (``estimation/data/mc_profiles.npz``, written by ``python -m simulators.mc.tables``; see
docs/monte-carlo.md) holds, for a grid of reduced albedo alpha' x relative index eta, the cumulative reflectance

    C(rho) = int_0^rho R(rho') 2 pi rho' drho'      and its complement      T(rho) = R_d - C(rho)

of a semi-infinite medium under a normally incident pencil beam, computed by the Monte Carlo renderer
(simulators/mc) with isotropic scattering (g = 0) in optical units: rho = r sigma_t' (transport mean free paths),
sigma_t' = 1. R_d = C(inf) is the total diffuse reflectance. Everything is normalized per unit power *entering*
the medium (the specular Fresnel reflection at entry is excluded), as for the dipoles of :mod:`.dipole`
(R_d -> 1 as alpha' -> 1), so the table is a drop-in for their R(r), int_0^r R dA and R_d.

Physical units: for (sigma_s', sigma_a) [1/mm], rho = r sigma_t', C_mm(r) = C(r sigma_t') (dimensionless),
R_mm(r) = sigma_t'^2 R(r sigma_t') [1/mm^2]. The profile depends on (sigma_s', sigma_a) only through alpha' and
the length scale 1/sigma_t' (exactly, by the similarity of the transport equation with g = 0).

Interpolation (all in float64; pure numpy + scipy):

- in albedo: cubic spline (not-a-knot, C^2) in u = logit(alpha') = ln(sigma_s'/sigma_a) (dense near alpha' = 1,
  exact for sigma_a -> 0, well behaved at low albedo where R_d ~ alpha');
- in eta: cubic spline (not-a-knot) in eta;
- what is interpolated across (alpha', eta), at each radius node, is F = ln(C/T) - k rho: bounded, because the
  tail decays like e^(-k rho)/rho (ln(C/T) itself reaches 1e4 at low albedo and would spill into its neighbours);
- in radius: the variable y(ln rho) = ln(C/T), increasing from -inf (source) to +inf (far field), is interpolated by
  a monotone cubic Hermite spline in ln rho (4th-order finite-difference slopes with the Hyman monotonicity
  filter). Then C = R_d sigma(y), T = R_d sigma(-y) (so C(inf) = R_d exactly, C is monotone) and the profile is the
  exact derivative of the interpolant, R = dC/dA = R_d sigma(y) sigma(-y) y'(ln rho) / (2 pi rho^2) (evaluated in
  log space: no cancellation in C ~ R_d or in the far tail);
- below the table's first radius rho_min (1e-3): R constant = C(rho_min)/(pi rho_min^2) (the transport profile
  diverges like 1/rho at the source; this keeps R(0) finite and C = int R dA exact);
- beyond its last radius rho_max: the asymptotic transport tail T(rho) = T(rho_max) (rho_max/rho) e^(-k (rho -
  rho_max)), k(alpha') the exact decay constant of isotropic transport (alpha' artanh(k) = k).

Outside the grid's alpha' or eta range every function raises ValueError naming the parameter and the range
(``out_of_range="clip"`` evaluates at the nearest edge instead, for optimizers).

R is exitance; :func:`exit_radiance_factor` turns it into radiance with a normalized angular factor.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline

__all__ = ["MODEL_NAME", "TABLE_FORMAT", "McProfileTable", "default_table", "decay_constant",
           "exit_radiance_factor", "OUT_OF_RANGE_MODES"]

MODEL_NAME = "mc-table"
TABLE_FORMAT = 1
DEFAULT_RESOURCE = "mc_profiles.npz"
OUT_OF_RANGE_MODES = ("raise", "clip")

Array = NDArray[np.float64]
_LOG_2PI = float(np.log(2.0 * np.pi))


def _f64(x: ArrayLike) -> Array:
    return np.asarray(x, dtype=np.float64)


def _softplus(x: Array) -> Array:
    return np.logaddexp(0.0, x)


def decay_constant(alpha_prime: ArrayLike) -> Array:
    """Asymptotic decay constant k (units of sigma_t) of isotropic transport with single-scattering albedo
    ``alpha_prime``: the root in (0, 1) of alpha' artanh(k) = k (Case & Zweifel 1967; the diffusion limit is
    sqrt(3 (1 - alpha')) for alpha' -> 1; k -> 1 for alpha' -> 0). 0 at alpha' = 1, 1 at alpha' = 0.

    Solved for t = artanh(k), h(t) = 1 - tanh(t)/t = 1 - alpha' (h increasing from 0 to 1), by Newton's method
    safeguarded with bisection, with series for h and h' at small t: accurate to ~1e-15 relative down to
    1 - alpha' ~ 1e-14.
    """
    a = _f64(alpha_prime)
    if np.any(~((a >= 0) & (a <= 1))):
        raise ValueError("alpha_prime must lie in [0, 1]")
    shape = a.shape
    a = a.ravel()
    target = 1.0 - a
    inner = (a > 0) & (a < 1)
    ai = np.where(inner, a, 0.5)
    ti = np.where(inner, target, 0.5)
    lo = np.zeros_like(ai)
    hi = 1.0 / ai + 1.0
    # start: diffusion guess near alpha' = 1, the bound 1/alpha' otherwise
    t = np.where(ti < 0.3, np.sqrt(3.0 * ti) * (1.0 + 0.3 * ti), 1.0 / ai)
    t = np.clip(t, 1e-300, hi)
    for _ in range(100):
        t2 = t * t
        small = t < 0.02
        th = np.tanh(t)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            h_direct = 1.0 - th / t
            dh_direct = (th - t * (1.0 - th * th)) / t2
        h = np.where(small, t2 / 3.0 - 2.0 * t2 ** 2 / 15.0 + 17.0 * t2 ** 3 / 315.0 - 62.0 * t2 ** 4 / 2835.0,
                     h_direct)
        dh = np.where(small, t * (2.0 / 3.0 - 8.0 * t2 / 15.0 + 34.0 * t2 ** 2 / 105.0 - 496.0 * t2 ** 3 / 2835.0),
                      dh_direct)
        f = h - ti
        lo = np.where(f < 0, t, lo)
        hi = np.where(f > 0, t, hi)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_new = t - f / dh
        outside = ~((t_new > lo) & (t_new < hi)) | ~np.isfinite(t_new)
        t_new = np.where(outside, 0.5 * (lo + hi), t_new)
        done = np.abs(t_new - t) <= 1e-15 * t
        t = t_new
        if np.all(done):
            break
    k = np.tanh(t)
    k = np.where(a >= 1.0, 0.0, np.where(a <= 0.0, 1.0, k))
    return k.reshape(shape)


def exit_radiance_factor(eta: ArrayLike, cos_out: ArrayLike) -> Array:
    """Radiance leaving at cos_out per unit exitance [1/sr]: F_t(eta, cos_out) / (pi c), c = 1 - 2 FM1_ext(eta)
    (the normalization of pbrt's SeparableBSSRDF::Sw, so that it integrates to 1 over the hemisphere).

    The table's R is exitance (all exit directions); radiance is L_o = exit_radiance_factor * sum_k R c_k. Jensen's
    S_d (and the seed paper's l_j = pi L_o / F_t) use F_t/pi, i.e. c = 1: with the table that predicts radiance low
    by c (0.939 at eta 1.3, 0.908 at 1.5). Against the Monte Carlo's own exit distribution (alpha' 0.9-0.999, eta
    1.3-1.5) this factor is within ~5 % for cos_out >= 0.2 and ~25-30 % low at grazing exit (cos_out < 0.1).
    """
    from .fresnel import fresnel_moment, fresnel_transmittance

    c = 1.0 - 2.0 * fresnel_moment(eta, 1, side="external")
    return fresnel_transmittance(eta, cos_out) / (np.pi * c)


def _hermite_slopes(x: Array, y: Array) -> Array:
    """Slopes for a monotone cubic Hermite interpolant along the last axis of y (x uniformly spaced, increasing).

    4th-order central differences inside, 2nd-order one-sided at the ends, then the Hyman (1983) filter:
    |d_k| <= 3 min(|m_{k-1}|, |m_k|) with the sign of the secants (0 where they differ). Increasing data give an
    increasing interpolant; smooth data keep (near) 4th-order accuracy.
    """
    h = x[1] - x[0]
    n = y.shape[-1]
    m = np.diff(y, axis=-1) / h  # secants (..., n-1)
    d = np.empty_like(y)
    if n >= 5:
        d[..., 2:-2] = (y[..., :-4] - 8.0 * y[..., 1:-3] + 8.0 * y[..., 3:-1] - y[..., 4:]) / (12.0 * h)
        d[..., 1] = 0.5 * (m[..., 0] + m[..., 1])
        d[..., -2] = 0.5 * (m[..., -2] + m[..., -1])
    else:
        d[..., 1:-1] = 0.5 * (m[..., :-1] + m[..., 1:])
    if n >= 3:
        d[..., 0] = (-3.0 * y[..., 0] + 4.0 * y[..., 1] - y[..., 2]) / (2.0 * h)
        d[..., -1] = (3.0 * y[..., -1] - 4.0 * y[..., -2] + y[..., -3]) / (2.0 * h)
    else:
        d[..., 0] = d[..., -1] = m[..., 0]
    # Hyman filter
    m_left = np.concatenate([m[..., :1], m], axis=-1)
    m_right = np.concatenate([m, m[..., -1:]], axis=-1)
    same = (m_left * m_right) > 0
    sgn = np.sign(m_right)
    bound = 3.0 * np.minimum(np.abs(m_left), np.abs(m_right))
    lim = np.where(same, sgn * np.minimum(np.maximum(sgn * d, 0.0), bound), 0.0)
    return lim


def _hermite_eval(x: Array, y: Array, d: Array, row: Array, xq: Array) -> tuple[Array, Array]:
    """Value and derivative of the cubic Hermite interpolant (rows y[row], slopes d[row]) at xq (clamped inside)."""
    h = x[1] - x[0]
    j = np.clip(np.floor((xq - x[0]) / h).astype(np.int64), 0, x.size - 2)
    t = (xq - x[j]) / h
    y0, y1 = y[row, j], y[row, j + 1]
    d0, d1 = d[row, j] * h, d[row, j + 1] * h
    t2 = t * t
    t3 = t2 * t
    val = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * d0 + (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * d1
    der = ((6 * t2 - 6 * t) * y0 + (3 * t2 - 4 * t + 1) * d0 + (-6 * t2 + 6 * t) * y1 + (3 * t2 - 2 * t) * d1) / h
    return val, der


class _AxisSpline:
    """Cardinal not-a-knot cubic-spline weights on one axis (linear for 2-3 nodes, identity for 1)."""

    def __init__(self, nodes: Array):
        self.nodes = _f64(nodes)
        n = self.nodes.size
        if n >= 4:
            self._sp = CubicSpline(self.nodes, np.eye(n), bc_type="not-a-knot")
        else:
            self._sp = None

    def weights(self, q: Array) -> Array:
        n = self.nodes.size
        q = _f64(q)
        if n == 1:
            return np.ones((q.size, 1))
        if self._sp is None:
            w = np.zeros((q.size, n))
            j = np.clip(np.searchsorted(self.nodes, q, side="right") - 1, 0, n - 2)
            t = (q - self.nodes[j]) / (self.nodes[j + 1] - self.nodes[j])
            w[np.arange(q.size), j] = 1.0 - t
            w[np.arange(q.size), j + 1] = t
            return w
        return np.asarray(self._sp(q), dtype=np.float64).reshape(q.size, n)


@dataclass(frozen=True)
class _Rows:
    """Interpolated table rows for U distinct (u, eta): y over the radius nodes, slopes, log R_d, alpha'."""

    y: Array
    d: Array
    log_rd: Array
    alpha_prime: Array
    k: Array


class McProfileTable:
    """Monte Carlo profile table; see the module docstring. Build with :meth:`load` (the packaged table by default)
    or :meth:`from_arrays`.

    All evaluation methods broadcast their array arguments against each other (like :mod:`.dipole`).
    """

    def __init__(self, alpha_prime: ArrayLike, eta: ArrayLike, radius: ArrayLike, log_cumulative: ArrayLike,
                 log_tail: ArrayLike, *, metadata: dict[str, Any] | None = None,
                 arrays: dict[str, NDArray[Any]] | None = None):
        a = _f64(alpha_prime)
        e = _f64(eta)
        r = _f64(radius)
        lc = _f64(log_cumulative)
        lt = _f64(log_tail)
        if a.ndim != 1 or e.ndim != 1 or r.ndim != 1 or a.size < 1 or e.size < 1 or r.size < 3:
            raise ValueError("alpha_prime, eta, radius must be 1-D (radius with >= 3 nodes)")
        if lc.shape != (a.size, e.size, r.size) or lt.shape != lc.shape:
            raise ValueError(f"log_cumulative and log_tail must have shape {(a.size, e.size, r.size)}")
        if np.any(np.diff(a) <= 0) or a[0] <= 0 or a[-1] >= 1:
            raise ValueError("alpha_prime nodes must increase inside (0, 1)")
        if np.any(np.diff(e) <= 0):
            raise ValueError("eta nodes must increase")
        lr = np.log(r)
        if r[0] <= 0 or not np.allclose(np.diff(lr), lr[1] - lr[0], rtol=1e-6, atol=0):
            raise ValueError("radius nodes must be > 0 and log-spaced uniformly")
        if not (np.all(np.isfinite(lc)) and np.all(np.isfinite(lt))):
            raise ValueError("log_cumulative and log_tail must be finite")
        y = lc - lt
        if np.any(np.diff(y, axis=-1) <= 0):
            raise ValueError("C(rho) must increase strictly along the radius axis")
        log_rd = np.logaddexp(lc, lt)  # C + T = R_d at every radius (check consistency)
        if np.max(np.abs(log_rd - log_rd[..., -1:])) > 1e-5:
            raise ValueError("cumulative + tail must equal R_d (the same) at every radius")
        self.alpha_prime_nodes = a
        self.eta_nodes = e
        self.radius_nodes = r
        self._u_nodes = np.log(a) - np.log1p(-a)
        self._lr = lr
        # interpolated across (alpha', eta): F = ln(C/T) - k rho, bounded at large rho (the far tail decays like
        # e^(-k rho)/rho), so distant nodes with huge ln(C/T) cannot spill into their neighbours
        self._F = y - self._decay(a)[:, None, None] * r
        self._log_rd = np.mean(log_rd, axis=-1)
        self._u_axis = _AxisSpline(self._u_nodes)
        self._e_axis = _AxisSpline(e)
        self.metadata: dict[str, Any] = dict(metadata or {})
        self.arrays: dict[str, NDArray[Any]] = dict(arrays or {})

    @staticmethod
    def _decay(alpha_prime: Array) -> Array:
        """Far-field decay constant (optical units) used to flatten the table: :func:`decay_constant`."""
        return decay_constant(alpha_prime)

    # ------------------------------------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(cls, arrays: dict[str, NDArray[Any]]) -> "McProfileTable":
        """From the arrays of a table file (keys alpha_prime, eta, radius, cumulative, tail, metadata_json...)."""
        if "format_version" in arrays and int(np.asarray(arrays["format_version"])) != TABLE_FORMAT:
            raise ValueError(f"unsupported table format {int(np.asarray(arrays['format_version']))} "
                             f"(this code reads format {TABLE_FORMAT})")
        meta: dict[str, Any] = {}
        if "metadata_json" in arrays:
            meta = json.loads(str(np.asarray(arrays["metadata_json"])))
        return cls(arrays["alpha_prime"], arrays["eta"], arrays["radius"], arrays["log_cumulative"],
                   arrays["log_tail"], metadata=meta, arrays=dict(arrays))

    @classmethod
    def load(cls, path: str | Path | None = None) -> "McProfileTable":
        """Load a table file; default: the packaged ``estimation/data/mc_profiles.npz``."""
        if path is None:
            ref = resources.files("estimation.data").joinpath(DEFAULT_RESOURCE)
            with resources.as_file(ref) as p:
                return cls._load_path(Path(p))
        return cls._load_path(Path(path))

    @classmethod
    def _load_path(cls, path: Path) -> "McProfileTable":
        if not path.is_file():
            raise FileNotFoundError(f"Monte Carlo profile table not found: {path} (generate it with "
                                    "`python -m simulators.mc.tables --out estimation/data/mc_profiles.npz`)")
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        return cls.from_arrays(arrays)

    # ------------------------------------------------------------------------------------------------ ranges
    @property
    def alpha_prime_range(self) -> tuple[float, float]:
        return float(self.alpha_prime_nodes[0]), float(self.alpha_prime_nodes[-1])

    @property
    def eta_range(self) -> tuple[float, float]:
        return float(self.eta_nodes[0]), float(self.eta_nodes[-1])

    @property
    def radius_range(self) -> tuple[float, float]:
        """First and last tabulated radius in transport mean free paths (1/sigma_t')."""
        return float(self.radius_nodes[0]), float(self.radius_nodes[-1])

    def _check_u(self, u: Array, out_of_range: str) -> Array:
        lo, hi = self._u_nodes[0], self._u_nodes[-1]
        tol = 1e-9 * max(1.0, abs(lo), abs(hi))
        bad = ~((u >= lo - tol) & (u <= hi + tol))  # (NaN is bad too)
        if np.any(bad):
            if out_of_range == "clip" and not np.any(np.isnan(u)):
                return np.clip(u, lo, hi)
            a_bad = float(1.0 / (1.0 + np.exp(-u[bad].ravel()[0])))
            a_lo, a_hi = self.alpha_prime_range
            raise ValueError(f"reduced albedo alpha' = sigma_s'/(sigma_s' + sigma_a) = {a_bad:.10g} is outside the "
                             f"Monte Carlo table's range [{a_lo:.10g}, {a_hi:.10g}] (1 - alpha' in "
                             f"[{1 - a_hi:.3g}, {1 - a_lo:.3g}])")
        return np.clip(u, lo, hi)

    def _check_eta(self, eta: Array, out_of_range: str) -> Array:
        lo, hi = self.eta_range
        tol = 1e-9
        bad = ~((eta >= lo - tol) & (eta <= hi + tol))
        if np.any(bad):
            if out_of_range == "clip" and not np.any(np.isnan(eta)):
                return np.clip(eta, lo, hi)
            raise ValueError(f"eta = {float(eta[bad].ravel()[0]):.10g} is outside the Monte Carlo table's range "
                             f"[{lo:.10g}, {hi:.10g}]")
        return np.clip(eta, lo, hi)

    def check_eta(self, eta: ArrayLike) -> None:
        """Raise ValueError (naming the range) unless every ``eta`` lies in the table's eta range."""
        self._check_eta(_f64(eta).ravel(), "raise")

    def check_alpha_prime(self, alpha_prime: ArrayLike) -> None:
        """Raise ValueError (naming the range) unless every ``alpha_prime`` lies in the table's albedo range."""
        a = _f64(alpha_prime).ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.log(a) - np.log1p(-a)
        self._check_u(np.where((a > 0) & (a < 1), u, np.where(a >= 1, np.inf, -np.inf)), "raise")

    def __repr__(self) -> str:
        a, e, r = self.alpha_prime_range, self.eta_range, self.radius_range
        return (f"McProfileTable(alpha' {a[0]:.4g}..1-{1 - a[1]:.3g} ({self.alpha_prime_nodes.size} nodes), "
                f"eta {e[0]:g}..{e[1]:g} ({self.eta_nodes.size}), rho {r[0]:g}..{r[1]:g} mfp "
                f"({self.radius_nodes.size}))")

    @staticmethod
    def _check_mode(out_of_range: str) -> None:
        if out_of_range not in OUT_OF_RANGE_MODES:
            raise ValueError(f"out_of_range must be one of {OUT_OF_RANGE_MODES}, got {out_of_range!r}")

    # ------------------------------------------------------------------------------------------------ core
    def _rows(self, u: Array, eta: Array) -> _Rows:
        wu = self._u_axis.weights(u)
        we = self._e_axis.weights(eta)
        a = 1.0 / (1.0 + np.exp(-u))
        k = self._decay(a)
        F = np.einsum("ue,aer->uar", we, self._F)
        y = np.einsum("ua,uar->ur", wu, F) + k[:, None] * self.radius_nodes
        log_rd = np.einsum("ua,ue,ae->u", wu, we, self._log_rd)
        d = _hermite_slopes(self._lr, y)
        return _Rows(y, d, log_rd, a, k)

    def _params(self, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike) -> tuple[Array, Array]:
        ssp = _f64(sigma_s_prime_per_mm)
        sa = _f64(sigma_a_per_mm)
        if np.any(ssp < 0) or np.any(sa < 0) or not (np.all(np.isfinite(ssp)) and np.all(np.isfinite(sa))):
            raise ValueError("sigma_s_prime_per_mm and sigma_a_per_mm must be finite and >= 0")
        st = ssp + sa
        if np.any(st <= 0):
            raise ValueError("sigma_t' = sigma_s' + sigma_a must be > 0")
        with np.errstate(divide="ignore"):
            u = np.log(ssp) - np.log(sa)
        return u, st

    def _log_eval(self, rho: Array, u: Array, eta: Array, out_of_range: str) -> tuple[Array, Array, Array, Array]:
        """log C, log T, log R (optical units), log R_d for broadcast (rho, u, eta)."""
        self._check_mode(out_of_range)
        rho = _f64(rho)
        u_b, e_b = np.broadcast_arrays(_f64(u), _f64(eta))
        pshape = u_b.shape
        shape = np.broadcast_shapes(rho.shape, pshape)
        if np.any(rho < 0) or np.any(np.isnan(rho)):
            raise ValueError("radius_mm must be >= 0")
        u = self._check_u(u_b.ravel(), out_of_range)
        eta = self._check_eta(e_b.ravel(), out_of_range)
        # distinct parameter pairs (usually few: one per theta), evaluated once each
        if u.size == 1:
            uniq, inv = np.stack([u, eta], axis=1), np.zeros(1, np.int64)
        else:
            uniq, inv = np.unique(np.stack([u, eta], axis=1), axis=0, return_inverse=True)
        inv = np.broadcast_to(inv.reshape(pshape), shape).ravel()
        rho = np.broadcast_to(rho, shape).ravel()
        rows = self._rows(uniq[:, 0], uniq[:, 1])
        log_rd = rows.log_rd[inv]
        lr = self._lr
        r_min, r_max = self.radius_nodes[0], self.radius_nodes[-1]
        with np.errstate(divide="ignore"):
            x = np.log(rho)
        xi = np.clip(x, lr[0], lr[-1])
        y, yp = _hermite_eval(lr, rows.y, rows.d, inv, xi)
        log_c = log_rd - _softplus(-y)
        log_t = log_rd - _softplus(y)
        with np.errstate(divide="ignore"):
            log_r = log_rd - _softplus(-y) - _softplus(y) + np.log(np.maximum(yp, 0.0)) - _LOG_2PI - 2.0 * xi
        # below rho_min: constant R = C(rho_min) / (pi rho_min^2)
        lo = rho < r_min
        if np.any(lo):
            log_r0 = log_c[lo] - np.log(np.pi) - 2.0 * lr[0]
            with np.errstate(divide="ignore"):
                lc = log_r0 + np.log(np.pi) + 2.0 * x[lo]
            log_c[lo] = lc
            log_t[lo] = log_rd[lo] + np.log(-np.expm1(np.minimum(lc - log_rd[lo], -1e-300)))
            log_r[lo] = log_r0
        hi = rho > r_max
        if np.any(hi):
            k = rows.k[inv[hi]]
            lt = log_t[hi] - (x[hi] - lr[-1]) - k * (rho[hi] - r_max)
            log_t[hi] = lt
            log_c[hi] = log_rd[hi] + np.log(-np.expm1(np.minimum(lt - log_rd[hi], -1e-300)))
            log_r[hi] = lt + np.log1p(k * rho[hi]) - _LOG_2PI - 2.0 * x[hi]
        return (log_c.reshape(shape), log_t.reshape(shape), log_r.reshape(shape), log_rd.reshape(shape))

    # ------------------------------------------------------------------------------------------------ public API
    def cumulative(self, radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                   eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """Exact disk integral int_0^r R 2 pi r' dr' (dimensionless) of the interpolated profile: the model's
        replacement for :func:`estimation.dipole.cumulative_disk` (self-patch and ring integrals)."""
        u, st = self._params(sigma_s_prime_per_mm, sigma_a_per_mm)
        lc, _, _, _ = self._log_eval(_f64(radius_mm) * st, u, eta, out_of_range)
        return np.exp(lc)

    def tail_beyond_disk(self, radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                         eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """int_r^inf R 2 pi r' dr' = R_d - cumulative, from its own representation (no cancellation)."""
        u, st = self._params(sigma_s_prime_per_mm, sigma_a_per_mm)
        _, lt, _, _ = self._log_eval(_f64(radius_mm) * st, u, eta, out_of_range)
        return np.exp(lt)

    def log_profile(self, radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                    eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """ln R(r) [R in 1/mm^2]; R = dC/dA is the exact derivative of :meth:`cumulative`."""
        u, st = self._params(sigma_s_prime_per_mm, sigma_a_per_mm)
        _, _, lr, _ = self._log_eval(_f64(radius_mm) * st, u, eta, out_of_range)
        return lr + 2.0 * np.log(st)

    def profile(self, radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """Diffuse reflectance profile R(r) [1/mm^2] (finite at r = 0; underflows to 0, never NaN)."""
        return np.exp(self.log_profile(radius_mm, sigma_s_prime_per_mm, sigma_a_per_mm, eta,
                                       out_of_range=out_of_range))

    def total_reflectance(self, alpha_prime: ArrayLike, eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """Total diffuse reflectance R_d(alpha', eta) (per unit power entering the medium)."""
        self._check_mode(out_of_range)
        a = _f64(alpha_prime)
        if np.any((a <= 0) | (a >= 1)) and out_of_range == "raise":
            lo, hi = self.alpha_prime_range
            raise ValueError(f"alpha_prime must lie in the table's range [{lo:.10g}, {hi:.10g}]")
        a, eta_b = np.broadcast_arrays(np.clip(a, 1e-300, 1.0 - 1e-16), _f64(eta))
        u = np.log(a) - np.log1p(-a)
        return self._total_u(u, eta_b, out_of_range)

    def _total_u(self, u: Array, eta: Array, out_of_range: str) -> Array:
        u, eta = np.broadcast_arrays(_f64(u), _f64(eta))
        shape = u.shape
        uu = self._check_u(u.ravel(), out_of_range)
        ee = self._check_eta(eta.ravel(), out_of_range)
        wu = self._u_axis.weights(uu)
        we = self._e_axis.weights(ee)
        return np.exp(np.einsum("ua,ue,ae->u", wu, we, self._log_rd)).reshape(shape)

    def total_diffuse_reflectance(self, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                                  eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """R_d from (sigma_s', sigma_a) (a function of alpha' = sigma_s'/sigma_t' only)."""
        u, st = self._params(sigma_s_prime_per_mm, sigma_a_per_mm)
        return self._total_u(u, np.broadcast_to(_f64(eta), np.broadcast(u, _f64(eta)).shape), out_of_range)

    def invert_albedo(self, R_d: ArrayLike, eta: ArrayLike, *, out_of_range: str = "raise") -> Array:
        """Reduced albedo alpha' with total_reflectance(alpha', eta) = R_d.

        R_d is strictly increasing in u = logit(alpha') on the table (checked by the tests), so this is a vectorized
        bisection in u to double precision. R_d outside [R_d(alpha'_min), R_d(alpha'_max)] at that eta raises
        ValueError naming the range (``out_of_range="clip"``: the nearest end of the table's albedo range).
        """
        self._check_mode(out_of_range)
        r, eta_b = np.broadcast_arrays(_f64(R_d), _f64(eta))
        shape = r.shape
        r = r.ravel()
        e = self._check_eta(eta_b.ravel(), out_of_range)
        u_lo = np.full(r.shape, self._u_nodes[0])
        u_hi = np.full(r.shape, self._u_nodes[-1])
        r_lo = self._total_u(u_lo, e, "clip")
        r_hi = self._total_u(u_hi, e, "clip")
        bad = ~((r >= r_lo * (1 - 1e-12)) & (r <= r_hi * (1 + 1e-12)))
        if np.any(bad) and out_of_range == "raise":
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"R_d = {float(r[i]):.10g} is outside the range the Monte Carlo table covers at eta = "
                             f"{float(e[i]):.10g}: [{float(r_lo[i]):.10g}, {float(r_hi[i]):.10g}] (alpha' in "
                             f"[{self.alpha_prime_range[0]:.10g}, {self.alpha_prime_range[1]:.10g}])")
        rc = np.clip(r, r_lo, r_hi)
        lo, hi = u_lo.copy(), u_hi.copy()
        log_target = np.log(np.maximum(rc, 1e-300))
        for _ in range(64):
            mid = 0.5 * (lo + hi)
            below = np.log(self._total_u(mid, e, "clip")) < log_target
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        u = 0.5 * (lo + hi)
        return (1.0 / (1.0 + np.exp(-u))).reshape(shape)

    def diffuse_mean_free_path_mm(self, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike) -> Array:
        """l_d = 1 / (k sigma_t') [mm], k = :func:`decay_constant`(alpha'): the e-folding length of the far
        tail (the transport analogue of the dipole's 1/sigma_tr); inf when sigma_a = 0."""
        u, st = self._params(sigma_s_prime_per_mm, sigma_a_per_mm)
        a = _f64(sigma_s_prime_per_mm) / st
        k = decay_constant(a)
        with np.errstate(divide="ignore"):
            return np.where(k > 0, 1.0 / (np.where(k > 0, k, 1.0) * st), np.inf)

    def reflectance_from_coefficients(self, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                                      eta: ArrayLike, *, out_of_range: str = "raise") -> tuple[Array, Array, Array]:
        """(sigma_s', sigma_a) -> (R_d, l_d_mm, D_mm) like :func:`estimation.dipole.reflectance_from_coefficients`;
        l_d from the exact transport decay constant, D = 1/(3 sigma_t') (nominal: the table has no D)."""
        rd = self.total_diffuse_reflectance(sigma_s_prime_per_mm, sigma_a_per_mm, eta, out_of_range=out_of_range)
        ld = self.diffuse_mean_free_path_mm(sigma_s_prime_per_mm, sigma_a_per_mm)
        st = _f64(sigma_s_prime_per_mm) + _f64(sigma_a_per_mm)
        return rd, ld, 1.0 / (3.0 * st)

    def coefficients_from_reflectance(self, R_d: ArrayLike, l_d_mm: ArrayLike, eta: ArrayLike, *,
                                      out_of_range: str = "raise") -> tuple[Array, Array]:
        """(R_d, l_d [mm]) -> (sigma_s', sigma_a) [1/mm]: alpha' by :meth:`invert_albedo`, sigma_t' = 1/(k l_d)."""
        a = self.invert_albedo(R_d, eta, out_of_range=out_of_range)
        st = 1.0 / (_f64(l_d_mm) * decay_constant(a))
        return a * st, (1.0 - a) * st

    def cutoff_radius_mm(self, tolerance: float, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                         eta: ArrayLike, *, out_of_range: str = "raise", max_radius_mm: float = 1e7) -> float:
        """Smallest radius beyond which the profile carries less than ``tolerance`` of R_d (max over the inputs);
        ``max_radius_mm`` if even that leaves more (like :func:`estimation.dipole.cutoff_radius_mm`)."""
        if not 0.0 < tolerance < 1.0:
            raise ValueError("tolerance must lie in (0, 1)")
        u, st = self._params(sigma_s_prime_per_mm, sigma_a_per_mm)
        u, st, eta_b = np.broadcast_arrays(u, st, _f64(eta))
        u, st, eta_b = u.ravel(), st.ravel(), eta_b.ravel()
        lo = np.full(u.shape, np.log(1e-9))
        hi = np.full(u.shape, np.log(max_radius_mm))
        log_tol = np.log(tolerance)

        def excess(log_r: Array) -> Array:
            _, lt, _, lrd = self._log_eval(np.exp(log_r) * st, u, eta_b, out_of_range)
            return lt - lrd - log_tol

        if np.any(excess(hi) > 0):
            return float(max_radius_mm)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            pos = excess(mid) > 0
            lo = np.where(pos, mid, lo)
            hi = np.where(pos, hi, mid)
        return float(np.max(np.exp(hi)))


@lru_cache(maxsize=1)
def default_table() -> McProfileTable:
    """The packaged table, loaded once per process."""
    return McProfileTable.load()


# ---------------------------------------------------------------------------------------------------- additions
# (issue 8 item 3/4 for the gradients estimator: the table's second radial moment, like the dipoles'
# second_moment_factor_G; nothing above is changed)
_GL8_X, _GL8_W = np.polynomial.legendre.leggauss(8)


def second_moment_factor(alpha_prime: ArrayLike, eta: float, *, table: "McProfileTable | None" = None,
                         out_of_range: str = "raise", panels: int = 48) -> Array:
    """G_mc(alpha', eta) with <r^2> = l'^2 G_mc, l' = 1/sigma_t': the normalized second radial moment
    int r^2 R dA / R_d of the table's half-space profile in optical units (the analogue of the Jensen dipole's
    :func:`estimation.dipole.second_moment_factor_G`).

    Integration by parts, int_0^inf r^2 dC = int_0^inf 2 r T(r) dr (T = R_d - C, from its own log representation:
    no cancellation), evaluated as int 2 r^2 T d(ln r) by composite 8-point Gauss-Legendre over ``panels`` panels of
    ln r from 1e-6 to max(rho_max, 60/k) + 60/k (k the exact far-field decay constant: the table's exponential tail
    beyond rho_max is integrated to e^-60). Converged to < 1e-6 relative with the default panels (checked against
    twice as many). Infinite where alpha' = 1 (sigma_a = 0).
    """
    tab = default_table() if table is None else table
    a = np.atleast_1d(_f64(alpha_prime))
    shape = a.shape
    a = a.ravel()
    out = np.full(a.shape, np.inf)
    ok = a < 1.0
    if not np.any(ok):
        return out.reshape(np.shape(alpha_prime))
    av = a[ok]
    if out_of_range == "clip":
        av = np.clip(av, *tab.alpha_prime_range)
    k = decay_constant(av)
    r_hi = np.maximum(tab.radius_range[1], 60.0 / k) + 60.0 / k
    lo = np.log(1e-6)
    edges = np.linspace(0.0, 1.0, panels + 1)
    # nodes in ln r: (n, panels * 8)
    t = ((edges[:-1, None] + edges[1:, None]) / 2 + (edges[1:, None] - edges[:-1, None]) / 2 * _GL8_X).ravel()
    w = np.broadcast_to(((edges[1:] - edges[:-1])[:, None] / 2) * _GL8_W, (panels, 8)).ravel()
    span = np.log(r_hi) - lo
    x = lo + t[None, :] * span[:, None]
    u = np.log(av) - np.log1p(-av)
    _, log_t, _, log_rd = tab._log_eval(np.exp(x), u[:, None], np.full((av.size, 1), float(eta)), out_of_range)
    integrand = 2.0 * np.exp(2.0 * x + log_t - log_rd)  # 2 r^2 T / R_d
    out[ok] = np.sum(integrand * w[None, :], axis=1) * span
    return out.reshape(shape)


def second_moment_mm2(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: float, *,
                      out_of_range: str = "raise") -> Array:
    """<r^2> [mm^2] of the table's normalized half-space profile at (sigma_s', sigma_a): G_mc(alpha') / sigma_t'^2
    (like :func:`estimation.dipole.second_moment_mm2`)."""
    ssp, sa = np.broadcast_arrays(_f64(sigma_s_prime_per_mm), _f64(sigma_a_per_mm))
    st = ssp + sa
    return second_moment_factor(ssp / st, eta, out_of_range=out_of_range) / (st * st)
