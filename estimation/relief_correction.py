"""Reference-corrected relief fit: the relief-blur estimate of a region corrected by Monte Carlo renders of the
same relief (issue 16, acceptance line 1; the relief counterpart of :mod:`estimation.gradient_correction`).

The relief fit (:func:`estimation.relief.fit_relief_windows`, :func:`estimation.relief.summarize_relief`) reads a
reduced albedo alpha' from the R_d map and a reduced mean free path l' from the attenuation of the diffuse normal
field against the true one, through the Jensen dipole's modulation transfer M(k l'). On Monte Carlo frames that
read is biased (docs/model-error.md, "Relief slabs' l_d (relief16)": A / M <= 0.62 in the red and blue channels,
l' +12 to +40 % on a quiet skin1 slab): the dipole's MTF is not real transport. Here the *same pipeline* is run on
renders of the same relief at the current estimate (a "reference"), and the estimate is moved by the defect
between what the pipeline reads on the frame and on the render -- the defect correction of the sphere loop, one
per channel and per unknown, in logarithms:

    u = log l',  v = log(1 - alpha')          (read(.) : the pipeline's reading of a render at those values)
    u_{n+1} = u_n + (u_obs - u_read(u_n, v_n)),   v_{n+1} = v_n + (v_obs - v_read(u_n, v_n))

(a fixed point where the render at (u, v) reads what the frame reads; unit slope is exact when the pipeline's bias
is a constant factor, and a contraction when the factor varies slowly with the parameters). Each reference is
rendered with the same random numbers (seed) so that the steps are not dominated by the renders' own noise.

Intervals (per channel): the frame's profile interval of l' (its noise; the fit's model-bias widening
``model_bias_rel`` taken out again, since the correction replaces it) moved by the last correction factor, widened
in log space by the last reference reading's own noise interval (also without the model-bias widening, added in
quadrature), by the last step (the loop's distance from its fixed point) and by ``residual_bias_rel`` (the
correction's own model error: the reference is rendered at the estimate, not the truth; not measured, a stated
allowance). alpha' likewise from the frame's alpha' interval. The other parameters from the corners (all monotone
in alpha' and l', :func:`estimation.relief.parameters_from_l_prime`). Status: the frame's status ("unknown" stays
unknown, "weak" stays weak: the correction removes a bias, not the information limit), "weak" as well where the loop
did not converge (last step > ``rel_tol``) or the corrected l' interval spans more than ``weak_ratio``.

References: Ma et al. 2007 sec. 5; Jensen et al. 2001; the defect correction of
:func:`estimation.gradient_correction.estimate_sphere_with_reference`; docs/model-error.md, "Relief reference".
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .relief import RELIEF_PARAMS, parameters_from_l_prime

__all__ = ["ReliefReading", "ReliefCorrection", "as_reading", "correct_relief_with_reference", "reading_from_summary"]

Array = NDArray[np.float64]
_Z95 = 1.959963984540054


@dataclass(frozen=True)
class ReliefReading:
    """What the relief pipeline reads on one capture (frame or render), per channel (3,): alpha', l' (mm), the
    l' and alpha' intervals (3, 2) as the fit reports them, the status, and the fit's model-bias widening."""

    alpha_prime: Array
    l_prime_mm: Array
    l_prime_interval_mm: Array
    alpha_prime_interval: Array
    status: tuple[str, str, str]
    model_bias_rel: float = 0.3

    def usable(self) -> NDArray[np.bool_]:
        return (np.array([s != "unknown" for s in self.status]) & np.isfinite(self.l_prime_mm)
                & np.isfinite(self.alpha_prime) & (self.l_prime_mm > 0) & (self.alpha_prime < 1))


def reading_from_summary(diffusion: dict[str, Any]) -> ReliefReading:
    """A :class:`ReliefReading` from the ``diffusion`` block of ``rig estimate gradients``'s summary of a relief
    (:meth:`estimation.relief.ReliefRegion.as_dict`). Missing numbers (JSON null) become NaN / (0, inf)."""
    def arr(key: str) -> Array:
        v = (diffusion.get(key) or {}).get("value") or [None] * 3
        return np.array([np.nan if x is None else float(x) for x in v], dtype=np.float64)

    def iv(key: str) -> Array:
        v = (diffusion.get(key) or {}).get("interval") or [[None, None]] * 3
        return np.array([[0.0 if a is None else float(a), np.inf if b is None else float(b)] for a, b in v])

    st = list(diffusion.get("status") or ["unknown"] * 3)
    if len(st) != 3:
        raise ValueError(f"diffusion.status must list 3 channels, got {st!r}")
    return ReliefReading(arr("alpha_prime"), arr("l_prime_mm"), iv("l_prime_mm"), iv("alpha_prime"),
                         (str(st[0]), str(st[1]), str(st[2])), float(diffusion.get("model_bias_rel", 0.3)))


@dataclass(frozen=True)
class ReliefCorrection:
    """The corrected per-channel estimate: ``values[name]`` (3,) and ``intervals[name]`` (3, 2) for name in
    :data:`estimation.relief.RELIEF_PARAMS`, ``status`` per channel, the correction factors of the last render
    (``kappa_l_prime`` = rendered l' / read l', ``kappa_one_minus_alpha`` likewise), the steps (rendered and read
    values of every reference), ``converged`` per channel and the ``uncorrected`` values."""

    values: dict[str, Array]
    intervals: dict[str, Array]
    status: tuple[str, str, str]
    kappa_l_prime: Array
    kappa_one_minus_alpha: Array
    converged: NDArray[np.bool_]
    steps: list[dict[str, Any]]
    uncorrected: dict[str, Any]
    provenance: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"status": list(self.status), "converged": self.converged.tolist(),
                               "kappa_l_prime": self.kappa_l_prime.tolist(),
                               "kappa_one_minus_alpha": self.kappa_one_minus_alpha.tolist(),
                               "steps": self.steps, "uncorrected": self.uncorrected}
        for k in RELIEF_PARAMS:
            out[k] = {"value": self.values[k].tolist(), "interval": self.intervals[k].tolist()}
        out.update(self.provenance)
        return out


def _half_width_log(interval: Array, bias_rel: float) -> Array:
    """Half-width of a (3, 2) positive interval in log space without a symmetric x/÷ (1 + bias_rel) widening
    (inf where an end is 0 or inf)."""
    lo, hi = interval[:, 0], interval[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        h = 0.5 * np.log(hi / lo) - np.log1p(bias_rel)
    return np.where(np.isfinite(h), np.maximum(h, 0.0), np.inf)


def correct_relief_with_reference(observed: ReliefReading, render_and_read: Callable[[Array, Array], ReliefReading],
                                  *, max_renders: int = 3, rel_tol: float = 0.05, residual_bias_rel: float = 0.1,
                                  weak_ratio: float = 4.0, l_prime_bounds_mm: tuple[float, float] = (1e-3, 1e3),
                                  min_one_minus_alpha: float = 2e-4, default_alpha: float = 0.99,
                                  default_l_prime_mm: float = 0.5) -> ReliefCorrection:
    """Correct ``observed`` (the frame's reading) by references: ``render_and_read(alpha_prime (3,), l_prime_mm
    (3,))`` renders the same relief with those parameters per channel and returns the pipeline's reading of it.
    At most ``max_renders`` references; stops early once every usable channel's step in log l' and log(1 - alpha')
    is below log(1 + ``rel_tol``). Rendered parameters are clipped to ``l_prime_bounds_mm`` and 1 - alpha' >=
    ``min_one_minus_alpha`` (a reading far out of range would otherwise ask for a render of unbounded cost);
    channels the frame leaves unknown are rendered at (``default_alpha``, ``default_l_prime_mm``) and stay unknown.
    """
    if max_renders < 1:
        raise ValueError(f"max_renders must be >= 1, got {max_renders}")
    if not rel_tol > 0:
        raise ValueError(f"rel_tol must be > 0, got {rel_tol}")
    use = observed.usable()
    u_obs = np.log(np.where(use, observed.l_prime_mm, default_l_prime_mm))
    v_obs = np.log(np.where(use, 1.0 - observed.alpha_prime, 1.0 - default_alpha))
    lb = np.log(np.asarray(l_prime_bounds_mm, dtype=np.float64))
    v_max = np.log(min_one_minus_alpha)

    def clip(u: Array, v: Array) -> tuple[Array, Array]:
        return np.clip(u, lb[0], lb[1]), np.clip(v, v_max, 0.0)

    u, v = clip(u_obs.copy(), v_obs.copy())
    steps: list[dict[str, Any]] = []
    tol = np.log1p(rel_tol)
    last_step = np.full(3, np.inf)
    read: ReliefReading | None = None
    u_ren, v_ren = u, v
    for n in range(int(max_renders)):
        u_ren, v_ren = u, v
        alpha_r, l_r = 1.0 - np.exp(v_ren), np.exp(u_ren)
        read = render_and_read(alpha_r, l_r)
        r_use = read.usable()
        du = np.where(r_use & use, u_obs - np.log(np.where(r_use, read.l_prime_mm, 1.0)), 0.0)
        dv = np.where(r_use & use, v_obs - np.log(np.where(r_use, 1.0 - read.alpha_prime, 1.0)), 0.0)
        u, v = clip(u_ren + du, v_ren + dv)
        last_step = np.maximum(np.abs(u - u_ren), np.abs(v - v_ren))
        last_step = np.where(use & ~r_use, np.inf, last_step)
        steps.append({"render": n, "rendered_alpha_prime": alpha_r.tolist(), "rendered_l_prime_mm": l_r.tolist(),
                      "read_alpha_prime": read.alpha_prime.tolist(), "read_l_prime_mm": read.l_prime_mm.tolist(),
                      "read_status": list(read.status), "step_log": last_step.tolist()})
        if bool(np.all(last_step[use] <= tol)):
            break
    assert read is not None
    r_use = read.usable()
    # the point: the last update (the fixed-point iterate after the last render's defect)
    alpha_c, l_c = 1.0 - np.exp(v), np.exp(u)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa_l = np.where(r_use, np.exp(u_ren) / read.l_prime_mm, np.nan)
        kappa_a = np.where(r_use, np.exp(v_ren) / (1.0 - read.alpha_prime), np.nan)
    converged = use & r_use & (last_step <= tol)
    # intervals in log space: frame noise (moved by the correction) (+) reference noise, + last step + allowance
    h_obs = _half_width_log(observed.l_prime_interval_mm, observed.model_bias_rel)
    h_ref = _half_width_log(read.l_prime_interval_mm, read.model_bias_rel)
    step_l = np.where(np.isfinite(last_step), last_step, np.inf)
    h_l = np.sqrt(h_obs ** 2 + h_ref ** 2) + step_l + np.log1p(residual_bias_rel)
    ha_obs = _half_width_log(1.0 - observed.alpha_prime_interval[:, ::-1], 0.0)
    ha_ref = _half_width_log(1.0 - read.alpha_prime_interval[:, ::-1], 0.0)
    h_a = np.sqrt(ha_obs ** 2 + ha_ref ** 2) + step_l + np.log1p(residual_bias_rel)
    # the frame's interval is not symmetric in log: keep its shape around the moved point
    with np.errstate(divide="ignore", invalid="ignore"):
        c_obs = 0.5 * np.log(observed.l_prime_interval_mm[:, 0] * observed.l_prime_interval_mm[:, 1])
        shift = np.where(np.isfinite(c_obs), c_obs - u_obs, 0.0)
    centre = u + shift
    l_lo, l_hi = np.exp(centre - h_l), np.exp(centre + h_l)
    l_lo, l_hi = np.minimum(l_lo, l_c), np.maximum(l_hi, l_c)
    om_lo, om_hi = (1.0 - alpha_c) * np.exp(-h_a), (1.0 - alpha_c) * np.exp(h_a)
    a_lo, a_hi = np.clip(1.0 - om_hi, 0.0, 1.0), np.clip(1.0 - om_lo, 0.0, 1.0)
    point = parameters_from_l_prime(alpha_c, l_c)
    corners = [parameters_from_l_prime(a, lp) for a in (a_lo, a_hi) for lp in (l_lo, l_hi)]
    values: dict[str, Array] = {}
    intervals: dict[str, Array] = {}
    for k in RELIEF_PARAMS:
        cv = np.stack([np.broadcast_to(c[k], (3,)) for c in corners])
        with np.errstate(invalid="ignore"):
            lo = np.where(np.isfinite(cv).all(0), cv.min(0), 0.0)
            hi = np.where(np.isfinite(cv).all(0), cv.max(0), np.inf)
        values[k] = np.where(use, point[k], np.nan)
        intervals[k] = np.where(use[:, None], np.stack([lo, hi], -1), np.array([0.0, np.inf]))
    status = []
    for c in range(3):
        if not use[c]:
            status.append("unknown")
        elif observed.status[c] == "weak" or not converged[c] or l_hi[c] / l_lo[c] > weak_ratio:
            status.append("weak")
        else:
            status.append("ok")
    unc = parameters_from_l_prime(observed.alpha_prime, observed.l_prime_mm)
    prov = {"estimator": "relief blur corrected by Monte Carlo references of the same relief "
                         "(estimation.relief_correction)",
            "renders": len(steps), "max_renders": int(max_renders), "rel_tol": rel_tol,
            "residual_bias_rel": residual_bias_rel, "weak_ratio": weak_ratio}
    return ReliefCorrection(values, intervals, (status[0], status[1], status[2]), kappa_l, kappa_a, converged,
                            steps, {k: np.asarray(unc[k]).tolist() for k in ("l_prime_mm", "l_d_mm", "alpha_prime")},
                            prov)


def as_reading(alpha_prime: ArrayLike, l_prime_mm: ArrayLike, rel_halfwidth: float = 0.2,
               status: tuple[str, str, str] = ("ok", "ok", "ok")) -> ReliefReading:
    """A :class:`ReliefReading` with x/÷ (1 + ``rel_halfwidth``) intervals and no model-bias widening (for
    readings computed by a model rather than the relief fit, e.g. in tests)."""
    a = np.asarray(alpha_prime, dtype=np.float64)
    lp = np.asarray(l_prime_mm, dtype=np.float64)
    f = 1.0 + rel_halfwidth
    om = 1.0 - a
    return ReliefReading(a, lp, np.stack([lp / f, lp * f], -1), np.stack([1.0 - om * f, 1.0 - om / f], -1),
                         status, 0.0)
