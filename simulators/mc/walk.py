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

Derivatives (``want_d``): the same paths also estimate the derivatives of every contribution with respect to
log sigma_s and log sigma_a (perturbation Monte Carlo, the likelihood-ratio / score-function estimator; Hayakawa
et al. 2001, "Perturbation Monte Carlo methods to solve inverse photon migration problems in heterogeneous
tissues", Opt. Lett. 26(17); Gkioulekas et al. 2013, "Inverse volume rendering with material dictionaries", use
the same differentiation of the path throughput). A path with N scattering events and length L inside the medium
has the throughput sigma_s^N exp(-sigma_t L) times factors that do not depend on the medium, so its contribution
C has d C / d log sigma_s = C (N - sigma_s L) and d C / d log sigma_a = -C sigma_a L; a next-event connection adds
its own attenuation exp(-sigma_t l_c), whose derivative is taken by a forward difference in sigma_t of the
(deterministic) connection with the same roulette decision. Roulette and the Fresnel choices are sampling
decisions and leave the score unchanged, so both estimates are unbiased; their variance grows like N.

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


#: relative step of the forward difference in sigma_t of a next-event connection (derivative estimates)
_NEE_FD_REL = 1e-6


@njit(cache=True, error_model="numpy")
def walk(kind, prm, nbox, nidx, tris, eps_t, nudge, stack, x, y, z, dx, dy, dz, state,
         sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
         light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau, want_d, n0, len0):
    """Walk from (x, y, z) inside along unit (dx, dy, dz) with weight 1.

    Returns (status, x, y, z, dx, dy, dz, weight, nee, state, collisions, length, nee_ds, nee_da): at EXITED the
    position is just outside the boundary and the direction the refracted outgoing one; ``nee`` is the sum of
    next-event contributions (0 without lights); ``length`` the distance travelled inside (including the last
    flight to the boundary). With ``want_d``, ``nee_ds`` and ``nee_da`` are the derivatives of ``nee`` with
    respect to log sigma_s and log sigma_a (module docstring), for a path that had ``n0`` scattering events and
    length ``len0`` inside before this walk (non-convex bodies are entered several times); else 0.
    """
    w = 1.0
    nee = 0.0
    nee_ds = 0.0
    nee_da = 0.0
    n_coll = 0
    length = 0.0
    do_nee = light_pos.shape[0] > 0
    inv_eta = 1.0 / eta
    sigma_s = sigma_t * albedo
    sigma_a = sigma_t - sigma_s
    st_fd = sigma_t * (1.0 + _NEE_FD_REL)
    while True:
        t_b, nx, ny, nz = nearest_hit(kind, prm, nbox, nidx, tris, x, y, z, dx, dy, dz, eps_t, stack)
        state, u = uniform(state)
        s = -math.log(u) / sigma_t
        if s < t_b:
            x += s * dx
            y += s * dy
            z += s * dz
            length += s
            n_coll += 1
            if do_nee:
                state, u_rr = uniform(state)
                # every connection's roulette probability is <= exp(-sigma_t d_surf) / nee_tau: reject cheaply
                if u_rr * nee_tau < math.exp(-sigma_t * surface_distance(kind, prm, x, y, z)):
                    state, u_pick = uniform(state)
                    p_nee = point_light_nee(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z,
                                            dx, dy, dz, sigma_t, g, eta, light_pos, light_int,
                                            light_cdf, sample_one, n_scan, nee_tau, u_rr, u_pick, sigma_t)
                    c = w * albedo * p_nee
                    nee += c
                    if want_d and p_nee != 0.0:
                        p_fd = point_light_nee(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z,
                                               dx, dy, dz, sigma_t, g, eta, light_pos, light_int,
                                               light_cdf, sample_one, n_scan, nee_tau, u_rr, u_pick, st_fd)
                        dconn = w * albedo * (p_fd - p_nee) / (st_fd - sigma_t)  # d c / d sigma_t (connection)
                        tot_len = len0 + length
                        nee_ds += c * (n0 + n_coll - sigma_s * tot_len) + sigma_s * dconn
                        nee_da += -c * sigma_a * tot_len + sigma_a * dconn
            w *= albedo
            if w < rr_weight:
                state, u = uniform(state)
                if u < rr_survival:
                    w /= rr_survival
                else:
                    return TERMINATED, x, y, z, dx, dy, dz, 0.0, nee, state, n_coll, length, nee_ds, nee_da
            if n_coll >= max_collisions:
                return TRUNCATED, x, y, z, dx, dy, dz, 0.0, nee, state, n_coll, length, nee_ds, nee_da
            state, u = uniform(state)
            ct = sample_hg_cos(g, u)
            state, u = uniform(state)
            dx, dy, dz = spin(dx, dy, dz, ct, _TWO_PI * u)
        else:
            x += t_b * dx
            y += t_b * dy
            z += t_b * dz
            length += t_b
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
                return EXITED, x, y, z, tx, ty, tz, w, nee, state, n_coll, length, nee_ds, nee_da
