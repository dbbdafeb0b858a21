"""Dipole diffusion profiles R(r) of a homogeneous semi-infinite medium, their closed-form integrals and inversions.

Two models, chosen by ``model=`` (see :data:`MODELS`):

- ``"dipole-jensen"``: Jensen, Marschner, Levoy, Hanrahan 2001, "A Practical Model for Subsurface Light
  Transport" (SIGGRAPH), Eq. 4-5 — the R(d) of Mukaigawa, Suzuki, Yagi 2009 Eq. 3.
- ``"dipole-better"``: d'Eon 2012, "A Better Dipole" (Grosjean D, A = (1 + 3 FM2)/(1 - 2 FM1), fluence and
  flux terms with C_phi, C_E), as in pbrt-v3 ``BeamDiffusionMS`` for a single point source.

Units: lengths in mm, coefficients in 1/mm, R(r) in 1/mm^2 (exitance per unit incident power), integrals
of R over area are dimensionless. Notation (science.md sec. 1): sigma_t' = sigma_a + sigma_s',
alpha' = sigma_s'/sigma_t', sigma_tr = sqrt(3 sigma_a sigma_t') (Jensen) or sqrt(sigma_a / D) (better),
s = sqrt(3 (1 - alpha')), z_r = 1/sigma_t'.

All functions are vectorized: every array argument broadcasts against the others with numpy's rules, so
per-channel coefficients of shape (C,) with ``radius_mm[:, None]`` of shape (N, 1) give (N, C).
The profiles are evaluated in log space (logaddexp of the two dipole terms; the better dipole's difference
of two near-equal fluence terms is factored with expm1) so nothing underflows to 0/0 or NaN at r = 1000 mm.
"""
from __future__ import annotations

from dataclasses import dataclass
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from .fresnel import boundary_A, fresnel_moment

__all__ = [
    "MODELS",
    "DipoleCoefficients",
    "check_model",
    "dipole_coefficients",
    "log_profile",
    "profile",
    "profile_from_coefficients",
    "profile_laplacian",
    "cumulative_disk",
    "tail_beyond_disk",
    "total_diffuse_reflectance",
    "total_diffuse_reflectance_albedo",
    "reduced_albedo_from_total_reflectance",
    "hankel_transform",
    "second_moment_mm2",
    "second_moment_factor_G",
    "cutoff_radius_mm",
    "diffusion_coefficient_mm",
    "reflectance_from_coefficients",
    "coefficients_from_reflectance",
    "coefficients_from_diffusion",
]

MODELS: tuple[str, ...] = ("dipole-jensen", "dipole-better")

Array = NDArray[np.float64]


def check_model(model: str) -> str:
    """Return ``model`` if it names a known profile, else raise ValueError listing the valid names."""
    if model not in MODELS:
        raise ValueError(f"unknown dipole model {model!r}; valid models: {', '.join(MODELS)}")
    return model


@dataclass(frozen=True)
class DipoleCoefficients:
    """Derived quantities of one model for broadcast (sigma_s', sigma_a, eta); lengths in mm."""

    model: str
    sigma_t_prime_per_mm: Array
    alpha_prime: Array
    sigma_tr_per_mm: Array
    z_r_mm: Array
    z_v_abs_mm: Array  # |z_v|: Jensen z_r (1 + 4A/3); better z_r + 4 A D
    A: Array
    D_mm: Array
    c_phi: Array  # better dipole only (nan for Jensen)
    c_e: Array  # better dipole only (nan for Jensen)


def _as_f64(x: ArrayLike) -> Array:
    return np.asarray(x, dtype=np.float64)


def dipole_coefficients(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: ArrayLike, *,
                        model: str = "dipole-jensen", fdr: str = "fit") -> DipoleCoefficients:
    """Compute sigma_t', alpha', sigma_tr, z_r, |z_v|, A, D (and C_phi, C_E) for ``model``.

    ``fdr`` selects Jensen's F_dr: ``"fit"`` (default: Jensen's polynomial as printed in the paper and used by
    the seed paper; the oracle values of science.md sec. 1 are computed with it; ValueError for eta < 1) or
    ``"exact"`` (2 FM1 by quadrature; valid for any eta, A(1) = 1). The better dipole always uses exact
    Fresnel moments and ignores ``fdr``.
    Raises ValueError for negative coefficients or sigma_t' = 0.
    """
    check_model(model)
    ssp = _as_f64(sigma_s_prime_per_mm)
    sa = _as_f64(sigma_a_per_mm)
    eta_arr = _as_f64(eta)
    if np.any(ssp < 0) or np.any(sa < 0) or not (np.all(np.isfinite(ssp)) and np.all(np.isfinite(sa))):
        raise ValueError("sigma_s_prime_per_mm and sigma_a_per_mm must be finite and >= 0")
    st = ssp + sa
    if np.any(st <= 0):
        raise ValueError("sigma_t' = sigma_s' + sigma_a must be > 0")
    alpha = ssp / st
    z_r = 1.0 / st
    if model == "dipole-jensen":
        A = boundary_A(eta_arr, fdr=fdr)
        D = 1.0 / (3.0 * st)
        sigma_tr = np.sqrt(3.0 * sa * st)
        z_v = z_r * (1.0 + 4.0 * A / 3.0)
        nan = np.full(np.broadcast(st, A).shape, np.nan)
        c_phi, c_e = nan, nan
    else:
        fm1 = fresnel_moment(eta_arr, 1)
        fm2 = fresnel_moment(eta_arr, 2)
        A = (1.0 + 3.0 * fm2) / (1.0 - 2.0 * fm1)
        c_phi = 0.25 * (1.0 - 2.0 * fm1)
        c_e = 0.5 * (1.0 - 3.0 * fm2)
        D = (2.0 * sa + ssp) / (3.0 * st * st)
        sigma_tr = np.sqrt(sa / D)
        z_v = z_r + 4.0 * A * D
    return DipoleCoefficients(model, st, alpha, sigma_tr, z_r, z_v, _as_f64(A), D, _as_f64(c_phi), _as_f64(c_e))


def _log_point_term(z: Array, d: Array, sigma_tr: Array) -> Array:
    """log of z (1 + sigma_tr d) e^(-sigma_tr d) / d^3 (z > 0)."""
    x = sigma_tr * d
    return np.log(z) + np.log1p(x) - x - 3.0 * np.log(d)


def _log_one_minus_ratio(z_r: Array, z_v: Array, d_r: Array, d_v: Array, sigma_tr: Array) -> Array:
    """log(1 - (d_r/d_v) e^(-sigma_tr (d_v - d_r))), stable for d_v ~ d_r (large r) via expm1."""
    dz2 = z_v * z_v - z_r * z_r  # > 0
    delta = dz2 / (d_v + d_r)
    x = -sigma_tr * delta + 0.5 * np.log1p(-dz2 / (d_v * d_v))
    return np.log(-np.expm1(x))


def log_profile(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                eta: ArrayLike, *, model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """Natural log of the diffuse reflectance profile R(r) [1/mm^2]; -inf where alpha' = 0.

    Jensen 2001 Eq. 4 (log of the sum of the real and virtual source terms by logaddexp) or d'Eon 2012
    (three positive terms by logsumexp). Finite for r up to 1e6 mm and sigma_a down to 0.

    >>> round(float(np.exp(log_profile(0.0, 2.19, 0.0021, 1.3))), 3)
    0.4
    """
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    r = _as_f64(radius_mm)
    if np.any(r < 0):
        raise ValueError("radius_mm must be >= 0")
    r2 = r * r
    d_r = np.sqrt(r2 + c.z_r_mm**2)
    d_v = np.sqrt(r2 + c.z_v_abs_mm**2)
    with np.errstate(divide="ignore"):
        t_r = _log_point_term(c.z_r_mm, d_r, c.sigma_tr_per_mm)
        t_v = _log_point_term(c.z_v_abs_mm, d_v, c.sigma_tr_per_mm)
        if c.model == "dipole-jensen":
            return np.log(c.alpha_prime / (4.0 * np.pi)) + np.logaddexp(t_r, t_v)
        log_ce = np.log(c.c_e)
        t_phi = (np.log(c.c_phi / c.D_mm) - c.sigma_tr_per_mm * d_r - np.log(d_r)
                 + _log_one_minus_ratio(c.z_r_mm, c.z_v_abs_mm, d_r, d_v, c.sigma_tr_per_mm))
        terms = np.stack(np.broadcast_arrays(log_ce + t_r, log_ce + t_v, t_phi), axis=0)
        from scipy.special import logsumexp

        return np.log(c.alpha_prime**2 / (4.0 * np.pi)) + logsumexp(terms, axis=0)


def profile_from_coefficients(coefficients: DipoleCoefficients, radius_mm: ArrayLike) -> Array:
    """R(r) [1/mm^2] evaluated directly (not in log space) from precomputed :class:`DipoleCoefficients`.

    The fast path for large pair sums (forward model, system matrices): every term is a product of finite
    factors with d >= z_r > 0, so far tails underflow to exactly 0, never to NaN. Use :func:`log_profile`
    when the logarithm itself is needed (fitting in log R).
    """
    c = coefficients
    r = _as_f64(radius_mm)
    r2 = r * r
    d_r = np.sqrt(r2 + c.z_r_mm**2)
    d_v = np.sqrt(r2 + c.z_v_abs_mm**2)
    s = c.sigma_tr_per_mm
    ex_r = np.exp(-s * d_r)
    ex_v = np.exp(-s * d_v)
    flux = (c.z_r_mm * (1.0 + s * d_r) * ex_r / (d_r * d_r * d_r)
            + c.z_v_abs_mm * (1.0 + s * d_v) * ex_v / (d_v * d_v * d_v))
    if c.model == "dipole-jensen":
        return (c.alpha_prime / (4.0 * np.pi)) * flux
    dz2 = c.z_v_abs_mm**2 - c.z_r_mm**2
    x = -s * dz2 / (d_v + d_r) + 0.5 * np.log1p(-dz2 / (d_v * d_v))
    fluence = (c.c_phi / c.D_mm) * ex_r / d_r * (-np.expm1(x))
    return (c.alpha_prime**2 / (4.0 * np.pi)) * (c.c_e * flux + fluence)


def profile_laplacian(coefficients: DipoleCoefficients, radius_mm: ArrayLike, *, step: float = 1e-3) -> Array:
    """Surface (2-D) Laplacian of the profile, R'' + R'/r = (1/r^2) d^2 R / d(ln r)^2 [1/mm^4], for r > 0.

    Central differences in ln r (relative step ``step``; truncation ~step^2). Used for the second-order patch
    average R_bar(d) = R(d) + kappa A Laplacian R(d) of a patch of area A at distance d (kappa = 1/24 for a
    square, 1/(12 sqrt 3) for an equilateral triangle, 1/(8 pi) for a disk).
    """
    r = _as_f64(radius_mm)
    if np.any(r <= 0):
        raise ValueError("radius_mm must be > 0 for the Laplacian")
    up = profile_from_coefficients(coefficients, r * np.exp(step))
    mid = profile_from_coefficients(coefficients, r)
    dn = profile_from_coefficients(coefficients, r * np.exp(-step))
    return (up - 2.0 * mid + dn) / (step * step * r * r)


def profile(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: ArrayLike,
            *, model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """Diffuse reflectance profile R(r) [1/mm^2] = exp(:func:`log_profile`) (underflows to 0, never NaN)."""
    return np.exp(log_profile(radius_mm, sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr))


def _phi1(y: Array) -> Array:
    """(1 - e^(-y)) / y with the limit 1 at y = 0."""
    y = _as_f64(y)
    small = np.abs(y) < 1e-8
    ys = np.where(small, 1.0, y)
    return np.where(small, 1.0 - 0.5 * y, -np.expm1(-ys) / ys)


def _exp_diff_over_sigma(a: Array, b: Array, sigma: Array) -> Array:
    """(e^(-sigma a) - e^(-sigma b)) / sigma for b >= a >= 0, limit (b - a) at sigma = 0."""
    return np.exp(-sigma * a) * (b - a) * _phi1(sigma * (b - a))


def _one_minus_ratio_exp(z: Array, rho: Array, sigma: Array) -> Array:
    """e^(-sigma z) - z e^(-sigma d)/d with d = sqrt(rho^2 + z^2), stable for rho << z (expm1)."""
    d = np.sqrt(rho * rho + z * z)
    x = -sigma * (rho * rho / (d + z)) - 0.5 * np.log1p((rho / z) ** 2)
    return np.exp(-sigma * z) * (-np.expm1(x))


def _tail_terms(c: DipoleCoefficients, rho: Array) -> Array:
    """int_rho^inf R 2 pi r dr (closed form; no cancellation)."""
    d_r = np.sqrt(rho * rho + c.z_r_mm**2)
    d_v = np.sqrt(rho * rho + c.z_v_abs_mm**2)
    s = c.sigma_tr_per_mm
    if c.model == "dipole-jensen":
        return 0.5 * c.alpha_prime * (c.z_r_mm * np.exp(-s * d_r) / d_r + c.z_v_abs_mm * np.exp(-s * d_v) / d_v)
    e_part = c.c_e * (c.z_r_mm * np.exp(-s * d_r) / d_r + c.z_v_abs_mm * np.exp(-s * d_v) / d_v)
    phi_part = (c.c_phi / c.D_mm) * _exp_diff_over_sigma(d_r, d_v, s)
    return 0.5 * c.alpha_prime**2 * (e_part + phi_part)


def _total(c: DipoleCoefficients) -> Array:
    s = c.sigma_tr_per_mm
    e_r = np.exp(-s * c.z_r_mm)
    e_v = np.exp(-s * c.z_v_abs_mm)
    if c.model == "dipole-jensen":
        return 0.5 * c.alpha_prime * (e_r + e_v)
    return 0.5 * c.alpha_prime**2 * (c.c_e * (e_r + e_v)
                                      + (c.c_phi / c.D_mm) * _exp_diff_over_sigma(c.z_r_mm, c.z_v_abs_mm, s))


def cumulative_disk(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                    eta: ArrayLike, *, model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """Exact disk integral int_0^rho R(r) 2 pi r dr (dimensionless) — self-patch and bin integrals.

    Jensen: (alpha'/2) [e^(-sigma_tr z_r) - z_r e^(-sigma_tr d_r)/d_r + (same for z_v)], d = sqrt(rho^2+z^2),
    each bracket in a cancellation-free expm1 form for rho << z. Better dipole: the analogous closed form
    (flux terms as above; fluence terms (e^(-sigma a) - e^(-sigma b))/sigma).
    Tends to :func:`total_diffuse_reflectance` as rho -> inf.

    >>> round(float(cumulative_disk(2.0, 2.19, 0.0021, 1.3, fdr="fit")), 6)
    0.524326
    """
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    rho = _as_f64(radius_mm)
    if np.any(rho < 0):
        raise ValueError("radius_mm must be >= 0")
    s = c.sigma_tr_per_mm
    if c.model == "dipole-jensen":
        return 0.5 * c.alpha_prime * (_one_minus_ratio_exp(c.z_r_mm, rho, s)
                                      + _one_minus_ratio_exp(c.z_v_abs_mm, rho, s))
    d_r = np.sqrt(rho * rho + c.z_r_mm**2)
    d_v = np.sqrt(rho * rho + c.z_v_abs_mm**2)
    e_part = c.c_e * (_one_minus_ratio_exp(c.z_r_mm, rho, s) + _one_minus_ratio_exp(c.z_v_abs_mm, rho, s))
    # (e^-s z_r - e^-s d_r - e^-s z_v + e^-s d_v)/s = g(z_r, z_v) - e^(-s d_r) g'(d_r -> d_v)
    phi_part = (_exp_diff_over_sigma(c.z_r_mm, c.z_v_abs_mm, s) - _exp_diff_over_sigma(d_r, d_v, s))
    return 0.5 * c.alpha_prime**2 * (e_part + (c.c_phi / c.D_mm) * phi_part)


def tail_beyond_disk(radius_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                     eta: ArrayLike, *, model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """int_rho^inf R(r) 2 pi r dr = total - cumulative, from its own closed form (no cancellation)."""
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    return _tail_terms(c, _as_f64(radius_mm))


def total_diffuse_reflectance(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: ArrayLike, *,
                              model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """Total diffuse reflectance R_d = int_0^inf R(r) 2 pi r dr (a function of alpha' and eta only)."""
    return _total(dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr))


def total_diffuse_reflectance_albedo(alpha_prime: ArrayLike, A: ArrayLike) -> Array:
    """Jensen 2001 Eq. 11: R_d(alpha') = (alpha'/2)(1 + e^(-(4/3) A sqrt(3(1-alpha')))) e^(-sqrt(3(1-alpha')))."""
    a = _as_f64(alpha_prime)
    s = np.sqrt(3.0 * np.clip(1.0 - a, 0.0, None))
    return 0.5 * a * (1.0 + np.exp(-4.0 / 3.0 * _as_f64(A) * s)) * np.exp(-s)


def _total_of_s(s: Array, eta: ArrayLike, model: str, fdr: str) -> Array:
    """R_d as a function of s = sqrt(3(1 - alpha')) (sigma_t' = 1; R_d is scale-free)."""
    s = _as_f64(s)
    sa = s * s / 3.0
    return total_diffuse_reflectance(np.clip(1.0 - sa, 0.0, None), sa, eta, model=model, fdr=fdr)


def _s_from_total(R_d: ArrayLike, eta: ArrayLike, model: str, fdr: str, out_of_range: str) -> Array:
    r = _as_f64(R_d)
    eta_b = _as_f64(eta)
    r, eta_b = np.broadcast_arrays(r, eta_b)
    bad = (r < -1e-12) | (r > 1.0 + 1e-12)
    if np.any(bad):
        if out_of_range == "raise":
            raise ValueError("R_d must lie in [0, 1] (use out_of_range='clip' or 'nan')")
        if out_of_range not in ("clip", "nan"):
            raise ValueError("out_of_range must be one of ('raise', 'clip', 'nan')")
    rc = np.clip(r, 0.0, 1.0)
    s_max = np.sqrt(3.0)
    out = np.empty(r.shape)
    flat_r = rc.ravel()
    flat_eta = eta_b.ravel()
    flat_out = out.reshape(-1)
    finite = np.isfinite(flat_r)
    if flat_r.size <= 4096:
        for i, (ri, ei) in enumerate(zip(flat_r, flat_eta)):
            if not finite[i]:
                flat_out[i] = np.nan
            elif ri >= 1.0:
                flat_out[i] = 0.0
            elif ri <= 0.0:
                flat_out[i] = s_max
            else:
                flat_out[i] = optimize.brentq(lambda s: float(_total_of_s(s, ei, model, fdr)) - ri, 0.0, s_max,
                                              xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=200)
    else:  # large maps: vectorized bisection to full double precision (R_d(s) is strictly decreasing)
        lo = np.zeros_like(flat_r)
        hi = np.full_like(flat_r, s_max)
        for _ in range(64):
            mid = 0.5 * (lo + hi)
            above = _total_of_s(mid, flat_eta, model, fdr) > flat_r
            lo = np.where(above, mid, lo)
            hi = np.where(above, hi, mid)
        flat_out[:] = np.where(finite, 0.5 * (lo + hi), np.nan)
    if out_of_range == "nan":
        out = np.where(bad, np.nan, out)
    return out


def reduced_albedo_from_total_reflectance(R_d: ArrayLike, eta: ArrayLike, *, model: str = "dipole-jensen",
                                          fdr: str = "fit", out_of_range: str = "raise") -> Array:
    """Invert R_d(alpha') for the reduced albedo alpha' (science.md sec. 1).

    Solved for s = sqrt(3(1 - alpha')) in [0, sqrt 3] by Brent's method (R_d(s) is strictly decreasing from
    1 to 0, no square-root singularity at alpha' -> 1); alpha' = 1 - s^2/3. For more than 4096 values a
    vectorized bisection to double precision is used instead. ``out_of_range``: "raise" (default), "clip",
    or "nan" for R_d outside [0, 1].

    >>> round(float(reduced_albedo_from_total_reflectance(0.5, 1.3)), 4)
    0.9726
    """
    check_model(model)
    s = _s_from_total(R_d, eta, model, fdr, out_of_range)
    return 1.0 - s * s / 3.0


def hankel_transform(k_per_mm: ArrayLike, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                     eta: ArrayLike, *, model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """2-D Fourier (zeroth-order Hankel) transform R^(k) = int R(r) J0(k r) 2 pi r dr (the MTF times R_d).

    Jensen: (alpha'/2) [e^(-z_r s_k) + e^(-z_v s_k)], s_k = sqrt(sigma_tr^2 + k^2) (k in rad/mm).
    Better dipole: (alpha'^2/2) [C_E (e^(-z_r s_k) + e^(-|z_v| s_k)) + (C_phi/D)(e^(-z_r s_k) - e^(-|z_v| s_k))/s_k].
    """
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    k = _as_f64(k_per_mm)
    sk = np.sqrt(c.sigma_tr_per_mm**2 + k * k)
    e_r = np.exp(-sk * c.z_r_mm)
    e_v = np.exp(-sk * c.z_v_abs_mm)
    if c.model == "dipole-jensen":
        return 0.5 * c.alpha_prime * (e_r + e_v)
    return 0.5 * c.alpha_prime**2 * (c.c_e * (e_r + e_v)
                                      + (c.c_phi / c.D_mm) * _exp_diff_over_sigma(c.z_r_mm, c.z_v_abs_mm, sk))


_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)


def second_moment_mm2(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: ArrayLike, *,
                      model: str = "dipole-jensen", fdr: str = "fit") -> Array:
    """Normalized second moment <r^2> = int r^2 R dA / int R dA [mm^2] = -4 R^'(k^2 = 0) / R^(0).

    Jensen: 2 (z_r e_r + z_v e_v) / (sigma_tr (e_r + e_v)), e = e^(-sigma_tr z). Infinite when sigma_a = 0.
    """
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    s = c.sigma_tr_per_mm
    e_r = np.exp(-s * c.z_r_mm)
    e_v = np.exp(-s * c.z_v_abs_mm)
    flux = c.z_r_mm * e_r + c.z_v_abs_mm * e_v
    with np.errstate(divide="ignore", invalid="ignore"):
        if c.model == "dipole-jensen":
            m = 2.0 * flux / (s * (e_r + e_v))
        else:
            # int_{z_r}^{|z_v|} t e^(-s t) dt by Gauss-Legendre (smooth; avoids 1/s^2 cancellation)
            a, b = np.broadcast_arrays(c.z_r_mm, c.z_v_abs_mm)
            half = 0.5 * (b - a)[..., None]
            t = 0.5 * (a + b)[..., None] + half * _GL_X
            s_b = np.broadcast_to(s, a.shape)[..., None]
            i1 = np.sum(_GL_W * t * np.exp(-s_b * t), axis=-1) * half[..., 0]
            num = 0.5 * c.alpha_prime**2 * (c.c_e * flux + (c.c_phi / c.D_mm) * i1)
            m = (2.0 / s) * num / _total(c)
    return np.where(s > 0, m, np.inf)


def second_moment_factor_G(alpha_prime: ArrayLike, A: ArrayLike) -> Array:
    """G(alpha', A) with <r^2> = l'^2 G, l' = 1/sigma_t' (Jensen dipole; science.md sec. 4).

    G = 2 (e_r + (1 + 4A/3) e_v) / (s (e_r + e_v)), s = sqrt(3(1 - alpha')), e_r = e^(-s), e_v = e^(-s(1+4A/3)).
    """
    a = _as_f64(alpha_prime)
    A_arr = _as_f64(A)
    s = np.sqrt(3.0 * np.clip(1.0 - a, 0.0, None))
    k = 1.0 + 4.0 * A_arr / 3.0
    e_r = np.exp(-s)
    e_v = np.exp(-s * k)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * (e_r + k * e_v) / (s * (e_r + e_v))
    return np.where(s > 0, g, np.inf)


def cutoff_radius_mm(tolerance: float, sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike,
                     eta: ArrayLike, *, model: str = "dipole-jensen", fdr: str = "fit",
                     max_radius_mm: float = 1e7) -> float:
    """Smallest radius beyond which the profile carries less than ``tolerance`` of R_d (max over channels).

    Solves tail(rho)/R_d = tolerance (closed-form tail, Brent in log rho). Returns ``max_radius_mm`` if even
    that radius leaves more than ``tolerance`` in the tail (sigma_a -> 0: the tail decays like 1/rho).
    """
    if not 0.0 < tolerance < 1.0:
        raise ValueError("tolerance must lie in (0, 1)")
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    total = np.ravel(_total(c))
    shape = np.broadcast(c.sigma_t_prime_per_mm, c.A).shape
    fields = [np.ravel(np.broadcast_to(getattr(c, f), shape)) for f in
              ("sigma_t_prime_per_mm", "alpha_prime", "sigma_tr_per_mm", "z_r_mm", "z_v_abs_mm", "A", "D_mm",
               "c_phi", "c_e")]
    best = 0.0
    log_tol = np.log(tolerance)
    for i in range(total.size):
        if not total[i] > 0:
            continue
        ci = DipoleCoefficients(c.model, *[f[i] for f in fields])

        def f(log_rho: float, ci: DipoleCoefficients = ci, tot: float = float(total[i])) -> float:
            t = float(_tail_terms(ci, np.exp(log_rho)))
            return (np.log(t) if t > 0 else -1e3) - np.log(tot) - log_tol

        lo, hi = np.log(1e-9), np.log(max_radius_mm)
        if f(hi) > 0:
            return float(max_radius_mm)
        if f(lo) < 0:
            continue
        best = max(best, float(np.exp(optimize.brentq(f, lo, hi, xtol=1e-6))))
    return best


def diffusion_coefficient_mm(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, *,
                             model: str = "dipole-jensen") -> Array:
    """Diffusion coefficient D [mm]: 1/(3 sigma_t') (Jensen) or (2 sigma_a + sigma_s')/(3 sigma_t'^2) (d'Eon)."""
    check_model(model)
    ssp = _as_f64(sigma_s_prime_per_mm)
    sa = _as_f64(sigma_a_per_mm)
    st = ssp + sa
    if model == "dipole-jensen":
        return 1.0 / (3.0 * st)
    return (2.0 * sa + ssp) / (3.0 * st * st)


def reflectance_from_coefficients(sigma_s_prime_per_mm: ArrayLike, sigma_a_per_mm: ArrayLike, eta: ArrayLike, *,
                                  model: str = "dipole-jensen", fdr: str = "fit") -> tuple[Array, Array, Array]:
    """(sigma_s', sigma_a) -> (R_d, l_d_mm = 1/sigma_tr (inf if sigma_a = 0), D_mm)."""
    c = dipole_coefficients(sigma_s_prime_per_mm, sigma_a_per_mm, eta, model=model, fdr=fdr)
    with np.errstate(divide="ignore"):
        l_d = np.where(c.sigma_tr_per_mm > 0, 1.0 / np.where(c.sigma_tr_per_mm > 0, c.sigma_tr_per_mm, 1.0), np.inf)
    return _total(c), l_d, c.D_mm


def _sigma_tr_over_sigma_t(s: Array, model: str) -> Array:
    if model == "dipole-jensen":
        return s
    return s / np.sqrt(1.0 + s * s / 3.0)


def _d_over_l(s: Array, model: str) -> Array:
    """D * sigma_t' as a function of s."""
    if model == "dipole-jensen":
        return np.full_like(s, 1.0 / 3.0)
    return (1.0 + s * s / 3.0) / 3.0


def _from_s_and_sigma_t(s: Array, st: Array) -> tuple[Array, Array]:
    return (1.0 - s * s / 3.0) * st, (s * s / 3.0) * st


def coefficients_from_reflectance(R_d: ArrayLike, l_d_mm: ArrayLike, eta: ArrayLike, *,
                                  model: str = "dipole-jensen", fdr: str = "fit",
                                  out_of_range: str = "raise") -> tuple[Array, Array]:
    """(R_d, diffuse mean free path l_d = 1/sigma_tr [mm]) -> (sigma_s'_per_mm, sigma_a_per_mm).

    alpha' from R_d (Brent in s), then sigma_t' = 1/(l_d * sigma_tr/sigma_t') with sigma_tr/sigma_t' = s
    (Jensen; s/sqrt(1 + s^2/3) for the better dipole). R_d = 1 forces sigma_a = 0; then sigma_t' is
    undetermined by l_d (= inf) and sigma_s' is returned as inf.
    """
    check_model(model)
    s = _s_from_total(R_d, eta, model, fdr, out_of_range)
    ld = _as_f64(l_d_mm)
    with np.errstate(divide="ignore"):
        st = 1.0 / (ld * _sigma_tr_over_sigma_t(s, model))
    return _from_s_and_sigma_t(s, st)


def coefficients_from_diffusion(R_d: ArrayLike, D_mm: ArrayLike, eta: ArrayLike, *,
                                model: str = "dipole-jensen", fdr: str = "fit",
                                out_of_range: str = "raise") -> tuple[Array, Array]:
    """(R_d, D [mm]) -> (sigma_s'_per_mm, sigma_a_per_mm); Jensen sigma_t' = 1/(3 D)."""
    check_model(model)
    s = _s_from_total(R_d, eta, model, fdr, out_of_range)
    st = _d_over_l(s, model) / _as_f64(D_mm)
    return _from_s_and_sigma_t(s, st)

