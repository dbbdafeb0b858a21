"""Photon-launch tools: the pencil-beam reflectance profile R(r) of a half-space (or slab), angular exchange
between direction sets (reciprocity), and the energy balance of closed objects.

A photon enters at ``entry_mm`` with the deterministic Fresnel split of MCML (specular reflectance F_r recorded
exactly, weight F_t transmitted), runs :func:`.walk.walk` and leaves once (Fresnel sampled at every internal
boundary hit), so every photon contributes its exit weight to exactly one tally bin: the per-bin mean over N
photons and its standard error sqrt((E[x^2] - E[x]^2)/(N - 1)) are exact (no batching needed). Photons are
simulated in chunks by a numba kernel (random stream keyed by (seed, photon index): thread-count independent)
and tallied in numpy in a fixed order, so results are bit-identical for a given seed.

R(r) is the radiant exitance per unit incident power [1/mm^2] at distance r from the beam's entry point,
integrated over all exit directions -- the quantity of the dipole (Jensen et al. 2001 Eq. 4, estimation.dipole):
the tally per annulus divided by its area. :func:`optical_medium` (sigma_t = 1) makes lengths mean free paths.

References: Wang, Jacques, Zheng 1995 (MCML: R_d(r) on annuli, specular at entry); van de Hulst 1980
"Multiple Light Scattering"; Chandrasekhar 1950 "Radiative Transfer" (H-function albedo of the half-space).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import numpy.typing as npt
from numba import njit, prange

from .media import Medium
from .optics import fresnel_r, orthonormal_basis, refract
from .rng import stream, uniform
from .shapes import HalfSpace, Shape, Slab, STACK_SIZE, nearest_hit
from .walk import EXITED, TRUNCATED, walk

__all__ = ["DirectionSet", "PhotonExits", "PencilBeamProfile", "EnergyBalance", "simulate_photons",
           "pencil_beam_profile", "exchange_fraction", "energy_balance", "mean_and_stderr"]

FloatArray = npt.NDArray[np.float64]
_TWO_PI = 2.0 * math.pi
_TAG_PHOTON = 0x50484F54  # "PHOT": keeps photon streams apart from camera streams


@dataclass(frozen=True)
class DirectionSet:
    """Directions about the outward normal n with cos(theta) in [cos_min, cos_max] and azimuth phi in
    [phi_min_rad, phi_max_rad] measured in the tangent frame (t1, t2) of :func:`.optics.orthonormal_basis`(n)
    (for n = +z: t1 = +x, t2 = +y); on a half-space only differences of azimuth matter.

    As an incidence spec, directions are drawn cosine-weighted (uniform in projected solid angle), the
    distribution of diffuse light; a single direction when cos_min = cos_max and phi_min = phi_max.
    """

    cos_min: float = 1.0
    cos_max: float = 1.0
    phi_min_rad: float = 0.0
    phi_max_rad: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.cos_min <= self.cos_max <= 1.0:
            raise ValueError("need 0 <= cos_min <= cos_max <= 1")
        if self.phi_max_rad < self.phi_min_rad:
            raise ValueError("phi_max_rad < phi_min_rad")

    @property
    def projected_solid_angle_sr(self) -> float:
        """int cos dOmega over the set = (cos_max^2 - cos_min^2)/2 * (phi_max - phi_min)."""
        return 0.5 * (self.cos_max ** 2 - self.cos_min ** 2) * (self.phi_max_rad - self.phi_min_rad)

    def contains(self, cos_theta: npt.ArrayLike, phi_rad: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        c = np.asarray(cos_theta, float)
        p = np.mod(np.asarray(phi_rad, float) - self.phi_min_rad, _TWO_PI)
        return (c >= self.cos_min) & (c <= self.cos_max) & (p <= self.phi_max_rad - self.phi_min_rad)

    @classmethod
    def normal(cls) -> "DirectionSet":
        return cls(1.0, 1.0, 0.0, 0.0)

    @classmethod
    def at_angle(cls, theta_rad: float, phi_rad: float = 0.0) -> "DirectionSet":
        c = float(np.cos(theta_rad))
        return cls(c, c, float(phi_rad), float(phi_rad))


@njit(parallel=True, cache=True, error_model="numpy")
def _launch_kernel(start, count, seed, kind, prm, nbox, nidx, tris, eps_t, nudge, ex, ey, ez, nx, ny, nz,
                   c0, c1, p0, p1, sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
                   out_status, out_rec, out_spec, out_coll):
    t1, t2 = orthonormal_basis(nx, ny, nz)
    no_pos = np.zeros((0, 3))
    no_val = np.zeros(0)
    for i in prange(count):
        stack = np.empty(STACK_SIZE, np.int64)
        state = stream(seed, _TAG_PHOTON, start + i, 0)
        state, u = uniform(state)
        mu = math.sqrt(c0 * c0 + u * (c1 * c1 - c0 * c0))
        state, u = uniform(state)
        phi = p0 + u * (p1 - p0)
        st = math.sqrt(max(0.0, 1.0 - mu * mu))
        cp, sp = math.cos(phi), math.sin(phi)
        wx = mu * nx + st * (cp * t1[0] + sp * t2[0])
        wy = mu * ny + st * (cp * t1[1] + sp * t2[1])
        wz = mu * nz + st * (cp * t1[2] + sp * t2[2])
        fr = fresnel_r(eta, mu)
        out_spec[i] = fr
        ok, dx, dy, dz = refract(-wx, -wy, -wz, nx, ny, nz, eta)
        if not ok or fr >= 1.0:
            out_status[i] = -1
            out_rec[i, 6] = 0.0
            continue
        status, x, y, z, dx, dy, dz, w, _nee, state, nc, _len, _ds, _da, _straight = walk(
            kind, prm, nbox, nidx, tris, eps_t, nudge, stack, ex - nudge * nx, ey - nudge * ny, ez - nudge * nz,
            dx, dy, dz, state, sigma_t, albedo, g, eta, rr_weight, rr_survival, max_collisions,
            no_pos, no_val, no_val, False, 0, 1.0, False, 0, 0.0, np.zeros((0, 5)), 1, 1, 1.0, np.zeros(0), 0)
        out_status[i] = status
        out_rec[i, 0] = x
        out_rec[i, 1] = y
        out_rec[i, 2] = z
        out_rec[i, 3] = dx
        out_rec[i, 4] = dy
        out_rec[i, 5] = dz
        out_rec[i, 6] = w * (1.0 - fr)
        out_coll[i] = nc


@dataclass(frozen=True)
class PhotonExits:
    """One chunk of photons: status (n,) (0 exited, 1 terminated by roulette, 2 truncated, -1 not entered),
    exit position (n, 3) just outside the boundary, outgoing direction (n, 3), exit weight (n,) including the
    entry transmittance, specular reflectance at entry (n,), collisions (n,)."""

    status: npt.NDArray[np.int8]
    position_mm: FloatArray
    direction: FloatArray
    weight: FloatArray
    specular: FloatArray
    collisions: npt.NDArray[np.int64]


def simulate_photons(shape: Shape, medium: Medium, n_photons: int, *, seed: int = 0,
                     entry_mm: npt.ArrayLike = (0.0, 0.0, 0.0), incidence: DirectionSet | None = None,
                     chunk: int = 1 << 17, rr_weight: float = 0.01, rr_survival: float = 0.1,
                     max_collisions: int = 1_000_000) -> Iterator[PhotonExits]:
    """Launch ``n_photons`` at ``entry_mm`` (a point on the surface; the outward normal there is found by a ray
    query) with directions from ``incidence`` (default: normal incidence); yield :class:`PhotonExits` chunks."""
    if n_photons < 1:
        raise ValueError("n_photons must be >= 1")
    inc = incidence or DirectionSet.normal()
    geo = shape.geometry()
    e = np.asarray(entry_mm, float).reshape(3)
    n = _outward_normal_at(geo, e)
    done = 0
    while done < n_photons:
        cnt = min(chunk, n_photons - done)
        status = np.empty(cnt, dtype=np.int8)
        rec = np.empty((cnt, 7))
        spec = np.empty(cnt)
        coll = np.zeros(cnt, dtype=np.int64)
        _launch_kernel(done, cnt, int(seed), geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles,
                       geo.eps_t, geo.nudge, e[0], e[1], e[2], n[0], n[1], n[2], float(inc.cos_min),
                       float(inc.cos_max), float(inc.phi_min_rad), float(inc.phi_max_rad), medium.sigma_t_per_mm,
                       medium.albedo, medium.g, medium.eta, float(rr_weight), float(rr_survival),
                       int(max_collisions), status, rec, spec, coll)
        yield PhotonExits(status, rec[:, :3], rec[:, 3:6], rec[:, 6], spec, coll)
        done += cnt


def _outward_normal_at(geo, point: FloatArray) -> FloatArray:
    """Outward unit normal at a surface point: rays from just outside along the axes towards it; the first one that
    hits the surface at ``point`` (within 1e-6 of the shape's scale) from outside gives the normal."""
    stack = np.empty(STACK_SIZE, np.int64)
    tol = 1e-6 * geo.scale_mm
    for d in ([0, 0, -1], [0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]):
        d = np.asarray(d, float)
        o = point - d * 1e-3 * geo.scale_mm
        t, nx, ny, nz = nearest_hit(geo.kind, geo.params, geo.nodes_box, geo.nodes_idx, geo.triangles,
                                    o[0], o[1], o[2], d[0], d[1], d[2], geo.eps_t, stack)
        nrm = np.array([nx, ny, nz])
        if np.isfinite(t) and np.dot(nrm, d) < 0 and np.linalg.norm(o + t * d - point) < tol:
            return nrm
    raise ValueError("entry_mm is not on the shape's surface")


def mean_and_stderr(sum_x: npt.ArrayLike, sum_x2: npt.ArrayLike, n: int) -> tuple[FloatArray, FloatArray]:
    """Mean of n i.i.d. per-photon contributions and its standard error from their sums and sums of squares."""
    s1 = np.asarray(sum_x, float)
    s2 = np.asarray(sum_x2, float)
    m = s1 / n
    var = np.maximum(s2 / n - m * m, 0.0) * n / max(n - 1, 1)
    return m, np.sqrt(var / n)


@dataclass(frozen=True)
class PencilBeamProfile:
    """Result of :func:`pencil_beam_profile` (lengths in the medium's mm; see its docstring)."""

    radius_edges_mm: FloatArray
    radius_mm: FloatArray                 # area-weighted bin centres sqrt((r0^2 + r1^2)/2)
    reflectance_per_mm2: FloatArray       # R(r) per annulus [1/mm^2]
    reflectance_stderr_per_mm2: FloatArray
    annulus_fraction: FloatArray          # int over the annulus of R 2 pi r dr (dimensionless)
    annulus_fraction_stderr: FloatArray
    total_diffuse_reflectance: float      # all photons leaving through the lit face (any r)
    total_diffuse_reflectance_stderr: float
    specular_reflectance: float
    transmittance: float                  # slab: leaving through the bottom face (diffuse and unscattered)
    transmittance_stderr: float
    cos_edges: FloatArray                 # exit-angle bins (cos theta_o, lit face)
    brdf_per_sr: FloatArray               # dR / (cos theta_o dOmega_o) per cos bin [1/sr]
    brdf_stderr_per_sr: FloatArray
    absorbed_fraction: float              # 1 - specular - R - T (roulette-terminated weight is the absorption)
    truncated_fraction: float
    mean_collisions: float
    n_photons: int
    seconds: float


def pencil_beam_profile(medium: Medium, radius_edges_mm: npt.ArrayLike, n_photons: int, *, seed: int = 0,
                        thickness_mm: float | None = None, incidence: DirectionSet | None = None,
                        cos_edges: npt.ArrayLike = (0.0, 1.0), chunk: int = 1 << 17, rr_weight: float = 0.01,
                        rr_survival: float = 0.1, max_collisions: int = 1_000_000) -> PencilBeamProfile:
    """Radial reflectance profile of a half-space z <= 0 (or a slab of ``thickness_mm``) under a pencil beam
    entering at the origin (default: normal incidence), with standard errors.

    ``radius_edges_mm``: increasing annulus edges (start at 0 for the central disk). Photons leaving beyond the
    last edge count in the total R_d but in no annulus. ``cos_edges``: bins of the exit cosine for the angular
    distribution (brdf = tally / (N * pi (c1^2 - c0^2)), azimuthally averaged).
    """
    edges = np.asarray(radius_edges_mm, float)
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0) or edges[0] < 0:
        raise ValueError("radius_edges_mm must be increasing and >= 0")
    cedges = np.asarray(cos_edges, float)
    shape: Shape = HalfSpace(0.0) if thickness_mm is None else Slab(float(thickness_mm), 0.0)
    nb = len(edges) - 1
    nc = len(cedges) - 1
    s1 = np.zeros(nb)
    s2 = np.zeros(nb)
    c1 = np.zeros(nc)
    c2 = np.zeros(nc)
    rt1 = rt2 = tt1 = tt2 = spec = 0.0
    trunc = 0
    coll = 0
    t0 = time.perf_counter()
    for ch in simulate_photons(shape, medium, n_photons, seed=seed, incidence=incidence, chunk=chunk,
                               rr_weight=rr_weight, rr_survival=rr_survival, max_collisions=max_collisions):
        spec += float(ch.specular.sum())
        trunc += int(np.count_nonzero(ch.status == TRUNCATED))
        coll += int(ch.collisions.sum())
        ex = ch.status == EXITED
        top = ex & (ch.direction[:, 2] > 0)
        bot = ex & (ch.direction[:, 2] < 0)
        w = ch.weight
        rt1 += float(w[top].sum())
        rt2 += float((w[top] ** 2).sum())
        tt1 += float(w[bot].sum())
        tt2 += float((w[bot] ** 2).sum())
        r = np.hypot(ch.position_mm[top, 0], ch.position_mm[top, 1])
        k = np.searchsorted(edges, r, side="right") - 1
        ok = (k >= 0) & (k < nb)
        s1 += np.bincount(k[ok], weights=w[top][ok], minlength=nb)
        s2 += np.bincount(k[ok], weights=w[top][ok] ** 2, minlength=nb)
        ct = ch.direction[top, 2]
        kc = np.clip(np.searchsorted(cedges, ct, side="right") - 1, 0, nc - 1)
        okc = (ct >= cedges[0]) & (ct <= cedges[-1])
        c1 += np.bincount(kc[okc], weights=w[top][okc], minlength=nc)
        c2 += np.bincount(kc[okc], weights=w[top][okc] ** 2, minlength=nc)
    seconds = time.perf_counter() - t0
    N = int(n_photons)
    frac, frac_se = mean_and_stderr(s1, s2, N)
    area = np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    rd, rd_se = mean_and_stderr(rt1, rt2, N)
    tt, tt_se = mean_and_stderr(tt1, tt2, N)
    cf, cf_se = mean_and_stderr(c1, c2, N)
    proj = np.pi * (cedges[1:] ** 2 - cedges[:-1] ** 2)
    rs = spec / N
    return PencilBeamProfile(edges, np.sqrt(0.5 * (edges[1:] ** 2 + edges[:-1] ** 2)), frac / area,
                             frac_se / area, frac, frac_se, float(rd), float(rd_se), rs, float(tt), float(tt_se),
                             cedges, cf / proj, cf_se / proj, float(1.0 - rs - rd - tt), trunc / N, coll / N, N,
                             seconds)


def exchange_fraction(medium: Medium, incidence: DirectionSet, exit_set: DirectionSet, n_photons: int, *,
                      seed: int = 0, thickness_mm: float | None = None) -> tuple[float, float]:
    """Fraction (mean, standard error) of the power incident on a half-space (or slab, top face) with directions
    cosine-distributed over ``incidence`` that leaves the top face with directions in ``exit_set``
    (azimuth measured in the same tangent frame). Reciprocity: Pi_A P(A -> B) = Pi_B P(B -> A), Pi the
    projected solid angle (:attr:`DirectionSet.projected_solid_angle_sr`)."""
    shape: Shape = HalfSpace(0.0) if thickness_mm is None else Slab(float(thickness_mm), 0.0)
    t1, t2 = orthonormal_basis(0.0, 0.0, 1.0)
    s1 = s2 = 0.0
    for ch in simulate_photons(shape, medium, n_photons, seed=seed, incidence=incidence):
        ex = (ch.status == EXITED) & (ch.direction[:, 2] > 0)
        d = ch.direction[ex]
        phi = np.arctan2(d @ np.asarray(t2), d @ np.asarray(t1))
        inside = exit_set.contains(d[:, 2], phi)
        w = ch.weight[ex][inside]
        s1 += float(w.sum())
        s2 += float((w ** 2).sum())
    m, se = mean_and_stderr(s1, s2, n_photons)
    return float(m), float(se)


@dataclass(frozen=True)
class EnergyBalance:
    """Fate of the power entering a closed object: exited (+ specular), absorbed (roulette), truncated."""

    exited: float
    exited_stderr: float
    specular: float
    absorbed: float
    truncated_fraction: float
    not_entered_fraction: float
    n_photons: int


def energy_balance(shape: Shape, medium: Medium, n_photons: int, *, entry_mm: npt.ArrayLike, seed: int = 0,
                   incidence: DirectionSet | None = None, max_collisions: int = 1_000_000) -> EnergyBalance:
    """Launch photons into ``shape`` at ``entry_mm`` and account for every one of them. With albedo 1 every
    photon keeps weight F_t and leaves (zero variance), so exited + specular = 1 up to rounding."""
    e1 = e2 = spec = 0.0
    trunc = 0
    missed = 0
    for ch in simulate_photons(shape, medium, n_photons, seed=seed, entry_mm=entry_mm, incidence=incidence,
                               max_collisions=max_collisions):
        ex = ch.status == EXITED
        e1 += float(ch.weight[ex].sum())
        e2 += float((ch.weight[ex] ** 2).sum())
        spec += float(ch.specular.sum())
        trunc += int(np.count_nonzero(ch.status == TRUNCATED))
        missed += int(np.count_nonzero(ch.status == -1))
    m, se = mean_and_stderr(e1, e2, n_photons)
    N = int(n_photons)
    return EnergyBalance(float(m), float(se), spec / N, float(1.0 - m - spec / N), trunc / N, missed / N, N)
