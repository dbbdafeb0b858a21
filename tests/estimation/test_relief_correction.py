"""The reference-corrected relief fit's loop (estimation.relief_correction) on a synthetic pipeline whose reading is
biased like the relief fit on Monte Carlo frames (l' read +12 to +40 % and a slowly varying factor, 1 - alpha' read
a few per cent off): the loop must remove the bias, keep unknown / weak channels so, and cover the truth. The Monte
Carlo path (renders of a relief slab through the CLI's pipeline) is measured by benchmarks/relief_reference.py."""
from __future__ import annotations

import numpy as np
import pytest

from estimation.relief import parameters_from_l_prime
from estimation.relief_correction import (ReliefReading, as_reading, correct_relief_with_reference,
                                          reading_from_summary)

TRUE_ALPHA = np.array([0.9990, 0.9950, 0.9800])
TRUE_L = np.array([0.80, 0.45, 0.30])
BIAS_L = np.array([1.30, 1.12, 1.40])


def biased_pipeline(alpha: np.ndarray, l_mm: np.ndarray, noise_rel: float = 0.0, seed: int = 0,
                    status: tuple[str, str, str] = ("weak", "ok", "ok")) -> ReliefReading:
    """A pipeline reading l' x BIAS_L x (l'/0.5)^0.15 (the factor varies with l') and 1 - alpha' x 1.08."""
    rng = np.random.default_rng(seed)
    l_read = l_mm * BIAS_L * (l_mm / 0.5) ** 0.15 * np.exp(noise_rel * rng.standard_normal(3))
    om = (1.0 - alpha) * 1.08
    r = as_reading(1.0 - om, l_read, rel_halfwidth=0.2, status=status)
    return ReliefReading(r.alpha_prime, r.l_prime_mm, r.l_prime_interval_mm * np.array([1 / 1.3, 1.3]),
                         r.alpha_prime_interval, status, 0.3)      # intervals widened like the fit's


def test_the_loop_removes_a_multiplicative_bias_and_keeps_the_frames_status() -> None:
    observed = biased_pipeline(TRUE_ALPHA, TRUE_L)
    before = parameters_from_l_prime(observed.alpha_prime, observed.l_prime_mm)["l_d_mm"]
    truth_ld = parameters_from_l_prime(TRUE_ALPHA, TRUE_L)["l_d_mm"]
    assert np.all(np.abs(before / truth_ld - 1) > 0.05)             # the bias is there before
    res = correct_relief_with_reference(observed, biased_pipeline, max_renders=6, rel_tol=0.01)
    assert np.allclose(res.values["l_prime_mm"], TRUE_L, rtol=0.02)
    assert np.allclose(res.values["l_d_mm"], truth_ld, rtol=0.03)
    assert res.converged.all()
    assert res.status == ("weak", "ok", "ok")                        # weak information stays weak
    for k in ("l_prime_mm", "l_d_mm", "alpha_prime"):
        lo, hi = res.intervals[k].T
        t = {"l_prime_mm": TRUE_L, "l_d_mm": truth_ld, "alpha_prime": TRUE_ALPHA}[k]
        assert np.all((lo <= t) & (t <= hi)), k
    l_last = np.array(res.steps[-1]["rendered_l_prime_mm"])
    assert np.allclose(res.kappa_l_prime, 1 / (BIAS_L * (l_last / 0.5) ** 0.15), rtol=1e-9)


def test_unknown_channels_stay_unknown_and_noisy_references_widen_the_interval() -> None:
    obs = biased_pipeline(TRUE_ALPHA, TRUE_L, status=("ok", "ok", "unknown"))
    obs = ReliefReading(obs.alpha_prime, np.array([obs.l_prime_mm[0], obs.l_prime_mm[1], np.nan]),
                        obs.l_prime_interval_mm, obs.alpha_prime_interval, obs.status, 0.3)
    quiet = correct_relief_with_reference(obs, lambda a, l: biased_pipeline(a, l, status=("ok", "ok", "unknown")),
                                          max_renders=4)
    assert quiet.status[2] == "unknown" and np.isnan(quiet.values["l_d_mm"][2])
    assert list(quiet.intervals["l_d_mm"][2]) == [0.0, np.inf]

    def noisy(a: np.ndarray, l: np.ndarray) -> ReliefReading:
        r = biased_pipeline(a, l, noise_rel=0.3, seed=1, status=("ok", "ok", "unknown"))
        return ReliefReading(r.alpha_prime, r.l_prime_mm, r.l_prime_interval_mm * np.array([1 / 2.0, 2.0]),
                             r.alpha_prime_interval, r.status, 0.3)

    loud = correct_relief_with_reference(obs, noisy, max_renders=4)
    w_q = np.log(quiet.intervals["l_prime_mm"][:2, 1] / quiet.intervals["l_prime_mm"][:2, 0])
    w_l = np.log(loud.intervals["l_prime_mm"][:2, 1] / loud.intervals["l_prime_mm"][:2, 0])
    assert np.all(w_l > w_q * 1.3)


def test_reading_from_summary_refuses_a_bad_status_and_reads_nulls() -> None:
    d = {"status": ["ok", "weak", "unknown"], "model_bias_rel": 0.3,
         "l_prime_mm": {"value": [0.5, 0.4, None], "interval": [[0.3, 0.9], [0.1, 2.0], [None, None]]},
         "alpha_prime": {"value": [0.99, 0.98, None], "interval": [[0.98, 0.995], [0.97, 0.99], [None, None]]}}
    r = reading_from_summary(d)
    assert r.usable().tolist() == [True, True, False]
    assert r.l_prime_interval_mm[2].tolist() == [0.0, np.inf]
    with pytest.raises(ValueError, match="status"):
        reading_from_summary({**d, "status": ["ok"]})
