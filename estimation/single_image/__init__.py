"""Subsurface-scattering parameters from one image under known illumination (Mukaigawa, Suzuki, Yagi 2009).

"Analysis of Subsurface Scattering under Generic Illumination" (ICPR 2008 / seed 000): with known geometry and
illumination, the radiance of every visible patch j is (Eq. 10-13)

    l_j = pi L_o(P_j) / F_t(eta, w_o) = sum_k R(d_jk) c_k,   c_k = E_t(P_k) A_k,

and R is recovered either (as published) by quantizing the distances with linear-interpolation weights,
l ~ W r (Eq. 20-27), r = pinv(W) l (Eq. 28) and a dipole fit to r (Eq. 29), or — better — by fitting
(log sigma_s', log sigma_a) directly to the l_j with exact self-patch integrals. Methods (``method=``):

- ``"pinv"``: the published method. Uniform bins of ``bin_mm`` from 0 (the self term is point-sampled at d=0
  as in the paper); empty bins are zero columns of W — pinv returns 0 for them — so they are reported in the
  diagnostics and left out of the dipole fit (the one deviation from the paper). Unweighted fit of Eq. 29.
- ``"tikhonov"``: same bins, exact near-field integrals of the hat functions, second-difference penalty with
  lambda by generalized cross-validation, non-negative (NNLS), optionally monotone. The dipole is then fitted
  to R' in the metric of the data, || w (W R(theta) - W R') ||: under smooth irradiance the profile within
  ~1 mm is seen only through its disk integrals, so a pointwise fit to R' near d = 0 would be biased.
- ``"direct"`` (default): fit (log sigma_s', log sigma_a) to l_j = sum_k R(d_jk) c_k with exact self-patch
  integrals: the near field of patch j uses the equal-area rings of :func:`estimation.forward.ring_radii`
  (own patch = central disk), integrated exactly through the closed-form disk integral G(r) = int_0^r R 2 pi r dr
  (:func:`estimation.dipole.cumulative_disk`); far pairs are point terms. G and R are represented on log-spaced
  nodes (4 %, 4-point Lagrange interpolation in log r, relative error <= 3e-5), so l = W [G(nodes); R(nodes)] and
  one model evaluation is one mat-vec. The weighted system is reduced once by a QR factorization to n x n
  (n ~ 130 nodes, whatever the number m of observations), then: grid start, a lockstep bounded
  Levenberg-Marquardt from up to 9 starts (one batched model evaluation per iteration) and one
  ``scipy.optimize.least_squares`` polish of the best; recovers its own forward model to ~1e-5.

Cost. The far field (pairs beyond 2 patch spacings) of the direct method is summed exactly for small problems
and, above :data:`EXACT_PAIR_BUDGET` (observation, source) pairs, over a Barnes-Hut hierarchy of source
clusters, each represented by 6 pseudo-sources matching its c-weighted moments to second order (``far_field``,
``far_field_theta``; :class:`_SourceClusters`): O(m log K) instead of O(m K) pairs, rms error of l ~0.03 % at the
default opening ratio 0.35 for long profiles (marble), ~0.15 % for short ones (skin-B, ketchup-G at 5k patches;
tests/estimation/test_single_image_far_field.py); the fitted parameters move by < 1 %. Every far term (pair or
pseudo-source) enters W through its interval index and the moments sum w v^p (p = 0..3, v its offset in the
interval): four bincounts per channel, mapped to the nodes once (:class:`_CubicLogBasis`; the hat basis of the
binned methods likewise with two moments, :class:`_HatBasis`). Every method then works on the QR-reduced n x n
system (one Householder QR of [W | l] without forming Q). The published ``pinv`` route is ill-conditioned
(cond(W) ~1e4-1e5): it reacts to a 0.03 % far-field change by a few % in its parameters (+2.7 % in sigma_s' at
10k patches with the direct method's clustering), so the binned methods sum every pair (dense blocks) up to
:data:`EXACT_PAIR_BUDGET_BINNED` pairs — reproducing the dense textbook computation — and cluster beyond it
with the tighter opening :data:`FAR_FIELD_THETA_BINNED` (0.2; at 10k patches -0.13 % in sigma_s', but the
ill-conditioning makes that error erratic in the opening: 0.15 gave -0.8 %, 0.25 -3.6 %). Measured
(benchmarks/single_image.py section 3, sphere, marble-R under a sky map, one BLAS thread; ratios within one
run): at 10k patches (3148 observed) the direct method takes ~0.12 s, ~6x faster than the literal dense pinv
(0.78 s), and our exact-far-field pinv ~2x (equal parameters); 50k patches take ~0.8 s; the literal dense method
needs 8 m_obs m bytes (6.3 GB at 50k). Anatomy at 10k: far field ~0.07 s (3.0 M pseudo-source and point terms,
~23 ns each: traversal, gathers, log-index, four bincounts), cluster build ~0.015 s, near rings ~0.01 s, the two
fits with their QR reductions ~0.022 s. Tried and not adopted (measured at 10k): a dual-tree second-order
Cartesian Taylor FMM (114 k cell pairs + 280 k point terms instead of 3.0 M terms, but no faster — every
accepted pair scatters 4 nodes x 10 monomials — and 3-4x the error, rms 1.0e-3 of l for marble-R); per-cell
quadrupole terms instead of 6 pseudo-sources (0.9 M terms, 1.5x the error); two threads (numpy's bincount,
gathers and einsum hold the GIL: 0.7-0.9x); scipy.sparse products for the moment sums (1.5-2.5x slower than
bincount).

Models (``model=``, :data:`MODELS_ALL`): the dipoles of :mod:`.dipole` and ``"mc-table"``, the packaged Monte Carlo
table of the half-space profile (:mod:`.mc_table`, eta 1.0-1.8, checked up front). For the table every method uses
its exact disk integral C(r) (``cumulative``) where the dipoles use theirs, its R_d / l_d and cutoff, and
out-of-range albedos are evaluated at the table's edge (``out_of_range="clip"``: the sigma_a floor of 1e-7/mm lies
below the table's 1 - alpha' = 1e-5, so the objective is flat there, which the intervals report as "sigma_a not
identifiable"). The table's R diverges like 1/r at the source, so the binned methods do not point-sample it at
d = 0: ``pinv``'s self term uses the mean over the own patch's disk, C(r_p)/(pi r_p^2) (r_p = sqrt(median area /
pi)), and ``tikhonov``'s first node the value that gives its hat interval the exact disk integral.
Exit radiance: the dipoles keep Jensen's (and the paper's) angular factor F_t(eta, w_o)/pi, l_j = pi L_o / F_t,
unchanged. That factor integrates to c = 1 - 2 FM1_ext(eta) over the hemisphere, not 1; the table's R is true
exitance, so for ``"mc-table"`` the estimator uses the normalized factor F_t/(pi c)
(:func:`estimation.mc_table.exit_radiance_factor`, within ~5 % of the Monte Carlo exit distribution for
cos_o >= 0.2): l_j = pi c L_o / F_t, and :func:`predict_radiance` renders with the same factor. ``extra`` records
``exit_normalization`` (c; 1 for dipoles) and, for every model, ``model_bias`` (:func:`model_bias`): the
model's R_d and profile (at 0.5, 1, 2, 5 transport mean free paths) against the Monte Carlo table at the fitted
parameters, the radiance ratio including the exit normalization, and the table-equivalent parameters.

Every method reports Jacobian confidence intervals and a profile-likelihood interval for sigma_a (which is
one-sided near 0: science.md sec. 6), ``sigma_a_identifiable`` with the reason, and diagnostics. Failures
return a falsy :class:`SingleImageResult` whose ``message`` says why; no returned number is NaN or inf.

Geometry in mm (rig frame), colour channels on the last axis.

Modules: :mod:`.geometry` (patches, lights, irradiance), :mod:`.far_field` (pair geometry, source clusters,
interpolation bases), :mod:`.models` (the profile models as the fit sees them), :mod:`.fit` (the per-channel fit and
its intervals), :mod:`.results` (result types), :mod:`.estimate` (the entry points), :mod:`.decimation` (patches of a decimated copy
of a large mesh, seen and shadowed by the full mesh).
"""
from __future__ import annotations

from ..mc_table import MODEL_NAME as MC_MODEL
from .estimate import METHODS, estimate_single_image, map_parameters, predict_radiance
from .far_field import (EXACT_PAIR_BUDGET, EXACT_PAIR_BUDGET_BINNED, FAR_FIELD_MODES, FAR_FIELD_THETA,
                        FAR_FIELD_THETA_BINNED, _CubicLogBasis, _cubic_log_basis, _Geometry, _hat_basis, _log_grid,
                        quantization_weights)
from .fit import (_LOG_SA_MAX, _LOG_SSP_BOUNDS, _box_qp_2d, _fit_channel, _golden_batch, _lm_multistart,
                  _Problem, _reduce)
from .decimation import (DecimatedPatches, decimate_mesh, gather_patch_pixels,
                         patches_from_decimated)
from .geometry import (DirectionalLights, EnvironmentMap, Lights, Patches, PointLights, patch_irradiance,
                       patches_from_mesh, sample_image_at_patches)
from .models import BIAS_RADII_MFP, MODELS_ALL, _binned_profile, check_model, model_bias
from .results import SingleImageDiagnostics, SingleImageResult, sigma_a_verdict
from .validity import MAX_OK_INTERVAL_RATIO, flat_model_reasons, parameter_status
from .estimate import MAX_BINS

__all__ = [
    "METHODS",
    "MODELS_ALL",
    "MC_MODEL",
    "BIAS_RADII_MFP",
    "check_model",
    "model_bias",
    "Patches",
    "PointLights",
    "DirectionalLights",
    "EnvironmentMap",
    "patches_from_mesh",
    "DecimatedPatches",
    "decimate_mesh",
    "patches_from_decimated",
    "gather_patch_pixels",
    "sample_image_at_patches",
    "patch_irradiance",
    "quantization_weights",
    "SingleImageDiagnostics",
    "SingleImageResult",
    "estimate_single_image",
    "predict_radiance",
    "FAR_FIELD_MODES",
    "EXACT_PAIR_BUDGET",
    "EXACT_PAIR_BUDGET_BINNED",
    "FAR_FIELD_THETA",
    "FAR_FIELD_THETA_BINNED",
    "MAX_BINS",
    "Lights",
    "sigma_a_verdict",
    "parameter_status",
    "flat_model_reasons",
    "MAX_OK_INTERVAL_RATIO",
]
