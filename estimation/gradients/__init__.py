"""Diffuse / specular albedo and normal maps from polarized spherical gradient illumination (Ma et al. 2007).

Inputs are linear RGB frames (H, W, 3) — black-subtracted, white level ``white_level`` (1.0 for
``drivers.contracts.RawFrame``) — taken under the constant pattern ("full"), the gradients ("x", "y", "z")
and/or their complements ("x_c", "y_c", "z_c"), cross-polarized and optionally parallel-polarized, plus an
all-off ("ambient") frame that is subtracted. Frame keys: ``(pattern, polarization)`` tuples, or a bare
pattern name for the cross-polarized frame (see :func:`frame_key` and ``docs/gradients.md``).

Two response models:

- ``ideal=True``: continuous spherical gradients. v_i = 2 I_i / I_c - 1, or with complements
  v_i = (I_i - I~_i)/(I_i + I~_i) (Ma et al. 2007, Eq. 2-3). A flat surface that is Lambertian behind a
  smooth dielectric boundary (Fresnel transmission F_t(eta, n.w)) gives v = (tau1/tau0) n,
  tau_k = 2 pi int_0^1 F_t(mu) mu^(k+1) dmu (0.685 at eta = 1.3; science.md sec. 3).
- ``leds=LedRig(...)``: the sphere is a sum of discrete LEDs with calibrated gains and the pattern values that
  were actually displayed. The expected response E_P(n) = sum_j g_j p_jP F_t(eta, n.w_j) (n.w_j)+ of every
  pattern is tabulated over normal space (octahedral grid) as a *local affine model* a_P(n0) + b_P(n0).n,
  fitted by Gaussian-weighted least squares over a cap of normals around each node. Each pixel then solves
  the linear system I_P = rho a_P + b_P.(rho n~) for (rho, rho n~) (4 unknowns, one equation per pattern),
  twice (second pass at the refined normal), with the least-squares inverse pinv(A(n)) tabulated on a 4x finer
  octahedral grid (nearest node, one gather per pixel). The output ``diffuse_vectors`` = (tau1/tau0) n~ is the
  *ideal-equivalent* gradient vector: exactly (tau1/tau0) n for a flat surface, and (tau1/tau0) times the
  profile-weighted mean normal for a translucent curved one — the quantity ``estimation.diffusion`` needs.
  Because the model is affine in n, averaging over a blur footprint commutes with it (to second order in the
  footprint's normal spread relative to the LUT smoothing), so the |v| bias from discreteness is removed.

Large frames: inputs may be memory maps; everything is computed per row tile in blocks of 16384 pixels in
float32, and with ``out_dir`` the outputs are written tile by tile into ``.npy`` memory maps (bounded memory,
``benchmarks/gradients.py``).

Albedo convention (``docs/gradients.md``): ``albedo`` is the dipole's total diffuse reflectance R_d, defined by
    I_full = F_t(eta, n.v) * E_full(n) / E_full(n_ref) * R_d / albedo_scale
i.e. ``albedo_scale`` (per channel) converts the ambient-subtracted cross-polarized full-on value of a surface
at the rig origin facing ``reference_normal`` and viewed head-on (exit Fresnel divided out) to R_d.
See :func:`albedo_scale_from_lambertian` and :func:`albedo_scale_from_radiometry`.

References: Ma, Hawkins, Peers, Chabert, Weiss, Debevec 2007, "Rapid acquisition of specular and diffuse normal
maps from polarized spherical gradient illumination" (EGSR); Jensen et al. 2001 (F_t, R_d); science.md sec. 3.
"""
from __future__ import annotations

from .compute import compute_maps
from .response import (GRADIENT_PATTERNS, PATTERNS, POLARIZATIONS, LedRig, ResponseLUT, albedo_scale_from_lambertian,
                       albedo_scale_from_radiometry, build_response_lut, frame_key, oct_decode, oct_encode, tau_ratio)
from .storage import DerivedMap, GradientMaps, GradientMasks, UnitVectorMap, map_allocator, tile_workers


__all__ = [
    "PATTERNS",
    "POLARIZATIONS",
    "GRADIENT_PATTERNS",
    "frame_key",
    "tau_ratio",
    "LedRig",
    "ResponseLUT",
    "build_response_lut",
    "GradientMasks",
    "GradientMaps",
    "compute_maps",
    "albedo_scale_from_lambertian",
    "albedo_scale_from_radiometry",
    "oct_encode",
    "oct_decode",
    "map_allocator",
    "DerivedMap",
    "UnitVectorMap",
    "tile_workers"
]
