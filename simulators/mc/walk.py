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

Environment next-event estimation (``env_nee``, a table from :func:`.lights.env_nee_table`): a map's bright
pixels (a sun lobe) are found by escaping walks only when a walk happens to leave towards them, so a 3.5 deg sun
made 1024-spp frames 24-36 % noisy per pixel. Instead, at every collision one direction w is drawn from those
pixels (pixel by power, then uniformly in solid angle within it: pdf = P_pixel / Omega_pixel) and connected like
a point light far away in direction w (``far_mm`` from the origin, intensity L / pdf x far^2, so its irradiance is
L / pdf): the refracted connections of :mod:`.nee`, roulette, occlusion and derivatives included. Escaping paths
look those pixels up as 0 (the renderer passes the map without them) when they left straight from their last
scattering vertex — exactly the paths the connection covers; a path whose last stretch inside had an internal
(Fresnel or total) reflection, or that never scattered, still finds them (measured without this split: a box at
eta 1.3 under a sun 3.4 % dark, 2.8 standard errors), so nothing is counted twice or lost. Through a refracting
convex faceted body (``chain_prm``, a face table) the straight connection is the closed form for a light at
infinity (:func:`.env_chains.distant_face_connections`), and chains of 1..``chain_k`` internal reflections are
connected as well (:func:`.env_chains.chain_nee`); escaping paths then look the sun pixels up as 0 after at most
``chain_k`` internal reflections since their last scattering vertex (the reflected lookups carried 98-99 % of the
sun-lit variance of the zoo's boxes, docs/monte-carlo.md "Sun lobes"). Pharr, Jakob,
Humphreys PBR 3rd ed. sec. 14.2.4 (infinite area lights sampled by a piecewise-constant distribution).

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

import numpy as np
from numba import njit

from .env_chains import chain_nee, distant_face_connections
from .nee import point_light_nee
from .optics import fresnel_r, reflect, refract, sample_hg_cos, spin
from .rng import uniform
from .shapes import nearest_hit_below, surface_distance

__all__ = ["walk", "EXITED", "TERMINATED", "TRUNCATED"]

EXITED, TERMINATED, TRUNCATED = 0, 1, 2
_TWO_PI = 2.0 * math.pi


#: relative step of the forward difference in sigma_t of a next-event connection (derivative estimates)
_NEE_FD_REL = 1e-6


@njit(cache=True, error_model="numpy")
def walk(kind, prm, nbox, nidx, tris, eps_t, nudge, stack, x, y, z, dx, dy, dz, state,
         sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
         light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau, want_d, n0, len0,
         env_nee, env_h, env_w, far_mm, chain_prm, chain_k):
    """Walk from (x, y, z) inside along unit (dx, dy, dz) with weight 1.

    Returns (status, x, y, z, dx, dy, dz, weight, nee, state, collisions, length, nee_ds, nee_da, straight): at EXITED the
    position is just outside the boundary and the direction the refracted outgoing one; ``nee`` is the sum of
    next-event contributions (0 without lights); ``length`` the distance travelled inside (including the last
    flight to the boundary). With ``want_d``, ``nee_ds`` and ``nee_da`` are the derivatives of ``nee`` with
    respect to log sigma_s and log sigma_a (module docstring), for a path that had ``n0`` scattering events and
    length ``len0`` inside before this walk (non-convex bodies are entered several times); else 0. ``straight``: the
    path has scattered and left from its last scattering vertex after at most ``chain_k`` internal reflections (0:
    straight), i.e. on a chain the environment connections cover. ``chain_prm``: the convex face table through
    which the environment connections also follow chains of 1..``chain_k`` internal reflections
    (:func:`.env_chains.chain_nee`; ``chain_k`` = 0: straight connections only).
    """
    w = 1.0
    nee = 0.0
    nee_ds = 0.0
    nee_da = 0.0
    n_coll = 0
    length = 0.0
    do_nee = light_pos.shape[0] > 0
    do_env = env_nee.shape[0] > 0
    one_pos = np.zeros((1, 3))
    one_int = np.ones(1)
    one_cdf = np.ones(1)
    inv_eta = 1.0 / eta
    sigma_s = sigma_t * albedo
    sigma_a = sigma_t - sigma_s
    st_fd = sigma_t * (1.0 + _NEE_FD_REL)
    n_refl = 0  # internal reflections since the last collision
    env_faces = do_env and chain_prm.shape[0] > 0      # distant-light connections through the convex face table
    do_chain = env_faces and chain_k > 0
    chain_work = np.zeros((max(chain_k, 0) + 1, 5))
    while True:
        state, u = uniform(state)
        s = -math.log(u) / sigma_t
        # only a crossing before the sampled flight's end matters (the query consumes no random numbers, so the
        # walk is the same as with the unbounded query; meshes prune their BVH at s: deep flights are cheap)
        t_b, nx, ny, nz = nearest_hit_below(kind, prm, nbox, nidx, tris, x, y, z, dx, dy, dz, eps_t, stack, s)
        if s < t_b:
            x += s * dx
            y += s * dy
            z += s * dz
            length += s
            n_coll += 1
            n_refl = 0
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
            if do_env:
                state, u_rr = uniform(state)
                e_surf = math.exp(-sigma_t * surface_distance(kind, prm, x, y, z))
                if u_rr * nee_tau < e_surf:
                    state, u_p = uniform(state)
                    state, u_t = uniform(state)
                    state, u_f = uniform(state)
                    lo, hi = 0, env_nee.shape[0] - 1
                    while lo < hi:
                        mid = (lo + hi) // 2
                        if env_nee[mid, 0] < u_p:
                            lo = mid + 1
                        else:
                            hi = mid
                    pmf = env_nee[lo, 0] - (env_nee[lo - 1, 0] if lo > 0 else 0.0)
                    if pmf > 0.0:
                        row, col = env_nee[lo, 1], env_nee[lo, 2]
                        c0 = math.cos(math.pi * row / env_h)
                        c1 = math.cos(math.pi * (row + 1.0) / env_h)
                        ct_l = c0 + u_t * (c1 - c0)
                        st_l = math.sqrt(max(0.0, 1.0 - ct_l * ct_l))
                        phi = 2.0 * math.pi * (col + u_f) / env_w
                        one_pos[0, 0] = far_mm * st_l * math.cos(phi)
                        one_pos[0, 1] = far_mm * st_l * math.sin(phi)
                        one_pos[0, 2] = far_mm * ct_l
                        one_int[0] = env_nee[lo, 3] * env_nee[lo, 4] / pmf * far_mm * far_mm
                        if env_faces:
                            # the closed form with the light at infinity, gated like the chains below
                            q_c = min(1.0, e_surf / nee_tau)
                            l_over_pdf = env_nee[lo, 3] * env_nee[lo, 4] / pmf / q_c
                            v_f, vl_f = distant_face_connections(chain_prm, x, y, z, dx, dy, dz, st_l * math.cos(phi),
                                                                 st_l * math.sin(phi), ct_l, eta, sigma_t, g)
                            c = w * albedo * l_over_pdf * v_f
                            nee += c
                            if want_d and v_f != 0.0:
                                dconn = -w * albedo * l_over_pdf * vl_f
                                tot_len = len0 + length
                                nee_ds += c * (n0 + n_coll - sigma_s * tot_len) + sigma_s * dconn
                                nee_da += -c * sigma_a * tot_len + sigma_a * dconn
                            p_env = 0.0
                        else:
                            p_env = point_light_nee(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dx, dy, dz,
                                                    sigma_t, g, eta, one_pos, one_int, one_cdf, False, n_scan,
                                                    nee_tau, u_rr, 0.0, sigma_t)
                        c = w * albedo * p_env
                        nee += c
                        if want_d and p_env != 0.0:
                            p_fd = point_light_nee(kind, prm, nbox, nidx, tris, eps_t, stack, x, y, z, dx, dy, dz,
                                                   sigma_t, g, eta, one_pos, one_int, one_cdf, False, n_scan,
                                                   nee_tau, u_rr, 0.0, st_fd)
                            dconn = w * albedo * (p_fd - p_env) / (st_fd - sigma_t)
                            tot_len = len0 + length
                            nee_ds += c * (n0 + n_coll - sigma_s * tot_len) + sigma_s * dconn
                            nee_da += -c * sigma_a * tot_len + sigma_a * dconn
                        if do_chain:
                            # chains of internal reflections to the same sun direction, evaluated with the gate's
                            # probability q = min(1, exp(-sigma_t d_surf) / nee_tau) (every chain is longer than
                            # d_surf) and divided by it
                            q_c = min(1.0, e_surf / nee_tau)
                            v_ch, vl_ch, state = chain_nee(chain_prm, x, y, z, dx, dy, dz, st_l * math.cos(phi),
                                                           st_l * math.sin(phi), ct_l, eta, sigma_t, g, chain_k,
                                                           chain_work, state)
                            if v_ch != 0.0:
                                l_over_pdf = env_nee[lo, 3] * env_nee[lo, 4] / pmf / q_c
                                c = w * albedo * l_over_pdf * v_ch
                                nee += c
                                if want_d:
                                    dconn = -w * albedo * l_over_pdf * vl_ch   # d c / d sigma_t (attenuation)
                                    tot_len = len0 + length
                                    nee_ds += c * (n0 + n_coll - sigma_s * tot_len) + sigma_s * dconn
                                    nee_da += -c * sigma_a * tot_len + sigma_a * dconn
            w *= albedo
            if w < rr_weight:
                state, u = uniform(state)
                if u < rr_survival:
                    w /= rr_survival
                else:
                    return TERMINATED, x, y, z, dx, dy, dz, 0.0, nee, state, n_coll, length, nee_ds, nee_da, False
            if n_coll >= max_collisions:
                return TRUNCATED, x, y, z, dx, dy, dz, 0.0, nee, state, n_coll, length, nee_ds, nee_da, False
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
                n_refl += 1
            else:
                ok, tx, ty, tz = refract(dx, dy, dz, -nx, -ny, -nz, inv_eta)
                if not ok:  # numerically at the critical angle: reflect
                    dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
                    x -= nudge * nx
                    y -= nudge * ny
                    z -= nudge * nz
                    n_refl += 1
                    continue
                x += nudge * nx
                y += nudge * ny
                z += nudge * nz
                return (EXITED, x, y, z, tx, ty, tz, w, nee, state, n_coll, length, nee_ds, nee_da,
                        (n0 + n_coll) > 0 and n_refl <= (chain_k if do_chain else 0))
