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
  twice (second pass at the refined normal). The output ``diffuse_vectors`` = (tau1/tau0) n~ is the
  *ideal-equivalent* gradient vector: exactly (tau1/tau0) n for a flat surface, and (tau1/tau0) times the
  profile-weighted mean normal for a translucent curved one — the quantity ``estimation.diffusion`` needs.
  Because the model is affine in n, averaging over a blur footprint commutes with it (to second order in the
  footprint's normal spread relative to the LUT smoothing), so the |v| bias from discreteness is removed.

Albedo convention (``docs/gradients.md``): ``albedo`` is the dipole's total diffuse reflectance R_d, defined by
    I_full = F_t(eta, n.v) * E_full(n) / E_full(n_ref) * R_d / albedo_scale
i.e. ``albedo_scale`` (per channel) converts the ambient-subtracted cross-polarized full-on value of a surface
at the rig origin facing ``reference_normal`` and viewed head-on (exit Fresnel divided out) to R_d.
See :func:`albedo_scale_from_lambertian` and :func:`albedo_scale_from_radiometry`.

References: Ma, Hawkins, Peers, Chabert, Weiss, Debevec 2007, "Rapid acquisition of specular and diffuse normal
maps from polarized spherical gradient illumination" (EGSR); Jensen et al. 2001 (F_t, R_d); science.md sec. 3.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .fresnel import fresnel_moment, fresnel_transmittance

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
]

Array = NDArray[np.float64]

PATTERNS: tuple[str, ...] = ("ambient", "full", "x", "y", "z", "x_c", "y_c", "z_c")
GRADIENT_PATTERNS: tuple[str, ...] = ("full", "x", "y", "z", "x_c", "y_c", "z_c")
POLARIZATIONS: tuple[str, ...] = ("cross", "parallel")
_AXES = ("x", "y", "z")
_DEFAULT_VIEW = (0.0, -1.0, 0.0)  # rig frame: camera on the -y side looking along +y


# --------------------------------------------------------------------------------------------------------------
# keys
# --------------------------------------------------------------------------------------------------------------
def _polarization_name(pol: Any) -> str:
    name = getattr(pol, "name", pol)  # accepts drivers.contracts.Polarization without importing it
    name = str(name).lower()
    if name not in POLARIZATIONS:
        raise ValueError(f"unknown polarization {pol!r}; valid: {', '.join(POLARIZATIONS)}")
    return name


def frame_key(key: Any) -> tuple[str, str]:
    """Normalize a frame key to ``(pattern, polarization)``.

    Accepted: ``"x"`` (cross-polarized), ``("x", "cross")``, ``("x", "parallel")``; the polarization may also
    be any enum whose ``name`` is CROSS / PARALLEL (``drivers.contracts.Polarization``).

    >>> frame_key("x_c"), frame_key(("full", "parallel"))
    (('x_c', 'cross'), ('full', 'parallel'))
    """
    if isinstance(key, str):
        pattern, pol = key, "cross"
    else:
        try:
            pattern, pol = key
        except (TypeError, ValueError):
            raise ValueError(f"frame key must be a pattern name or (pattern, polarization), got {key!r}") from None
    pattern = str(pattern)
    if pattern not in PATTERNS:
        raise ValueError(f"unknown pattern {pattern!r}; valid: {', '.join(PATTERNS)}")
    return pattern, _polarization_name(pol)


# --------------------------------------------------------------------------------------------------------------
# continuous (ideal) response
# --------------------------------------------------------------------------------------------------------------
def tau_ratio(eta: float) -> float:
    """tau1/tau0 = int F_t mu^2 dmu / int F_t mu dmu: |v| of a flat Fresnel-Lambertian surface (0.685 at 1.3).

    F_t is the unpolarized transmittance from outside (``fresnel.fresnel_moment(side="external")``).

    >>> round(tau_ratio(1.3), 3), round(tau_ratio(1.0), 4)
    (0.685, 0.6667)
    """
    t0 = 0.5 - float(fresnel_moment(eta, 1, side="external"))
    t1 = 1.0 / 3.0 - float(fresnel_moment(eta, 2, side="external"))
    return t1 / t0


def _kernel_table(eta: float, n: int = 4097) -> tuple[Array, Array]:
    """K(t) = F_t(eta, t) t on a uniform grid of t in [0, 1] (the Fresnel-Lambertian irradiance kernel)."""
    t = np.linspace(0.0, 1.0, n)
    return t, fresnel_transmittance(eta, t) * t


def _kernel(cos: Array, kt: tuple[Array, Array]) -> Array:
    """K(max(cos, 0)) by linear interpolation on the uniform table (much faster than np.interp)."""
    table = kt[1]
    n = table.size - 1
    x = np.clip(cos, 0.0, 1.0) * n
    i = np.minimum(x.astype(np.intp), n - 1)
    f = x - i
    return table[i] * (1.0 - f) + table[i + 1] * f


# --------------------------------------------------------------------------------------------------------------
# octahedral normal-space parameterization
# --------------------------------------------------------------------------------------------------------------
def _sign_nz(a: Array) -> Array:
    return np.where(a >= 0.0, 1.0, -1.0)


def oct_encode(n: ArrayLike) -> Array:
    """Unit vectors (..., 3) -> octahedral coordinates (..., 2) in [-1, 1]^2 (continuous surjection inverse)."""
    v = np.asarray(n, dtype=np.float64)
    p = v / np.sum(np.abs(v), axis=-1, keepdims=True)
    u, w, z = p[..., 0], p[..., 1], p[..., 2]
    lower = z < 0
    uu = np.where(lower, (1.0 - np.abs(w)) * _sign_nz(u), u)
    ww = np.where(lower, (1.0 - np.abs(u)) * _sign_nz(w), w)
    return np.stack([uu, ww], axis=-1)


def oct_decode(uv: ArrayLike) -> Array:
    """Octahedral coordinates (..., 2) -> unit vectors (..., 3)."""
    q = np.asarray(uv, dtype=np.float64)
    u, w = q[..., 0], q[..., 1]
    z = 1.0 - np.abs(u) - np.abs(w)
    lower = z < 0
    x = np.where(lower, (1.0 - np.abs(w)) * _sign_nz(u), u)
    y = np.where(lower, (1.0 - np.abs(u)) * _sign_nz(w), w)
    v = np.stack([x, y, z], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------------------------------------------
# LED description and response lookup table
# --------------------------------------------------------------------------------------------------------------
def _default_pattern(name: str, directions: Array) -> Array:
    if name == "full":
        return np.ones(directions.shape[0])
    axis = _AXES.index(name[0])
    w = directions[:, axis]
    return 0.5 * (1.0 - w) if name.endswith("_c") else 0.5 * (1.0 + w)


@dataclass(frozen=True)
class LedRig:
    """Calibrated LED sphere as seen from the rig origin.

    ``directions`` (N, 3): unit vectors from the origin towards each LED (normalized here).
    ``gains`` (N, 3): per-channel irradiance at the origin on a surface facing the LED, at full drive
    (calibrated intensity x solid angle, or I / d^2 for a point LED).
    ``distances_mm`` (N,) or None: LED distance from the origin; enables the near-field model (1/d^2 and the
    direction change across the object; see :func:`build_response_lut`). None = distant LEDs.
    ``patterns``: {pattern name: (N,) or (N, 3) drive values in [0, 1] actually displayed}; missing patterns
    default to the ideal values full = 1, x = (w_x + 1)/2, x_c = (1 - w_x)/2, ...
    """

    directions: Array
    gains: Array
    distances_mm: Array | None = None
    patterns: Mapping[str, ArrayLike] | None = None

    def __post_init__(self) -> None:
        d = np.asarray(self.directions, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] == 0:
            raise ValueError("directions must be (N, 3) with N >= 1")
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(~np.isfinite(norm)) or np.any(norm <= 0):
            raise ValueError("directions must be finite and non-zero")
        g = np.asarray(self.gains, dtype=np.float64)
        if g.ndim == 1:
            g = np.repeat(g[:, None], 3, axis=1)
        if g.shape != (d.shape[0], 3) or np.any(~np.isfinite(g)) or np.any(g < 0):
            raise ValueError("gains must be finite, >= 0, shape (N, 3) (or (N,) for grey)")
        object.__setattr__(self, "directions", d / norm)
        object.__setattr__(self, "gains", g)
        if self.distances_mm is not None:
            r = np.asarray(self.distances_mm, dtype=np.float64).reshape(-1)
            if r.shape != (d.shape[0],) or np.any(~(r > 0)):
                raise ValueError("distances_mm must be (N,) and > 0")
            object.__setattr__(self, "distances_mm", r)
        pats: dict[str, Array] = {}
        for name, val in dict(self.patterns or {}).items():
            if name not in GRADIENT_PATTERNS:
                raise ValueError(f"unknown pattern {name!r}; valid: {', '.join(GRADIENT_PATTERNS)}")
            p = np.asarray(val, dtype=np.float64)
            if p.ndim == 1:
                p = np.repeat(p[:, None], 3, axis=1)
            if p.shape != (d.shape[0], 3) or np.any(~np.isfinite(p)) or np.any(p < 0):
                raise ValueError(f"pattern {name!r} must be (N,) or (N, 3), finite, >= 0")
            pats[name] = p
        object.__setattr__(self, "patterns", pats)

    @classmethod
    def from_positions(cls, positions_mm: ArrayLike, intensities: ArrayLike, *,
                       patterns: Mapping[str, ArrayLike] | None = None) -> "LedRig":
        """Point LEDs at ``positions_mm`` (N, 3) with radiant intensity ``intensities`` (N, 3): g = I / |p|^2."""
        p = np.asarray(positions_mm, dtype=np.float64)
        r = np.linalg.norm(p, axis=1)
        inten = np.asarray(intensities, dtype=np.float64)
        if inten.ndim == 1:
            inten = np.repeat(inten[:, None], 3, axis=1)
        return cls(p, inten / (r * r)[:, None], r, patterns)

    @property
    def count(self) -> int:
        return int(self.directions.shape[0])

    def pattern_values(self, name: str) -> Array:
        """Drive values (N, 3) of ``name`` (explicit if given, else the ideal gradient)."""
        if name not in GRADIENT_PATTERNS:
            raise ValueError(f"unknown pattern {name!r}; valid: {', '.join(GRADIENT_PATTERNS)}")
        assert isinstance(self.patterns, dict)
        if name in self.patterns:
            return self.patterns[name]
        return np.repeat(_default_pattern(name, self.directions)[:, None], 3, axis=1)

    def spacing_rad(self) -> float:
        """Mean angular LED spacing sqrt(4 pi / N) over the covered part of the sphere (a scale, not exact)."""
        return float(np.sqrt(4.0 * np.pi / self.count))


def _tangent_frames(n: Array) -> tuple[Array, Array]:
    a = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)


def _stencil(sigma: float) -> tuple[Array, Array, Array]:
    """Polar angles, azimuths and weights of a Gaussian-weighted cap quadrature (rings out to 2 sigma)."""
    thetas, phis, weights = [0.0], [0.0], [1.0]
    step = 0.5 * sigma
    for k in range(1, 5):
        th = k * step
        m = max(6, int(round(2 * np.pi * np.sin(th) / step)))
        ring_w = np.exp(-0.5 * (th / sigma) ** 2) * np.sin(th) * step * (2 * np.pi / m) / (step * step * np.pi / 4)
        for i in range(m):
            thetas.append(th)
            phis.append(2 * np.pi * (i + 0.5 * (k % 2)) / m)
            weights.append(ring_w)
    w = np.asarray(weights)
    return np.asarray(thetas), np.asarray(phis), w / w.sum()


@dataclass(frozen=True)
class ResponseLUT:
    """Local affine response model of an LED sphere over normal space (see :func:`build_response_lut`).

    ``coeffs`` (size, size, P, 3, 4): for pattern p and channel c, [a, b_x, b_y, b_z] with
    E_p,c(n) ~ a + b.n near the node, in units of E_full,c(reference_normal) (so a_full ~ 1).
    """

    size: int
    patterns: tuple[str, ...]
    coeffs: Array
    reference_full: Array  # (3,) E_full,c(reference_normal) at the origin, in LED gain units
    smoothing_rad: float
    eta: float
    fit_residual: Array  # (size, size, P, 3) RMS relative misfit of the affine model over the cap
    provenance: dict[str, Any] = field(default_factory=dict)

    def affine(self, normals: ArrayLike) -> Array:
        """Bilinearly interpolated coefficients (M, P, 3, 4) at unit ``normals`` (M, 3)."""
        uv = oct_encode(np.asarray(normals, dtype=np.float64))
        g = (np.clip(uv, -1.0, 1.0) + 1.0) * 0.5 * (self.size - 1)
        i0 = np.clip(np.floor(g).astype(np.intp), 0, self.size - 2)
        f = g - i0
        fu, fv = f[:, 0, None, None, None], f[:, 1, None, None, None]
        c = self.coeffs
        a = c[i0[:, 0], i0[:, 1]]
        b = c[i0[:, 0] + 1, i0[:, 1]]
        cc = c[i0[:, 0], i0[:, 1] + 1]
        d = c[i0[:, 0] + 1, i0[:, 1] + 1]
        return (1 - fu) * (1 - fv) * a + fu * (1 - fv) * b + (1 - fu) * fv * cc + fu * fv * d


def _led_response(normals: Array, leds: LedRig, weights: Array, kt: tuple[Array, Array],
                  center: Array, radius: float) -> Array:
    """E (M, P*3) = sum_j K(cos_j(n)) * falloff_j(n) * weights[j] for unit normals (M, 3)."""
    out = np.empty((normals.shape[0], weights.shape[1]))
    w = leds.directions
    for s in range(0, normals.shape[0], 2048):
        n = normals[s:s + 2048]
        if leds.distances_mm is None:
            cos = n @ w.T
            fall = 1.0
        else:
            x = center[None, :] + radius * n  # surface point model x(n) = c + r n
            p = leds.distances_mm[:, None] * w  # (N, 3)
            vec = p[None, :, :] - x[:, None, :]
            dist2 = np.einsum("mjk,mjk->mj", vec, vec)
            cos = np.einsum("mjk,mk->mj", vec, n) / np.sqrt(dist2)
            fall = (leds.distances_mm ** 2)[None, :] / dist2
        k = _kernel(cos, kt)
        out[s:s + 2048] = (k * fall) @ weights
    return out


def build_response_lut(leds: LedRig, *, eta: float = 1.3, size: int = 65, smoothing_rad: float | None = None,
                       reference_normal: ArrayLike = _DEFAULT_VIEW,
                       surface_center_mm: ArrayLike = (0.0, 0.0, 0.0),
                       surface_radius_mm: float = 0.0) -> ResponseLUT:
    """Tabulate the local affine response a_P(n0) + b_P(n0).n of ``leds`` on a size x size octahedral grid.

    At each node n0 the discrete response E_P,c(n) is sampled on a cap quadrature (rings to 2 sigma,
    sigma = ``smoothing_rad``, default max(0.08, half the LED spacing sqrt(4 pi/N))) and fitted by Gaussian-weighted
    least squares. For ideal continuous gradients the fit is exact (a = tau0/2, b = tau1/2 e_i); for discrete
    LEDs it removes the low-order bias (uneven gains, missing LEDs, quantized patterns) and averages the
    LED-scale ripple, which a blur footprint also averages.

    Near field (``leds.distances_mm`` given): the surface point with normal n is modelled as
    x(n) = ``surface_center_mm`` + ``surface_radius_mm`` n (exact for a sphere; for other shapes pass a rough
    centre and size — the effect is of relative order 2 |x| / R_led). The reference E_full(reference_normal)
    is always taken at the origin.
    """
    if size < 5:
        raise ValueError("size must be >= 5")
    sigma = float(smoothing_rad) if smoothing_rad is not None else max(0.08, 0.5 * leds.spacing_rad())
    if not 0.01 <= sigma <= 0.6:
        raise ValueError("smoothing_rad must lie in [0.01, 0.6] rad")
    pats = tuple(p for p in GRADIENT_PATTERNS)
    wts = np.concatenate([leds.gains * leds.pattern_values(p) for p in pats], axis=1)  # (N, P*3)
    kt = _kernel_table(eta)
    center = np.asarray(surface_center_mm, dtype=np.float64).reshape(3)
    nref = np.asarray(reference_normal, dtype=np.float64).reshape(1, 3)
    nref = nref / np.linalg.norm(nref)
    far = LedRig(leds.directions, leds.gains, None, leds.patterns)
    ref = _led_response(nref, far, leds.gains * leds.pattern_values("full"), kt, center * 0, 0.0)[0]
    if np.any(ref <= 0):
        raise ValueError("no LED lights a surface facing reference_normal: cannot normalize")
    g = np.linspace(-1.0, 1.0, size)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    nodes = oct_decode(np.stack([uu, vv], axis=-1).reshape(-1, 2))
    th, ph, qw = _stencil(sigma)
    e1, e2 = _tangent_frames(nodes)
    coeffs = np.empty((nodes.shape[0], len(pats), 3, 4))
    resid = np.empty((nodes.shape[0], len(pats), 3))
    sw = np.sqrt(qw)
    for s in range(0, nodes.shape[0], 64):
        n0, a1, a2 = nodes[s:s + 64], e1[s:s + 64], e2[s:s + 64]
        q = (np.cos(th)[None, :, None] * n0[:, None, :]
             + (np.sin(th) * np.cos(ph))[None, :, None] * a1[:, None, :]
             + (np.sin(th) * np.sin(ph))[None, :, None] * a2[:, None, :])  # (m, Q, 3)
        m, nq = q.shape[:2]
        e = _led_response(q.reshape(-1, 3), leds, wts, kt, center, float(surface_radius_mm))
        e = e.reshape(m, nq, len(pats), 3) / ref[None, None, None, :]
        # weighted LS in a local frame (1, n.n0 - c0, n.e1, n.e2) for conditioning, then mapped back
        c0 = float(np.sum(qw * np.cos(th)))
        X = np.stack([np.ones_like(th), np.cos(th) - c0, np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph)], 1)
        Xw = X * sw[:, None]
        pinv = np.linalg.pinv(Xw)  # (4, Q): same stencil at every node
        y = e * sw[None, :, None, None]
        beta = np.einsum("kq,mqpc->mpck", pinv, y)  # local coefficients
        fit = np.einsum("qk,mpck->mqpc", X, beta)
        rms = np.sqrt(np.einsum("q,mqpc->mpc", qw, (fit - e) ** 2))
        scale = np.sqrt(np.einsum("q,mqpc->mpc", qw, e * e))
        resid[s:s + m] = np.where(scale > 0, rms / np.where(scale > 0, scale, 1.0), 0.0)
        # a + b.n with b = b0 n0 + b1 e1 + b2 e2 and a = beta0 - b0 c0
        b = (beta[..., 1, None] * n0[:, None, None, :] + beta[..., 2, None] * a1[:, None, None, :]
             + beta[..., 3, None] * a2[:, None, None, :])
        a = beta[..., 0] - beta[..., 1] * c0
        coeffs[s:s + m, ..., 0] = a
        coeffs[s:s + m, ..., 1:] = b
    prov = {"led_count": leds.count, "near_field": leds.distances_mm is not None,
            "surface_center_mm": center.tolist(), "surface_radius_mm": float(surface_radius_mm),
            "reference_normal": nref[0].tolist(), "max_fit_residual": float(resid.max())}
    return ResponseLUT(size, pats, coeffs.reshape(size, size, len(pats), 3, 4), ref, sigma, float(eta),
                       resid.reshape(size, size, len(pats), 3), prov)


# --------------------------------------------------------------------------------------------------------------
# albedo calibration helpers
# --------------------------------------------------------------------------------------------------------------
def _full_transmitted_over_plain(eta: float, leds: LedRig | None, reference_normal: ArrayLike) -> Array:
    """E_t / E (Fresnel-transmitted over plain irradiance) of the full pattern at the reference normal."""
    if leds is None:
        t0 = 0.5 - float(fresnel_moment(eta, 1, side="external"))
        return np.full(3, 2.0 * t0)  # tau0 / pi with tau0 = 2 pi (1/2 - FM1_ext)
    nref = np.asarray(reference_normal, dtype=np.float64).reshape(3)
    nref = nref / np.linalg.norm(nref)
    cos = np.clip(leds.directions @ nref, 0.0, 1.0)
    w = leds.gains * leds.pattern_values("full")
    plain = cos @ w
    trans = (fresnel_transmittance(eta, cos) * cos) @ w
    return trans / plain


def albedo_scale_from_lambertian(signal: ArrayLike, reflectance: ArrayLike, *, eta: float = 1.3,
                                 leds: LedRig | None = None,
                                 reference_normal: ArrayLike = _DEFAULT_VIEW) -> Array:
    """``albedo_scale`` (3,) from a Lambertian reference (Spectralon) facing ``reference_normal`` at the origin.

    ``signal``: its ambient-subtracted cross-polarized full-on value (3,); ``reflectance``: its known
    hemispherical reflectance (3,). A Lambertian target sees the plain irradiance E while a translucent
    dielectric sees E_t = (E_t/E) E, so albedo_scale = reflectance / (signal * E_t/E) (E_t/E = tau0/pi = 0.94
    at eta 1.3 for continuous light; computed from ``leds`` if given).
    """
    s = np.asarray(signal, dtype=np.float64).reshape(-1)
    r = np.asarray(reflectance, dtype=np.float64).reshape(-1)
    if np.any(~(s > 0)):
        raise ValueError("reference signal must be > 0 in every channel")
    return r / (s * _full_transmitted_over_plain(eta, leds, reference_normal))


def albedo_scale_from_radiometry(value_per_radiance: ArrayLike, leds: LedRig, *, eta: float = 1.3,
                                 polarization_factor: float = 0.5,
                                 reference_normal: ArrayLike = _DEFAULT_VIEW) -> Array:
    """``albedo_scale`` (3,) for a radiometrically known camera (simulators, calibrated rigs).

    The cross-polarized value of a translucent surface is I = k * polarization_factor * F_t(eta, n.v)/pi
    * R_d * E_t,full(n), with ``value_per_radiance`` = k (frame units per unit radiance, per channel; e.g.
    gain * exposure / white level) and E_t,full in the units of ``leds.gains``. Then
    albedo_scale = pi / (k * polarization_factor * E_t,full(reference_normal)).
    """
    k = np.asarray(value_per_radiance, dtype=np.float64).reshape(-1)
    nref = np.asarray(reference_normal, dtype=np.float64).reshape(3)
    nref = nref / np.linalg.norm(nref)
    cos = np.clip(leds.directions @ nref, 0.0, 1.0)
    et = (fresnel_transmittance(eta, cos) * cos) @ (leds.gains * leds.pattern_values("full"))
    return np.pi / (k * polarization_factor * et)


# --------------------------------------------------------------------------------------------------------------
# result types
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GradientMasks:
    """Boolean masks; per-channel ones are (H, W, 3), per-pixel ones (H, W)."""

    saturated: NDArray[np.bool_]      # (H, W, 3) any input frame >= saturation * white_level in that channel
    dark: NDArray[np.bool_]           # (H, W, 3) full-on signal below dark_threshold * white_level
    inconsistent: NDArray[np.bool_]   # (H, W, 3) non-finite input, rho <= 0 or |n~| > max_length
    grazing: NDArray[np.bool_]        # (H, W) n.v < cos(grazing_deg)
    background: NDArray[np.bool_]     # (H, W) all channels dark, or outside object_mask

    @property
    def unknown(self) -> NDArray[np.bool_]:
        """(H, W, 3): no usable diffuse estimate (the union of all masks)."""
        return (self.saturated | self.dark | self.inconsistent
                | self.grazing[..., None] | self.background[..., None])


@dataclass(frozen=True)
class GradientMaps:
    """Maps from :func:`compute_maps`. Float maps are float32 and NaN wherever ``masks.unknown`` is set.

    ``diffuse_vectors`` (H, W, 3 channels, 3 xyz): ideal-equivalent gradient vector v (length tau_ratio for a
    flat surface, shorter where subsurface blur averages curved normals). ``diffuse_normals``: v normalized.
    ``albedo`` (H, W, 3): total diffuse reflectance R_d (see the module docstring). ``specular_*`` are None
    without parallel-polarized frames; ``specular_normals`` (H, W, 3) come from the channel-summed specular
    signal (halfway between the reflection vector and the view direction), ``specular_albedo`` (H, W, 3).
    ``consistency`` (H, W, 3): ideal mode with full + complements: max_i |(I_i + I~_i)/I_c - 1|; LED mode:
    relative RMS residual of the per-pixel least-squares solve (0 when exactly determined).
    """

    albedo: NDArray[np.float32]
    diffuse_vectors: NDArray[np.float32]
    diffuse_normals: NDArray[np.float32]
    masks: GradientMasks
    tau_ratio: float
    eta: float
    view_dirs: NDArray[np.float32]
    specular_albedo: NDArray[np.float32] | None = None
    specular_normals: NDArray[np.float32] | None = None
    reflection_vectors: NDArray[np.float32] | None = None
    specular_unknown: NDArray[np.bool_] | None = None
    consistency: NDArray[np.float32] | None = None
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def unknown(self) -> NDArray[np.bool_]:
        return self.masks.unknown

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.albedo.shape[0]), int(self.albedo.shape[1]))

    def diffuse_length(self) -> NDArray[np.float32]:
        """|v| / tau_ratio (H, W, 3): 1 for a flat Fresnel-Lambertian surface."""
        return (np.linalg.norm(self.diffuse_vectors, axis=-1) / self.tau_ratio).astype(np.float32)


# --------------------------------------------------------------------------------------------------------------
# per-tile computations
# --------------------------------------------------------------------------------------------------------------
def _ideal_vectors(I: Mapping[str, Array]) -> tuple[Array, Array, Array | None]:
    """Continuous formulas: v (h, w, 3ch, 3xyz), full-on signal (h, w, 3ch), complement consistency or None."""
    full = I.get("full")
    if full is None:
        sums = [I[a] + I[a + "_c"] for a in _AXES if a in I and a + "_c" in I]
        full_sig = np.mean(sums, axis=0)
    else:
        full_sig = full
    comps = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in _AXES:
            if a in I and a + "_c" in I:
                s = I[a] + I[a + "_c"]
                comps.append((I[a] - I[a + "_c"]) / s)
            elif a in I and full is not None:
                comps.append(2.0 * I[a] / full - 1.0)
            elif a + "_c" in I and full is not None:
                comps.append(1.0 - 2.0 * I[a + "_c"] / full)
            else:
                raise ValueError(f"axis {a!r}: need '{a}' and '{a}_c', or either one with 'full'")
        cons = None
        if full is not None:
            terms = [np.abs((I[a] + I[a + "_c"]) / full - 1.0) for a in _AXES if a in I and a + "_c" in I]
            if terms:
                cons = np.max(terms, axis=0)
    return np.stack(comps, axis=-1), full_sig, cons


def _weighted_mean_normal(v: Array, w: Array) -> Array:
    """Signal-weighted mean direction of per-channel vectors (h, w, 3, 3) -> (h, w, 3), NaN-safe."""
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / np.linalg.norm(v, axis=-1, keepdims=True)
    ok = np.isfinite(u).all(axis=-1) & (w > 0)
    s = np.sum(np.where(ok[..., None], u * np.where(ok, w, 0.0)[..., None], 0.0), axis=-2)
    n = np.linalg.norm(s, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / n, np.nan)


def _finite_rows(n: Array, fallback: Array) -> Array:
    """Rows of ``n`` (M, 3) that are finite unit vectors, else the ``fallback`` rows."""
    ok = np.isfinite(n).all(axis=-1) & (np.abs(np.linalg.norm(np.nan_to_num(n), axis=-1) - 1.0) < 1e-6)
    return np.where(ok[:, None], n, fallback)


def _solve_affine(lut: ResponseLUT, I: Mapping[str, Array], n0: Array, rows: list[int]
                  ) -> tuple[Array, Array, Array]:
    """Per pixel/channel least squares I_P = rho a_P + b_P.(rho n~). Inputs flattened: I[p] (M, 3), n0 (M, 3).

    Returns rho (M, 3) (in units of the reference full-on response), n~ (M, 3, 3), relative residual (M, 3).
    """
    names = [lut.patterns[r] for r in rows]
    m_vec = np.stack([I[p] for p in names], axis=1)  # (M, P, 3)
    A = lut.affine(n0)[:, rows]  # (M, P, 3, 4)
    A = np.moveaxis(A, 2, 1)  # (M, 3, P, 4)
    y = np.moveaxis(m_vec, 2, 1)  # (M, 3, P)
    AtA = np.einsum("mcpi,mcpj->mcij", A, A)
    Aty = np.einsum("mcpi,mcp->mci", A, y)
    det_ok = np.abs(np.linalg.det(AtA)) > 1e-300
    AtA = np.where(det_ok[..., None, None], AtA, np.eye(4))
    x = np.linalg.solve(AtA, Aty[..., None])[..., 0]  # (M, 3, 4)
    x = np.where(det_ok[..., None], x, np.nan)
    fit = np.einsum("mcpi,mci->mcp", A, x)
    with np.errstate(invalid="ignore", divide="ignore"):
        res = np.sqrt(np.mean((fit - y) ** 2, axis=-1)) / np.sqrt(np.mean(y * y, axis=-1))
        rho = x[..., 0]
        nt = x[..., 1:] / rho[..., None]
    return rho, nt, res


def _as_tile(a: Any, sl: slice) -> Array:
    return np.asarray(a[sl], dtype=np.float64)


def compute_maps(frames: Mapping[Any, ArrayLike], *, albedo_scale: ArrayLike, leds: LedRig | None = None,
                 ideal: bool = False, eta: float = 1.3, view_dirs: ArrayLike | None = None,
                 tile_rows: int = 256, white_level: float = 1.0, saturation: float = 0.98,
                 dark_threshold: float = 0.01, grazing_deg: float = 70.0,
                 object_mask: ArrayLike | None = None, geometry_normals: ArrayLike | None = None,
                 reference_normal: ArrayLike = _DEFAULT_VIEW, surface_center_mm: ArrayLike = (0.0, 0.0, 0.0),
                 surface_radius_mm: float = 0.0, lut: ResponseLUT | None = None, lut_size: int = 65,
                 lut_smoothing_rad: float | None = None, iterations: int = 2,
                 max_length: float = 1.3, exposure_s: Mapping[Any, float] | None = None) -> GradientMaps:
    """Diffuse albedo / normals (per RGB channel) and specular albedo / normals from gradient frames.

    ``frames``: {key: (H, W, 3) linear array} with keys ``(pattern, polarization)`` or bare pattern names
    (cross-polarized); patterns ``ambient``, ``full``, ``x``, ``y``, ``z``, ``x_c``, ``y_c``, ``z_c``. Needed:
    an ambient frame and, per axis, the gradient and its complement or either one with ``full`` (all
    cross-polarized). Parallel-polarized frames of the same patterns add the specular maps; a parallel ambient
    frame is used for them if given, otherwise the cross one. Arrays may be memory maps: they are read in
    ``tile_rows`` row tiles.

    ``albedo_scale`` (3,) or scalar: see the module docstring. ``leds``: discrete-LED correction (required
    unless ``ideal=True``); ``lut``: a prebuilt :func:`build_response_lut` (else built from ``leds`` with
    ``lut_size``, ``lut_smoothing_rad``, ``reference_normal``, ``surface_center_mm``, ``surface_radius_mm``).
    ``view_dirs`` (H, W, 3) or (3,): unit vectors from the surface towards the camera (default (0, -1, 0), the
    rig's camera side). ``geometry_normals`` (H, W, 3): known normals, used (instead of the specular or mean
    diffuse normal) for the grazing mask and the exit-Fresnel correction of the albedo.
    Masks: saturated (>= ``saturation`` * ``white_level`` in any frame), dark (full-on signal
    < ``dark_threshold`` * ``white_level``), grazing (n.v < cos ``grazing_deg``), background (all channels dark
    or outside ``object_mask``), inconsistent (non-finite, rho <= 0 or |n~| > ``max_length``).
    ``exposure_s``: {key: exposure time} for every frame when exposures differ; each frame is then divided by its
    exposure after the saturation test (so ``albedo_scale`` converts value *per second*). Without it all frames
    must share one exposure.
    """
    if not ideal and leds is None and lut is None:
        raise ValueError("pass leds= (discrete LED correction) or ideal=True (continuous formulas)")
    keyed: dict[tuple[str, str], Any] = {}
    for k, v in frames.items():
        nk = frame_key(k)
        if nk in keyed:
            raise ValueError(f"duplicate frame for {nk}")
        keyed[nk] = v
    cross = {p: a for (p, pol), a in keyed.items() if pol == "cross" and p != "ambient"}
    par = {p: a for (p, pol), a in keyed.items() if pol == "parallel" and p != "ambient"}
    amb_c = keyed.get(("ambient", "cross"), keyed.get(("ambient", "parallel")))
    amb_p = keyed.get(("ambient", "parallel"), amb_c)
    if amb_c is None:
        raise ValueError("an ambient (all-off) frame is required: key 'ambient' or ('ambient', pol)")
    if not cross:
        raise ValueError("no cross-polarized gradient frames given")
    shape = np.shape(amb_c)
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"frames must be (H, W, 3), got {shape}")
    for k, a in keyed.items():
        if np.shape(a) != shape:
            raise ValueError(f"frame {k} has shape {np.shape(a)}, expected {shape}")
    H, W = int(shape[0]), int(shape[1])
    expo: dict[tuple[str, str], float] = {k: 1.0 for k in keyed}
    if exposure_s is not None:
        given_e = {frame_key(k): float(v) for k, v in exposure_s.items()}
        missing = [k for k in keyed if k not in given_e]
        if missing:
            raise ValueError(f"exposure_s lacks frames {missing}")
        if any(not (v > 0 and np.isfinite(v)) for v in given_e.values()):
            raise ValueError("exposures must be finite and > 0")
        expo = {k: given_e[k] for k in keyed}
    inv_e = {k: 1.0 / v for k, v in expo.items()}
    amb_c_key = ("ambient", "cross") if ("ambient", "cross") in keyed else ("ambient", "parallel")
    amb_p_key = ("ambient", "parallel") if ("ambient", "parallel") in keyed else amb_c_key
    scale = np.broadcast_to(np.asarray(albedo_scale, dtype=np.float64).reshape(-1), (3,)).copy()
    if np.any(~np.isfinite(scale)) or np.any(scale <= 0):
        raise ValueError("albedo_scale must be finite and > 0")
    if tile_rows < 1:
        raise ValueError("tile_rows must be >= 1")
    # validate pattern completeness early (raises a clear ValueError)
    _ideal_vectors({p: np.ones((1, 1, 3)) for p in cross})
    spec_pats = [p for p in par if p in cross]
    want_spec = False
    if spec_pats:
        try:
            _ideal_vectors({p: np.ones((1, 1, 3)) for p in spec_pats})
            want_spec = True
        except ValueError:
            want_spec = False
    tau = tau_ratio(eta)
    if not ideal and lut is None:
        assert leds is not None
        lut = build_response_lut(leds, eta=eta, size=lut_size, smoothing_rad=lut_smoothing_rad,
                                 reference_normal=reference_normal, surface_center_mm=surface_center_mm,
                                 surface_radius_mm=surface_radius_mm)
    rows = [lut.patterns.index(p) for p in GRADIENT_PATTERNS if p in cross] if lut is not None else []
    if lut is not None and abs(lut.eta - eta) > 1e-9:
        raise ValueError(f"lut was built for eta={lut.eta}, not {eta}")

    vd_given = view_dirs is not None
    vd = np.asarray(view_dirs if vd_given else _DEFAULT_VIEW, dtype=np.float64)
    if vd.shape == (3,):
        vd = np.broadcast_to(vd / np.linalg.norm(vd), (H, W, 3))
    elif vd.shape != (H, W, 3):
        raise ValueError("view_dirs must be (3,) or (H, W, 3)")
    omask = None if object_mask is None else np.asarray(object_mask, dtype=bool)
    if omask is not None and omask.shape != (H, W):
        raise ValueError("object_mask must be (H, W)")
    gnorm = None if geometry_normals is None else np.asarray(geometry_normals, dtype=np.float64)
    if gnorm is not None and gnorm.shape != (H, W, 3):
        raise ValueError("geometry_normals must be (H, W, 3)")

    f32 = np.float32
    albedo = np.full((H, W, 3), np.nan, f32)
    dvec = np.full((H, W, 3, 3), np.nan, f32)
    dnorm = np.full((H, W, 3, 3), np.nan, f32)
    cons_out = np.full((H, W, 3), np.nan, f32)
    m_sat = np.zeros((H, W, 3), bool)
    m_dark = np.zeros((H, W, 3), bool)
    m_inc = np.zeros((H, W, 3), bool)
    m_graz = np.zeros((H, W), bool)
    m_bg = np.zeros((H, W), bool)
    if want_spec:
        s_alb = np.full((H, W, 3), np.nan, f32)
        s_norm = np.full((H, W, 3), np.nan, f32)
        s_refl = np.full((H, W, 3), np.nan, f32)
        s_unk = np.ones((H, W), bool)
    sat_level = saturation * white_level
    dark_level = dark_threshold * white_level * (inv_e[("full", "cross")] if ("full", "cross") in inv_e
                                                 else min(inv_e.values()))
    cos_graz = float(np.cos(np.deg2rad(grazing_deg)))
    have_cons = False

    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # garbage pixels become NaN + masks
        for r0 in range(0, H, tile_rows):
            sl = slice(r0, min(H, r0 + tile_rows))
            a_c = _as_tile(amb_c, sl)
            raw_c = {p: _as_tile(a, sl) for p, a in cross.items()}
            sat = a_c >= sat_level
            bad = ~np.isfinite(a_c)
            for a in raw_c.values():
                sat |= a >= sat_level
                bad |= ~np.isfinite(a)
            a_c = a_c * inv_e[amb_c_key]
            raw_c = {p: a * inv_e[(p, "cross")] for p, a in raw_c.items()}
            I = {p: a - a_c for p, a in raw_c.items()}
            raw_p: dict[str, Array] = {}
            if want_spec:
                a_p = _as_tile(amb_p, sl)
                sat |= a_p >= sat_level
                raw_p = {p: _as_tile(par[p], sl) for p in spec_pats}
                for a in raw_p.values():
                    sat |= a >= sat_level
                    bad |= ~np.isfinite(a)
                a_p = a_p * inv_e[amb_p_key]
                raw_p = {p: a * inv_e[(p, "parallel")] for p, a in raw_p.items()}
            with np.errstate(invalid="ignore"):
                v0, full_sig, cons = _ideal_vectors(I)
            dark = ~(full_sig >= dark_level)
            bg = np.all(dark, axis=-1)
            if omask is not None:
                bg |= ~omask[sl]
            vt = vd[sl]
            if ideal:
                rho_full = full_sig
                v = v0
                res = cons
            else:
                assert lut is not None
                h, w = full_sig.shape[:2]
                todo = ~bg & ~np.all(bad | dark, axis=-1)
                idx = np.flatnonzero(todo.reshape(-1))
                v = np.full((h * w, 3, 3), np.nan)
                rho_full = np.full((h * w, 3), np.nan)
                res = np.full((h * w, 3), np.nan)
                if idx.size:
                    flatI = {p: np.nan_to_num(a.reshape(-1, 3)[idx], nan=0.0, posinf=0.0, neginf=0.0)
                             for p, a in I.items()}  # non-finite channels are flagged via `bad`
                    wsig = np.nan_to_num(np.clip(full_sig.reshape(-1, 3)[idx], 0.0, None), posinf=0.0)
                    n0 = _finite_rows(_weighted_mean_normal(v0.reshape(-1, 3, 3)[idx], wsig), vt.reshape(-1, 3)[idx])
                    for _ in range(max(1, iterations)):
                        rho, nt, rr = _solve_affine(lut, flatI, n0, rows)
                        n0 = _finite_rows(_weighted_mean_normal(nt, np.nan_to_num(np.clip(rho, 0.0, None))), n0)
                    v[idx] = tau * nt
                    rho_full[idx] = rho
                    res[idx] = rr
                v = v.reshape(h, w, 3, 3)
                rho_full = rho_full.reshape(h, w, 3)
                res = res.reshape(h, w, 3)
            with np.errstate(invalid="ignore", divide="ignore"):
                length = np.linalg.norm(v, axis=-1) / tau
                inc = bad | ~np.isfinite(length) | ~(rho_full > 0) | (length > max_length)
                unit = v / np.linalg.norm(v, axis=-1, keepdims=True)
            # specular
            spec_n = None
            if want_spec:
                with np.errstate(invalid="ignore", divide="ignore"):
                    S = {p: np.clip((raw_p[p] - a_p) - (raw_c[p] - a_c), 0.0, None) for p in spec_pats}
                    Ssum = {p: np.repeat(np.sum(a, axis=-1, keepdims=True), 3, axis=-1) for p, a in S.items()}
                    vs, _sfull_sum, _ = _ideal_vectors(Ssum)
                    _, sfull, _ = _ideal_vectors(S)
                    r = vs[..., 0, :]
                    r = r / np.linalg.norm(r, axis=-1, keepdims=True)
                    hvec = r + vt
                    spec_n = hvec / np.linalg.norm(hvec, axis=-1, keepdims=True)
                s_ok = (np.isfinite(spec_n).all(-1) & (np.sum(sfull, -1) >= dark_level) & ~np.any(sat | bad, -1)
                        & ~bg)
                s_alb[sl] = np.where(s_ok[..., None], scale * sfull / 2.0, np.nan)
                s_norm[sl] = np.where(s_ok[..., None], spec_n, np.nan)
                s_refl[sl] = np.where(s_ok[..., None], r, np.nan)
                s_unk[sl] = ~s_ok
                spec_n = np.where(s_ok[..., None], spec_n, np.nan)
            # geometry for grazing + exit Fresnel: known > specular > mean diffuse
            n_geo = _weighted_mean_normal(np.where(inc[..., None], np.nan, v), np.where(dark, 0.0, 1.0))
            if spec_n is not None:
                n_geo = np.where(np.isfinite(spec_n), spec_n, n_geo)
            if gnorm is not None:
                n_geo = gnorm[sl]
            cos_v = np.sum(n_geo * vt, axis=-1)
            graz = ~(cos_v >= cos_graz)
            ft_out = fresnel_transmittance(eta, np.clip(np.nan_to_num(cos_v), 0.0, 1.0))
            # ideal: rho_full is the full-on signal; LED mode: the LUT is normalized by E_full(n_ref), so rho is the
            # full-on signal this surface would give facing reference_normal at the origin.
            alb = scale * rho_full
            with np.errstate(invalid="ignore", divide="ignore"):
                alb = alb / ft_out[..., None]
            unk = sat | dark | inc | graz[..., None] | bg[..., None]
            albedo[sl] = np.where(unk, np.nan, alb)
            dvec[sl] = np.where(unk[..., None], np.nan, v)
            dnorm[sl] = np.where(unk[..., None], np.nan, unit)
            if res is not None:
                have_cons = True
                cons_out[sl] = np.where(unk, np.nan, res)
            m_sat[sl], m_dark[sl], m_inc[sl], m_graz[sl], m_bg[sl] = sat, dark & ~bg[..., None], inc & ~bg[..., None], \
                graz & ~bg, bg

    masks = GradientMasks(m_sat, m_dark, m_inc, m_graz, m_bg)
    prov: dict[str, Any] = {
        "module": "estimation.gradients", "version": 1, "method": "Ma2007",
        "mode": "ideal" if ideal else "leds", "eta": float(eta), "tau_ratio": tau,
        "patterns_cross": sorted(cross), "patterns_parallel": sorted(spec_pats) if want_spec else [],
        "albedo_scale": scale.tolist(), "reference_normal": list(map(float, np.ravel(reference_normal))),
        "view_dirs": "given" if vd_given else f"default {_DEFAULT_VIEW}",
        "geometry_normals": gnorm is not None, "white_level": white_level, "saturation": saturation,
        "dark_threshold": dark_threshold, "grazing_deg": grazing_deg, "max_length": max_length,
        "tile_rows": tile_rows, "iterations": iterations,
        "exposure_s": None if exposure_s is None else {f"{k[0]}/{k[1]}": v for k, v in expo.items()},
    }
    if lut is not None and not ideal:
        prov["lut"] = {"size": lut.size, "smoothing_rad": lut.smoothing_rad, **lut.provenance}
    return GradientMaps(
        albedo=albedo, diffuse_vectors=dvec, diffuse_normals=dnorm, masks=masks, tau_ratio=tau, eta=float(eta),
        view_dirs=np.ascontiguousarray(vd, dtype=f32),
        specular_albedo=s_alb if want_spec else None, specular_normals=s_norm if want_spec else None,
        reflection_vectors=s_refl if want_spec else None, specular_unknown=s_unk if want_spec else None,
        consistency=cons_out if have_cons else None, provenance=prov)
