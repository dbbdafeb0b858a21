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

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
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
    "map_allocator",
    "DerivedMap",
    "UnitVectorMap",
    "tile_workers",
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
    """K(t) = F_t(eta, t) t on a uniform grid of t in [0, 1] (the Fresnel-Lambertian irradiance kernel): the node
    values and the slopes to the next node."""
    t = np.linspace(0.0, 1.0, n)
    k = fresnel_transmittance(eta, t) * t
    return k, np.append(np.diff(k), 0.0)


def _kernel(cos: Array, kt: tuple[Array, Array]) -> Array:
    """K(max(cos, 0)) by linear interpolation on the uniform table (much faster than np.interp)."""
    table, slope = kt
    n = table.size - 1
    x = np.clip(cos, 0.0, 1.0)
    x *= n
    i = x.astype(np.intp)
    x -= i
    x *= slope[i]
    x += table[i]
    return x


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
    _solve_tables: dict[tuple[int, ...], _SolveTable] = field(default_factory=dict, init=False, repr=False,
                                                              compare=False)

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
    """E (M, P*3) = sum_j K(cos_j(n)) * falloff_j(n) * weights[j] for unit normals (M, 3).

    Near field (``leds.distances_mm``): LED j at p_j, surface point x = c + r n, so with q_j = n.p_j:
    |p_j - x|^2 = |p_j|^2 - 2 (c.p_j + r q_j) + |c|^2 + 2 r c.n + r^2 and (p_j - x).n = q_j - c.n - r: one
    (M, N) product per block, formed elementwise (tiny inner dimension: no BLAS call overhead)."""
    out = np.empty((normals.shape[0], weights.shape[1]))
    near = leds.distances_mm is not None
    p = (leds.distances_mm[:, None] if near else 1.0) * leds.directions  # (N, 3)
    if near:
        p2 = np.einsum("jk,jk->j", p, p)[None, :]
        cp = (p @ center)[None, :]
        d2 = (leds.distances_mm ** 2)[None, :]
    step = 2048
    for s in range(0, normals.shape[0], step):
        n = normals[s:s + step]
        q = n[:, 0:1] * p[:, 0] + n[:, 1:2] * p[:, 1] + n[:, 2:3] * p[:, 2]  # (m, N)
        if not near:
            k = _kernel(q, kt)
        else:
            cn = (n @ center)[:, None]
            dist2 = p2 - 2.0 * (cp + radius * q) + (center @ center + 2.0 * radius * cn + radius * radius)
            q -= cn + radius
            q /= np.sqrt(dist2)
            k = _kernel(q, kt)
            k *= d2
            k /= dist2
        out[s:s + step] = k @ weights
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
# output storage: RAM or per-tile memory maps (bounded memory)
# --------------------------------------------------------------------------------------------------------------
Allocator = Callable[[str, tuple[int, ...], Any], NDArray[Any]]


def map_allocator(out_dir: str | Path | None, prefix: str = "") -> Allocator:
    """``allocate(name, shape, dtype)`` for full-size output maps: ``np.empty`` in RAM when ``out_dir`` is None,
    otherwise a ``<prefix><name>.npy`` memory map (``np.lib.format.open_memmap``) in ``out_dir`` (created).

    With memory maps the maps are written tile by tile and never held whole in the process's memory; they stay
    readable as ordinary arrays (and with ``np.load(path, mmap_mode="r")`` later).
    """
    if out_dir is None:
        return lambda name, shape, dtype: np.empty(shape, dtype)
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)

    def allocate(name: str, shape: tuple[int, ...], dtype: Any) -> NDArray[Any]:
        return np.lib.format.open_memmap(folder / f"{prefix}{name}.npy", mode="w+", dtype=dtype, shape=shape)

    return allocate


class DerivedMap:
    """A read-only full-size map that is *not stored*: computed element-wise from stored maps on access.

    ``func(*sources)`` must be element-wise (so it commutes with indexing); every source has this map's
    ``shape`` (use ``np.broadcast_to`` views for lower-dimensional ones). Indexing (``m[r0:r1]``,
    ``m[..., c][mask]``) evaluates only the selection; ``np.asarray(m)`` materializes the whole map in RAM
    (row tiles of 256, so temporaries stay small); other ndarray attributes and arithmetic go through that
    materialization. ``definition`` says how the map is derived (copied into the provenance / sidecar).
    """

    __array_priority__ = 20.0
    _rows = 256

    def __init__(self, func: Callable[..., Any], sources: tuple[Any, ...], shape: tuple[int, ...],
                 dtype: Any = np.float32, definition: str = "") -> None:
        self._func = func
        self._sources = tuple(sources)
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self.definition = definition
        for src in self._sources:
            if tuple(np.shape(src)) != self.shape:
                raise ValueError(f"source of shape {np.shape(src)} for a derived map of shape {self.shape}")

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def _eval(self, key: Any) -> NDArray[Any]:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return np.asarray(self._func(*(src[key] for src in self._sources)), dtype=self.dtype)

    def __getitem__(self, key: Any) -> NDArray[Any]:
        return self._eval(key)

    def __array__(self, dtype: Any = None, copy: Any = None) -> NDArray[Any]:
        out = np.empty(self.shape, self.dtype)
        for r0 in range(0, max(self.shape[0], 1), self._rows):
            out[r0:r0 + self._rows] = self._eval(slice(r0, r0 + self._rows))
        return out if dtype is None else out.astype(dtype, copy=False)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(np.asarray(self), name)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(shape={self.shape}, dtype={self.dtype}, {self.definition!r})"


def _binary(op: Callable[[Any, Any], Any], reflected: bool) -> Callable[[Any, Any], Any]:
    if reflected:
        return lambda self, other: op(other, np.asarray(self))
    return lambda self, other: op(np.asarray(self), other)


import operator as _op  # noqa: E402

for _name, _f in (("add", _op.add), ("sub", _op.sub), ("mul", _op.mul), ("truediv", _op.truediv),
                  ("pow", _op.pow), ("matmul", _op.matmul), ("lt", _op.lt), ("le", _op.le), ("gt", _op.gt),
                  ("ge", _op.ge), ("eq", _op.eq), ("ne", _op.ne), ("and", _op.and_), ("or", _op.or_)):
    setattr(DerivedMap, f"__{_name}__", _binary(_f, False))
    if _name not in ("lt", "le", "gt", "ge", "eq", "ne"):
        setattr(DerivedMap, f"__r{_name}__", _binary(_f, True))
DerivedMap.__neg__ = lambda self: -np.asarray(self)  # type: ignore[attr-defined]
DerivedMap.__invert__ = lambda self: ~np.asarray(self)  # type: ignore[attr-defined]
DerivedMap.__hash__ = None  # type: ignore[assignment]


def _unit(v: NDArray[np.float32]) -> NDArray[np.float32]:
    """v / |v| over the last axis, in float32 exactly as compute_maps forms it (sqrt(x^2 + y^2 + z^2))."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    n = np.sqrt(x * x + y * y + z * z)
    return v / n[..., None]


class UnitVectorMap(DerivedMap):
    """``diffuse_normals`` = ``diffuse_vectors`` / |``diffuse_vectors``| (H, W, 3 channels, 3 xyz), derived on
    access (a normalization over the last axis: the leading part of a key selects the vectors first)."""

    def __init__(self, vectors: Any) -> None:
        super().__init__(_unit, (vectors,), np.shape(vectors), np.float32,
                         "diffuse_vectors / |diffuse_vectors| (per channel)")

    def _eval(self, key: Any) -> NDArray[Any]:
        src = self._sources[0]
        k = key if isinstance(key, tuple) else (key,)
        nd = self.ndim
        if any(e is None for e in k) or sum(e is Ellipsis for e in k) > 1:
            return np.asarray(self)[key]
        ell = [j for j, e in enumerate(k) if e is Ellipsis]
        if ell:
            i = ell[0]
            used = sum(np.ndim(e) if isinstance(e, np.ndarray) and e.dtype == bool else 1
                       for e in k if e is not Ellipsis)
            k = k[:i] + (slice(None),) * (nd - used) + k[i + 1:]
        used = sum(np.ndim(e) if isinstance(e, np.ndarray) and e.dtype == bool else 1 for e in k)
        if used < nd:  # the last axis is not indexed
            k = k + (slice(None),) * (nd - used)
        last = k[-1]
        lead = k[:-1]
        advanced = any(isinstance(e, (np.ndarray, list)) for e in lead)
        if advanced and not (isinstance(last, slice) and last == slice(None)):
            return np.asarray(self)[key]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return np.asarray(_unit(np.asarray(src[lead + (slice(None),)], dtype=np.float32))[..., last])


def tile_workers(workers: int | None) -> int:
    """Threads over row tiles: ``workers`` if given (>= 1), else min(2, CPUs). numpy releases the GIL inside its
    array operations, so tiles overlap; each tile writes only its own rows, so the result does not depend on it."""
    import os

    if workers is None:
        return max(1, min(2, os.cpu_count() or 1))
    if int(workers) < 1:
        raise ValueError("workers must be >= 1")
    return int(workers)


def _run_tiles(fn: Callable[[int, int], None], H: int, tile_rows: int, workers: int) -> None:
    """fn(r0, r1) over the row tiles, in ``workers`` threads (in order when 1); exceptions propagate."""
    starts = list(range(0, H, tile_rows))
    if workers <= 1 or len(starts) <= 1:
        for r0 in starts:
            fn(r0, min(H, r0 + tile_rows))
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=workers) as ex:
        for f in [ex.submit(fn, r0, min(H, r0 + tile_rows)) for r0 in starts]:
            f.result()


def _flat(a: NDArray[Any], n: int) -> NDArray[Any]:
    """(H, W, *rest) output array viewed as (H*W, *rest) without copying (outputs are allocated contiguous)."""
    if not a.flags.c_contiguous:  # pragma: no cover - allocators return C-contiguous arrays
        raise ValueError("output arrays must be C-contiguous")
    return a.reshape((n,) + a.shape[2:])


# --------------------------------------------------------------------------------------------------------------
# per-pixel computations (vectorized over blocks of pixels; float32; channel last)
# --------------------------------------------------------------------------------------------------------------
_BLOCK_PX = 1 << 14  # pixels per vectorized block: (M, 3) float32 temporaries of 192 kB stay in the L2 cache


def _ideal_vectors(I: Mapping[str, Array]) -> tuple[Array, Array, Array | None]:
    """Continuous formulas: v (..., 3ch, 3xyz), full-on signal (..., 3ch), complement consistency or None."""
    comps, full_sig, cons = _ideal_components(I)
    return np.stack(comps, axis=-1), full_sig, cons


def _ideal_components(I: Mapping[str, Array]) -> tuple[list[Array], Array, Array | None]:
    """v_x, v_y, v_z (each (..., 3ch)), the full-on signal and max_i |(I_i + I~_i)/I_c - 1| (or None)."""
    full = I.get("full")
    if full is None:
        sums = [I[a] + I[a + "_c"] for a in _AXES if a in I and a + "_c" in I]
        full_sig = sums[0] if len(sums) == 1 else sum(sums[1:], sums[0]) / len(sums)
    else:
        full_sig = full
    comps = []
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for a in _AXES:
            if a in I and a + "_c" in I:
                comps.append((I[a] - I[a + "_c"]) / (I[a] + I[a + "_c"]))
            elif a in I and full is not None:
                comps.append(2.0 * I[a] / full - 1.0)
            elif a + "_c" in I and full is not None:
                comps.append(1.0 - 2.0 * I[a + "_c"] / full)
            else:
                raise ValueError(f"axis {a!r}: need '{a}' and '{a}_c', or either one with 'full'")
        cons = None
        if full is not None:
            for a in _AXES:
                if a in I and a + "_c" in I:
                    t = np.abs((I[a] + I[a + "_c"]) / full - 1.0)
                    cons = t if cons is None else np.fmax(cons, t)
    return comps, full_sig, cons


def _norm3(x: Array, y: Array, z: Array) -> Array:
    return np.sqrt(x * x + y * y + z * z)


def _mean_direction(comps: list[Array], w: Array) -> Array:
    """Weighted mean direction (M, 3) of per-channel vectors ``comps`` = [x, y, z] (each (M, 3ch)); NaN rows where
    no channel has a finite vector with weight > 0."""
    inv = 1.0 / _norm3(*comps)
    ok = np.isfinite(inv) & (w > 0)
    wn = np.where(ok, w * inv, 0.0)
    s = np.stack([np.einsum("mc,mc->m", wn, np.where(ok, c, 0.0)) for c in comps], axis=-1)
    n = np.sqrt(np.einsum("mk,mk->m", s, s))[:, None]
    return np.where(n > 0, s / n, np.nan)


def _finite_or(n: Array, fallback: Array) -> Array:
    """Rows of ``n`` (M, 3) that are finite, else ``fallback``."""
    return np.where(np.isfinite(n[:, 0] + n[:, 1] + n[:, 2])[:, None], n, fallback)


def _oct_index(n: Array, size: int) -> NDArray[np.intp]:
    """Index of the nearest node of a size x size octahedral grid (row-major) for unit vectors ``n`` (M, 3)."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    a = np.abs(x) + np.abs(y) + np.abs(z)
    u, w, z = x / a, y / a, z / a
    lower = z < 0
    uu = np.where(lower, (1.0 - np.abs(w)) * np.where(u >= 0, 1.0, -1.0), u)
    ww = np.where(lower, (1.0 - np.abs(u)) * np.where(w >= 0, 1.0, -1.0), w)
    h = 0.5 * (size - 1)
    with np.errstate(invalid="ignore"):  # NaN normals -> clipped index, their pixels are masked
        iu = np.clip(np.rint((uu + 1.0) * h).astype(np.intp), 0, size - 1)
        iv = np.clip(np.rint((ww + 1.0) * h).astype(np.intp), 0, size - 1)
    return iu * size + iv


@dataclass(frozen=True)
class _SolveTable:
    """Per-node least-squares inverse of the affine response on a fine octahedral grid (nearest-node lookup).

    ``G`` (4P, N) complex128 = 4 float32 lanes (R, G, B, 0) per entry: x_i = sum_p G[i*P + p] I_p per channel,
    x = (rho, rho n~). ``AtA`` (10, N): the upper triangle of A^T A, for the residual |I - A x|^2 =
    |I|^2 - x^T (A^T A) x (None when P = 4: the system is square). Four-lane, 16-byte entries make the per-pixel
    gather one aligned copy.
    """

    size: int
    n_patterns: int
    G: NDArray[np.complex128]
    AtA: NDArray[np.complex128] | None


def _lanes(a: Array) -> NDArray[np.complex128]:
    """(N, 3, E) float -> (E, N) complex128 holding float32 lanes (ch0, ch1, ch2, 0)."""
    n, _, e = a.shape
    out = np.zeros((e, n, 4), np.float32)
    out[..., :3] = a.transpose(2, 0, 1)
    return out.view(np.complex128)[..., 0]


def _solve_table(lut: ResponseLUT, rows: tuple[int, ...]) -> _SolveTable:
    """Build (once per LUT and pattern subset) the fine table of G(n) = pinv(A(n)), A from :meth:`ResponseLUT.affine`.

    The grid is 4x finer than the LUT (257 x 257 for the default 65): nearest-node lookup moves the lookup normal
    by < 0.3 deg, which changes the affine model far less than its own residual (the response is smooth on the
    scale of the LUT smoothing, >= 0.08 rad); on the test rigs the recovered |v| and D agree with bilinear
    interpolation of the LUT to < 1e-4.
    """
    cached = lut._solve_tables.get(rows)
    if cached is not None:
        return cached
    size = max(257, 4 * (lut.size - 1) + 1)
    g = np.linspace(-1.0, 1.0, size)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    nodes = oct_decode(np.stack([uu, vv], axis=-1).reshape(-1, 2))
    P = len(rows)
    G = np.empty((size * size, 3, 4, P))
    N = np.empty((size * size, 3, 10))
    iu = np.triu_indices(4)
    for s in range(0, nodes.shape[0], 8192):
        A = np.moveaxis(lut.affine(nodes[s:s + 8192])[:, list(rows)], 2, 1)  # (m, 3, P, 4)
        AtA = np.einsum("mcpi,mcpj->mcij", A, A)
        ok = np.abs(np.linalg.det(AtA)) > 1e-300
        inv = np.linalg.inv(np.where(ok[..., None, None], AtA, np.eye(4)))
        G[s:s + 8192] = np.where(ok[..., None, None], np.einsum("mcij,mcpj->mcip", inv, A), np.nan)
        N[s:s + 8192] = AtA[..., iu[0], iu[1]] * np.where(iu[0] == iu[1], 1.0, 2.0)  # off-diagonals twice
    table = _SolveTable(size, P, _lanes(G.reshape(-1, 3, 4 * P)), _lanes(N) if P > 4 else None)
    lut._solve_tables[rows] = table
    return table


def _led_solve(table: _SolveTable, Y4: Array, n0: Array, residual: bool) -> tuple[Array, list[Array], Array | None]:
    """Per pixel and channel least squares I_P = rho a_P + b_P.(rho n~) at the lookup normals ``n0`` (M, 3).

    ``Y4`` (P, M, 4): the ambient-subtracted signals in four lanes (R, G, B, 0). Returns rho (M, 3) (in units of
    the reference full-on response), [n~_x, n~_y, n~_z] (each (M, 3)) and the relative RMS residual (M, 3)
    (None unless ``residual``).
    """
    P = table.n_patterns
    M = n0.shape[0]
    idx = _oct_index(n0, table.size)
    Gg = np.take(table.G, idx, axis=1).view(np.float32).reshape(4 * P, M, 4)
    x = [np.einsum("pml,pml->ml", Gg[i * P:(i + 1) * P], Y4) for i in range(4)]
    res = None
    if residual:
        if table.AtA is None:
            res = np.zeros((M, 3), np.float32)
        else:  # |I - A x|^2 = |I|^2 - x^T (A^T A) x (x solves the normal equations); > 0 up to rounding
            Ng = np.take(table.AtA, idx, axis=1).view(np.float32).reshape(10, M, 4)
            yy = np.einsum("pml,pml->ml", Y4, Y4)
            xAx = np.zeros_like(yy)
            for k, (i, j) in enumerate(zip(*np.triu_indices(4))):
                xAx += Ng[k] * x[i] * x[j]
            res = np.sqrt(np.maximum(yy - xAx, 0.0) / yy)[:, :3]
    rho = x[0][:, :3]
    return np.ascontiguousarray(rho), [x[1][:, :3] / rho, x[2][:, :3] / rho, x[3][:, :3] / rho], res


@lru_cache(maxsize=16)
def _exit_fresnel_table(eta: float, n: int = 4097) -> NDArray[np.float32]:
    """F_t(eta, t) on a uniform grid of t in [0, 1] (linear interpolation error < 1e-7 for t > cos 85 deg)."""
    return fresnel_transmittance(eta, np.linspace(0.0, 1.0, n)).astype(np.float32)


def _exit_fresnel(cos: Array, table: NDArray[np.float32]) -> Array:
    n = table.size - 1
    x = np.clip(np.nan_to_num(cos), 0.0, 1.0) * n
    i = np.minimum(x.astype(np.intp), n - 1)
    f = (x - i).astype(np.float32)
    return table[i] * (1.0 - f) + table[i + 1] * f


def _read(a: Any, r0: int, r1: int) -> NDArray[Any]:
    """Rows r0:r1 of an (H, W, C) frame as an (h*W, C) array (a view of a memory map when contiguous)."""
    t = np.asarray(a[r0:r1])
    return t.reshape((-1,) + t.shape[2:])


def compute_maps(frames: Mapping[Any, ArrayLike], *, albedo_scale: ArrayLike, leds: LedRig | None = None,
                 ideal: bool = False, eta: float = 1.3, view_dirs: ArrayLike | None = None,
                 tile_rows: int = 256, white_level: float = 1.0, saturation: float = 0.98,
                 dark_threshold: float = 0.01, grazing_deg: float = 70.0,
                 object_mask: ArrayLike | None = None, geometry_normals: ArrayLike | None = None,
                 reference_normal: ArrayLike = _DEFAULT_VIEW, surface_center_mm: ArrayLike = (0.0, 0.0, 0.0),
                 surface_radius_mm: float = 0.0, lut: ResponseLUT | None = None, lut_size: int = 65,
                 lut_smoothing_rad: float | None = None, iterations: int = 2,
                 max_length: float = 1.3, exposure_s: Mapping[Any, float] | None = None,
                 out_dir: str | Path | None = None, workers: int | None = None,
                 consistency: bool = True) -> GradientMaps:
    """Diffuse albedo / normals (per RGB channel) and specular albedo / normals from gradient frames.

    ``frames``: {key: (H, W, 3) linear array} with keys ``(pattern, polarization)`` or bare pattern names
    (cross-polarized); patterns ``ambient``, ``full``, ``x``, ``y``, ``z``, ``x_c``, ``y_c``, ``z_c``. Needed:
    an ambient frame and, per axis, the gradient and its complement or either one with ``full`` (all
    cross-polarized). Parallel-polarized frames of the same patterns add the specular maps; a parallel ambient
    frame is used for them if given, otherwise the cross one. Arrays may be memory maps: they are read in
    ``tile_rows`` row tiles (and processed in blocks of 16384 pixels), so the working memory is bounded by the tile.

    ``albedo_scale`` (3,) or scalar: see the module docstring. ``leds``: discrete-LED correction (required
    unless ``ideal=True``); ``lut``: a prebuilt :func:`build_response_lut` (else built from ``leds`` with
    ``lut_size``, ``lut_smoothing_rad``, ``reference_normal``, ``surface_center_mm``, ``surface_radius_mm``).
    The per-pixel solve uses the LUT's least-squares inverse tabulated on a 4x finer octahedral grid (nearest
    node; built once per LUT and pattern set, ~0.3 s). ``iterations``: solves per pixel, each at the normal of
    the previous one (the first at the normal of the continuous formulas).
    ``view_dirs`` (H, W, 3) or (3,): unit vectors from the surface towards the camera (default (0, -1, 0), the
    rig's camera side). ``geometry_normals`` (H, W, 3): known normals, used (instead of the specular or mean
    diffuse normal) for the grazing mask and the exit-Fresnel correction of the albedo.
    Masks: saturated (>= ``saturation`` * ``white_level`` in any frame), dark (full-on signal
    < ``dark_threshold`` * ``white_level``), grazing (n.v < cos ``grazing_deg``), background (all channels dark
    or outside ``object_mask``), inconsistent (non-finite, rho <= 0, |n~| = 0 or |n~| > ``max_length``).
    ``exposure_s``: {key: exposure time} for every frame when exposures differ; each frame is then divided by its
    exposure after the saturation test (so ``albedo_scale`` converts value *per second*). Without it all frames
    must share one exposure.
    ``out_dir``: write every output map tile by tile into ``<name>.npy`` memory maps in this folder
    (:func:`map_allocator`) instead of RAM; then nothing of frame size is held in memory (``view_dirs`` given as a
    (3,) vector is stored as a zero-stride broadcast view either way). ``diffuse_normals`` is not stored: it is a
    :class:`UnitVectorMap` of ``diffuse_vectors`` (normalized on access, bit-identical to normalizing in the
    loop); ``provenance["stored"]`` / ``["derived"]`` list what was written and how the rest is derived.
    ``workers``: threads over row tiles (:func:`tile_workers`; default min(2, CPUs)); results do not depend on it.
    ``consistency=False``: skip the diagnostic ``consistency`` map (None; LED mode then also skips the residual).
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
    n_workers = tile_workers(workers)
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
    if lut is not None and abs(lut.eta - eta) > 1e-9:
        raise ValueError(f"lut was built for eta={lut.eta}, not {eta}")
    used = [p for p in GRADIENT_PATTERNS if p in cross]
    table = None
    if not ideal:
        assert lut is not None
        table = _solve_table(lut, tuple(lut.patterns.index(p) for p in used))

    vd_given = view_dirs is not None
    vd_in = None
    if vd_given and np.shape(view_dirs) == (H, W, 3):
        vd_in = view_dirs
    else:
        v3 = np.asarray(view_dirs if vd_given else _DEFAULT_VIEW, dtype=np.float64)
        if v3.shape != (3,):
            raise ValueError("view_dirs must be (3,) or (H, W, 3)")
        v3 = (v3 / np.linalg.norm(v3)).astype(np.float32)
    omask = None
    if object_mask is not None:
        if np.shape(object_mask) != (H, W):
            raise ValueError("object_mask must be (H, W)")
        omask = object_mask
    gnorm = None
    if geometry_normals is not None:
        if np.shape(geometry_normals) != (H, W, 3):
            raise ValueError("geometry_normals must be (H, W, 3)")
        gnorm = geometry_normals

    f32 = np.float32
    alloc = map_allocator(out_dir)
    npx = H * W
    have_cons = consistency and ((not ideal) or ("full" in cross and any(a in cross and a + "_c" in cross
                                                                         for a in _AXES)))
    albedo = alloc("albedo", (H, W, 3), f32)
    dvec = alloc("diffuse_vectors", (H, W, 3, 3), f32)
    cons_out = alloc("consistency", (H, W, 3), f32) if have_cons else None
    m_sat = alloc("mask_saturated", (H, W, 3), bool)
    m_dark = alloc("mask_dark", (H, W, 3), bool)
    m_inc = alloc("mask_inconsistent", (H, W, 3), bool)
    m_graz = alloc("mask_grazing", (H, W), bool)
    m_bg = alloc("mask_background", (H, W), bool)
    s_alb = s_norm = s_refl = s_unk = None
    if want_spec:
        s_alb = alloc("specular_albedo", (H, W, 3), f32)
        s_norm = alloc("specular_normals", (H, W, 3), f32)
        s_refl = alloc("reflection_vectors", (H, W, 3), f32)
        s_unk = alloc("specular_unknown", (H, W), bool)
    if vd_in is not None and not (isinstance(vd_in, np.ndarray) and vd_in.dtype == f32):
        vd_store = alloc("view_dirs", (H, W, 3), f32)
    elif vd_in is not None:
        vd_store = vd_in
    else:
        vd_store = np.broadcast_to(v3, (H, W, 3))
    out = {"albedo": _flat(albedo, npx), "dvec": _flat(dvec, npx),
           "sat": _flat(m_sat, npx), "dark": _flat(m_dark, npx), "inc": _flat(m_inc, npx),
           "graz": _flat(m_graz, npx), "bg": _flat(m_bg, npx)}
    if cons_out is not None:
        out["cons"] = _flat(cons_out, npx)
    if want_spec:
        assert s_alb is not None and s_norm is not None and s_refl is not None and s_unk is not None
        out.update(s_alb=_flat(s_alb, npx), s_norm=_flat(s_norm, npx), s_refl=_flat(s_refl, npx),
                   s_unk=_flat(s_unk, npx))
    vd_out = _flat(vd_store, npx) if vd_store is not vd_in and vd_in is not None else None

    sat_level = float(saturation * white_level)
    dark_level = float(dark_threshold * white_level * (inv_e[("full", "cross")] if ("full", "cross") in inv_e
                                                       else min(inv_e.values())))
    cos_graz = float(np.cos(np.deg2rad(grazing_deg)))
    scale32 = scale.astype(f32)
    ft_table = _exit_fresnel_table(float(eta))
    nan = f32(np.nan)
    cross_keys = [("ambient", amb_c_key)] + [(p, (p, "cross")) for p in used]
    par_keys = ([("ambient", amb_p_key)] + [(p, (p, "parallel")) for p in spec_pats]) if want_spec else []

    def tile(r0: int, r1: int) -> None:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # garbage pixels become NaN + masks
            t_c = {p: _read(keyed[k], r0, r1) for p, k in cross_keys}
            t_p = {p: _read(keyed[k], r0, r1) for p, k in par_keys}
            t_vd = _read(vd_in, r0, r1) if vd_in is not None else None
            t_om = _read(omask, r0, r1) if omask is not None else None
            t_gn = _read(gnorm, r0, r1) if gnorm is not None else None
            n_tile = (r1 - r0) * W
            for b0 in range(0, n_tile, _BLOCK_PX):
                b1 = min(n_tile, b0 + _BLOCK_PX)
                o0, o1 = r0 * W + b0, r0 * W + b1
                raw_c = {p: np.asarray(a[b0:b1], dtype=f32) for p, a in t_c.items()}
                raw_p = {p: np.asarray(a[b0:b1], dtype=f32) for p, a in t_p.items()}
                frames_used = list(raw_c.values()) + list(raw_p.values())
                mx = frames_used[0]
                tot = frames_used[0]
                for a in frames_used[1:]:
                    mx = np.fmax(mx, a)
                    tot = tot + a
                sat = mx >= sat_level
                bad = ~np.isfinite(tot)
                a_c = raw_c.pop("ambient")
                if inv_e[amb_c_key] != 1.0:
                    a_c = a_c * f32(inv_e[amb_c_key])
                I = {p: (a * f32(inv_e[(p, "cross")]) if inv_e[(p, "cross")] != 1.0 else a) - a_c
                     for p, a in raw_c.items()}
                comps, full_sig, cons = _ideal_components(I)
                dark = ~(full_sig >= dark_level)
                bg = dark[:, 0] & dark[:, 1] & dark[:, 2]
                if t_om is not None:
                    bg |= ~np.asarray(t_om[b0:b1], dtype=bool)
                vt = np.asarray(t_vd[b0:b1], dtype=f32) if t_vd is not None else v3
                if ideal:
                    rho_full, vc, res = full_sig, comps, cons
                else:
                    assert table is not None
                    Y = np.zeros((len(used), b1 - b0, 4), f32)
                    for k, p in enumerate(used):
                        Y[k, :, :3] = I[p]
                    w0 = np.where(full_sig > 0, full_sig, 0.0)
                    n0 = _finite_or(_mean_direction(comps, w0), vt)
                    n_it = max(1, iterations)
                    for it in range(n_it):
                        rho_full, nt, res = _led_solve(table, Y, n0, residual=have_cons and it == n_it - 1)
                        if it < n_it - 1:
                            n0 = _finite_or(_mean_direction(nt, np.where(rho_full > 0, rho_full, 0.0)), n0)
                    vc = [tau * c for c in nt]
                vlen = _norm3(*vc)
                length = vlen / tau
                inc = bad | ~np.isfinite(length) | ~(rho_full > 0) | ~(length > 0) | (length > max_length)
                unit = [c / vlen for c in vc] if t_gn is None else None
                # specular
                spec_n = None
                if want_spec:
                    a_p = raw_p.pop("ambient")
                    if inv_e[amb_p_key] != 1.0:
                        a_p = a_p * f32(inv_e[amb_p_key])
                    S = {}
                    for p, a in raw_p.items():
                        ap = a * f32(inv_e[(p, "parallel")]) if inv_e[(p, "parallel")] != 1.0 else a
                        S[p] = np.maximum((ap - a_p) - I[p], 0.0)
                    Ssum = {p: np.sum(a, axis=-1) for p, a in S.items()}
                    rc, _, _ = _ideal_components(Ssum)
                    sfull = _ideal_components(S)[1]
                    rn = _norm3(*rc)
                    r = np.stack([c / rn for c in rc], axis=-1)
                    hvec = r + vt
                    spec_n = hvec / np.sqrt(np.einsum("mk,mk->m", hvec, hvec))[:, None]
                    s_ok = (np.isfinite(spec_n).all(-1) & (np.sum(sfull, -1) >= dark_level)
                            & ~np.any(sat | bad, -1) & ~bg)
                    out["s_alb"][o0:o1] = np.where(s_ok[:, None], scale32 * sfull / 2.0, nan)
                    out["s_norm"][o0:o1] = np.where(s_ok[:, None], spec_n, nan)
                    out["s_refl"][o0:o1] = np.where(s_ok[:, None], r, nan)
                    out["s_unk"][o0:o1] = ~s_ok
                    spec_n = np.where(s_ok[:, None], spec_n, nan)
                # geometry for grazing + exit Fresnel: known > specular > mean diffuse
                if t_gn is not None:
                    n_geo = np.asarray(t_gn[b0:b1], dtype=f32)
                else:
                    assert unit is not None
                    n_geo = _mean_direction(unit, np.where(dark | inc, 0.0, 1.0).astype(f32))
                    if spec_n is not None:
                        n_geo = np.where(np.isfinite(spec_n), spec_n, n_geo)
                cos_v = np.einsum("mk,mk->m", n_geo, np.broadcast_to(vt, n_geo.shape))
                graz = ~(cos_v >= cos_graz)
                # ideal: rho_full is the full-on signal; LED mode: the LUT is normalized by E_full(n_ref), so rho is
                # the full-on signal this surface would give facing reference_normal at the origin.
                alb = scale32 * rho_full / _exit_fresnel(cos_v, ft_table)[:, None]
                inc |= ~np.isfinite(alb) & ~graz[:, None]
                unk = sat | dark | inc | graz[:, None] | bg[:, None]
                o_alb = out["albedo"][o0:o1]
                o_alb[...] = alb
                np.copyto(o_alb, nan, where=unk)
                dv = out["dvec"][o0:o1]
                for k in range(3):
                    dv[..., k] = vc[k]
                np.copyto(dv, nan, where=unk[..., None])
                if cons_out is not None:
                    assert res is not None
                    o_c = out["cons"][o0:o1]
                    o_c[...] = res
                    np.copyto(o_c, nan, where=unk)
                nbg = ~bg
                out["sat"][o0:o1] = sat
                out["dark"][o0:o1] = dark & nbg[:, None]
                out["inc"][o0:o1] = inc & nbg[:, None]
                out["graz"][o0:o1] = graz & nbg
                out["bg"][o0:o1] = bg
                if vd_out is not None:
                    vd_out[o0:o1] = vt

    _run_tiles(tile, H, tile_rows, n_workers)
    masks = GradientMasks(m_sat, m_dark, m_inc, m_graz, m_bg)
    prov: dict[str, Any] = {
        "module": "estimation.gradients", "version": 2, "method": "Ma2007",
        "mode": "ideal" if ideal else "leds", "eta": float(eta), "tau_ratio": tau,
        "patterns_cross": sorted(cross), "patterns_parallel": sorted(spec_pats) if want_spec else [],
        "albedo_scale": scale.tolist(), "reference_normal": list(map(float, np.ravel(reference_normal))),
        "view_dirs": "given" if vd_given else f"default {_DEFAULT_VIEW}",
        "geometry_normals": gnorm is not None, "white_level": white_level, "saturation": saturation,
        "dark_threshold": dark_threshold, "grazing_deg": grazing_deg, "max_length": max_length,
        "tile_rows": tile_rows, "iterations": iterations,
        "exposure_s": None if exposure_s is None else {f"{k[0]}/{k[1]}": v for k, v in expo.items()},
        "storage": "RAM" if out_dir is None else f"memory maps in {out_dir}",
        "stored": sorted(["albedo", "diffuse_vectors", "mask_saturated", "mask_dark", "mask_inconsistent",
                          "mask_grazing", "mask_background"] + (["consistency"] if cons_out is not None else [])
                         + (["specular_albedo", "specular_normals", "reflection_vectors", "specular_unknown"]
                            if want_spec else [])),
        "derived": {"diffuse_normals": "diffuse_vectors / |diffuse_vectors| (per channel), on access"},
        "workers": n_workers,
    }
    if table is not None and lut is not None:
        prov["lut"] = {"size": lut.size, "smoothing_rad": lut.smoothing_rad, "solve_grid": table.size,
                       **lut.provenance}
    return GradientMaps(
        albedo=albedo, diffuse_vectors=dvec, diffuse_normals=UnitVectorMap(dvec), masks=masks, tau_ratio=tau, eta=float(eta),
        view_dirs=vd_store, specular_albedo=s_alb, specular_normals=s_norm, reflection_vectors=s_refl,
        specular_unknown=s_unk, consistency=cons_out, provenance=prov)
