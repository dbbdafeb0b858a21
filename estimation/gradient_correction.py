"""Gradient (diffusion) estimates on known spheres corrected by a reference renderer (analysis by synthesis).

The grounded sphere estimator (:func:`estimation.diffusion.estimate_sphere`) pools two observables per channel
over the sphere — the median *apparent albedo* A of the gradient albedo map and the median *shortening*
S = v.n_true / (tau1/tau0) of the diffuse vectors — and inverts the pair exactly with the truncated half-space
Jensen dipole summed over the sphere at chord distances (:func:`~estimation.diffusion.sphere_albedo`,
:func:`~estimation.diffusion.sphere_shortening`, :func:`~estimation.diffusion.invert_sphere_scalar`). Real
transport in a convex body of the size of the diffusion length is not that model: measured on Monte Carlo frames
of a 10 mm sphere (``tests/simulators/test_mc_frames_gradients.py``), the albedo map is 1.16 x R_table (marble)
and 1.26-1.45 x (skin1) — a 6.5 % exit normalization times the *curvature gain* of a small convex body — and the
inversion reads that as a lower absorption: D is off by -11 to +8 % (marble, red/green albedo above the model's
maximum, i.e. censored at sigma_a = 0) and +23 / +99 / +188 % (skin1).

This module removes that bias on the *observables*, by analysis by synthesis as in
:mod:`estimation.model_correction` (Gkioulekas et al. 2013, "Inverse volume rendering with material
dictionaries", ACM TOG 32(6): Monte Carlo renderings in the role of the forward model). Per channel, with
x = (log sigma_s', log sigma_a) and u = (log A, log b), b = 1 - S the blur:

1. uncorrected estimate x_0 = F(u_obs), F the exact sphere inversion;
2. render the reference at x_i — the same capture (camera, LEDs, patterns, exposure) of the known sphere by full
   light transport, reduced by the same map computation and region summary as the observations — giving
   u_ref(x_i); the fast model gives u_fast(x_i) in closed form; the *defect* d_i = u_ref - u_fast = (log kappa_A,
   log kappa_B) is the scene's model bias (kappa_A = A_ref / A_fast, kappa_B = b_ref / b_fast);
3. iteration 1 is the plain defect correction x_1 = F(A_obs / kappa_A, 1 - b_obs / kappa_B) (nonlinear: it
   brings a censored albedo back into range). It converges only as fast as kappa is constant, and here it is not:
   measured with common random numbers, the reference's albedo responds ~2 x more to l' than the model's (the
   curvature gain grows with the diffusion length) and the blur contains a part that does not scale with l' at
   all (b_ref / b_fast = 1.5-2 marble, 2.5 / 5 / 8-16 skin1 R/G/B), so the plain iteration contracts by only
   0.2-0.9 per render. From iteration 2 on, the defect is therefore linearised, d(x) ~ d_i + K (x - x_i), with
   its 2 x 2 Jacobian K learnt from the renders by Broyden's rank-one secant update (Broyden 1965, Math. Comp. 19,
   577; start K = 0), and u_fast(x) + d_i + K (x - x_i) = u_obs is solved with the fast model's *exact*
   nonlinearity (damped Newton, steps clipped to ``max_step`` in log). A secant that makes J_fast + K nearly
   singular or flips its orientation is noise and is dropped (K = 0: plain defect correction for that channel).
   Steps that reverse sign are halved (floor 1/4), as in :mod:`estimation.model_correction`, and grow back.

If the observations are u_ref(x_true) the truth is a fixed point (the defect there makes the fast model exact).
Every render uses the same ``seed`` (common random numbers: the reference is one fixed realisation, a smooth
function of x, so secants are meaningful and the iteration converges to that realisation's fixed point). Stop
rule of :mod:`estimation.model_correction`: every parameter's last step is below ``rel_tol`` or below a quarter of
the half-width of its own interval (log), or ``max_iterations`` renders were made; the result is the last
solution x_{i+1} (not rendered again). With sample-count levels (issue 19) the loop may also end by the *D stop*
(:data:`D_STOP_MIN_FULL_RENDERS`): D is what the estimate reports, and a weakly absorbing channel's sigma_a can keep
moving by several per cent while D has settled; its intervals then carry the last steps as a systematic allowance.

Censoring: where A_obs exceeds the albedo of a non-absorbing sphere of the observed shortening (marble red and
green on Monte Carlo frames) the uncorrected inversion clips sigma_a to 0. The reference is then rendered at a
floor ``sigma_a_floor_rel`` x sigma_t' (a log iteration needs sigma_a > 0); dividing by kappa_A (> 1) brings the
corrected albedo back into range. A channel still censored after step 1, or whose later solution sits on that
floor (the corrected observables want sigma_a below it, as for a non-absorbing material such as Spectralon), is
reported censored: sigma_a 0, a one-sided interval, D from sigma_s' alone.

Intervals (95 %): the observed (A, b) intervals (the summary's order-statistic intervals of the medians: pixel
noise plus the summary's systematic allowances) and the reference's (the same intervals of the reference render:
its Monte Carlo error) are combined in quadrature on (log A, log b) and mapped through the inverse of the
corrected Jacobian J_fast + K at the result (linearised). They cover the observation's noise and the reference
realisation's error — not a wrong geometry, not the error of a poorly learnt K (where the blur carries little
information, as in skin1's blue channel, the interval is wide and itself uncertain).

The reference is any callable ``reference(sigma_s_prime_per_mm (C,), sigma_a_per_mm (C,), eta, seed) ->
SphereObservables``; ``rig.estimate.reference.mc_reference.GradientsMonteCarloReference`` builds one from the Monte Carlo capture
simulator (this package imports nothing else of ours).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .diffusion import DiffusionSummary, invert_sphere, sphere_albedo, sphere_shortening
from .single_image.validity import MAX_OK_INTERVAL_RATIO
from .sphere_scan import needs_scan, scan_start

#: with a reference of several sample-count levels: at most this many renders per level below the top
MAX_LOW_LEVEL_RENDERS: int = 2
#: Broyden's secant between two renders of different sample-count levels (different Monte Carlo realisations: the
#: difference of their defects carries the cheaper level's noise, not only the defect's slope)
SECANT_ACROSS_LEVELS: bool = True
#: with a reference of several sample-count levels: from this many full-level renders on, the loop also stops when
#: every usable channel's last step of D (log sigma_t') is at most D_STOP_STEP_FRACTION of the half-width of D's own
#: 95 % interval and that interval, widened by the step, is still "ok"-narrow (MAX_OK_INTERVAL_RATIO); the reported
#: intervals are then widened by the last step of each quantity (a systematic allowance for the distance still to
#: go). 0 disables (issue 19: D is what the estimate reports; sigma_a of a weakly absorbing channel can keep moving
#: by several per cent while D has settled)
D_STOP_MIN_FULL_RENDERS: int = 2
#: the D stop's bounds on D's last step: a fraction of the half-width of D's 95 % interval (log), and at most this
#: change in log D (with a contraction of 1/2 per render the distance still to go is about one more such step)
D_STOP_STEP_FRACTION: float = 0.5
D_STOP_MAX_LOG_STEP: float = 0.02

__all__ = ["SphereObservables", "SphereReference", "SphereReferenceStep", "SphereReferenceEstimate",
           "sphere_model_observables", "estimate_sphere_with_reference"]

Array = NDArray[np.float64]



@dataclass(frozen=True)
class SphereObservables:
    """Per-channel observables of the sphere inversion: median apparent albedo and median shortening (C,), with
    optional intervals (C, 2) of those medians (NaN or None: unknown)."""

    albedo: Array
    shortening: Array
    albedo_interval: Array | None = None
    shortening_interval: Array | None = None

    def __post_init__(self) -> None:
        a = np.atleast_1d(np.asarray(self.albedo, dtype=np.float64))
        s = np.atleast_1d(np.asarray(self.shortening, dtype=np.float64))
        if a.ndim != 1 or s.shape != a.shape:
            raise ValueError(f"albedo and shortening must both be (C,); got {np.shape(self.albedo)} and "
                             f"{np.shape(self.shortening)}")
        object.__setattr__(self, "albedo", a)
        object.__setattr__(self, "shortening", s)
        for name in ("albedo_interval", "shortening_interval"):
            v = getattr(self, name)
            if v is None:
                continue
            iv = np.asarray(v, dtype=np.float64)
            if iv.shape != (a.size, 2):
                raise ValueError(f"{name} must be ({a.size}, 2); got {iv.shape}")
            object.__setattr__(self, name, iv)

    @classmethod
    def from_summary(cls, summary: DiffusionSummary) -> "SphereObservables":
        """The pooled observables of :func:`estimation.diffusion.summarize` on a known sphere."""
        return cls(summary.value("albedo"), summary.value("shortening"), summary.params["albedo"].interval,
                   summary.params["shortening"].interval)

    @property
    def n_channels(self) -> int:
        return int(self.albedo.size)


class SphereReference(Protocol):
    """Observables of the capture of the known sphere under full light transport at the given parameters."""

    def __call__(self, sigma_s_prime_per_mm: Array, sigma_a_per_mm: Array, eta: float, seed: int
                 ) -> SphereObservables:
        ...


def sphere_model_observables(radius_mm: float, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                             eta: float, *, fdr: str = "fit") -> SphereObservables:
    """The fast model's observables: (C(2 rho), S) of the truncated half-space Jensen dipole on the sphere
    (:func:`estimation.diffusion.sphere_albedo`, :func:`~estimation.diffusion.sphere_shortening`) — exactly what
    :func:`~estimation.diffusion.invert_sphere_scalar` inverts."""
    return SphereObservables(np.atleast_1d(sphere_albedo(radius_mm, sigma_s_prime_per_mm, sigma_a_per_mm, eta,
                                                         fdr=fdr)),
                             np.atleast_1d(sphere_shortening(radius_mm, sigma_s_prime_per_mm, sigma_a_per_mm, eta,
                                                             fdr=fdr)))


@dataclass(frozen=True)
class SphereReferenceStep:
    """One iteration: the render point, the corrections found there and the refit."""

    iteration: int
    render_sigma_s_prime_per_mm: list[float]
    render_sigma_a_per_mm: list[float]
    kappa_albedo: list[float]
    kappa_blur: list[float]
    sigma_s_prime_per_mm: list[float]  # the refit p_i'
    sigma_a_per_mm: list[float]
    censored: list[bool]
    change: float  # max relative change |p_i' / p_i - 1| over parameters and channels
    render_seconds: float
    spp: int = 0      # the reference's sample count for this render where it states one (0: unknown)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class SphereReferenceEstimate:
    """Reference-corrected sphere estimate (per channel, (C,)); intervals (C, 2).

    ``uncorrected``: the plain inversion of the observations (what :func:`estimate_sphere` reports);
    ``kappa_albedo`` / ``kappa_blur``: the scene's model bias at the last render point (reference over fast
    model, > 1 = real transport brighter / more blurred than the truncated half-space dipole) with their
    relative standard errors (from the reference's intervals, ~95 % -> /1.96); ``corrected``: the observables
    the result inverts; ``steps``: every iteration; ``converged``: the stop rule was met.
    """

    sigma_s_prime_per_mm: Array
    sigma_a_per_mm: Array
    alpha_prime: Array
    l_prime_mm: Array
    D_mm: Array
    intervals: dict[str, Array]
    censored: NDArray[np.bool_]
    kappa_albedo: Array
    kappa_blur: Array
    kappa_albedo_rel_stderr: Array
    kappa_blur_rel_stderr: Array
    corrected: SphereObservables
    uncorrected: dict[str, Array]
    steps: list[SphereReferenceStep]
    converged: bool
    iterations: int
    seconds: float
    message: str
    provenance: dict[str, Any] = field(default_factory=dict)
    #: per channel: "ok" (met the stop rule, not censored, D's 95 % interval at most MAX_OK_INTERVAL_RATIO wide),
    #: "weak" (stopped by the render budget before meeting the stop rule, censored: a one-sided interval, or an
    #: interval wider than that: the capture holds little information on D) or "unknown" (no usable observables)
    status: list[str] = field(default_factory=list)
    #: per channel: the stop rule was met at the last render
    channel_converged: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: np.asarray(getattr(self, k)).tolist() for k in (
            "sigma_s_prime_per_mm", "sigma_a_per_mm", "alpha_prime", "l_prime_mm", "D_mm", "censored",
            "kappa_albedo", "kappa_blur", "kappa_albedo_rel_stderr", "kappa_blur_rel_stderr")}
        out["intervals"] = {k: v.tolist() for k, v in self.intervals.items()}
        out["uncorrected"] = {k: np.asarray(v).tolist() for k, v in self.uncorrected.items()}
        out.update(steps=[s.as_dict() for s in self.steps], converged=self.converged, iterations=self.iterations,
                   seconds=self.seconds, message=self.message, provenance=self.provenance, status=list(self.status),
                   channel_converged=np.asarray(self.channel_converged).tolist())
        return out


# --------------------------------------------------------------------------------------------------------------
def _invert(albedo: Array, shortening: Array, radius_mm: float, eta: float, fdr: str
            ) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Per-channel exact inversion -> (sigma_s', sigma_a, censored); NaN where the observables are unusable."""
    n = albedo.size
    ssp, sa, cens = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, bool)
    # all channels in one vectorized inversion (agrees with invert_sphere_scalar to < 1e-9 relative, ~10x faster)
    al, lp, ce = invert_sphere(np.asarray(albedo, dtype=np.float64).reshape(n),
                               np.asarray(shortening, dtype=np.float64).reshape(n), radius_mm, eta, fdr=fdr)
    good = np.isfinite(al) & np.isfinite(lp) & (lp > 0)
    ssp[good], sa[good], cens[good] = al[good] / lp[good], (1.0 - al[good]) / lp[good], ce[good]
    return ssp, sa, cens


def _half_widths_log(value: Array, interval: Array | None) -> tuple[Array, Array]:
    """(lower, upper) half-widths of log(value) from an interval (0 where unknown)."""
    if interval is None:
        z = np.zeros(value.shape)
        return z, z
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.log(value / interval[:, 0])
        hi = np.log(interval[:, 1] / value)
    return (np.where(np.isfinite(lo) & (lo > 0), lo, 0.0), np.where(np.isfinite(hi) & (hi > 0), hi, 0.0))


def _blur(obs: SphereObservables) -> tuple[Array, Array | None]:
    """b = 1 - S and its interval (C, 2) (the interval's ends swap)."""
    b = 1.0 - obs.shortening
    if obs.shortening_interval is None:
        return b, None
    return b, np.stack([1.0 - obs.shortening_interval[:, 1], 1.0 - obs.shortening_interval[:, 0]], axis=1)


def _check_observables(obs: Any, name: str, n_ch: int | None = None) -> SphereObservables:
    if isinstance(obs, DiffusionSummary):
        obs = SphereObservables.from_summary(obs)
    if not isinstance(obs, SphereObservables):
        raise ValueError(f"{name} must be a SphereObservables or a DiffusionSummary; got {type(obs).__name__}")
    if n_ch is not None and obs.n_channels != n_ch:
        raise ValueError(f"{name} has {obs.n_channels} channels; expected {n_ch}")
    return obs


def _log_obs(obs: SphereObservables) -> Array:
    """(C, 2) log albedo, log blur (NaN where not positive)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.stack([np.log(obs.albedo), np.log(1.0 - obs.shortening)], axis=1)
    return np.where(np.isfinite(u), u, np.nan)


def _obs_sigma(obs: SphereObservables) -> Array:
    """(C, 2) standard deviations of (log A, log b) from the ~95 % intervals (half-width / 1.96; 0 if none)."""
    b, b_int = _blur(obs)
    out = []
    for v, iv in ((obs.albedo, obs.albedo_interval), (b, b_int)):
        lo, hi = _half_widths_log(v, iv)
        out.append(0.5 * (lo + hi) / 1.96)
    return np.stack(out, axis=1)


def _fast_jacobian(x: Array, radius_mm: float, eta: float, fdr: str, h: float = 1e-4) -> Array:
    """(C, 2, 2) d(log A, log b) / d(log sigma_s', log sigma_a) of the fast model (central differences)."""
    J = np.empty((x.shape[0], 2, 2))
    for k in range(2):
        e = np.zeros_like(x)
        e[:, k] = h
        up = _log_obs(sphere_model_observables(radius_mm, *np.exp(x + e).T, eta, fdr=fdr))
        dn = _log_obs(sphere_model_observables(radius_mm, *np.exp(x - e).T, eta, fdr=fdr))
        J[:, :, k] = (up - dn) / (2.0 * h)
    return J


def estimate_sphere_with_reference(observed: SphereObservables | DiffusionSummary, reference: SphereReference,
                                   radius_mm: float, eta: float, *, seed: int = 1, max_iterations: int = 6,
                                   rel_tol: float = 0.01, max_step: float = 1.0, sigma_a_floor_rel: float = 1e-4,
                                   fdr: str = "fit", scan: bool = True) -> SphereReferenceEstimate:
    """Correct the sphere inversion of ``observed`` by ``reference`` renders until the parameters settle.

    ``observed``: the region observables of the captured sphere (:class:`SphereObservables`, or the
    :class:`~estimation.diffusion.DiffusionSummary` of :func:`~estimation.diffusion.estimate_sphere`, which
    carries them); ``reference``: ``(sigma_s' (C,), sigma_a (C,), eta, seed) -> SphereObservables`` computed from
    a render of the same capture exactly as ``observed`` was (same maps, same region), called at most
    ``max_iterations`` times at its full sample count, always with ``seed`` (a reference with sample-count levels,
    ``n_levels`` / ``set_level(i)`` / ``current_spp``, is first called at its cheapest level: the loop stops there
    only when the stop rule holds and every usable channel's D interval is narrow enough to be "ok", else moves up
    after a settled step or :data:`MAX_LOW_LEVEL_RENDERS` renders; from :data:`D_STOP_MIN_FULL_RENDERS` full renders on
    it also stops when D's last step is well inside D's interval, widening the intervals by the last steps; issue 19);
    ``radius_mm``, ``eta``: the known sphere; ``rel_tol`` and
    the stop rule: module docstring; ``max_step``: largest change of log sigma_s' or log sigma_a in one
    quasi-Newton step (a trust region; the first, defect-correction step is not limited);
    ``sigma_a_floor_rel``: render points keep sigma_a >= this fraction of sigma_t' (censored starts); ``fdr``:
    the dipole's boundary term (as in :func:`~estimation.diffusion.summarize`); ``scan``: start channels whose
    observed shortening is outside the dipole's range (a lens-like sphere) from a coarse scan of 9 renders
    (:mod:`estimation.sphere_scan`; they do not count against ``max_iterations``). Channels whose observables are not
    usable are NaN. Raises ``ValueError`` naming the argument for bad input, and naming ``reference`` when it
    returns no usable observables.
    """
    t_all = time.perf_counter()
    obs = _check_observables(observed, "observed")
    n_ch = obs.n_channels
    rho = float(radius_mm)
    if not (np.isfinite(rho) and rho > 0):
        raise ValueError(f"radius_mm must be a finite number > 0; got {radius_mm!r}")
    eta_f = float(eta)
    if not (np.isfinite(eta_f) and eta_f > 0):
        raise ValueError(f"eta must be a finite number > 0; got {eta!r}")
    if max_iterations < 1:
        raise ValueError("max_iterations must be >= 1")
    if not rel_tol > 0:
        raise ValueError("rel_tol must be > 0")
    if not max_step > 0:
        raise ValueError("max_step must be > 0")
    if not 0 < sigma_a_floor_rel < 1:
        raise ValueError("sigma_a_floor_rel must be in (0, 1)")
    u_obs = _log_obs(obs)
    sd_obs = _obs_sigma(obs)
    usable = np.all(np.isfinite(u_obs), axis=1)
    if not usable.any():
        raise ValueError("observed has no channel with a finite albedo > 0 and a shortening < 1")

    ssp0, sa0, cens0 = _invert(obs.albedo, obs.shortening, rho, eta_f, fdr)
    uncorrected = {"sigma_s_prime_per_mm": ssp0, "sigma_a_per_mm": sa0, "D_mm": 1.0 / (3.0 * (ssp0 + sa0)),
                   "censored": cens0}
    ok = usable & np.isfinite(ssp0) & np.isfinite(sa0) & (ssp0 > 0)
    if not ok.any():
        raise ValueError("observed: the sphere inversion gives no finite sigma_s' > 0 in any channel")

    def floored(ssp: Array, sa: Array) -> Array:
        """log render point (C, 2): unusable channels at a stand-in (their correction is not used), sigma_a
        floored at sigma_a_floor_rel * sigma_t' so that a censored channel has a finite log."""
        ssp_r = np.where(ok & np.isfinite(ssp), ssp, np.median(ssp0[ok]))
        sa_r = np.where(ok & np.isfinite(sa), sa, np.median(sa0[ok]))
        return np.log(np.stack([ssp_r, np.maximum(sa_r, sigma_a_floor_rel * (ssp_r + sa_r))], axis=1))

    x = floored(ssp0, sa0)
    scanned = needs_scan(obs.shortening, usable) if scan else np.zeros(n_ch, dtype=bool)
    scan_res = None
    if scanned.any():
        def render_at(xr: Array) -> tuple[Array, Array]:
            pr = np.exp(xr)
            r = _check_observables(reference(pr[:, 0].copy(), pr[:, 1].copy(), eta_f, int(seed)), "reference result",
                                   n_ch)
            return _log_obs(r), _obs_sigma(r)
        scan_res = scan_start(u_obs, sd_obs, render_at, x, scanned, rho)
        x = np.where(scanned[:, None], scan_res.x_start, x)
        ok = ok | (scanned & np.all(np.isfinite(scan_res.x_start), axis=1))
    x_prev = d_prev = K = last_step = None
    B = np.zeros((n_ch, 2, 2))
    relax = np.ones((n_ch, 2))
    steps: list[SphereReferenceStep] = []
    converged = False
    x_new = x
    sd_ref = np.zeros((n_ch, 2))
    kA = kB = np.full(n_ch, np.nan)
    cens = cens0.copy()
    conv_c = np.zeros(n_ch, dtype=bool)
    # adaptive sample counts (issue 19; a reference with n_levels / set_level, e.g.
    # rig.estimate.reference.mc_reference.GradientsMonteCarloReference with spp_levels): start at the cheapest level;
    # stop there only when the stop rule holds with every usable channel's D interval narrow enough to be "ok" (the
    # reference's noise is inside it), else move up once the steps settle within that level's error or after
    # MAX_LOW_LEVEL_RENDERS renders; only top-level renders count towards max_iterations
    n_levels = max(1, int(getattr(reference, "n_levels", 1)))
    level = 0
    if n_levels > 1:
        reference.set_level(0)
    low_renders = full_renders = 0
    it = 0
    d_stop = False
    last_logs = np.zeros((n_ch, 3))   # the last step of (log sigma_s', log sigma_a, log D), for the D stop's widening
    level_prev = level
    while full_renders < max_iterations:
        it += 1
        lev_now = level
        at_top = level == n_levels - 1
        if at_top:
            full_renders += 1
        else:
            low_renders += 1
        p = np.exp(x)
        spp_now = int(getattr(reference, "current_spp", 0) or 0)
        t_r = time.perf_counter()
        ref = _check_observables(reference(p[:, 0].copy(), p[:, 1].copy(), eta_f, int(seed)), "reference result",
                                 n_ch)
        render_s = time.perf_counter() - t_r
        u_ref = _log_obs(ref)
        sd_ref = _obs_sigma(ref)
        fast = sphere_model_observables(rho, p[:, 0], p[:, 1], eta_f, fdr=fdr)
        u_fast = _log_obs(fast)
        use = ok & np.all(np.isfinite(u_ref), axis=1) & np.all(np.isfinite(u_fast), axis=1)
        if not use.any():
            raise ValueError(f"reference returned no usable observables (albedo > 0, shortening < 1) at iteration "
                             f"{it} (sigma_s' {p[:, 0].tolist()}, sigma_a {p[:, 1].tolist()})")
        kA = np.where(use, np.exp(u_ref[:, 0] - u_fast[:, 0]), np.nan)
        kB = np.where(use, np.exp(u_ref[:, 1] - u_fast[:, 1]), np.nan)
        d = np.where(use[:, None], u_ref - u_fast, 0.0)  # the defect log kappa
        if K is None:
            # iteration 1, plain defect correction (nonlinear): invert the observations divided by kappa, which
            # also brings a censored albedo back into the model's range
            K = np.zeros((n_ch, 2, 2))
            A_c = obs.albedo / np.where(use, kA, 1.0)
            b_c = (1.0 - obs.shortening) / np.where(use, kB, 1.0)
            ssp_n, sa_n, cens = _invert(A_c, 1.0 - b_c, rho, eta_f, fdr)
            fin = use & np.isfinite(ssp_n) & (ssp_n > 0)
            x_new = np.where(fin[:, None], floored(ssp_n, sa_n), x)
            if scan_res is not None:
                # scanned channels: the dipole cannot invert their observables; solve with the defect's Jacobian
                # taken from the scan's renders (K = J_ref - J_fast) instead
                jr = scanned & use & np.all(np.isfinite(scan_res.J_ref), axis=(1, 2))
                K = np.where(jr[:, None, None], np.nan_to_num(scan_res.J_ref) - _fast_jacobian(x, rho, eta_f, fdr),
                             0.0)
                x_s = _solve_corrected(u_obs, d, K, x, rho, eta_f, fdr, max_step, sigma_a_floor_rel, jr)
                x_new = np.where(jr[:, None], x_s, x_new)
                p_s = np.exp(x_s)
                cens = np.where(jr, p_s[:, 1] <= sigma_a_floor_rel * (p_s[:, 0] + p_s[:, 1]) * (1.0 + 1e-6), cens)
        else:
            # the defect's Jacobian K by Broyden's rank-one secant update from the last two renders (common random
            # numbers make the defect a deterministic, smooth function of x); then solve
            # u_fast(x) + d_i + K (x - x_i) = u_obs with the fast model's exact nonlinearity
            dx, dd = x - x_prev, d - d_prev
            nrm = np.einsum("ck,ck->c", dx, dx)
            upd = use & (nrm > 1e-8) & (SECANT_ACROSS_LEVELS or level_prev == lev_now)
            corr = (dd - np.einsum("cij,cj->ci", K, dx)) / np.where(upd, nrm, 1.0)[:, None]
            K = K + np.where(upd[:, None, None], corr[:, :, None] * dx[:, None, :], 0.0)
            # a secant that flips the orientation of the map or makes it nearly singular is Monte Carlo noise,
            # not the defect's slope: drop it (plain defect correction for that channel)
            det_f = np.linalg.det(_fast_jacobian(x, rho, eta_f, fdr))
            ratio = np.linalg.det(_fast_jacobian(x, rho, eta_f, fdr) + K) / det_f
            K = np.where((~(ratio > 0.1))[:, None, None], 0.0, K)
            x_new = _solve_corrected(u_obs, d, K, x, rho, eta_f, fdr, max_step, sigma_a_floor_rel, use)
            # relaxation as in estimation.model_correction: halve a parameter's step (floor 1/4) whenever it
            # reverses the sign of the previous one; double it back (up to 1) when it does not
            if last_step is not None:
                rev = np.sign(x_new - x) * np.sign(last_step) < 0
                relax = np.where(rev, np.maximum(relax * 0.5, 0.25), np.minimum(relax * 2.0, 1.0))
            x_new = x + relax * (x_new - x)
            # a solution on the sigma_a floor (the solve wants sigma_a below it) is censored at 0, as in step 1
            p_n = np.exp(x_new)
            cens = p_n[:, 1] <= sigma_a_floor_rel * (p_n[:, 0] + p_n[:, 1]) * (1.0 + 1e-6)
        B = _fast_jacobian(x_new, rho, eta_f, fdr) + K
        step = np.where(use[:, None], x_new - x, 0.0)
        if it > 1:
            last_step = step  # the defect-correction step of iteration 1 is not compared (it jumps far)
        ci = _log_intervals(x_new, B, np.hypot(sd_obs, sd_ref))
        p_new = np.exp(x_new)
        change = float(np.expm1(np.max(np.abs(step[use]), initial=0.0)))
        steps.append(SphereReferenceStep(it, p[:, 0].tolist(), p[:, 1].tolist(), kA.tolist(), kB.tolist(),
                                         np.where(ok, p_new[:, 0], np.nan).tolist(),
                                         np.where(ok, np.where(cens, 0.0, p_new[:, 1]), np.nan).tolist(),
                                         cens.tolist(), change, render_s, spp_now))
        tol = np.maximum(np.log1p(rel_tol), 0.25 * ci)
        tol[:, 1] = np.where(cens, np.inf, tol[:, 1])
        conv_c = use & np.all(np.abs(step) <= tol, axis=1)
        settled = bool(np.all(np.abs(step[use]) <= tol[use]))
        if settled and not at_top:
            # a cheap level ends the loop only where its D interval is already narrow enough to be "ok"
            st_n = np.exp(x_new).sum(axis=1)
            w_n = np.exp(x_new) / st_n[:, None]
            sd_n = np.sqrt(np.einsum("ci,cij,cj->c", w_n, _log_cov(B, np.hypot(sd_obs, sd_ref)), w_n))
            settled = bool(np.all(np.exp(2 * 1.96 * sd_n[use]) <= MAX_OK_INTERVAL_RATIO))
        if (not settled and at_top and n_levels > 1 and D_STOP_MIN_FULL_RENDERS > 0
                and full_renders >= D_STOP_MIN_FULL_RENDERS):
            # the D stop (issue 19): D's step well inside D's interval, the interval widened by it still "ok"
            st_o, st_n = np.exp(x).sum(axis=1), np.exp(x_new).sum(axis=1)
            w_n = np.exp(x_new) / st_n[:, None]
            half_d = 1.96 * np.sqrt(np.einsum("ci,cij,cj->c", w_n, _log_cov(B, np.hypot(sd_obs, sd_ref)), w_n))
            step_d = np.abs(np.log(st_n / st_o))
            d_ok = ((~cens) & (step_d <= np.minimum(D_STOP_STEP_FRACTION * half_d, D_STOP_MAX_LOG_STEP))
                    & (np.exp(2.0 * (half_d + step_d)) <= MAX_OK_INTERVAL_RATIO))
            if bool(np.all(d_ok[use])):
                settled = d_stop = True
                conv_c = use.copy()
                last_logs = np.where(use[:, None], np.abs(np.column_stack([step[:, 0], step[:, 1], step_d])), 0.0)
        if settled:
            converged = True
            break
        if not at_top and (bool(np.all(np.abs(step[use]) <= tol[use])) or low_renders >= MAX_LOW_LEVEL_RENDERS):
            level += 1
            low_renders = 0
            reference.set_level(level)
        x_prev, d_prev, x = x, d, x_new
        level_prev = lev_now
    p_new = np.exp(x_new)
    ssp_f = np.where(ok, p_new[:, 0], np.nan)
    sa_f = np.where(ok, np.where(cens, 0.0, p_new[:, 1]), np.nan)
    ci = _log_intervals(x_new, B, np.hypot(sd_obs, sd_ref))
    st = ssp_f + sa_f
    w = np.stack([ssp_f, sa_f], axis=1) / st[:, None]  # d log sigma_t' / d (log sigma_s', log sigma_a)
    cov = _log_cov(B, np.hypot(sd_obs, sd_ref))
    sd_lst = np.sqrt(np.einsum("ci,cij,cj->c", w, cov, w))
    z = 1.96
    with np.errstate(over="ignore", invalid="ignore"):   # an unbounded log half-width is an infinite end
        intervals = {"sigma_s_prime_per_mm": ssp_f[:, None] * np.exp(np.stack([-ci[:, 0], ci[:, 0]], axis=1)),
                     "sigma_a_per_mm": np.where(cens[:, None], np.stack([np.zeros(n_ch), sa_f * np.exp(ci[:, 1])],
                                                                        axis=1),
                                                sa_f[:, None] * np.exp(np.stack([-ci[:, 1], ci[:, 1]], axis=1))),
                     "D_mm": (1.0 / (3.0 * st))[:, None] * np.exp(np.stack([-z * sd_lst, z * sd_lst], axis=1))}
    if not converged:
        intervals = _widen_unconverged(intervals, steps, conv_c)
    elif d_stop:
        intervals = _widen_by(intervals, last_logs)
    with np.errstate(divide="ignore", invalid="ignore"):
        # as the single-image loop's stop rule: wider than the bound means weak information on D, whatever the
        # iteration did (measured: skimmilk red on the 5 mm acceptance sphere, -10.3 % in [0.27, 0.67] mm, said "ok")
        wide = ~(intervals["D_mm"][:, 1] / intervals["D_mm"][:, 0] <= MAX_OK_INTERVAL_RATIO)
    status = ["unknown" if not (ok[c] and np.isfinite(st[c])) else
              "weak" if (cens[c] or not conv_c[c] or wide[c]) else "ok" for c in range(n_ch)]
    alpha = ssp_f / st
    kA_se = np.where(np.isfinite(kA), sd_ref[:, 0], np.nan)
    kB_se = np.where(np.isfinite(kB), sd_ref[:, 1], np.nan)
    u_c = u_obs - np.stack([np.log(kA), np.log(kB)], axis=1)
    corrected = SphereObservables(np.exp(u_c[:, 0]), 1.0 - np.exp(u_c[:, 1]))
    msg = (f"converged after {len(steps)} reference renders" + (" (D's last step inside its interval)" if d_stop
                                                                   else "") if converged else
           f"reference iteration stopped after {len(steps)} renders with a last change of {steps[-1].change:.1%}"
           f" (> rel_tol {rel_tol:.1%} and > 1/4 of the interval)")
    if np.any(cens & ok):
        msg += f"; sigma_a censored at 0 after the correction in channel(s) {np.flatnonzero(cens & ok).tolist()}"
    return SphereReferenceEstimate(
        sigma_s_prime_per_mm=ssp_f, sigma_a_per_mm=sa_f, alpha_prime=alpha, l_prime_mm=1.0 / st, D_mm=1.0 / (3 * st),
        intervals=intervals, censored=cens & ok, kappa_albedo=kA, kappa_blur=kB, kappa_albedo_rel_stderr=kA_se,
        kappa_blur_rel_stderr=kB_se, corrected=corrected, uncorrected=uncorrected, steps=steps,
        converged=converged, iterations=len(steps), seconds=time.perf_counter() - t_all, message=msg,
        status=status, channel_converged=conv_c.copy(),
        provenance={"radius_mm": rho, "eta": eta_f, "seed": int(seed), "rel_tol": rel_tol, "fdr": fdr,
                    "model": "dipole-jensen (truncated, sphere chord distance)+reference",
                    "jacobian": B.tolist(),
                    "stop": "D" if d_stop else "parameters" if converged else "budget",
                    "scan": None if scan_res is None else scan_res.as_dict(),
                    "interval": "95 %: observed median intervals and the reference's Monte Carlo error in "
                                "quadrature on (log albedo, log (1 - shortening)), through the secant Jacobian"})


def _widen_unconverged(intervals: dict[str, Array], steps: list[SphereReferenceStep],
                       converged: NDArray[np.bool_]) -> dict[str, Array]:
    """Widen the intervals of channels stopped before the stop rule by the distance to the fixed point that the
    iteration's own path suggests (Aitken's estimate, as in :mod:`estimation.reference_intervals`): with G_i the last
    refit's change of a log parameter and s the secant slope of G between the last two render points (clipped to
    SECANT_SLOPE_BOUNDS; one step only: the assumed slope), the remaining error is |G| |1 + s| / |s|; the interval's
    ends move out by that much in log (added to the statistical half-width, not in quadrature: the error is
    systematic). The stop rule's intervals cover noise only; a non-converged result also carries this bias."""
    from .reference_intervals import _ASSUMED_SLOPE, SECANT_SLOPE_BOUNDS

    def log_d(ssp: list[float], sa: list[float]) -> Array:
        a, b = np.asarray(ssp, dtype=np.float64), np.asarray(sa, dtype=np.float64)
        return {"D_mm": -np.log(3.0 * (a + b)), "sigma_s_prime_per_mm": np.log(a),
                "sigma_a_per_mm": np.log(np.maximum(b, 1e-300))}  # type: ignore[return-value]

    last = steps[-1]
    x_r, x_n = log_d(last.render_sigma_s_prime_per_mm, last.render_sigma_a_per_mm), \
        log_d(last.sigma_s_prime_per_mm, last.sigma_a_per_mm)
    prev = steps[-2] if len(steps) >= 2 else None
    out = dict(intervals)
    for k in ("D_mm", "sigma_s_prime_per_mm", "sigma_a_per_mm"):
        g = x_n[k] - x_r[k]      # type: ignore[index]
        slope = np.full(g.shape, _ASSUMED_SLOPE)
        if prev is not None:
            xp_r = log_d(prev.render_sigma_s_prime_per_mm, prev.render_sigma_a_per_mm)[k]   # type: ignore[index]
            xp_n = log_d(prev.sigma_s_prime_per_mm, prev.sigma_a_per_mm)[k]                   # type: ignore[index]
            with np.errstate(divide="ignore", invalid="ignore"):
                sl = (g - (xp_n - xp_r)) / (x_r[k] - xp_r)   # type: ignore[index]
            slope = np.where(np.isfinite(sl) & (np.abs(x_r[k] - xp_r) > 1e-9),   # type: ignore[index]
                             np.clip(sl, *SECANT_SLOPE_BOUNDS), slope)
        extra = np.where(converged | ~np.isfinite(g), 0.0, np.abs(g) * np.abs(1.0 + slope) / np.abs(slope))
        iv = np.array(intervals[k], dtype=np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            iv[:, 0] = iv[:, 0] * np.exp(-extra)
            iv[:, 1] = iv[:, 1] * np.exp(extra)
        out[k] = iv
    return out


def _widen_by(intervals: dict[str, Array], log_extra: Array) -> dict[str, Array]:
    """The intervals with their ends moved out by ``log_extra`` (C, 3): per channel, in log, for sigma_s', sigma_a
    and D (the D stop's last steps; added to the statistical half-width, not in quadrature: the distance still to
    go is systematic). A censored sigma_a keeps its lower end 0."""
    out = dict(intervals)
    for j, k in enumerate(("sigma_s_prime_per_mm", "sigma_a_per_mm", "D_mm")):
        iv = np.array(intervals[k], dtype=np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            iv[:, 0] = iv[:, 0] * np.exp(-log_extra[:, j])
            iv[:, 1] = iv[:, 1] * np.exp(log_extra[:, j])
        out[k] = iv
    return out


def _solve_corrected(u_obs: Array, d: Array, K: Array, x0: Array, rho: float, eta: float, fdr: str,
                     max_step: float, floor_rel: float, use: NDArray[np.bool_], iterations: int = 30) -> Array:
    """Damped Newton on g(x) = u_fast(x) + d + K (x - x0) - u_obs per channel, from x0; the total step is clipped
    to ``max_step`` per parameter and sigma_a kept >= floor_rel * sigma_t'."""
    x = x0.copy()

    def g(xv: Array) -> Array:
        p = np.exp(xv)
        u = _log_obs(sphere_model_observables(rho, p[:, 0], p[:, 1], eta, fdr=fdr))
        return u + d + np.einsum("cij,cj->ci", K, xv - x0) - u_obs

    def clamp(xv: Array) -> Array:
        xv = np.clip(xv, x0 - max_step, x0 + max_step)
        lo = np.log(floor_rel) + np.log(np.exp(xv[:, 0]) + np.exp(xv[:, 1]))
        return np.stack([xv[:, 0], np.maximum(xv[:, 1], lo)], axis=1)

    gx = np.where(use[:, None], g(x), 0.0)
    for _ in range(iterations):
        J = _fast_jacobian(x, rho, eta, fdr) + K
        with np.errstate(invalid="ignore", divide="ignore"):
            dx = -np.linalg.solve(J, gx[..., None])[..., 0]
        dx = np.where(np.isfinite(dx) & use[:, None], dx, 0.0)
        t = np.ones(x.shape[0])
        norm0 = np.linalg.norm(gx, axis=1)
        acc = ~use
        xn, gn = x, gx
        for _ in range(8):
            xt = clamp(x + t[:, None] * dx)
            gt = np.where(use[:, None], g(xt), 0.0)
            better = ~acc & (np.linalg.norm(gt, axis=1) < norm0)
            xn = np.where(better[:, None], xt, xn)
            gn = np.where(better[:, None], gt, gn)
            acc = acc | better
            t = np.where(acc, t, 0.5 * t)
            if acc.all():
                break
        x, gx = xn, gn
        if np.max(np.linalg.norm(gx, axis=1)) < 1e-12:
            break
    return x


def _log_cov(B: Array, sd_u: Array) -> Array:
    """(C, 2, 2) covariance of (log sigma_s', log sigma_a) = B^-1 diag(sd_u^2) B^-T (NaN where singular)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        try:
            Binv = np.linalg.inv(B)
        except np.linalg.LinAlgError:
            return np.full(B.shape, np.nan)
        return np.einsum("cik,ck,cjk->cij", Binv, sd_u ** 2, Binv)


def _log_intervals(x: Array, B: Array, sd_u: Array) -> Array:
    """(C, 2) 95 % half-widths of (log sigma_s', log sigma_a)."""
    cov = _log_cov(B, sd_u)
    return 1.96 * np.sqrt(np.maximum(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1), 0.0))
