"""The random walk inside a homogeneous medium (numba kernel shared by the renderer and the profile tools).

From a point just inside the boundary, a photon (or, run backwards from the camera, an importance particle —
the transport here is reciprocal) travels exponential free flights of rate sigma_t, scatters with the
Henyey-Greenstein phase function, and carries a weight multiplied by the single-scattering albedo at each
collision (implicit capture / survival biasing, MCML sec. 3.4-3.6). At the boundary it is reflected with the
unpolarized Fresnel probability F_r(1/eta, cos) (total internal reflection included; eta = 1: never) and leaves
otherwise, refracted by Snell's law. Russian roulette when the weight falls below ``rr_weight``: the walk
survives with probability ``rr_survival`` and its weight is divided by it, which keeps the estimator unbiased
(MCML sec. 3.7). ``max_collisions`` is a safety cap; walks that hit it are reported (status TRUNCATED), their
weight is lost, so the truncated fraction bounds the bias.

With point lights, every collision adds next-event estimation (:mod:`.nee`) weighted by w * albedo; each
connection is done with probability q = min(1, exp(-sigma_t l_min) / nee_tau) and divided by q (l_min a lower
bound on its length inside the medium, so exp(-sigma_t l_min) bounds its transmittance): deep or shadowed
vertices, whose contribution is exponentially small, are skipped most of the time without bias.

References: Wang, Jacques, Zheng 1995 (MCML); Prahl, Keijzer, Jacques, Welch 1989 (Monte Carlo model of light
propagation in tissue); Pharr, Jakob, Humphreys, PBR 3rd ed. ch. 15 (volumetric path tracing, NEE).
"""
from __future__ import annotations

import math

from numba import njit

from .nee import point_light_nee
from .optics import fresnel_r, reflect, refract, sample_hg_cos, spin
from .rng import uniform
from .shapes import nearest_hit, surface_distance

__all__ = ["walk", "EXITED", "TERMINATED", "TRUNCATED"]

EXITED, TERMINATED, TRUNCATED = 0, 1, 2
_TWO_PI = 2.0 * math.pi


@njit(cache=True, error_model="numpy")
def walk(kind, prm, nbox, nidx, tris, eps_t, nudge, stack, x, y, z, dx, dy, dz, state,
         sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
         light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau):
    """Walk from (x, y, z) inside along unit (dx, dy, dz) with weight 1.

    Returns (status, x, y, z, dx, dy, dz, weight, nee, state, collisions): at EXITED the position is just
    outside the boundary and the direction the refracted outgoing one; ``nee`` is the sum of next-event
    contributions (0 without lights).
    """
    w = 1.0
    nee = 0.0
    n_coll = 0
    do_nee = light_pos.shape[0] > 0
    inv_eta = 1.0 / eta
    while True:
        t_b, nx, ny, nz = nearest_hit(kind, prm, nbox, nidx, tris, x, y, z, dx, dy, dz, eps_t, stack)
        state, u = uniform(state)
        s = -math.log(u) / sigma_t
        if s < t_b:
            x += s * dx
            y += s * dy
            z += s * dz
            n_coll += 1
            if do_nee:
                state, u_rr = uniform(state)
                # every connection's roulette probability is <= exp(-sigma_t d_surf) / nee_tau: reject cheaply
                if u_rr * nee_tau < math.exp(-sigma_t * surface_distance(kind, prm, x, y, z)):
                    state, u_pick = uniform(state)
                    nee += w * albedo * point_light_nee(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z,
                                                        dx, dy, dz, sigma_t, g, eta, light_pos, light_int,
                                                        light_cdf, sample_one, n_scan, nee_tau, u_rr, u_pick)
            w *= albedo
            if w < rr_weight:
                state, u = uniform(state)
                if u < rr_survival:
                    w /= rr_survival
                else:
                    return TERMINATED, x, y, z, dx, dy, dz, 0.0, nee, state, n_coll
            if n_coll >= max_collisions:
                return TRUNCATED, x, y, z, dx, dy, dz, 0.0, nee, state, n_coll
            state, u = uniform(state)
            ct = sample_hg_cos(g, u)
            state, u = uniform(state)
            dx, dy, dz = spin(dx, dy, dz, ct, _TWO_PI * u)
        else:
            x += t_b * dx
            y += t_b * dy
            z += t_b * dz
            cos_i = dx * nx + dy * ny + dz * nz
            fr = fresnel_r(inv_eta, cos_i)
            state, u = uniform(state)
            if u < fr:
                dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
                x -= nudge * nx
                y -= nudge * ny
                z -= nudge * nz
            else:
                ok, tx, ty, tz = refract(dx, dy, dz, -nx, -ny, -nz, inv_eta)
                if not ok:  # numerically at the critical angle: reflect
                    dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
                    x -= nudge * nx
                    y -= nudge * ny
                    z -= nudge * nz
                    continue
                x += nudge * nx
                y += nudge * ny
                z += nudge * nz
                return EXITED, x, y, z, tx, ty, tz, w, nee, state, n_coll
