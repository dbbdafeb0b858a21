"""Monte Carlo reference images of a homogeneous translucent object (subsurface light, optional specular).

For each pixel the camera ray meets the boundary at x_o (meshes: first hit of the BVH); the subsurface estimate
enters with the Fresnel transmittance, L_out = (F_t(eta, cos_o) / eta^2) L_in (the n^2 law of radiance), refracts,
and runs :func:`.walk.walk` backwards (light transport in the medium is reciprocal; the HG phase function is
symmetric). The two kinds of light are estimated without bias by:

- distant radiance (environment maps, gradient patterns): a walk that leaves the medium (Fresnel sampled at
  every boundary hit, total internal reflection included) carries eta^2 L_in -> L_out and looks the radiance up
  in its refracted exit direction. Non-convex meshes: the exit ray is traced and re-enters the object (Fresnel
  sampled again) when it hits it, so inter-reflection through the outside is exact.
- point lights: next-event estimation at every collision (:mod:`.nee`): straight-line connections with exact
  occlusion for eta = 1; refracted connections through smooth analytic boundaries (half-space, slab, box,
  sphere), convex triangle meshes, and non-convex meshes (shadow rays inside and outside; every face plane,
  :func:`.nee.nonconvex_mesh_connections`, up to ``MAX_CONNECTION_PLANES`` planes, else the triangles within the
  connection radius found by the BVH, :func:`.nee.bvh_mesh_connections`) for eta != 1. A point light is never
  hit by an escaping walk, so nothing is counted twice.

Estimator per pixel: ``spp`` independent paths, each with its own random stream keyed by (seed, channel, pixel,
sample) (:mod:`.rng`), so the image does not depend on the thread count or schedule; the per-pixel mean and its
standard error (sample standard deviation / sqrt(spp), Welford's update) are returned. The specular reflection
of distant radiance (``include_specular``; a point light's mirror image is a delta and is never seen) is added
deterministically for convex shapes and traced as a path for non-convex meshes (the mirrored ray may meet the
object again, which is then seen with its own subsurface and specular light).

Units: the image is radiance in the lights' units (point lights: intensity / mm^2 per sr; distant radiance: the
map's units).

References: Jensen et al. 2001 (BSSRDF picture); Pharr, Jakob, Humphreys, PBR 3rd ed. sec. 8.2, 15.3 (Fresnel,
radiance across an interface, volumetric path tracing with NEE); Veach 1997 ch. 5 (non-symmetric scattering due
to refraction).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import numpy.typing as npt
from numba import njit, prange

from .env_chains import MAX_CHAIN_REFLECTIONS
from .lights import kernel_lights
from .media import Medium
from .optics import fresnel_r, reflect, refract
from .rng import stream, uniform
from .shapes import (BOX, MESH, SPHERE, STACK_SIZE, Shape, convex_face_table, nearest_hit,
                     refracted_point_lights_supported)
from .walk import EXITED, TRUNCATED, walk

__all__ = ["MCImage", "render"]

FloatArray = npt.NDArray[np.float64]
_INV_PI = 1.0 / math.pi
_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class MCImage:
    """A rendered image: radiance (H, W, C), its per-pixel standard error (H, W, C), object mask (H, W)."""

    radiance: FloatArray
    stderr: FloatArray
    mask: npt.NDArray[np.bool_]
    spp: int
    seed: int
    seconds: float
    mean_collisions: float       # per path
    truncated_fraction: float    # paths stopped by max_collisions (their weight is lost)
    #: with ``render(..., derivatives=True)``: d radiance / d (log sigma_s, log sigma_a) (H, W, C, 2) from the same
    #: paths (score-function estimates, :mod:`.walk`; sigma_s is the unreduced scattering coefficient, so at fixed
    #: g this is also the derivative with respect to log sigma_s'), and its per-pixel standard error; else None
    d_log_sigma: FloatArray | None = None
    d_log_sigma_stderr: FloatArray | None = None


@njit(cache=True, error_model="numpy")
def env_radiance(dx, dy, dz, env_map, has_map, aff, has_aff):
    """Distant radiance towards direction d: lat-long map (row 0 = +z, azimuth from +x towards +y) + a + b.d."""
    val = 0.0
    if has_map:
        h, w = env_map.shape
        theta = math.acos(min(1.0, max(-1.0, dz)))
        phi = math.atan2(dy, dx)
        if phi < 0.0:
            phi += _TWO_PI
        i = min(h - 1, int(theta * _INV_PI * h))
        j = min(w - 1, int(phi / _TWO_PI * w))
        val += env_map[i, j]
    if has_aff:
        val += max(0.0, aff[0] + aff[1] * dx + aff[2] * dy + aff[3] * dz)
    return val


@njit(cache=True, error_model="numpy")
def _trace_path(kind, prm, nbox, nidx, tris, eps_t, nudge, convex, stack, inside, x, y, z, dx, dy, dz, beta, state,
                sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
                light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau,
                env_map, has_map, aff, has_aff, max_bounces, want_d, env_rest, env_nee, far_mm, chain_prm, chain_k):
    """Radiance estimate of one camera path with throughput ``beta`` that starts just inside the medium
    (``inside``) or just outside it, travelling along d. Alternates walks inside and ray segments outside
    (Fresnel sampled at every hit from outside) until the path escapes, is absorbed or hits ``max_bounces``.
    Returns (value, d value / d log sigma_s, d value / d log sigma_a, state, collisions, truncated); the two
    derivatives (score-function estimates, :mod:`.walk`) are 0 unless ``want_d``. With environment next-event
    estimation (``env_nee`` rows), a ray that leaves the medium straight from its last scattering vertex and escapes
    at once looks up ``env_rest`` (the map without the pixels the walk's connections sample, :mod:`.walk`); any other
    escaping ray (an internal reflection since the vertex, a reflection off the outside) the whole ``env_map``."""
    value = 0.0
    v_ds = 0.0
    v_da = 0.0
    has_env = has_map or has_aff
    e2 = eta * eta
    sigma_s = sigma_t * albedo
    sigma_a = sigma_t - sigma_s
    n_coll = 0
    len_in = 0.0  # path length inside the medium so far
    truncated = False
    just_exited = False
    straight_exit = False
    for _ in range(2 * max_bounces):
        if inside:
            status, x, y, z, dx, dy, dz, w, nee, state, nc, seg_len, nee_ds, nee_da, straight = walk(
                kind, prm, nbox, nidx, tris, eps_t, nudge, stack, x, y, z, dx, dy, dz, state,
                sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
                light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau, want_d, n_coll, len_in,
                env_nee, env_map.shape[0], env_map.shape[1], far_mm, chain_prm, chain_k)
            n_coll += nc
            len_in += seg_len
            value += beta * nee
            if want_d:
                v_ds += beta * nee_ds
                v_da += beta * nee_da
            if status != EXITED:
                truncated = status == TRUNCATED
                break
            beta *= w * e2
            inside = False
            just_exited = True
            straight_exit = straight
            continue
        if convex and just_exited:
            t = math.inf  # a ray leaving a convex object never meets it again
            nx = ny = nz = 0.0
        else:
            t, nx, ny, nz = nearest_hit(kind, prm, nbox, nidx, tris, x, y, z, dx, dy, dz, eps_t, stack)
        direct = just_exited and straight_exit
        just_exited = False
        if t == math.inf:
            if has_env:
                c_env = beta * env_radiance(dx, dy, dz, env_rest if direct else env_map, has_map, aff, has_aff)
                value += c_env
                if want_d:
                    v_ds += c_env * (n_coll - sigma_s * len_in)
                    v_da -= c_env * sigma_a * len_in
            break
        x += t * dx
        y += t * dy
        z += t * dz
        fr = fresnel_r(eta, -(dx * nx + dy * ny + dz * nz))
        state, u = uniform(state)
        if u < fr:
            dx, dy, dz = reflect(dx, dy, dz, nx, ny, nz)
            x += nudge * nx
            y += nudge * ny
            z += nudge * nz
            continue
        ok, dx, dy, dz = refract(dx, dy, dz, nx, ny, nz, eta)
        x -= nudge * nx
        y -= nudge * ny
        z -= nudge * nz
        beta /= e2
        inside = True
    return value, v_ds, v_da, state, n_coll, truncated


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def _render_kernel(origins, dirs, spp, seed, channel, pixel_ids, kind, prm, nbox, nidx, tris, eps_t, nudge, convex,
                   sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
                   light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau,
                   env_map, has_map, aff, has_aff, include_specular, max_bounces, want_d, env_rest, env_nee, far_mm, chain_prm, chain_k,
                   fd_h, sigma_t2, albedo2,
                   out_mean, out_se, out_hit, out_coll, out_trunc, out_d, out_d_se):
    n_pix = origins.shape[0]
    for p in prange(n_pix):
        stack = np.empty(STACK_SIZE, np.int64)
        ox, oy, oz = origins[p, 0], origins[p, 1], origins[p, 2]
        dx, dy, dz = dirs[p, 0], dirs[p, 1], dirs[p, 2]
        t, nx, ny, nz = nearest_hit(kind, prm, nbox, nidx, tris, ox, oy, oz, dx, dy, dz, eps_t, stack)
        if t == math.inf:
            out_hit[p] = False
            out_mean[p] = 0.0
            out_se[p] = 0.0
            if want_d:
                for q in range(2):
                    out_d[p, q] = 0.0
                    out_d_se[p, q] = 0.0
            continue
        out_hit[p] = True
        hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
        cos_o = -(dx * nx + dy * ny + dz * nz)
        fr = fresnel_r(eta, cos_o)
        spec = 0.0
        rx, ry, rz = reflect(dx, dy, dz, nx, ny, nz)
        spec_paths = include_specular and (has_map or has_aff) and not convex
        if include_specular and (has_map or has_aff) and convex:
            spec = fr * env_radiance(rx, ry, rz, env_map, has_map, aff, has_aff)
        ok, tx, ty, tz = refract(dx, dy, dz, nx, ny, nz, eta)
        beta0 = (1.0 - fr) / (eta * eta)
        mean = 0.0
        m2 = 0.0
        mean_s = 0.0
        m2_s = 0.0
        mean_a = 0.0
        m2_a = 0.0
        coll = 0
        trunc = 0
        if (ok and beta0 > 0.0) or spec_paths:
            for k in range(spp):
                state = stream(seed, channel, pixel_ids[p], k)
                state0 = state
                val = 0.0
                val_s = 0.0
                val_a = 0.0
                if ok and beta0 > 0.0:
                    val, val_s, val_a, state, nc, tr = _trace_path(
                        kind, prm, nbox, nidx, tris, eps_t, nudge, convex, stack, True,
                        hx - nudge * nx, hy - nudge * ny, hz - nudge * nz, tx, ty, tz, beta0, state,
                        sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
                        light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau,
                        env_map, has_map, aff, has_aff, max_bounces, want_d, env_rest, env_nee, far_mm, chain_prm, chain_k)
                    coll += nc
                    if tr:
                        trunc += 1
                if spec_paths and fr > 0.0:  # non-convex: the mirrored ray may see the object itself
                    v2, v2_s, v2_a, state, nc, tr = _trace_path(
                        kind, prm, nbox, nidx, tris, eps_t, nudge, convex, stack, False,
                        hx + nudge * nx, hy + nudge * ny, hz + nudge * nz, rx, ry, rz, fr, state,
                        sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
                        light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau,
                        env_map, has_map, aff, has_aff, max_bounces, want_d, env_rest, env_nee, far_mm, chain_prm, chain_k)
                    val += v2
                    val_s += v2_s
                    val_a += v2_a
                    coll += nc
                    if tr:
                        trunc += 1
                if want_d and fd_h > 0.0:
                    # the same path (same random stream) at log sigma_s + fd_h: a paired forward difference
                    state = state0
                    w1 = 0.0
                    if ok and beta0 > 0.0:
                        w1, _s1, _a1, state, nc, tr = _trace_path(
                            kind, prm, nbox, nidx, tris, eps_t, nudge, convex, stack, True,
                            hx - nudge * nx, hy - nudge * ny, hz - nudge * nz, tx, ty, tz, beta0, state,
                            sigma_t2, albedo2, g, eta, rr_weight, rr_survival, max_collisions,
                            light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau,
                            env_map, has_map, aff, has_aff, max_bounces, False, env_rest, env_nee, far_mm, chain_prm, chain_k)
                    if spec_paths and fr > 0.0:
                        w2, _s2, _a2, state, nc, tr = _trace_path(
                            kind, prm, nbox, nidx, tris, eps_t, nudge, convex, stack, False,
                            hx + nudge * nx, hy + nudge * ny, hz + nudge * nz, rx, ry, rz, fr, state,
                            sigma_t2, albedo2, g, eta, rr_weight, rr_survival, max_collisions,
                            light_pos, light_int, light_cdf, sample_one, n_scan, nee_tau,
                            env_map, has_map, aff, has_aff, max_bounces, False, env_rest, env_nee, far_mm, chain_prm, chain_k)
                        w1 += w2
                    val_s = (w1 - val) / fd_h
                delta = val - mean
                mean += delta / (k + 1)
                m2 += delta * (val - mean)
                if want_d:
                    delta = val_s - mean_s
                    mean_s += delta / (k + 1)
                    m2_s += delta * (val_s - mean_s)
                    delta = val_a - mean_a
                    mean_a += delta / (k + 1)
                    m2_a += delta * (val_a - mean_a)
        out_mean[p] = mean + spec
        out_se[p] = math.sqrt(m2 / (spp - 1) / spp) if spp > 1 else math.inf
        out_coll[p] = coll
        out_trunc[p] = trunc
        if want_d:
            out_d[p, 0] = mean_s
            out_d[p, 1] = mean_a
            out_d_se[p, 0] = math.sqrt(m2_s / (spp - 1) / spp) if spp > 1 else math.inf
            out_d_se[p, 1] = math.sqrt(m2_a / (spp - 1) / spp) if spp > 1 else math.inf


def _media_list(media: Medium | Sequence[Medium]) -> list[Medium]:
    if isinstance(media, Medium):
        return [media]
    out = list(media)
    if not out or not all(isinstance(m, Medium) for m in out):
        raise TypeError("media must be a Medium or a non-empty sequence of Medium (one per channel)")
    return out


#: environment next-event estimation through a refracting convex mesh only up to this many flat faces (``render``);
#: was 24 while each face cost a Newton solve of a far point light's connection; the closed form for a light at
#: infinity (:func:`.env_chains.distant_face_connections`) costs ~40 flops per face
ENV_NEE_MAX_FLAT_FACES: int = 4096
#: chains of internal reflections (:mod:`.env_chains`) only through convex bodies of at most this many flat faces
#: (a drawn face sequence through a near-sphere almost never holds a chain: the cost would buy nothing)
ENV_CHAIN_MAX_FLAT_FACES: int = 24


def render(shape: Shape, media: Medium | Sequence[Medium], camera: Any, lights: Any, *, spp: int = 64,
           seed: int = 0, include_specular: bool = False, nee_tau: float = 1.0, rr_weight: float = 0.01,
           rr_survival: float = 0.1, max_collisions: int = 1_000_000, max_bounces: int = 64,
           n_scan: int = 32, max_sampled_lights: int = 8, derivatives: bool = False, env_nee: bool = True,
           fd_log_sigma_s: float = 0.0, rows: tuple[int, int] | tuple[int, int, int] | None = None,
           env_chain_reflections: int | None = None) -> MCImage:
    """Render ``shape`` filled with ``media`` (one :class:`Medium` per colour channel, all with the same eta) as
    seen by ``camera`` (anything with ``width_px``, ``height_px``, ``pixel_rays()``: PinholeCamera,
    OrthographicCamera) under ``lights`` (see :mod:`.lights`).

    ``spp`` paths per pixel (>= 2 for a standard error). With more than ``max_sampled_lights`` point lights one
    light is drawn per collision with probability proportional to its intensity. ``nee_tau``, ``rr_weight``,
    ``rr_survival``: variance-only knobs (see :mod:`.walk`). ``derivatives``: also estimate, from the same paths,
    the derivatives of the radiance with respect to log sigma_s and log sigma_a of each channel's medium
    (``MCImage.d_log_sigma``; perturbation Monte Carlo, :mod:`.walk`; point-light connections cost twice).
    ``fd_log_sigma_s`` > 0 (with ``derivatives``): the derivative with respect to log sigma_s is instead the paired
    forward difference (Q(log sigma_s + h) - Q) / h over the same paths (each sample traced twice from the same
    random stream), with its standard error from the per-sample differences: for long walks (high albedo) the
    score-function estimate's variance grows with the number of collisions — measured on an apple-R box at 64 spp,
    per-patch noise ~2.5x the derivative's magnitude — where the paired difference stays well below it; it costs
    one more trace per sample. d/d log sigma_a stays the score function (~10 % per patch).
    ``rows`` = (r0, r1) or (r0, r1, step): render only the frame's rows r0, r0 + step, ... < r1 (an image of those
    rows, in order); every pixel keeps the random stream it has in the whole frame, so chunks of rows put back in
    place are bit-identical to the whole render (``rig.estimate.batch`` splits a render across Dask workers this
    way: interleaved rows, step = the number of chunks, so every chunk gets an equal share of the object).
    ``env_nee``: sample an environment map's bright pixels by next-event estimation (:mod:`.walk`; not for
    refracting non-convex meshes, whose connections are not supported, nor refracting convex meshes of more than
    :data:`ENV_NEE_MAX_FLAT_FACES` flat faces: there escaping paths find them; through refracting convex meshes and
    boxes the connections are the closed form for a light at infinity, :func:`.env_chains.distant_face_connections`). ``env_chain_reflections``: with ``env_nee`` through a refracting convex faceted body (a convex mesh
    within that face limit, or a box), the connections also follow chains of up to this many internal reflections
    (:mod:`.env_chains`; default :data:`.env_chains.MAX_CHAIN_REFLECTIONS`, 0 = straight connections only, the
    estimator before issue 15's sun-lit scenes). Raises ValueError for a point light inside the
    object, or for media with different eta. Point lights with eta != 1 through a non-convex mesh: every face
    plane is searched up to :data:`.shapes.MAX_CONNECTION_PLANES` planes, beyond that the triangles within the
    connection radius found by the BVH (:func:`.nee.bvh_mesh_connections`).
    """
    ms = _media_list(media)
    etas = {m.eta for m in ms}
    if len(etas) != 1:
        raise ValueError("all channels must share the boundary's eta")
    eta = ms[0].eta
    if spp < 1:
        raise ValueError("spp must be >= 1")
    geo = shape.geometry()
    kl = kernel_lights(lights, len(ms))
    if len(kl[0].positions_mm):
        if np.any(shape.contains(kl[0].positions_mm)):
            raise ValueError("point lights must lie outside the object")
        assert refracted_point_lights_supported(geo)       # every shape since issue 17 (BVH connections)
    origins, dirs = camera.pixel_rays()
    h, w = camera.height_px, camera.width_px
    r0, r1, step = (0, h, 1) if rows is None else (int(rows[0]), int(rows[1]), int(rows[2]) if len(rows) > 2 else 1)
    if not (0 <= r0 < r1 <= h and step >= 1 and len(rows or ()) in (0, 2, 3)):
        raise ValueError(f"rows must be (r0, r1) or (r0, r1, step) with 0 <= r0 < r1 <= height_px = {h} and "
                         f"step >= 1; got {rows!r}")
    row_idx = np.arange(r0, r1, step)
    h = len(row_idx)
    pixel_ids = (row_idx[:, None] * w + np.arange(w)[None, :]).ravel().astype(np.int64)
    o = np.ascontiguousarray(origins.reshape(-1, 3)[pixel_ids], dtype=np.float64)
    d = np.ascontiguousarray(dirs.reshape(-1, 3)[pixel_ids], dtype=np.float64)
    n = len(o)
    rad = np.zeros((n, len(ms)))
    se = np.zeros((n, len(ms)))
    # environment next-event estimation (:mod:`.walk`): needs the point-light connection, which a refracting
    # non-convex mesh does not have
    # (nor the analytic sphere's, whose stationary-point search is not made for a light 1e6 radii away: measured 0.08
    # of the path-traced image; a tessellated sphere works)
    # and not through a refracting mesh of very many flat faces: its connections are found face by face (a Newton
    # solve per face for the far point light made a 320-triangle icosphere 5x slower than plain path tracing; the
    # closed form for a light at infinity, env_chains.distant_face_connections, costs ~40 flops per face: measured on
    # the zoo's z03 icosphere by benchmarks/mc_sun_lobes.py, docs/monte-carlo.md "Sun lobes")
    refracting = abs(eta - 1.0) >= 1e-12
    env_nee = bool(env_nee) and not (geo.kind == MESH and refracting and (
        not geo.convex or int(geo.params[0]) > ENV_NEE_MAX_FLAT_FACES)) and not (geo.kind == SPHERE and refracting)
    no_nee = np.zeros((0, 5))
    # chains of internal reflections to the sun pixels (:mod:`.env_chains`): convex faceted bodies at eta != 1
    k_chain = MAX_CHAIN_REFLECTIONS if env_chain_reflections is None else int(env_chain_reflections)
    if k_chain < 0:
        raise ValueError(f"env_chain_reflections must be >= 0; got {env_chain_reflections!r}")
    chain_prm = np.zeros(0)
    if env_nee and refracting:
        if geo.kind == MESH and geo.convex and int(geo.params[0]) > 0:
            chain_prm = np.ascontiguousarray(geo.params, dtype=np.float64)
        elif geo.kind == BOX:
            import trimesh

            lo, hi = np.asarray(geo.params[:3], float), np.asarray(geo.params[3:6], float)
            bt = trimesh.creation.box(bounds=np.stack([lo, hi]))
            chain_prm = np.ascontiguousarray(convex_face_table(bt.vertices, bt.faces))
    if len(chain_prm) == 0 or int(chain_prm[0]) > ENV_CHAIN_MAX_FLAT_FACES:
        k_chain = 0
    far_mm = 1e6 * float(geo.scale_mm)
    want_d = bool(derivatives)
    d_all = np.zeros((n, len(ms), 2)) if want_d else None
    d_se_all = np.zeros((n, len(ms), 2)) if want_d else None
    hit = np.zeros(n, dtype=np.bool_)
    coll = np.zeros(n, dtype=np.int64)
    trunc = np.zeros(n, dtype=np.int64)
    tot_coll = 0
    tot_trunc = 0
    t0 = time.perf_counter()
    fd_h = float(fd_log_sigma_s) if (want_d and fd_log_sigma_s) else 0.0
    for c, (m, L) in enumerate(zip(ms, kl)):
        env_rest = L.env_rest
        # the medium at log sigma_s + fd_h (sigma_a and g fixed) for the paired difference
        m2 = None
        if fd_h > 0.0:
            s2 = m.sigma_s_per_mm * math.exp(fd_h)
            m2 = Medium(s2, m.sigma_a_per_mm, m.g, m.eta)
        mean_c = np.zeros(n)
        se_c = np.zeros(n)
        d_c = np.zeros((n if want_d else 1, 2))
        d_se_c = np.zeros((n if want_d else 1, 2))
        sample_one = len(L.positions_mm) > max_sampled_lights
        _render_kernel(o, d, int(spp), int(seed), c, pixel_ids, geo.kind, geo.params, geo.nodes_box, geo.nodes_idx,
                       geo.triangles, geo.eps_t, geo.nudge, geo.convex, m.sigma_t_per_mm, m.albedo, m.g, m.eta,
                       float(rr_weight), float(rr_survival), int(max_collisions),
                       L.positions_mm, L.intensity, L.cdf, sample_one, int(n_scan), float(nee_tau),
                       L.env_map, L.has_map, L.affine, L.has_affine, bool(include_specular), int(max_bounces),
                       want_d, env_rest if env_nee else L.env_map, L.env_nee if env_nee else no_nee, far_mm,
                       chain_prm, k_chain,
                       fd_h, m2.sigma_t_per_mm if m2 is not None else 1.0, m2.albedo if m2 is not None else 1.0,
                       mean_c, se_c, hit, coll, trunc, d_c, d_se_c)
        rad[:, c] = mean_c
        se[:, c] = se_c
        if want_d:
            d_all[:, c] = d_c
            d_se_all[:, c] = d_se_c
        tot_coll += int(coll.sum())
        tot_trunc += int(trunc.sum())
    seconds = time.perf_counter() - t0
    n_paths = max(1, int(hit.sum()) * spp * len(ms))
    return MCImage(rad.reshape(h, w, -1), se.reshape(h, w, -1), hit.reshape(h, w), int(spp), int(seed), seconds,
                   tot_coll / n_paths, tot_trunc / n_paths,
                   None if d_all is None else d_all.reshape(h, w, len(ms), 2),
                   None if d_se_all is None else d_se_all.reshape(h, w, len(ms), 2))
