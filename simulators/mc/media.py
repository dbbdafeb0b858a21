"""Homogeneous participating media for the Monte Carlo renderer.

A :class:`Medium` holds the *unreduced* coefficients a random walk needs (sigma_s, sigma_a, Henyey-Greenstein g)
and the relative index of refraction ``eta`` = n_medium / n_outside of its smooth boundary (1 = index-matched).
:meth:`Medium.from_reduced` builds one from the reduced scattering coefficient sigma_s' = sigma_s (1 - g) that
dipole models and Jensen et al. 2001 Table 2 use (science.md sec. 1-2); with g = 0 the two coincide.
:func:`optical_medium` gives the dimensionless medium of item 3's tables (sigma_t = 1 per unit length, so lengths
are in mean free paths and the profile depends only on albedo, g and eta).

References: Wang, Jacques, Zheng 1995 (MCML, Comput. Methods Programs Biomed. 47:131); Henyey & Greenstein 1941;
Jensen, Marschner, Levoy, Hanrahan 2001.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Medium", "optical_medium"]


@dataclass(frozen=True)
class Medium:
    """One homogeneous medium (one colour channel); coefficients in 1/mm.

    ``g`` in (-1, 1) is the Henyey-Greenstein anisotropy (0: isotropic); ``eta`` > 0 the relative index of the
    boundary (1: index-matched, no Fresnel reflection).
    """

    sigma_s_per_mm: float
    sigma_a_per_mm: float
    g: float = 0.0
    eta: float = 1.0

    def __post_init__(self) -> None:
        for name in ("sigma_s_per_mm", "sigma_a_per_mm", "g", "eta"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        if self.sigma_s_per_mm < 0 or self.sigma_a_per_mm < 0:
            raise ValueError("sigma_s_per_mm and sigma_a_per_mm must be >= 0")
        if self.sigma_t_per_mm <= 0:
            raise ValueError("sigma_t = sigma_s + sigma_a must be > 0")
        if not -1.0 < self.g < 1.0:
            raise ValueError("g must lie in (-1, 1)")
        if self.eta <= 0:
            raise ValueError("eta must be > 0")

    @classmethod
    def from_reduced(cls, sigma_s_prime_per_mm: float, sigma_a_per_mm: float, *, g: float = 0.0,
                     eta: float = 1.0) -> "Medium":
        """sigma_s = sigma_s' / (1 - g) (similarity relation), so the walk's reduced coefficient is sigma_s'."""
        if not -1.0 < g < 1.0:
            raise ValueError("g must lie in (-1, 1)")
        return cls(float(sigma_s_prime_per_mm) / (1.0 - g), float(sigma_a_per_mm), float(g), float(eta))

    @property
    def sigma_t_per_mm(self) -> float:
        """Extinction sigma_t = sigma_s + sigma_a (the free-flight rate)."""
        return float(self.sigma_s_per_mm + self.sigma_a_per_mm)

    @property
    def albedo(self) -> float:
        """Single-scattering albedo sigma_s / sigma_t."""
        return float(self.sigma_s_per_mm / self.sigma_t_per_mm)

    @property
    def sigma_s_prime_per_mm(self) -> float:
        return float(self.sigma_s_per_mm * (1.0 - self.g))

    @property
    def sigma_t_prime_per_mm(self) -> float:
        return float(self.sigma_s_prime_per_mm + self.sigma_a_per_mm)

    @property
    def reduced_albedo(self) -> float:
        """alpha' = sigma_s' / sigma_t' (the dipole's albedo)."""
        return float(self.sigma_s_prime_per_mm / self.sigma_t_prime_per_mm)

    @property
    def mean_free_path_mm(self) -> float:
        return 1.0 / self.sigma_t_per_mm

    @property
    def transport_mean_free_path_mm(self) -> float:
        """1 / sigma_t' (the dipole's z_r)."""
        return 1.0 / self.sigma_t_prime_per_mm


def optical_medium(albedo: float, *, eta: float = 1.0, g: float = 0.0) -> Medium:
    """Medium with sigma_t = 1 /mm: lengths in mean free paths (use radii in units of 1/sigma_t)."""
    if not 0.0 <= albedo <= 1.0:
        raise ValueError("albedo must lie in [0, 1]")
    return Medium(float(albedo), 1.0 - float(albedo), float(g), float(eta))
