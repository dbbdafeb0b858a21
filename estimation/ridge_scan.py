"""The reference loop's start on the ridge of constant albedo: a coarse scan of cheap renders.

The single-image method sees a uniformly lit body mostly through its brightness, which the albedo alpha' =
sigma_s' / (sigma_s' + sigma_a) sets; the optical size (sigma_s' times the body's size) changes the image only
through the profile's length. Under a sky or a sun (all faces lit at once) the flat-profile fit is then determined
along a *ridge of constant albedo* only — its correlation of log sigma_s' and log sigma_a is ~+1 (measured on the
scene zoo: 0.90-1.00 on every sky- and sun-lit scene, -0.64-0.16 on the point-lit ones) — and where its model
is also outside its validity it lands anywhere on that ridge: a 5 mm skimmilk pyramid under a sky (l_d 18 mm)
at the search range's edge, 176x the true sigma_s' (docs/model-error.md sec. 4, "Is the information there?").
A reference loop started there spends its renders far away (70x the truth after six renders).

:func:`scan_ridge` asks the frame instead: Monte Carlo renders of the scene at sigma_s' = f sigma_s'_0 and
sigma_a = f sigma_a_0 (albedo held) for a geometric grid of f, all with the same seed (common random numbers: the
renders' noise is shared and cancels from the comparison), each compared with the observations in the loop's own
metric and robust objective (Huber on the residuals normalized by the stated noise, the render's and a relative
model error), sigma_a re-optimised at each f to first order by the render's score-function derivative d Q / d log
sigma_a from the same paths (:func:`profile_chi2`, step clipped to +-:data:`MAX_DELTA_LOG_SA`). The best point of
the grid starts the loop. This is a profile likelihood (Murphy and van der Vaart 2000, "On profile likelihood",
JASA 95(450)) sampled on a coarse grid; ``benchmarks/zoo/information.py`` evaluates the same profile finely
around the truth as a diagnostic, with :func:`profile_chi2` from here.

:func:`ridge_channels` says which channels need it: the plain fit's sigma_s' at or near its start range's edge. A
weak fit on the ridge (a correlation of the log parameters of at least :data:`RIDGE_CORRELATION`) alone is reported
but not scanned: measured on the scene zoo, the low-spp scan moved such starts on its renders' noise under a sun
and gained nothing under a sky, where those scenes are at the information limit (docs/model-error.md sec. 4).
"""
from __future__ import annotations

import time
from statistics import NormalDist
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from .reference_intervals import _huber_sum
from .single_image import SingleImageResult

__all__ = ["MAX_DELTA_LOG_SA", "RIDGE_CORRELATION", "EDGE_FACTOR", "SCAN_RATIO", "SCAN_STEPS", "SCAN_EXTEND",
           "LINE_STEP_LOG", "LINE_EXTEND", "LINE_SIGNIFICANCE", "LINE_CHECK_SEED_OFFSETS", "line_gain_threshold",
           "line_check_kwargs", "profile_chi2", "profile_objective", "objective_gradient", "paired_gain_sd",
           "ridge_channels", "scan_ridge", "on_the_ridge", "ridge_line_search"]

Array = NDArray[np.float64]

#: the first-order sigma_a refit is trusted within this log step (a factor 2); larger steps are clipped to it
MAX_DELTA_LOG_SA: float = 0.7
#: a weak plain fit whose corr(log sigma_s', log sigma_a) is at least this lies on the ridge of constant albedo
RIDGE_CORRELATION: float = 0.85
#: a plain sigma_a within this factor of the fit's floor (1e-7 /mm) holds no albedo: no ridge scan for it
SA_FLOOR_PER_MM, SA_FLOOR_FACTOR = 1e-7, 100.0
#: a plain sigma_s' within this factor of the start range's bounds (or beyond them) is "at the edge"
EDGE_FACTOR: float = 2.0
#: the scan's grid: f = SCAN_RATIO ** k for k in range(SCAN_STEPS[0], SCAN_STEPS[1] + 1) (a factor 1/81 to 9 of
#: the plain fit's sigma_s', clipped to the start range; duplicates after clipping are rendered once)
SCAN_RATIO: float = 3.0
SCAN_STEPS: tuple[int, int] = (-4, 2)
#: at most this many more grid points past an end of the grid while the best point lies on that end
SCAN_EXTEND: int = 2
#: the start moves to the best grid point only when its objective beats the plain fit's point (k = 0) by more than
#: this times sqrt(n) (n observations: the Huber objective of n unit residuals has a standard deviation ~sqrt(n / 2),
#: so this is ~1.4 of them; measured: a 13 mm skimmilk pyramid under a sun, whose plain R was -2.7 % off after the
#: loop, moved to a scan point with sigma_a 4x off and ended at +9.7 %)
SCAN_MIN_GAIN_PER_SQRT_N: float = 1.0
#: Huber threshold of the robust objective (that of the reference loop, :func:`reference_intervals._huber_sum`)
_HUBER_K = 2.5
#: :func:`ridge_line_search`: the grid's step in log sigma_s' (albedo held; e^0.12 = 1.13) and at most this many
#: more points past an end of the grid while the best point lies on it
LINE_STEP_LOG: float = 0.12
LINE_EXTEND: int = 3
#: the ridge line search's significance gate renders its candidate and the loop's point again with seed + each of
#: these (independent seeds: the loop's renders all use ``seed``), :func:`ridge_line_search`'s ``render_check``;
#: three: one check seed's gain has an sd ~ the gain itself on the zoo's sky boxes (z11: 17 +- 12; docs/model-error.md)
LINE_CHECK_SEED_OFFSETS: tuple[int, ...] = (7919, 15838, 23757)
#: :func:`ridge_line_search` moves off the loop's point only when the best point's gain in the objective exceeds
#: the one-sided normal quantile of this level, Bonferroni-split over the points compared with the loop's (the best
#: of n - 1 noisy candidates: Bonferroni 1936), times the gain's standard deviation from the renders' noise
LINE_SIGNIFICANCE: float = 0.05


def _points_theta(base: Array, todo: list[int | None], point: Callable[[int, int], Array | None]) -> Array:
    """(C, 2): channel c at ``point(c, k)`` where ``todo[c]`` = k is set, at ``base[c]`` elsewhere."""
    th = base.copy()
    for c, k in enumerate(todo):
        if k is not None:
            th[c] = point(c, k)
    return th


def _render_points(render: Callable[[Array], tuple[Array, Array, Array | None, float]], base: Array,
                   todo: list[int | None], point: Callable[[int, int], Array | None]
                   ) -> tuple[Array, Array, Array | None, float]:
    """One render at :func:`_points_theta`."""
    return render(_points_theta(base, todo, point))


def line_check_kwargs(render: Callable[[Array, int], tuple[Array, Array, Array | None, float]], reference: Any,
                      eta: float, seed: int) -> dict[str, Any]:
    """:func:`ridge_line_search`'s ``render_check`` (``render(theta, seed + o)`` for o in
    :data:`LINE_CHECK_SEED_OFFSETS`) and ``prefetch``: for a ``reference`` renderer (called as ``reference(sigma_s',
    sigma_a, eta, seed)`` by ``render``) with a ``prefetch`` method taking such calls (rig's Monte Carlo references:
    renders at once on a cluster), else None."""
    seeds = [seed + o for o in LINE_CHECK_SEED_OFFSETS]
    fetch = getattr(reference, "prefetch", None)
    return {"render_check": [lambda th, s=s: render(th, s) for s in seeds],
            "prefetch": None if fetch is None else lambda pts: fetch([(np.exp(th[:, 0]), np.exp(th[:, 1]), eta,
                                                                       seed if r < 0 else seeds[r]) for th, r in pts])}


def profile_chi2(r: Array, d: Array, w: Array, max_delta: float = MAX_DELTA_LOG_SA) -> tuple[float, float, float]:
    """(chi^2 at the render, chi^2 with sigma_a re-optimised to first order, that delta log sigma_a) for residuals
    ``r`` = observed - rendered, the render's derivative ``d`` = d Q / d log sigma_a and weights ``w`` (1-D,
    finite): the weighted least-squares step delta = sum(w r d) / sum(w d d), clipped to +-``max_delta``."""
    c0 = float(np.sum(w * r * r))
    dd = float(np.sum(w * d * d))
    rd = float(np.sum(w * r * d))
    delta = float(np.clip(rd / dd, -max_delta, max_delta)) if dd > 0 else 0.0
    return c0, float(np.sum(w * (r - delta * d) ** 2)), delta


def _profile_residuals(q: Array, dq: Array | None, obs: Array, metric: Array, c: int
                       ) -> tuple[Array, float] | None:
    """Channel ``c``'s normalized residuals z (m,; NaN where unusable) after the first-order sigma_a refit (Huber
    weights of the render's residuals) and that delta log sigma_a; None with fewer than 3 usable rows."""
    r = obs[:, c] - q[:, c]
    m = metric[:, c]
    d_c = dq[:, c, 1] if dq is not None else np.zeros(q.shape[0])
    ok = np.isfinite(r) & np.isfinite(m) & (m > 0) & np.isfinite(d_c)
    if ok.sum() < 3:
        return None
    az = np.abs(r[ok] / m[ok])
    huber_w = np.where(az > _HUBER_K, _HUBER_K / np.where(az > 0, az, 1.0), 1.0)
    _, _, dl = profile_chi2(r[ok], d_c[ok], huber_w / m[ok] ** 2)
    z = np.full(q.shape[0], np.nan)
    z[ok] = (r[ok] - dl * d_c[ok]) / m[ok]
    return z, dl


def profile_objective(q: Array, se: Array, dq: Array | None, obs: Array, metric: Array, c: int
                      ) -> tuple[float, float, float]:
    """Channel ``c``'s robust objective of a render ``q`` (m, C) against ``obs`` in the loop's ``metric`` (m, C),
    sigma_a re-optimised to first order by the render's d Q / d log sigma_a (``dq[..., 1]``; Huber weights of the
    render's residuals): (objective, delta log sigma_a, its standard deviation from the render's noise); (inf, 0, inf)
    with fewer than 3 usable rows.

    The standard deviation is the delta method's (e.g. Casella and Berger 2002, "Statistical Inference", sec. 5.5.4)
    over the render's independent pixels: d objective / d q_i = -psi(z_i) / m_i (psi the Huber derivative, z_i the
    normalized residual; the sigma_a refit adds nothing to first order, the objective being stationary in it), so
    var = sum (psi(z_i) se_i / m_i)^2 with ``se`` the render's per-pixel standard errors."""
    res = _profile_residuals(q, dq, obs, metric, c)
    if res is None:
        return np.inf, 0.0, np.inf
    z, dl = res
    ok = np.isfinite(z)
    se_c = np.where(np.isfinite(se[ok, c]), se[ok, c], 0.0)
    sd = float(np.sqrt(np.sum((np.clip(z[ok], -_HUBER_K, _HUBER_K) * se_c / metric[ok, c]) ** 2)))
    return float(_huber_sum(z[ok][:, None], _HUBER_K)[0]), dl, sd


def objective_gradient(q: Array, dq: Array | None, obs: Array, metric: Array, c: int) -> Array | None:
    """(m,) d objective / d q_i = -psi(z_i) / m_i of channel ``c`` at a render ``q`` (psi the Huber derivative, z the
    normalized residual after the first-order sigma_a refit of :func:`profile_objective`; NaN where unusable), None
    with fewer than 3 usable rows."""
    res = _profile_residuals(q, dq, obs, metric, c)
    return None if res is None else -np.clip(res[0], -_HUBER_K, _HUBER_K) / metric[:, c]


def paired_gain_sd(a0: tuple[Array, Array | None], ab: tuple[Array, Array | None], b0: Array, bb: Array,
                   obs: Array, metric: Array, c: int) -> float:
    """The standard deviation of one seed's gain J(0) - J(b), measured from two seeds' renders of both points:
    ``a0``, ``ab`` = (radiance (m, C), d radiance or None) of seed A at the loop's point and at point b, ``b0``,
    ``bb`` seed B's radiances there. To first order the gain's noise is sum_i g0_i e0_i - gb_i eb_i (g = -psi(z) / m
    the objective's derivative at seed A's renders, e a render's noise; the renders of one seed share their paths, so
    e0 and eb are correlated: common random numbers), and over independent pixels its variance is
    sum_i (u_i(A) - u_i(B))^2 / 2 with u_i = g0_i q0_i - gb_i qb_i: the correlation included, no standard error
    assumed. NaN with fewer than 3 usable rows."""
    g = [objective_gradient(q, dq, obs, metric, c) for q, dq in (a0, ab)]
    if any(x is None for x in g):
        return float("nan")
    du = g[0] * (a0[0][:, c] - b0[:, c]) - g[1] * (ab[0][:, c] - bb[:, c])
    du = du[np.isfinite(du)]
    return float(np.sqrt(np.sum(du * du) / 2.0)) if du.size >= 3 else float("nan")


def line_gain_threshold(n_compared: int, level: float = LINE_SIGNIFICANCE) -> float:
    """The gain, in standard deviations, a line-search point must beat the loop's point by: the one-sided normal
    quantile at ``level`` / ``n_compared`` (Bonferroni over the points compared with the loop's; 1.64 for one, 1.96
    for two, 2.13 for three, 2.33 for five)."""
    if n_compared < 1 or not 0.0 < level < 1.0:
        raise ValueError(f"line_gain_threshold: need n_compared >= 1 and 0 < level < 1, got {n_compared}, {level}")
    return float(NormalDist().inv_cdf(1.0 - level / n_compared))


def ridge_line_search(render: Callable[[Array], tuple[Array, Array, Array | None, float]], obs: Array,
                      metric: Callable[[Array, Array], Array], theta: Array, channels: NDArray[np.bool_],
                      step_log: float = LINE_STEP_LOG, extend: int = LINE_EXTEND,
                      render_check: Sequence[Callable[[Array], tuple[Array, Array, Array | None, float]]] = (),
                      prefetch: Callable[[list[tuple[Array, int]]], None] | None = None
                      ) -> tuple[Array, dict[str, Any]]:
    """The profile objective along the ridge of constant albedo through ``theta`` (C, 2), minimised on renders.

    Renders (one seed: common random numbers) at log sigma_s' = theta + k ``step_log``, log sigma_a shifted alike
    (albedo held), k = -1, 0, 1 and up to ``extend`` more past an end while the best point lies on it, each read by
    :func:`profile_objective` (sigma_a re-optimised); the minimum is the vertex of the parabola through the best point
    and its two neighbours, kept within one step of the best (the best itself where the three are not convex), its
    sigma_a the best point's refit. This asks the renders themselves, not the corrected model's Jacobian, where the
    likelihood is nearly flat: on the zoo's sky-lit boxes the loop's fixed point sat at +13 to +18 % (z02) while the
    renders' own objective is lowest within a few % of the truth (``benchmarks/zoo/information.py``'s patch column);
    a slope error along the ridge moves a fixed point far where the curvature there is small. ``render``, ``obs``,
    ``metric`` as for :func:`scan_ridge`, the metric evaluated once, on the first render (k = 0), and used for all.

    The significance gate (issue 15: on a 32-spp frame, z19, the search moved +0.3 % -> +12.5 % on a gain of 9.6 in
    a jagged, flat profile; docs/model-error.md, "A significance gate for the ridge line search"). A channel moves
    only where its best point b beats the loop's point (k = 0) significantly:

    - with ``render_check`` (the same renderer with other seeds, n of them): b is chosen on ``render``'s renders and
      tested on 2 n more, each check seed's at k = 0 and b (sample splitting, Cox 1975, Biometrika 62(2): the test's
      gain is not biased by the choice): the check seeds' mean gain must exceed :func:`line_gain_threshold` (1) =
      1.64 times its standard deviation, sqrt(mean var / n), each var measured from the search's and a check seed's
      renders (:func:`paired_gain_sd`, common random numbers included);
    - without: the search's own gain must exceed :func:`line_gain_threshold` (the number of other points compared)
      times sqrt(sd_0^2 + sd_b^2) (:func:`profile_objective`'s delta method; a bound for the renders' shared seed,
      whose positive correlation makes the true spread smaller: measured on z11 2-3x).

    Else it keeps ``theta``. ``prefetch`` (optional) is told, before each group of renders that do not depend on
    one another (the three first points; all the check renders), what they are: a list of (theta (C, 2), r), r = -1
    for ``render``, i for ``render_check[i]``, in the order they are then asked for; a renderer may render them at
    once (rig.estimate.batch: in parallel on a Dask cluster). Returns the new point (``theta`` where ``channels`` is
    False or the gate says no) and a record (per channel ``gain``, ``gain_check``, ``gain_sd``, ``gain_threshold_sd``,
    ``moved``).
    """
    n_ch = theta.shape[0]
    rec: list[dict[int, tuple[float, float, float]]] = [{} for _ in range(n_ch)]
    seconds: list[float] = []
    fixed: list[Array] = []  # one metric for every render: the first's (a render's own would favour brighter ones)
    kept: list[dict[int, tuple[Array, Array | None]]] = [{} for _ in range(n_ch)]  # (radiance, d) per point

    def pt(c: int, k: float) -> Array:
        return theta[c] + k * step_log

    def run(todo: list[int | None]) -> None:
        q, se, dq, sec = _render_points(render, theta, todo, pt)
        seconds.append(sec)
        if not fixed:
            fixed.append(metric(se, q))
        m = fixed[0]
        for c, k in enumerate(todo):
            if k is not None:
                rec[c][k] = profile_objective(q, se, dq, obs, m, c)
                kept[c][k] = (q, dq)

    first = [[k if channels[c] else None for c in range(n_ch)] for k in (0, -1, 1)]
    if prefetch is not None:
        prefetch([(_points_theta(theta, todo, pt), -1) for todo in first])
    for todo in first:
        run(todo)
    for _ in range(extend):
        todo: list[int | None] = [None] * n_ch
        for c in range(n_ch):
            if rec[c]:
                best = min(rec[c], key=lambda k: rec[c][k][0])
                if np.isfinite(rec[c][best][0]) and best in (min(rec[c]), max(rec[c])):
                    todo[c] = best - 1 if best == min(rec[c]) else best + 1
        if all(t is None for t in todo):
            break
        run(todo)
    out = theta.copy()
    vertex: list[float | None] = [None] * n_ch
    gain: list[float | None] = [None] * n_ch
    gain_check: list[float | None] = [None] * n_ch
    gain_sd: list[float | None] = [None] * n_ch
    z_gate: list[float | None] = [None] * n_ch
    moved = [False] * n_ch
    bests: list[int | None] = [None] * n_ch
    for c in range(n_ch):
        if rec[c] and 0 in rec[c]:
            best = min(rec[c], key=lambda k: rec[c][k][0])
            if np.isfinite(rec[c][best][0]) and best != 0:
                bests[c] = best
                gain[c] = float(rec[c][0][0] - rec[c][best][0])
    check_seconds: list[float] = []
    if render_check and any(b is not None for b in bests):  # the candidates tested on other seeds
        gains: list[list[float]] = [[] for _ in range(n_ch)]
        variances: list[list[float]] = [[] for _ in range(n_ch)]
        pair = ([0 if b is not None else None for b in bests], bests)
        if prefetch is not None:
            prefetch([(_points_theta(theta, todo, pt), i) for i in range(len(render_check)) for todo in pair])
        for render_other in render_check:
            checked = []
            for todo in pair:
                q, se, dq, sec = _render_points(render_other, theta, todo, pt)
                check_seconds.append(sec)
                checked.append((q, se, dq))
            for c, b in enumerate(bests):
                if b is not None:
                    gains[c].append(profile_objective(*checked[0], obs, fixed[0], c)[0]
                                    - profile_objective(*checked[1], obs, fixed[0], c)[0])
                    variances[c].append(paired_gain_sd(kept[c][0], kept[c][b], checked[0][0], checked[1][0], obs,
                                                       fixed[0], c) ** 2)
        for c, b in enumerate(bests):
            if b is not None:  # the check seeds' mean gain and its sd (independent seeds: sd / sqrt(n))
                gain_check[c] = float(np.mean(gains[c]))
                gain_sd[c] = float(np.sqrt(np.mean(variances[c]) / len(variances[c])))
                z_gate[c] = line_gain_threshold(1)
    for c in range(n_ch):
        best = bests[c]
        if best is None:
            continue
        if not render_check:
            gain_sd[c] = float(np.hypot(rec[c][0][2], rec[c][best][2]))
            z_gate[c] = line_gain_threshold(max(len(rec[c]) - 1, 1))
            significant = gain[c] > z_gate[c] * gain_sd[c]
        else:
            significant = gain[c] > 0 and gain_check[c] > z_gate[c] * gain_sd[c]
        if not significant:  # not clearly better than the loop's point: keep it
            continue
        moved[c] = True
        k_min = float(best)
        if best - 1 in rec[c] and best + 1 in rec[c]:
            y0, y1, y2 = rec[c][best - 1][0], rec[c][best][0], rec[c][best + 1][0]
            curv = y0 - 2.0 * y1 + y2
            if np.isfinite(curv) and curv > 0:
                k_min = best + float(np.clip(0.5 * (y0 - y2) / curv, -1.0, 1.0))
        vertex[c] = k_min
        out[c] = pt(c, k_min) + np.array([0.0, rec[c][best][1]])
    info = {"channels": channels.tolist(), "step_log": step_log, "renders": len(seconds), "render_seconds": seconds,
            "grid": [[{"k": k, "sigma_s_prime_per_mm": float(np.exp(pt(c, k)[0])),
                       "sigma_a_per_mm": float(np.exp(pt(c, k)[1])), "objective": rec[c][k][0],
                       "objective_sd": rec[c][k][2], "delta_log_sigma_a": rec[c][k][1]} for k in sorted(rec[c])]
                     for c in range(n_ch)],
            "gain": gain, "gain_check": gain_check, "gain_sd": gain_sd, "gain_threshold_sd": z_gate, "moved": moved,
            "gate": ("paired: the best point chosen on one seed, the mean gain on the check seeds > gain_threshold_sd x "
                     "gain_sd (measured from the seeds' renders)" if render_check else
                     "move only where gain > gain_threshold_sd x gain_sd (renders' noise, delta method)"),
            "check_render_seconds": check_seconds,
            "vertex_k": vertex, "sigma_s_prime_per_mm": np.exp(out[:, 0]).tolist(),
            "sigma_a_per_mm": np.exp(out[:, 1]).tolist()}
    return out, info


def on_the_ridge(result: SingleImageResult) -> tuple[NDArray[np.bool_], Array]:
    """(C,) a weak plain fit on the ridge of constant albedo — corr(log sigma_s', log sigma_a) >=
    :data:`RIDGE_CORRELATION`, sigma_a above its floor (an albedo of 1 is no ridge, :data:`SA_FLOOR_FACTOR`) — and
    the correlations (C,). Measured on the zoo: every sky- and sun-lit scene, and of the point-lit ones z04, z10, z12
    (0.92-1.00), which converge; the other point-lit ones -0.75-0.59."""
    ssp = np.atleast_1d(np.asarray(result.sigma_s_prime_per_mm, dtype=np.float64))
    n_ch = ssp.size
    corr = np.full(n_ch, np.nan)
    if result.correlation_log is not None:
        corr = np.broadcast_to(np.asarray(result.correlation_log, dtype=np.float64).reshape(-1), (n_ch,))
    status = (result.extra or {}).get("status") or {}
    weak = np.array([s != "ok" for s in status.get("sigma_s_prime_per_mm", ["ok"] * n_ch)], dtype=bool)
    ridge = weak & (np.nan_to_num(corr, nan=-1.0) >= RIDGE_CORRELATION)
    # sigma_a at its floor: the plain fit's albedo is 1, no ridge to hold (measured: a 5 x 20 x 40 mm ketchup box
    # under a sun, plain sigma_a 1e-7 /mm, the scan along alpha' = 1 kept sigma_a there and the loop ended at -60 %
    # instead of -24 %)
    sa = np.broadcast_to(np.atleast_1d(np.asarray(result.sigma_a_per_mm, dtype=np.float64)), (n_ch,))
    return ridge & ~(sa <= SA_FLOOR_FACTOR * SA_FLOOR_PER_MM), corr


def ridge_channels(result: SingleImageResult, ssp_range_per_mm: tuple[float, float]) -> tuple[NDArray[np.bool_],
                                                                                                list[str]]:
    """(C,) channels whose plain fit is no start for the reference loop — sigma_s' within :data:`EDGE_FACTOR` of
    ``ssp_range_per_mm``'s bounds or beyond them — and why ("" where it is); the reasons also name a weak sigma_s'
    (``extra["status"]``) on the ridge of constant albedo (corr(log sigma_s', log sigma_a) >=
    :data:`RIDGE_CORRELATION`, sigma_a above its floor: an albedo of 1 is no ridge, :data:`SA_FLOOR_FACTOR`), which
    alone does not start a scan (measured: see the comment at the return)."""
    ssp = np.atleast_1d(np.asarray(result.sigma_s_prime_per_mm, dtype=np.float64))
    n_ch = ssp.size
    lo, hi = ssp_range_per_mm
    edge = (ssp <= EDGE_FACTOR * lo) | (ssp >= hi / EDGE_FACTOR)
    ridge, corr = on_the_ridge(result)
    why = [("; ".join(x for x in (
        f"sigma_s' {ssp[c]:.3g} /mm at the edge of the start range {lo:g}-{hi:g} /mm" if edge[c] else "",
        f"sigma_s' weak on the ridge of constant albedo (corr(log sigma_s', log sigma_a) = {corr[c]:.3f})"
        if ridge[c] else "") if x)) for c in range(n_ch)]
    # only the edge starts a scan: on the ridge alone, measured on the zoo, the scan's low-spp renders moved the start
    # on their noise under a sun (a 5 mm marble pyramid at 8 spp: +9.9 % -> +175 %; a 13 mm skimmilk pyramid R:
    # -2.7 % -> +9.7 %) and gained nothing under a sky (z02, z11 at the information limit; z21 +-10 % either way);
    # the ridge reason is still reported
    return edge, why


def scan_ridge(render: Callable[[Array], tuple[Array, Array, Array | None, float]], obs: Array,
               metric: Callable[[Array, Array], Array], theta_start: Array, ssp_range_per_mm: tuple[float, float],
               channels: NDArray[np.bool_]) -> tuple[Array, dict[str, Any]]:
    """Scan the ridge of constant albedo through ``theta_start`` (C, 2: log sigma_s', log sigma_a per channel) on
    the grid f = :data:`SCAN_RATIO` ** k (module docstring), extended by up to :data:`SCAN_EXTEND` more points past
    an end of the grid where the best point lies on it; return the start (C, 2) — the best grid point with its
    first-order sigma_a refit where ``channels`` and it beats the plain point (k = 0) by more than
    :data:`SCAN_MIN_GAIN_PER_SQRT_N` sqrt(n) (``info["moved"]``), ``theta_start`` elsewhere — and a JSON-able
    record of the scan.

    ``render(theta) -> (radiance (m, C), stderr (m, C), d_radiance (m, C, 2) or None, seconds)`` over the observed
    rows, all with one seed; ``metric(stderr, radiance) -> (m, C)`` the standard deviation an observation is
    compared with a render by (the reference loop's); ``obs`` (m, C) NaN where not observed. Channels render
    independently, so each render carries every channel's own grid point (its start where it has none left)."""
    n_ch = theta_start.shape[0]
    lo, hi = np.log(ssp_range_per_mm[0]), np.log(ssp_range_per_mm[1])

    step = np.log(SCAN_RATIO)

    def point(c: int, k: int) -> Array | None:
        """Channel c's grid point k (albedo held); outside the range only the first point beyond each end, clipped
        onto it (unless an inner point lies there already), else None."""
        s0 = theta_start[c, 0]
        s = s0 + k * step
        if s < lo - 1e-9 or s > hi + 1e-9:
            inner = s0 + (k + (1 if s < lo else -1)) * step  # the neighbour towards the range
            if not lo - 1e-9 <= inner <= hi + 1e-9 or abs(inner - (lo if s < lo else hi)) < 1e-9:
                return None
        t = float(np.clip(s, lo, hi))
        return np.array([t, theta_start[c, 1] + (t - s0)])

    ks = [[k for k in range(SCAN_STEPS[0], SCAN_STEPS[1] + 1) if point(c, k) is not None] if channels[c] else []
          for c in range(n_ch)]
    rec: list[dict[int, tuple[float, float, float]]] = [{} for _ in range(n_ch)]  # k -> (objective, delta, sd)
    seconds: list[float] = []
    t0 = time.perf_counter()

    def run(todo: list[int | None]) -> None:
        q, se, dq, sec = _render_points(render, theta_start, todo, point)
        seconds.append(sec)
        m = metric(se, q)
        for c, k in enumerate(todo):
            if k is not None:
                rec[c][k] = profile_objective(q, se, dq, obs, m, c)

    for i in range(max((len(x) for x in ks), default=0)):
        run([ks[c][i] if i < len(ks[c]) else None for c in range(n_ch)])
    for _ in range(SCAN_EXTEND):  # the best point on an end of the grid: one more step past it
        todo: list[int | None] = [None] * n_ch
        for c in range(n_ch):
            if not rec[c]:
                continue
            best = min(rec[c], key=lambda k: rec[c][k][0])
            for nxt in (best - 1, best + 1):
                if (nxt < min(rec[c]) or nxt > max(rec[c])) and point(c, nxt) is not None \
                        and np.isfinite(rec[c][best][0]):
                    todo[c] = nxt
        if all(t is None for t in todo):
            break
        run(todo)
    start = theta_start.copy()
    best_k: list[int | None] = [None] * n_ch
    moved = np.zeros(n_ch, bool)
    n_obs = np.isfinite(obs).sum(axis=0)
    for c in range(n_ch):
        if rec[c]:
            k = min(rec[c], key=lambda k: rec[c][k][0])
            if not np.isfinite(rec[c][k][0]):
                continue
            best_k[c] = k
            # the start moves only where the frame clearly prefers another point than the plain fit's (k = 0)
            gain = rec[c][0][0] - rec[c][k][0] if 0 in rec[c] else np.inf
            if k != 0 and gain > SCAN_MIN_GAIN_PER_SQRT_N * np.sqrt(max(int(n_obs[c]), 1)):
                start[c] = point(c, k) + np.array([0.0, rec[c][k][1]])
                moved[c] = True
    info = {"channels": channels.tolist(), "renders": len(seconds), "render_seconds": seconds,
            "seconds": time.perf_counter() - t0, "ratio": SCAN_RATIO,
            "grid": [[{"k": k, "sigma_s_prime_per_mm": float(np.exp(point(c, k)[0])),
                       "sigma_a_per_mm": float(np.exp(point(c, k)[1])), "objective": rec[c][k][0],
                       "delta_log_sigma_a": rec[c][k][1]} for k in sorted(rec[c])] for c in range(n_ch)],
            "best_k": best_k, "moved": moved.tolist(), "start_sigma_s_prime_per_mm": np.exp(start[:, 0]).tolist(),
            "start_sigma_a_per_mm": np.exp(start[:, 1]).tolist()}
    return start, info
