"""Generate the tabulated Monte Carlo reflectance profiles of the ``"mc-table"`` model (issue 8 item 3).

    python -m simulators.mc.tables --out estimation/data/mc_profiles.npz [--quick] [--threads 2]

For every node of a grid of reduced albedo alpha' x relative index eta, a normally incident pencil beam enters a
half-space (:func:`.profile.simulate_photons`, :class:`.shapes.HalfSpace`) of the dimensionless medium
sigma_t' = sigma_t = 1, alpha' = albedo, g = 0 (:func:`.media.optical_medium`): radii are in transport mean free
paths. Isotropic scattering with the reduced coefficients is used because the estimators are parametrized by
(sigma_s', sigma_a) only (the similarity relation sigma_s' = sigma_s (1 - g)): the table must be a function of
(alpha', eta), and g = 0 is the one phase function for which the reduced and the true coefficients coincide
(beyond ~1 transport mean free path the profile is insensitive to g at fixed sigma_s'; within it, a real
forward-scattering medium differs -- see docs/monte-carlo.md).

Each photon's exit weight is divided by the entry transmittance 1 - F_r(eta, normal) (the table is per unit power
entering the medium, like the dipoles) and tallied by its exit radius: C(rho_i) (photons exiting inside rho_i)
and T(rho_i) = R_d - C(rho_i) (outside), with exact standard errors from per-photon sums of squares (each photon
lands in exactly one bin). Where both relative standard errors are <= ``REL_SE_TRUST`` (2 %), y = ln(C/T) is
smoothed by a cubic smoothing spline in ln rho with sum(((y - y_s)/sigma_y)^2) = n/4 (the cumulative moves by
~0.4 sigma rms; the derivative, i.e. the profile R, loses its bin-to-bin noise; quarter-decade annulus integrals
still agree with the raw tallies at z rms 0.93). Where the relative standard error exceeds ``REL_SE_TRUST``:

- near the source (rho below rho_lo), C(rho) = C(rho_lo) M(rho)/M(rho_lo), M = c1 rho + c2 rho^2 (R = a/rho + b:
  single scattering makes R ~ 1/rho at the entry point) fitted to the MC cumulative on [rho_lo, 3 rho_lo];
- in the far tail (rho beyond rho_hi), T(rho) = T(rho_hi) (rho_hi/rho)^nu e^(-k (rho - rho_hi)), k the exact
  asymptotic decay constant of isotropic transport (estimation.mc_table.decay_constant; the far field of a source
  below the surface decays like e^(-k rho)/rho, nu -> 1) and nu fitted (weighted least squares) to the Monte Carlo
  tail on [rho_hi/2, rho_wide], rho_wide the last radius where its relative standard error is <= 25 %.

All nodes use the same seed: common random numbers, so the Monte Carlo errors of neighbouring albedo nodes are
strongly correlated and the interpolant is smooth in alpha'. Photon counts and streams depend only on the grid
and the seed, so the file is reproducible (bit-identical for the same software and seed; thread-count
independent). The file also records a leave-one-out interpolation check.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from drivers.atomic import atomic_write
from estimation.mc_table import TABLE_FORMAT, McProfileTable, decay_constant
from scipy.interpolate import UnivariateSpline

from .media import optical_medium
from .profile import simulate_photons
from .shapes import HalfSpace
from .walk import EXITED

__all__ = ["GridSpec", "FULL_GRID", "QUICK_GRID", "alpha_grid", "run_node", "process_node", "simulate_grid",
           "build_table", "generate", "leave_one_out", "main"]

REL_SE_TRUST = 0.02
FAR_FIT_REL_SE = 0.25
SMOOTHING = 0.25  # smoothing spline: sum ((y - y_smooth) / sigma_y)^2 = SMOOTHING * (number of radii)
NU_RANGE = (-1.0, 3.0)
SEED = 20240817


class GridSpec:
    """Grid of a table: alpha' uniform in logit between ``alpha_min`` and 1 - ``one_minus_alpha_max``; eta nodes;
    radii log-spaced ``per_decade`` from ``radius_min`` to ``radius_max`` (transport mean free paths)."""

    def __init__(self, n_alpha: int, alpha_min: float, one_minus_alpha_max: float, etas: list[float],
                 n_photons: int, radius_min: float = 1e-3, radius_max: float = 1e4, per_decade: int = 20,
                 rel_se_trust: float = REL_SE_TRUST, high_albedo_knee: float = 3e-4):
        self.n_alpha = int(n_alpha)
        self.alpha_min = float(alpha_min)
        self.one_minus_alpha_max = float(one_minus_alpha_max)
        self.etas = [float(e) for e in etas]
        self.n_photons = int(n_photons)
        self.radius_min = float(radius_min)
        self.radius_max = float(radius_max)
        self.per_decade = int(per_decade)
        self.rel_se_trust = float(rel_se_trust)
        self.high_albedo_knee = float(high_albedo_knee)

    def alphas(self) -> np.ndarray:
        return alpha_grid(self.n_alpha, self.alpha_min, self.one_minus_alpha_max)

    def photons(self, alpha: float) -> int:
        """Photons for a node: ``n_photons`` times clip(sqrt((1 - alpha')/0.01), 1, 8) (more at low albedo, where
        photons are cheap and the weights vary most) times min(1, sqrt((1 - alpha')/``high_albedo_knee``)) (fewer
        at the highest albedos, where a photon costs ~(1 - alpha')^(-1/2) collisions: constant cost per node
        there), rounded to a multiple of 1000. A smooth function of alpha': with common random numbers the
        photons of a node are a subset or superset of its neighbours'."""
        f = min(8.0, max(1.0, math.sqrt((1.0 - alpha) / 0.01)))
        f *= min(1.0, math.sqrt((1.0 - alpha) / self.high_albedo_knee))
        return int(round(self.n_photons * f / 1000.0)) * 1000

    def radii(self) -> np.ndarray:
        decades = math.log10(self.radius_max / self.radius_min)
        n = int(round(decades * self.per_decade)) + 1
        return self.radius_min * np.power(10.0, np.arange(n) / self.per_decade)

    def as_dict(self) -> dict[str, Any]:
        return dict(vars(self))


FULL_GRID = GridSpec(21, 0.01, 1e-5, [1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8], 250_000)
QUICK_GRID = GridSpec(6, 0.1, 1e-3, [1.0, 1.3, 1.6], 20_000, per_decade=10, rel_se_trust=0.05,
                      high_albedo_knee=1e-3)


def alpha_grid(n: int, alpha_min: float, one_minus_alpha_max: float) -> np.ndarray:
    """n reduced albedos uniform in u = logit(alpha') = ln(alpha'/(1 - alpha')) (dense near alpha' = 1)."""
    u = np.linspace(math.log(alpha_min / (1 - alpha_min)), math.log((1 - one_minus_alpha_max) / one_minus_alpha_max),
                    n)
    return 1.0 / (1.0 + np.exp(-u))


def run_node(alpha: float, eta: float, radius: np.ndarray, n_photons: int, seed: int) -> dict[str, Any]:
    """Monte Carlo tallies of one node: cumulative C and tail T at ``radius`` (per unit entering power), their
    standard errors, R_d and its standard error, counts and timing."""
    medium = optical_medium(alpha, eta=eta)
    nb = radius.size + 1  # bin 0: [0, r_0), bin i: [r_{i-1}, r_i), bin nb-1: beyond the last radius
    s1 = np.zeros(nb)
    s2 = np.zeros(nb)
    coll = 0
    trunc = 0
    t0 = time.perf_counter()
    spec = 0.0
    for ch in simulate_photons(HalfSpace(0.0), medium, n_photons, seed=seed, max_collisions=2_000_000_000):
        ex = (ch.status == EXITED) & (ch.direction[:, 2] > 0)
        w = ch.weight[ex] / (1.0 - ch.specular[ex])
        r = np.hypot(ch.position_mm[ex, 0], ch.position_mm[ex, 1])
        k = np.searchsorted(radius, r, side="right")
        s1 += np.bincount(k, weights=w, minlength=nb)
        s2 += np.bincount(k, weights=w * w, minlength=nb)
        coll += int(ch.collisions.sum())
        trunc += int(np.count_nonzero(ch.status == 2))
        spec = float(ch.specular[0])
    seconds = time.perf_counter() - t0
    N = float(n_photons)

    def mean_se(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = a / N
        var = np.maximum(b / N - m * m, 0.0) * N / (N - 1.0)
        return m, np.sqrt(var / N)

    c1, c2 = np.cumsum(s1)[:-1], np.cumsum(s2)[:-1]              # exits with r < radius[i]
    t1, t2 = np.cumsum(s1[::-1])[::-1][1:], np.cumsum(s2[::-1])[::-1][1:]  # exits with r >= radius[i]
    C, C_se = mean_se(c1, c2)
    T, T_se = mean_se(t1, t2)
    rd, rd_se = mean_se(np.array(s1.sum()), np.array(s2.sum()))
    return dict(alpha=alpha, eta=eta, C=C, C_se=C_se, T=T, T_se=T_se, R_d=float(rd), R_d_se=float(rd_se),
                n_photons=int(n_photons), seconds=seconds, mean_collisions=coll / N, truncated_fraction=trunc / N,
                specular=spec)


def _wls_line(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares line y = p0 + p1 x."""
    A = np.stack([np.ones_like(x), x], axis=1) * np.sqrt(w)[:, None]
    p, *_ = np.linalg.lstsq(A, y * np.sqrt(w), rcond=None)
    return float(p[0]), float(p[1])


def process_node(raw: dict[str, Any], radius: np.ndarray, rel_se_trust: float = REL_SE_TRUST, *,
                 smooth: bool = True) -> dict[str, Any]:
    """Smooth the Monte Carlo ln(C/T) where it is trusted (relative standard errors <= ``rel_se_trust``) and fill
    the other radii with the near-source and far-tail models of the module docstring; return ln C, ln T on every
    radius, the source of each value (0 Monte Carlo, 1 near model, 2 far model) and the model parameters."""
    C, T = raw["C"].copy(), raw["T"].copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_c = np.where(C > 0, raw["C_se"] / C, np.inf)
        rel_t = np.where(T > 0, raw["T_se"] / T, np.inf)
    ok_c = rel_c <= rel_se_trust
    ok_t = rel_t <= rel_se_trust
    # first radius from which C is trusted onwards, last radius up to which T is trusted
    bad_c = np.flatnonzero(~ok_c)
    i_lo = int(bad_c.max()) + 1 if bad_c.size else 0
    i_lo = min(i_lo, radius.size - 1)
    bad_t = np.flatnonzero(~ok_t)
    i_hi = int(bad_t.min()) - 1 if bad_t.size else radius.size - 1
    if i_hi - i_lo < 6:
        raise RuntimeError(f"node alpha'={raw['alpha']}, eta={raw['eta']}: too few trusted radii "
                           f"({i_lo}..{i_hi}); increase the photon count")
    rd = raw["R_d"]
    log_c = np.log(np.where(C > 0, C, 1.0))
    log_t = np.log(np.where(T > 0, T, 1.0))
    source = np.zeros(radius.size, dtype=np.int8)
    # ---- smoothing of y = ln(C/T) on the trusted range (removes the bin-to-bin noise of the derivative, R)
    sl = slice(i_lo, i_hi + 1)
    y_raw = log_c[sl] - log_t[sl]
    sig_y = np.hypot(rel_c[sl], rel_t[sl])
    smoothed = False
    if smooth and y_raw.size >= 8:
        sp = UnivariateSpline(np.log(radius[sl]), y_raw, w=1.0 / sig_y, k=3, s=SMOOTHING * y_raw.size)
        y_s = sp(np.log(radius[sl]))
        if np.all(np.diff(y_s) > 0) and np.all(np.isfinite(y_s)):
            log_c[sl] = math.log(rd) - np.logaddexp(0.0, -y_s)
            log_t[sl] = math.log(rd) - np.logaddexp(0.0, y_s)
            smoothed = True
    # ---- near source
    near = dict(c1=math.nan, c2=math.nan, radius=float(radius[i_lo]), kind="none")
    if i_lo > 0:
        r_lo = radius[i_lo]
        sel = np.arange(i_lo, radius.size)[radius[i_lo:] <= 3.0 * r_lo]
        A = np.stack([radius[sel], radius[sel] ** 2], axis=1) / raw["C_se"][sel, None]
        coef, *_ = np.linalg.lstsq(A, C[sel] / raw["C_se"][sel], rcond=None)
        c1, c2 = float(coef[0]), float(coef[1])
        m_lo = c1 * r_lo + c2 * r_lo ** 2
        if c1 > 0 and c1 + 2 * c2 * r_lo > 0 and m_lo > 0:
            rr = radius[:i_lo]
            log_c[:i_lo] = log_c[i_lo] + np.log(c1 * rr + c2 * rr ** 2) - math.log(m_lo)
            near.update(c1=c1, c2=c2, kind="c1 r + c2 r^2")
        else:  # power law with the local log-slope, clipped to [1, 2]
            p = float(np.clip(_wls_line(np.log(radius[sel]), log_c[sel], 1.0 / rel_c[sel] ** 2)[1], 1.0, 2.0))
            log_c[:i_lo] = log_c[i_lo] + p * (np.log(radius[:i_lo]) - math.log(r_lo))
            near.update(c1=p, kind="power law (c1 = exponent)")
        log_t[:i_lo] = math.log(rd) + np.log(-np.expm1(log_c[:i_lo] - math.log(rd)))
        source[:i_lo] = 1
    # ---- far tail: T = T(rho_hi) (rho_hi/rho)^nu e^(-k (rho - rho_hi)), nu fitted to the Monte Carlo on
    # [rho_hi/2, rho_wide] (rho_wide: last radius with relative standard error <= FAR_FIT_REL_SE)
    k = float(decay_constant(raw["alpha"]))
    r_hi = radius[i_hi]
    wide = np.flatnonzero(rel_t <= FAR_FIT_REL_SE)
    i_wide = int(wide.max()) if wide.size else i_hi
    sel = np.flatnonzero((radius >= 0.5 * r_hi) & (np.arange(radius.size) <= i_wide) & (rel_t <= FAR_FIT_REL_SE))
    x = np.log(radius[sel] / r_hi)
    yv = np.log(T[sel]) - log_t[i_hi] + k * (radius[sel] - r_hi)
    w = 1.0 / (rel_t[sel] ** 2 + 1e-4 ** 2)
    nu = float(np.clip(-np.sum(w * x * yv) / max(np.sum(w * x * x), 1e-300), NU_RANGE[0], NU_RANGE[1]))
    if i_hi < radius.size - 1:
        rr = radius[i_hi + 1:]
        log_t[i_hi + 1:] = log_t[i_hi] - nu * np.log(rr / r_hi) - k * (rr - r_hi)
        log_c[i_hi + 1:] = math.log(rd) + np.log(-np.expm1(log_t[i_hi + 1:] - math.log(rd)))
        source[i_hi + 1:] = 2
    y = log_c - log_t
    if np.any(np.diff(y) <= 0):
        j = int(np.flatnonzero(np.diff(y) <= 0)[0])
        raise RuntimeError(f"node alpha'={raw['alpha']}, eta={raw['eta']}: C not strictly increasing at radius "
                           f"{radius[j]:.4g} (empty bin in the trusted range?)")
    return dict(log_c=log_c, log_t=log_t, source=source, rel_se_c=np.where(source == 0, rel_c, np.nan),
                rel_se_t=np.where(source == 0, rel_t, np.nan), k=k, nu=nu, smoothed=smoothed,
                radius_lo=float(radius[i_lo]), radius_hi=float(r_hi), radius_fit=float(radius[i_wide]), near=near)


def leave_one_out(table_arrays: dict[str, np.ndarray], min_fraction: float = 1e-3) -> dict[str, Any]:
    """Leave-one-out interpolation check: drop one interior albedo node (resp. eta node), rebuild the table, and
    compare its C, T and R at the dropped node with the node's own values on the radii where the Monte Carlo is
    trusted and C, T >= ``min_fraction`` R_d (R where 2 pi rho^2 R >= min_fraction R_d). Relative errors; the
    spacing is doubled at the dropped node, so these bound the interpolation error at the table's own spacing
    (about 1/16 of it for a smooth function and cubic interpolation) plus the node's Monte Carlo noise."""
    a, e, r = table_arrays["alpha_prime"], table_arrays["eta"], table_arrays["radius"]
    lc, lt = table_arrays["log_cumulative"].astype(float), table_arrays["log_tail"].astype(float)
    src = table_arrays["source"]
    full = McProfileTable(a, e, r, lc, lt)
    out: dict[str, Any] = {}
    for axis, nodes in (("alpha_prime", a), ("eta", e)):
        worst = {"C": 0.0, "T": 0.0, "R": 0.0}
        where: dict[str, Any] = {}
        sq = {"C": [], "T": [], "R": []}
        if nodes.size < 5:
            out[axis] = None
            continue
        for i in range(1, nodes.size - 1):
            keep = np.arange(nodes.size) != i
            if axis == "alpha_prime":
                t = McProfileTable(a[keep], e, r, lc[keep], lt[keep])
                pts = [(i, j) for j in range(e.size)]
            else:
                t = McProfileTable(a, e[keep], r, lc[:, keep], lt[:, keep])
                pts = [(j, i) for j in range(a.size)]
            for (ia, ie) in pts:
                ssp, sa = a[ia], 1.0 - a[ia]
                m = src[ia, ie] == 0
                c_ref = np.exp(lc[ia, ie])
                t_ref = np.exp(lt[ia, ie])
                rd = c_ref[-1] + t_ref[-1]
                R_ref = full.profile(r, ssp, sa, e[ie])
                c_i = t.cumulative(r, ssp, sa, e[ie])
                t_i = t.tail_beyond_disk(r, ssp, sa, e[ie])
                R_i = t.profile(r, ssp, sa, e[ie])
                for name, ref, val, mask in (
                        ("C", c_ref, c_i, m & (c_ref >= min_fraction * rd)),
                        ("T", t_ref, t_i, m & (t_ref >= min_fraction * rd)),
                        ("R", R_ref, R_i, m & (2 * np.pi * r ** 2 * R_ref >= min_fraction * rd))):
                    if not np.any(mask):
                        continue
                    err = np.abs(val[mask] / ref[mask] - 1.0)
                    sq[name].append(err)
                    j = int(np.argmax(err))
                    if err[j] > worst[name]:
                        worst[name] = float(err[j])
                        where[name] = dict(alpha_prime=float(a[ia]), eta=float(e[ie]), radius=float(r[mask][j]))
        out[axis] = {name: dict(max=worst[name], rms=float(np.sqrt(np.mean(np.concatenate(sq[name]) ** 2))),
                                p95=float(np.percentile(np.concatenate(sq[name]), 95)), at=where.get(name))
                     for name in worst if sq[name]}
    return out


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version(), "numpy": np.__version__}
    for pkg in ("sssrig", "numba", "scipy"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:  # pragma: no cover
            out[pkg] = "unknown"
    return out


RAW_KEYS = ("C", "T", "C_se", "T_se", "R_d", "R_d_se", "n_photons", "seconds", "mean_collisions",
            "truncated_fraction", "specular")


def simulate_grid(grid: GridSpec, seed: int = SEED, *, log=print) -> dict[str, np.ndarray]:
    """Run the Monte Carlo for every node: the raw tallies (arrays over (alpha', eta[, radius]))."""
    alphas = grid.alphas()
    etas = np.asarray(grid.etas, float)
    radius = grid.radii()
    raw: dict[str, np.ndarray] = {}
    t_start = time.perf_counter()
    sim: dict[str, Any] = {"command": _command(), "started_utc": _utc_now(), "numba_threads": _numba_threads(),
                           "cpu_count": os.cpu_count(), "load_average_start": _loadavg(), "software": _versions()}
    for j, eta in enumerate(etas):
        for i, a in enumerate(alphas):
            node = run_node(float(a), float(eta), radius, grid.photons(float(a)), seed)
            for key in RAW_KEYS:
                v = np.asarray(node[key])
                if key not in raw:
                    raw[key] = np.zeros((alphas.size, etas.size) + v.shape, v.dtype)
                raw[key][i, j] = v
            log(f"eta {eta:.2f} alpha' {a:.8f}: R_d {node['R_d']:.5f} +- {node['R_d_se']:.5f}, "
                f"{node['n_photons']} photons, {node['mean_collisions']:.0f} collisions/photon, "
                f"{node['seconds']:.1f} s (total {time.perf_counter() - t_start:.0f} s)")
    sim.update(finished_utc=_utc_now(), load_average_end=_loadavg(),
               wall_seconds=round(time.perf_counter() - t_start, 1),
               photon_seconds_sum=round(float(raw["seconds"].sum()), 1))
    raw.update(alpha_prime=alphas, eta=etas, radius=radius, seed=np.array(seed, np.int64),
               wall_seconds=np.array(time.perf_counter() - t_start),
               grid_json=np.array(json.dumps(grid.as_dict())), simulation_json=np.array(json.dumps(sim)))
    return raw


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _command() -> str:
    return " ".join(["python -m simulators.mc.tables"] + sys.argv[1:])


def _loadavg() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover
        return None


def build_table(raw: dict[str, np.ndarray], grid: GridSpec, *, log=print) -> dict[str, np.ndarray]:
    """Process the raw tallies into the arrays of the table file (see docs/monte-carlo.md for the format)."""
    alphas, etas, radius = raw["alpha_prime"], raw["eta"], raw["radius"]
    na, ne, nr = alphas.size, etas.size, radius.size
    log_c = np.empty((na, ne, nr))
    log_t = np.empty((na, ne, nr))
    source = np.empty((na, ne, nr), np.int8)
    rel_c = np.empty((na, ne, nr))
    rel_t = np.empty((na, ne, nr))
    tail = np.empty((na, ne, 3))   # k, nu, last radius used in the fit of nu
    ranges = np.empty((na, ne, 2))  # radius_lo, radius_hi of the Monte Carlo data
    for j in range(ne):
        for i in range(na):
            node = {key: raw[key][i, j] for key in RAW_KEYS}
            node.update(alpha=float(alphas[i]), eta=float(etas[j]), R_d=float(node["R_d"]))
            p = process_node(node, radius, grid.rel_se_trust)
            log_c[i, j], log_t[i, j], source[i, j] = p["log_c"], p["log_t"], p["source"]
            rel_c[i, j], rel_t[i, j] = p["rel_se_c"], p["rel_se_t"]
            tail[i, j] = (p["k"], p["nu"], p["radius_fit"])
            ranges[i, j] = (p["radius_lo"], p["radius_hi"])
    secs = raw["seconds"]
    arrays: dict[str, np.ndarray] = {
        "format_version": np.array(TABLE_FORMAT),
        "alpha_prime": alphas,
        "eta": etas,
        "radius": radius,
        "log_cumulative": log_c.astype(np.float32),
        "log_tail": log_t.astype(np.float32),
        "cumulative_rel_stderr": rel_c.astype(np.float32),
        "tail_rel_stderr": rel_t.astype(np.float32),
        "source": source,
        "total_reflectance": raw["R_d"].astype(np.float64),
        "total_reflectance_stderr": raw["R_d_se"].astype(np.float64),
        "n_photons": raw["n_photons"].astype(np.int64),
        "seconds": secs.astype(np.float32),
        "mean_collisions": raw["mean_collisions"].astype(np.float32),
        "truncated_fraction": raw["truncated_fraction"].astype(np.float32),
        "tail_model": tail,
        "mc_radius_range": ranges,
        "seed": np.asarray(raw["seed"], np.int64),
    }
    meta = {
        "model": "mc-table",
        "description": "Radial diffuse reflectance of a semi-infinite medium under a normally incident pencil beam "
                       "(simulators.mc Monte Carlo), per unit power entering the medium; isotropic scattering "
                       "(g = 0) with sigma_t' = 1: radii in transport mean free paths 1/sigma_t'.",
        "quantities": {"log_cumulative": "ln C(rho), C = int_0^rho R 2 pi r dr",
                       "log_tail": "ln T(rho), T = R_d - C(rho)",
                       "source": "0 Monte Carlo tally, 1 near-source model, 2 far-tail model",
                       "tail_model": "k (exact decay constant), nu, last radius of the nu fit: beyond rho_hi "
                                     "T = T(rho_hi) (rho_hi/rho)^nu e^(-k (rho - rho_hi))",
                       "mc_radius_range": "radii (rho_lo, rho_hi) between which the values are Monte Carlo tallies"},
        "grid": grid.as_dict(),
        "alpha_interpolation": "cubic spline in logit(alpha')",
        "seed": int(np.asarray(raw["seed"])),
        "rel_se_trust": grid.rel_se_trust,
        "incidence": "normal, pencil beam at the origin",
        "phase_function": "isotropic (g = 0), reduced coefficients",
        "boundary": "smooth dielectric, unpolarized Fresnel (index-matched at eta = 1)",
        "generator": "python -m simulators.mc.tables",
    }
    sim = json.loads(str(raw["simulation_json"])) if "simulation_json" in raw else {}
    meta.update({
        "software": sim.get("software", _versions()),
        "command": sim.get("command", ""),
        "generated_utc": sim.get("finished_utc", _utc_now()),
        "generation_wall_seconds": round(float(np.asarray(raw["wall_seconds"])), 1),
        "photon_seconds_sum": round(float(secs.sum()), 1),
        "simulation": sim,
        "processing": {"command": _command(), "utc": _utc_now(), "software": _versions(),
                       "smoothing": SMOOTHING, "far_fit_rel_se": FAR_FIT_REL_SE},
    })
    arrays["metadata_json"] = np.array(json.dumps(meta))
    t_loo = time.perf_counter()
    meta["leave_one_out"] = leave_one_out(arrays)
    meta["leave_one_out_seconds"] = round(time.perf_counter() - t_loo, 1)
    arrays["metadata_json"] = np.array(json.dumps(meta))
    return arrays


def generate(grid: GridSpec, seed: int = SEED, *, log=print) -> dict[str, np.ndarray]:
    """Simulate and process: the arrays of the table file."""
    return build_table(simulate_grid(grid, seed, log=log), grid, log=log)


def _numba_threads() -> int:
    import numba

    return int(numba.get_num_threads())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m simulators.mc.tables", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="output .npz file")
    ap.add_argument("--quick", action="store_true", help="small grid and photon count (tests of the pipeline)")
    ap.add_argument("--photons", type=int, default=None, help="photons per node (default: the grid's)")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--threads", type=int, default=None, help="numba threads (results do not depend on it)")
    ap.add_argument("--save-raw", type=Path, default=None, help="also save the raw Monte Carlo tallies here")
    ap.add_argument("--from-raw", type=Path, default=None,
                    help="rebuild the table from saved raw tallies instead of simulating")
    args = ap.parse_args(argv)
    if args.threads:
        import numba

        numba.set_num_threads(args.threads)
    grid = QUICK_GRID if args.quick else FULL_GRID
    if args.photons:
        grid = GridSpec(grid.n_alpha, grid.alpha_min, grid.one_minus_alpha_max, grid.etas, args.photons,
                        grid.radius_min, grid.radius_max, grid.per_decade, grid.rel_se_trust,
                        grid.high_albedo_knee)
    say = lambda s: print(s, flush=True)  # noqa: E731
    if args.from_raw:
        with np.load(args.from_raw, allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
        g = json.loads(str(raw["grid_json"]))
        grid = GridSpec(**g)
    else:
        raw = simulate_grid(grid, args.seed, log=say)
        if args.save_raw:
            args.save_raw.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(args.save_raw, **raw)
    arrays = build_table(raw, grid, log=say)
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:      # a file object: np.savez would append ".npz" to a name
            np.savez_compressed(fh, **arrays)

    atomic_write(args.out, write)
    meta = json.loads(str(arrays["metadata_json"]))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KiB); Monte Carlo wall time "
          f"{meta['generation_wall_seconds']} s; leave-one-out: {json.dumps(meta['leave_one_out'])}", flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
