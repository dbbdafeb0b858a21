"""Diffusion parameters from polarized spherical gradient maps (issue 5, second seed: Zhu et al.).

Two estimators, kept side by side so their disagreement can be reported (``docs/gradients.md``):

1. **Seed** (Zhu, Peers, Debevec, Ghosh, "Estimating diffusion parameters from polarized spherical gradient
   illumination"): D = k R_d / |n_z|. A flat homogeneous region under distant light has the same exitance
   for every dipole (science.md sec. 4), so ``k`` is an *empirical length* that depends on the capture
   geometry: :func:`calibrate_k` measures it on a reference of known D in the actual geometry,
   :func:`diffusion_seed` applies it, :func:`seed_regression` checks the slope of log D on log(R_d/|n_z|).
   ``n_z`` here is the component of the ideal-equivalent diffuse vector along the surface normal (the
   camera-facing axis when no normals are given), divided by tau1/tau0: 1 for an unblurred surface.

2. **Grounded**: for pattern P_i the transmitted irradiance is E_t^i = tau0/2 + (tau1/2) n_i, so
   v(x_o) = (tau1/tau0) (R * n)(x_o) / (R * 1)(x_o): the diffuse normal is the true normal field blurred by the
   normalized dipole profile. The shortening S = v.n_true / (tau1/tau0) measures the profile's spread:
   - ``method="sphere"`` (exact for a sphere of radius rho with the Euclidean-distance dipole used by the
     renderers): with d the chord, dA = 2 pi d dd and cos(theta) = 1 - d^2/(2 rho^2), so
       albedo = C(2 rho) = int_0^{2 rho} R 2 pi d dd          (the apparent R_d, < R_d)
       S      = 1 - M2(2 rho) / (2 rho^2 C(2 rho)),   M2(D) = int_0^D R d^2 2 pi d dd  (closed form here).
     Both are functions of (alpha', l' = 1/sigma_t'); the pair (albedo, S) is inverted exactly (nested Brent
     for region summaries; per-pixel maps look it up in a tabulated exact inverse,
     or run damped Newton with a bisection fallback). No fitted constant.
     For a general surface with principal curvatures k1, k2, rho_eff = sqrt(2 / (k1^2 + k2^2)) is used.
   - ``method="small_blur"``: S ~ 1 - <r^2> (k1^2 + k2^2)/4 (first order; biased by 5-30% where the
     shortening is 5-15%), alpha' from R_d, l' = sqrt(<r^2>/G(alpha', A)).
   Then sigma_t' = 1/l', sigma_s' = alpha' sigma_t', sigma_a = (1 - alpha') sigma_t', D = l'/3 (Jensen).
   Where a region carries no information (flat, dark, masked, grazing) the value is NaN and ``unknown`` is set.

Only the Jensen 2001 dipole (``model="dipole-jensen"``, ``fdr`` as in :mod:`estimation.dipole`) is supported
by the grounded estimator. Units: mm, 1/mm.
"""
from __future__ import annotations

from .maps import DiffusionMaps, estimate_diffusion
from .models import METHODS, MODELS_GROUNDED, check_grounded_model, grounded_model_bias
from .relief_blur import fit_relief, relief_mtf
from .seed import (EstimateComparison, SeedCalibration, SeedEstimate, calibrate_k, compare_estimates, diffusion_seed,
                   seed_regression)
from .sphere import (curvature_sq_from_normals, invert_sphere, invert_sphere_scalar, sphere_albedo, sphere_shortening,
                     truncated_second_moment_mm4)
from .summary import DiffusionSummary, ParameterSummary, SphereEstimate, estimate_sphere, sphere_geometry, summarize


__all__ = [
    "METHODS",
    "MODELS_GROUNDED",
    "check_grounded_model",
    "grounded_model_bias",
    "sphere_albedo",
    "sphere_shortening",
    "truncated_second_moment_mm4",
    "invert_sphere",
    "invert_sphere_scalar",
    "DiffusionMaps",
    "estimate_diffusion",
    "curvature_sq_from_normals",
    "ParameterSummary",
    "DiffusionSummary",
    "summarize",
    "sphere_geometry",
    "SphereEstimate",
    "estimate_sphere",
    "SeedCalibration",
    "SeedEstimate",
    "calibrate_k",
    "diffusion_seed",
    "seed_regression",
    "EstimateComparison",
    "compare_estimates",
    "relief_mtf",
    "fit_relief"
]
