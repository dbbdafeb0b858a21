"""Result types of the single-image method."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class SingleImageDiagnostics:
    """How the solve went. ``condition_number``: of W (binned methods) or of the scaled Jacobian (direct),
    capped at 1/eps (a note says so); 0 on failures (not computed). Every number is finite."""

    condition_number: float
    n_bins: int
    empty_bins: int
    residual_rms: Array  # per channel, in the weighted residual units
    relative_residual_rms: Array  # per channel, rms of (model - l)/l over observed patches
    seconds: float
    n_observations: int
    n_patches: int
    nfev: int
    regularization: Array | None = None  # tikhonov lambda per channel
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class SingleImageResult:
    """Estimated parameters per colour channel, shape (C,), with 95 % intervals (C, 2); falsy on failure.

    ``sigma_a_ci_per_mm`` is the profile-likelihood interval (lower bound 0 when one-sided);
    ``sigma_a_ci_jacobian_per_mm`` the Wald interval in log sigma_a. ``profile_*`` hold the binned R'
    (pinv/tikhonov) or the fitted model at the bins (direct) as a diagnostic.
    """

    success: bool
    message: str
    method: str
    model: str
    eta: float
    sigma_s_prime_per_mm: Array | None = None
    sigma_a_per_mm: Array | None = None
    R_d: Array | None = None
    l_d_mm: Array | None = None
    D_mm: Array | None = None
    sigma_s_prime_ci_per_mm: Array | None = None
    sigma_a_ci_per_mm: Array | None = None
    sigma_a_ci_jacobian_per_mm: Array | None = None
    R_d_ci: Array | None = None
    l_d_ci_mm: Array | None = None
    correlation_log: Array | None = None  # corr(log sigma_s', log sigma_a) per channel
    sigma_a_identifiable: bool = False
    sigma_a_identifiable_per_channel: tuple[bool, ...] = ()
    identifiability_reason: str = ""
    profile_bins_mm: Array | None = None
    profile_values: Array | None = None  # (n_bins, C)
    diagnostics: SingleImageDiagnostics | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.success


def _failure(message: str, method: str, model: str, eta: float, t0: float, **extra: Any) -> SingleImageResult:
    diag = SingleImageDiagnostics(0.0, 0, 0, np.array([]), np.array([]), time.perf_counter() - t0, 0, 0, 0)
    return SingleImageResult(False, message, method, model, float(eta), diagnostics=diag, extra=dict(extra))



def sigma_a_verdict(lo: float, hi: float, identifiable_ratio: float, one_sided: bool = False) -> tuple[bool, str]:
    """Is sigma_a identified by its 95 % interval [lo, hi] (per mm)? (verdict, reason): not when the interval
    reaches the floor / 0 (one-sided) or spans more than a factor ``identifiable_ratio``."""
    if one_sided or not lo > 0:
        return False, f"the 95% interval of sigma_a reaches the floor ({lo:.3g}-{hi:.3g} /mm, one-sided)"
    if hi / lo > identifiable_ratio:
        return False, (f"the 95% interval of sigma_a spans a factor {hi / lo:.3g} (> {identifiable_ratio:g}): "
                       f"{lo:.3g}-{hi:.3g} /mm")
    return True, f"sigma_a within {lo:.3g}-{hi:.3g} /mm (factor {hi / lo:.3g})"
