"""The fitting core of estimation.single_image: the lockstep multistart Levenberg-Marquardt (``_lm_multistart``),
its exact 2-D box step (``_box_qp_2d``), ``_fit_channel`` against an independent sequential
``scipy.optimize.least_squares`` multistart, and the golden-section scan with its parabolic finish.

The synthetic problem has two basins in log sigma_s': a narrow global one (cost 0) between two points of
``_fit_channel``'s 21 x 21 start grid and a broad local one (cost ~0.077) on a grid point, so the best grid point
leads to the wrong minimum and only the other starts find the right one.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize

from estimation.dipole import profile_from_coefficients, dipole_coefficients
from estimation.single_image import (_LOG_SA_MAX, _LOG_SSP_BOUNDS, _box_qp_2d, _fit_channel, _golden_batch,
                                     _lm_multistart, _Problem)

SA_FLOOR = 1e-7
LB = np.array([_LOG_SSP_BOUNDS[0], np.log(SA_FLOOR)])
UB = np.array([_LOG_SSP_BOUNDS[1], _LOG_SA_MAX])
GRID_S = np.linspace(np.log(0.01), np.log(100.0), 21)  # _fit_channel's start grid in log sigma_s'
X_GLOBAL = GRID_S[14] + 0.23  # narrow global basin, between grid points
X_LOCAL = GRID_S[6]  # broad local basin, on a grid point


class _Counting:
    """vector_fn wrapper counting the parameter vectors evaluated."""

    def __init__(self, fn):
        self.fn, self.points = fn, 0

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        self.points += theta.shape[0]
        return self.fn(theta)


def _two_basin_problem(log_sa_target: float) -> tuple[_Problem, _Counting]:
    """Residuals (4, T) of (x, y) = (log sigma_s', log sigma_a): 4 (x - xg)(x - xl) has zeros in both basins,
    0.1 (x - xg) makes the narrow one global, y is pulled to ``log_sa_target`` (below the floor: optimum on it)
    with an x-coupling, and a weak cross term keeps J^T J full."""

    def fn(theta: np.ndarray) -> np.ndarray:
        x, y = theta[:, 0], theta[:, 1]
        return np.stack([4.0 * (x - X_GLOBAL) * (x - X_LOCAL), 0.1 * (x - X_GLOBAL),
                         (y - log_sa_target) + 0.2 * (x - X_GLOBAL) ** 2, 0.05 * (x - X_GLOBAL) * (y - log_sa_target)])

    counted = _Counting(fn)
    return _Problem(counted, None, np.zeros(4), 4, np.ones(4)), counted


def _sequential(problem: _Problem, starts: np.ndarray) -> list[optimize.OptimizeResult]:
    """One least_squares("trf") per start, the settings _fit_channel used before the lockstep multistart."""
    return [optimize.least_squares(lambda t: problem.resid(t[None, :])[:, 0], s, jac=problem.jacobian,
                                   bounds=(LB, UB), method="trf", x_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-12,
                                   max_nfev=400) for s in starts]


def _start_grid() -> np.ndarray:
    xs, ys = np.meshgrid(np.linspace(-4.0, 4.0, 9), np.linspace(-12.0, 2.0, 5), indexing="ij")
    return np.column_stack([xs.ravel(), ys.ravel()])


@pytest.mark.parametrize("log_sa_target", [-5.0, -20.0], ids=["interior", "on-floor"])
def test_fit_channel_matches_sequential_multistart(log_sa_target):
    problem, counted = _two_basin_problem(log_sa_target)
    seq = _sequential(problem, _start_grid())
    costs = np.array([r.cost for r in seq])
    best = seq[int(np.argmin(costs))]
    # the reference sees both basins, and the global one is the narrow one
    local = np.abs(np.array([r.x[0] for r in seq]) - X_LOCAL) < 0.1
    assert np.any(local) and np.min(costs[local]) > 0.05
    assert best.x[0] == pytest.approx(X_GLOBAL, abs=1e-6)
    y_opt = max(log_sa_target, LB[1])
    assert best.x[1] == pytest.approx(y_opt, abs=1e-6)

    counted.points = problem.nfev = 0
    for polish in (True, False):
        fit = _fit_channel(problem, SA_FLOOR, profile=False, polish=polish)
        assert fit.ok, fit.message
        assert fit.theta == pytest.approx(best.x, abs=1e-7)
        assert fit.ssr == pytest.approx(2.0 * best.cost, rel=1e-9, abs=1e-14)
        assert fit.theta[1] > LB[1]  # strictly inside the box, as TRF keeps it: sigma_a = exp(theta) >= its floor
        assert np.exp(fit.theta[1]) >= SA_FLOOR
        assert np.all(np.isfinite(fit.cov))
    assert fit.nfev == counted.points  # every evaluated parameter vector is counted, polish or not


def test_best_grid_point_alone_finds_the_local_basin():
    """Why the other starts matter: from the best grid point alone the multistart ends in the local basin."""
    problem, _ = _two_basin_problem(-5.0)
    ys = np.linspace(np.log(1e-6), np.log(10.0), 21)
    grid = np.array(np.meshgrid(GRID_S, ys, indexing="ij")).reshape(2, -1).T
    x0 = grid[int(np.argmin(problem.ssr(grid)))]
    assert x0[0] == pytest.approx(X_LOCAL)
    ms = _lm_multistart(problem, x0[None, :], LB, UB)
    assert ms.converged[0] and ms.x[0, 0] == pytest.approx(X_LOCAL, abs=1e-2) and ms.cost[0] > 0.05


@pytest.mark.parametrize("log_sa_target", [-5.0, -20.0], ids=["interior", "on-floor"])
def test_lockstep_starts_match_sequential_per_start(log_sa_target):
    """Each start deep in a basin ends where a sequential TRF from the same start ends (same minimum, same cost)."""
    problem, _ = _two_basin_problem(log_sa_target)
    starts = np.array([[X_GLOBAL - 0.1, -3.0], [X_GLOBAL + 0.1, -10.0], [X_LOCAL - 0.5, 0.0], [X_LOCAL + 0.5, -14.0],
                       [X_LOCAL, LB[1]]])
    n0 = problem.nfev
    ms = _lm_multistart(problem, starts, LB, UB)
    # one batched evaluation per iteration (3 damping variants x 5 stencil points per live start) plus the first
    assert problem.nfev - n0 <= 5 * len(starts) * (1 + 3 * ms.iterations)
    seq = _sequential(problem, starts)
    assert np.all(ms.converged)
    for i, ref in enumerate(seq):
        assert ms.x[i] == pytest.approx(ref.x, abs=1e-6), i
        assert ms.cost[i] == pytest.approx(ref.cost, rel=1e-9, abs=1e-14), i
        assert LB[1] <= ms.x[i, 1] <= UB[1]
    assert ms.jac[0] == pytest.approx(problem.jacobian(ms.x[0]), rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("sa_true, tail", [(0.01, 0.0), (1e-9, 0.02)], ids=["interior", "on-floor"])
def test_fit_channel_dipole_profile_matches_sequential(sa_true, tail):
    """A small dipole-profile fit (relative weights, 1 % noise): the same optimum as a sequential TRF multistart.
    With a tail heavier than any sigma_a > 0 allows (x (1 + 0.02 r/mm)) the optimum lies on the sigma_a floor."""
    radii = np.linspace(0.2, 6.0, 40)

    def fn(theta: np.ndarray) -> np.ndarray:
        co = dipole_coefficients(np.exp(theta[:, 0])[:, None], np.exp(theta[:, 1])[:, None], 1.3)
        return profile_from_coefficients(co, radii[None, :]).T

    noise = 1 + 0.01 * np.random.default_rng(3).standard_normal(radii.size)
    data = fn(np.log([[1.2, sa_true]]))[:, 0] * (1 + tail * radii) * noise
    problem = _Problem.weighted(fn, np.eye(radii.size), data, 1.0 / data)
    fit = _fit_channel(problem, SA_FLOOR, profile=True)
    seq = _sequential(problem, _start_grid())
    best = seq[int(np.argmin([r.cost for r in seq]))]
    assert fit.ok
    assert fit.theta == pytest.approx(best.x, abs=1e-6)
    assert fit.ssr == pytest.approx(2.0 * best.cost + problem.offset, rel=1e-9)
    if tail > 0:
        assert fit.theta[1] == pytest.approx(LB[1], abs=1e-6) and fit.one_sided and fit.sa_profile_ci[0] == 0.0
    else:
        assert not fit.one_sided and fit.sa_profile_ci[0] < np.exp(fit.theta[1]) < fit.sa_profile_ci[1]


def test_box_qp_2d_is_the_exact_box_minimizer():
    rng = np.random.default_rng(0)
    s = 300
    m = rng.standard_normal((s, 2, 2))
    a = m @ m.transpose(0, 2, 1) + rng.uniform(1e-6, 1.0, s)[:, None, None] * np.eye(2)
    a[::3] = np.eye(2) * rng.uniform(1e-8, 1.0, (s // 3, 1, 2))  # (diagonal, nearly singular ones)
    g = rng.standard_normal((s, 2)) * 10.0 ** rng.uniform(-3, 3, (s, 1))
    lo = -rng.uniform(0, 2, (s, 2)) * (rng.uniform(size=(s, 2)) > 0.2)  # (some bounds active at d = 0)
    hi = rng.uniform(0, 2, (s, 2)) * (rng.uniform(size=(s, 2)) > 0.2)
    d = _box_qp_2d(g, a, lo, hi)
    assert np.all(d >= lo) and np.all(d <= hi)

    def q(i: int, z: np.ndarray) -> float:
        return float(g[i] @ z + 0.5 * z @ a[i] @ z)

    for i in range(s):
        ref = optimize.minimize(lambda z: q(i, z), np.zeros(2), jac=lambda z: g[i] + a[i] @ z,
                                bounds=list(zip(lo[i], hi[i])), method="L-BFGS-B",
                                options=dict(ftol=1e-15, gtol=1e-12, maxiter=1000))
        assert q(i, d[i]) <= ref.fun + 1e-9 * max(abs(ref.fun), 1e-12), i


def test_golden_batch_with_parabolic_finish():
    """Smooth asymmetric minima inside the bracket: f within 1e-9 x curvature of the minimum (12 iterations + the
    parabola; 24 plain golden iterations leave up to (1e-4 / 2)^2 = 2.5e-9); a minimum beyond an end is that end
    exactly (plain golden section only approaches it geometrically)."""
    centre = np.array([-3.0, -0.7, 0.0, 0.4, 2.9, 6.0, -8.0])
    k = np.array([1.0, 50.0, 1e-3, 3.0, 1e4, 2.0, 0.5])

    def f(x: np.ndarray) -> np.ndarray:
        z = x - centre
        return k * (z**2 + 0.3 * z**3 + z**4) + 7.0

    lo, hi = np.full(centre.size, -4.0), np.full(centre.size, 4.0)
    x, fx = _golden_batch(f, lo, hi, iters=12)
    inside = (centre > lo) & (centre < hi)
    assert np.all(fx[inside] - 7.0 <= 1e-9 * k[inside])
    assert x[inside] == pytest.approx(centre[inside], abs=2e-4)
    edge = np.where(centre > hi, hi, lo)
    assert np.all(x[~inside] == edge[~inside]) and np.all(fx[~inside] == f(edge)[~inside])  # (the end itself)
    assert np.all(fx == f(x))


def test_golden_batch_concave_monotone_ends():
    """Concave and monotone on the bracket (the parabola has no vertex): the minimum is the end, found exactly."""
    sign = np.array([1.0, -1.0, 1.0, -1.0])
    k = np.array([1.0, 1.0, 1e3, 1e-3])

    def f(x: np.ndarray) -> np.ndarray:
        return 7.0 - k * (4.0 + sign * x) ** 2  # sign +1: decreasing towards hi; -1: towards lo

    lo, hi = np.full(4, -4.0), np.full(4, 4.0)
    x, fx = _golden_batch(f, lo, hi, iters=12)
    end = np.where(sign > 0, hi, lo)
    assert np.all(x == end) and np.all(fx == f(end))


def test_fit_channel_box_wholly_beyond_the_range_keeps_a_sliver_on_its_end():
    """A trust region wholly above sigma_s' = 1e3 /mm (or below sigma_a's floor) collapses onto the range's end and
    still fits there (was: least_squares "Each lower bound must be strictly less than each upper bound", which
    failed the reference loop on a 5 mm skimmilk pyramid)."""
    problem, _ = _two_basin_problem(-5.0)
    box = (np.array([UB[0] + 1.0, np.log(1e-3)]), np.array([UB[0] + 2.0, np.log(1e-2)]))
    fit = _fit_channel(problem, SA_FLOOR, profile=False, box=box)
    assert fit.ok, fit.message
    assert UB[0] - 2e-3 <= fit.theta[0] <= UB[0] + 1e-12
    box = (np.array([0.0, LB[1] - 3.0]), np.array([1.0, LB[1] - 2.0]))
    fit = _fit_channel(problem, SA_FLOOR, profile=False, box=box)
    assert fit.ok, fit.message
    assert LB[1] - 1e-12 <= fit.theta[1] <= LB[1] + 2e-3


def _quadratic_problem(x0: float, y0: float, sx: float, sy: float) -> _Problem:
    """Residuals (3, T) whose SSR is ((x - x0) / sx)^2 + ((y - y0) / sy)^2 + 0.25 (+ a coupling): the 95 % profile
    interval of y is y0 +- 1.96 sy exactly (known noise, s^2 = 1)."""

    def fn(theta: np.ndarray) -> np.ndarray:
        x, y = theta[:, 0], theta[:, 1]
        return np.stack([(x - x0) / sx + 0.5 * (y - y0) / sy, (y - y0) / sy, np.full_like(x, 0.5)])

    return _Problem(fn, None, np.zeros(3), 10, np.ones(3))


def test_warm_refit_profile_resolves_a_well_determined_sigma_a():
    """A refit near a known solution (``local``: box + hint; issue 19) finds the same minimum as the cold fit, and its
    sigma_a profile interval is the exact y0 +- 1.96 sy; the whole-range scan's 0.5-log grid cannot resolve an
    interval that narrow (linear interpolation between the estimate and its outside neighbour: far too narrow)."""
    x0, y0, sx, sy = np.log(0.8), np.log(0.16), 0.03, 0.02
    problem = _quadratic_problem(x0, y0, sx, sy)
    hint = np.array([x0 + 0.05, y0 - 0.04])
    box = (hint - 0.7, hint + 0.7)
    cold = _fit_channel(problem, SA_FLOOR, known_noise=True, box=box, start_hint=hint)
    warm = _fit_channel(problem, SA_FLOOR, known_noise=True, box=box, start_hint=hint, local=True)
    assert cold.ok and warm.ok, (cold.message, warm.message)
    assert warm.theta == pytest.approx(cold.theta, abs=1e-7)
    assert warm.theta == pytest.approx([x0, y0], abs=1e-7)
    exact = np.exp(y0 + np.array([-1.0, 1.0]) * 1.959963984540054 * sy)
    assert np.array(warm.sa_profile_ci) == pytest.approx(exact, rel=2e-3)
    lo, hi = cold.sa_profile_ci
    assert hi / lo < 1.0 + 0.5 * (exact[1] / exact[0] - 1.0)  # the coarse grid's artefact the local scan removes
    assert problem.nfev > 0


def test_warm_direct_refit_matches_the_cold_one():
    """fit_direct_channel with a box and a hint (the reference loop's refit) skips the first fit and reweights only
    while the weights move: the same estimate and intervals as the cold path (warm=False) on a noisy system."""
    from estimation.single_image.weights import fit_direct_channel

    rng = np.random.default_rng(19)
    m = 60
    matrix = rng.uniform(0.2, 1.0, (m, 2))

    def vector_fn(theta: np.ndarray) -> np.ndarray:
        return np.stack([np.exp(-theta[:, 0]), theta[:, 1] * np.exp(theta[:, 1])])

    truth = np.array([np.log(0.8), np.log(0.16)])
    clean = matrix @ vector_fn(truth[None, :])[:, 0]
    sigma = 0.01 * np.abs(clean)
    l = clean + sigma * rng.standard_normal(m)
    l[7] *= 3.0  # an outlier for the Huber weights
    hint = truth + np.array([0.03, -0.02])
    box = (hint - 0.7, hint + 0.7)
    kw = dict(sa_floor=SA_FLOOR, model_error=0.0, noise_floor=0.01, robust=True, profile=True, start_hint=hint,
              box=box)
    cold = fit_direct_channel(vector_fn, matrix, l, sigma, warm=False, **kw)
    warm = fit_direct_channel(vector_fn, matrix, l, sigma, **kw)
    assert cold.fit.ok and warm.fit.ok
    se = np.sqrt(np.diag(cold.fit.cov))
    assert np.all(np.abs(warm.fit.theta - cold.fit.theta) <= 1e-3 * se)
    assert warm.robust_weight[7] < 0.5 and cold.robust_weight[7] < 0.5
    assert warm.nfev_extra < cold.nfev_extra
