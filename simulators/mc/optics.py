"""Scalar optics for the numba kernels: unpolarized Fresnel reflectance, refraction and reflection of unit vectors,
Henyey-Greenstein sampling and evaluation.

The Fresnel formula is the one of :func:`estimation.fresnel.fresnel_reflectance` (exact unpolarized
s/p average, total internal reflection, eta = 1 handled), written for scalars; the tests compare the two.
HG sampling follows Wang, Jacques, Zheng 1995 (MCML) / Witt 1977; the direction update is MCML's "spin".
"""
from __future__ import annotations

import math

from numba import njit

__all__ = ["fresnel_r", "refract", "reflect", "hg_phase", "sample_hg_cos", "spin", "orthonormal_basis"]

_INV4PI = 1.0 / (4.0 * math.pi)


@njit(cache=True, error_model="numpy")
def fresnel_r(eta_rel, cos_i):
    """Unpolarized Fresnel reflectance for light going from index n_i to n_t, eta_rel = n_t/n_i, cos_i in [0, 1]."""
    c = min(max(cos_i, 0.0), 1.0)
    e2c = eta_rel * eta_rel - 1.0 + c * c  # eta^2 cos_t^2
    if e2c < 0.0:
        return 1.0  # total internal reflection
    cos_t = math.sqrt(e2c) / eta_rel
    den_s = c + eta_rel * cos_t
    den_p = eta_rel * c + cos_t
    if den_s <= 0.0 or den_p <= 0.0:
        return 1.0  # grazing
    r_s = (c - eta_rel * cos_t) / den_s
    r_p = (eta_rel * c - cos_t) / den_p
    f = 0.5 * (r_s * r_s + r_p * r_p)
    return min(max(f, 0.0), 1.0)


@njit(cache=True, error_model="numpy")
def refract(dx, dy, dz, nx, ny, nz, eta_rel):
    """Refract unit direction d through a surface with unit normal n on the incident side (d.n < 0).

    eta_rel = n_t / n_i. Returns (ok, tx, ty, tz); ok is False under total internal reflection.
    """
    cos_i = -(dx * nx + dy * ny + dz * nz)
    inv = 1.0 / eta_rel
    sin2_t = inv * inv * max(0.0, 1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return False, dx, dy, dz
    cos_t = math.sqrt(1.0 - sin2_t)
    k = inv * cos_i - cos_t
    tx = inv * dx + k * nx
    ty = inv * dy + k * ny
    tz = inv * dz + k * nz
    s = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
    return True, tx * s, ty * s, tz * s


@njit(cache=True, inline="always")
def reflect(dx, dy, dz, nx, ny, nz):
    """Mirror direction d about the plane with unit normal n."""
    k = 2.0 * (dx * nx + dy * ny + dz * nz)
    return dx - k * nx, dy - k * ny, dz - k * nz


@njit(cache=True, error_model="numpy")
def hg_phase(g, cos_theta):
    """Henyey-Greenstein phase function [1/sr], normalized over the sphere; cos_theta between propagation
    directions before and after scattering."""
    if abs(g) < 1e-6:
        return _INV4PI
    den = 1.0 + g * g - 2.0 * g * cos_theta
    return _INV4PI * (1.0 - g * g) / (den * math.sqrt(den))


@njit(cache=True, error_model="numpy")
def sample_hg_cos(g, u):
    """cos(theta) of the scattering angle drawn from HG(g) with uniform u (MCML Eq. 3.28)."""
    if abs(g) < 1e-6:
        return 2.0 * u - 1.0
    t = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    c = (1.0 + g * g - t * t) / (2.0 * g)
    return min(max(c, -1.0), 1.0)


@njit(cache=True, error_model="numpy")
def spin(dx, dy, dz, cos_t, phi):
    """Rotate unit direction d by polar angle acos(cos_t) and azimuth phi (MCML Eq. 3.31-3.32)."""
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    cp = math.cos(phi)
    sp = math.sin(phi)
    if abs(dz) > 0.99999:
        sgn = 1.0 if dz > 0 else -1.0
        return sin_t * cp, sin_t * sp, sgn * cos_t
    tmp = math.sqrt(1.0 - dz * dz)
    nx = sin_t * (dx * dz * cp - dy * sp) / tmp + dx * cos_t
    ny = sin_t * (dy * dz * cp + dx * sp) / tmp + dy * cos_t
    nz = -sin_t * cp * tmp + dz * cos_t
    s = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
    return nx * s, ny * s, nz * s


@njit(cache=True, error_model="numpy")
def orthonormal_basis(nx, ny, nz):
    """Two unit vectors completing n to a right-handed orthonormal basis (Duff et al. 2017)."""
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return (1.0 + sign * nx * nx * a, sign * b, -sign * nx), (b, sign + ny * ny * a, -ny)
