"""The objects of the virtual scene and their fast (dipole) subsurface exitance.

A sphere (:class:`SphereObject`), a slab with a seeded sinusoidal relief (:class:`BumpySlabObject`) and a closed
triangle mesh (:class:`MeshObject`, cast shadows for non-convex meshes through ``estimation.rays.RayEngine``), each
able to intersect camera rays, give normals and source patches; their diffuse exitance under LEDs follows the
BSSRDF factorisation of Jensen et al. 2001 as used by Mukaigawa et al. (seed 000, Eq. 10):
B(x_o) = sum_k R(|x_o - x_k|) E_t(x_k) A_k with E_t the Fresnel-transmitted irradiance (:func:`led_irradiance`,
``estimation.forward``). Rendering them into frames (polarization, specular lobe, Monte Carlo mode) is
:mod:`simulators.scene`; their Monte Carlo shapes are :mod:`simulators.mc_capture`'s.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import trimesh

from estimation.camera import PinholeCamera, intersect_sphere
from estimation.forward import diffuse_exitance
from estimation.rays import RayEngine
from estimation.fresnel import fresnel_transmittance
from estimation.shadows import is_convex_mesh, point_light_visibility

FloatArray = npt.NDArray[np.float64]


@dataclass
class SphereObject:
    """A sphere of homogeneous material; ``tessellation`` = icosphere subdivisions of the source patches."""

    center_mm: tuple[float, float, float]
    radius_mm: float
    sigma_s_prime_per_mm: tuple[float, float, float]
    sigma_a_per_mm: tuple[float, float, float]
    eta: float
    tessellation: int = 4
    specular_roughness: float = 0.15
    _patches: tuple[FloatArray, FloatArray, FloatArray] | None = field(default=None, repr=False)

    def patches(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Patch centres (K, 3) on the surface, outward normals (K, 3), areas (K,) summing to 4 pi r^2."""
        if self._patches is None:
            mesh = trimesh.creation.icosphere(subdivisions=self.tessellation, radius=1.0)
            n = mesh.triangles_center / np.linalg.norm(mesh.triangles_center, axis=1, keepdims=True)
            area = mesh.area_faces * (4 * np.pi / mesh.area_faces.sum()) * self.radius_mm ** 2
            centers = np.asarray(self.center_mm) + n * self.radius_mm
            self._patches = (centers, n, area)
        return self._patches

    def intersect(self, camera: PinholeCamera) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        origins, dirs = camera.pixel_rays()
        return intersect_sphere(origins, dirs, self.center_mm, self.radius_mm)

    def normals_at(self, points_mm: FloatArray) -> FloatArray:
        n = points_mm - np.asarray(self.center_mm)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def led_irradiance(points_mm: FloatArray, normals: FloatArray, led_positions_mm: FloatArray,
                   led_radiant_intensity: FloatArray, eta: float, *, transmitted: bool = True,
                   occluder: RayEngine | None = None, visibility: npt.NDArray[np.bool_] | None = None) -> FloatArray:
    """Irradiance (K, C) from point-like LEDs: sum_l V_kl I_l max(0, n.w) / d^2, times F_t(eta, n.w) if
    ``transmitted`` (the seed's c_k per unit area). V_kl: without ``occluder`` 1 (no self-shadowing beyond n.w,
    exact for a convex object); with one, the cast shadow of that mesh (one shadow ray per point and lit LED,
    :func:`estimation.shadows.point_light_visibility`); or given as ``visibility`` (K, N) (computed once for
    several emissions)."""
    lit = np.flatnonzero(np.any(led_radiant_intensity > 0, axis=1))
    out = np.zeros((len(points_mm), led_radiant_intensity.shape[1]))
    for start in range(0, len(lit), 64):
        idx = lit[start:start + 64]
        d = led_positions_mm[idx][None, :, :] - points_mm[:, None, :]          # (K, L, 3)
        dist2 = np.sum(d * d, axis=-1)
        cos = np.maximum(np.sum(d * normals[:, None, :], axis=-1) / np.sqrt(dist2), 0.0)
        w = cos / dist2
        if transmitted:
            w = w * fresnel_transmittance(eta, cos)
        if visibility is not None:
            w = w * visibility[:, idx]
        elif occluder is not None:
            w = w * point_light_visibility(occluder, points_mm, normals, led_positions_mm[idx])
        out += w @ led_radiant_intensity[idx]
    return out


def _tangent_basis(normal: npt.ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(n, e1, e2): unit normal and a right-handed tangent basis (for n = -y: e1 = +x, e2 = +z)."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    a = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, n)
    e1 /= np.linalg.norm(e1)
    return n, e1, np.cross(n, e1)


@dataclass
class BumpySlabObject:
    """A thick slab of homogeneous material whose surface (through ``center_mm``, outward ``normal``) carries a fine
    random relief h(u, v) = sum_k a_k cos(k_k . (u, v) + phi_k): ``n_waves`` plane waves with wavelengths
    log-uniform in ``wavelengths_mm``, scaled to an RMS slope ``rms_slope`` (seeded by ``seed``).

    The surface model is a square of side ``extent_mm`` sampled every ``patch_mm``; keep what the camera analyses
    at least ~3 diffuse mean free paths l_d from its edges (light leaks out there). Subsurface transport: the dipole
    BSSRDF of the other objects, with distances measured in the slab plane (the relief's slopes change them only
    to second order), so the exitance is the 2-D convolution of the Fresnel-transmitted irradiance (times the
    area element) with the cell-integrated profile — computed by FFT, which makes 10^5 source patches cheap.
    """

    center_mm: tuple[float, float, float]
    sigma_s_prime_per_mm: tuple[float, float, float]
    sigma_a_per_mm: tuple[float, float, float]
    eta: float
    normal: tuple[float, float, float] = (0.0, -1.0, 0.0)
    extent_mm: float = 40.0
    patch_mm: float = 0.1
    rms_slope: float = 0.1
    wavelengths_mm: tuple[float, float] = (1.5, 6.0)
    n_waves: int = 24
    seed: int = 0
    specular_roughness: float = 0.15
    _waves: tuple[FloatArray, FloatArray, FloatArray] | None = field(default=None, repr=False)

    def waves(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Wave vectors (K, 2) [rad/mm], amplitudes (K,) [mm], phases (K,)."""
        if self._waves is None:
            rng = np.random.default_rng(self.seed)
            lam = np.exp(rng.uniform(np.log(self.wavelengths_mm[0]), np.log(self.wavelengths_mm[1]), self.n_waves))
            ang = rng.uniform(0, np.pi, self.n_waves)
            k = (2 * np.pi / lam)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
            amp = lam / lam.max()  # more amplitude at longer wavelengths, roughly equal slope per wave
            slope_rms = np.sqrt(0.5 * np.sum((amp * np.linalg.norm(k, axis=1)) ** 2))
            amp *= self.rms_slope / slope_rms
            self._waves = (k, amp, rng.uniform(0, 2 * np.pi, self.n_waves))
        return self._waves

    def height(self, u: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """h(u, v) and its derivatives h_u, h_v [mm, dimensionless]."""
        k, a, ph = self.waves()
        h = np.zeros(np.shape(u))
        hu = np.zeros(np.shape(u))
        hv = np.zeros(np.shape(u))
        for (kx, ky), ak, pk in zip(k, a, ph):
            arg = kx * u + ky * v + pk
            h += ak * np.cos(arg)
            s = -ak * np.sin(arg)
            hu += s * kx
            hv += s * ky
        return h, hu, hv

    def _frame(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        n, e1, e2 = _tangent_basis(self.normal)
        return np.asarray(self.center_mm, float), n, e1, e2

    def grid(self) -> FloatArray:
        """Patch-centre coordinates u = v (n,) [mm] of the surface model."""
        m = int(round(self.extent_mm / self.patch_mm))
        return (np.arange(m) - (m - 1) / 2) * self.patch_mm

    def patches(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Patch centres (K, 3), outward normals (K, 3), areas (K,) of the relief surface (row-major u, v grid)."""
        c, n, e1, e2 = self._frame()
        g = self.grid()
        uu, vv = np.meshgrid(g, g, indexing="ij")
        h, hu, hv = self.height(uu, vv)
        pts = c + uu[..., None] * e1 + vv[..., None] * e2 + h[..., None] * n
        nrm = n - hu[..., None] * e1 - hv[..., None] * e2
        da = np.linalg.norm(nrm, axis=-1)
        return pts.reshape(-1, 3), (nrm / da[..., None]).reshape(-1, 3), (da * self.patch_mm ** 2).reshape(-1)

    def intersect(self, camera: PinholeCamera) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        """Ray / height-field intersection (Newton on the signed height, from the mean plane)."""
        origins, dirs = camera.pixel_rays()
        c, n, e1, e2 = self._frame()
        dn = dirs @ n
        t = ((c - origins) @ n) / np.where(np.abs(dn) > 1e-12, dn, np.nan)
        for _ in range(20):
            p = origins + t[..., None] * dirs - c
            u, v, w = p @ e1, p @ e2, p @ n
            h, hu, hv = self.height(u, v)
            f = w - h
            fp = dn - hu * (dirs @ e1) - hv * (dirs @ e2)
            t = t - f / fp
        pts = origins + t[..., None] * dirs
        p = pts - c
        half = 0.5 * self.extent_mm
        hit = np.isfinite(t) & (t > 0) & (np.abs(p @ e1) < half) & (np.abs(p @ e2) < half) & (dn < 0)
        pts[~hit] = np.nan
        return pts, hit

    def normals_at(self, points_mm: FloatArray) -> FloatArray:
        c, n, e1, e2 = self._frame()
        p = np.asarray(points_mm, float) - c
        _, hu, hv = self.height(p @ e1, p @ e2)
        nrm = n - hu[..., None] * e1 - hv[..., None] * e2
        return nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)

    def kernel(self, size: int) -> FloatArray:
        """Cell-integrated profile int_cell R dA (size, size, 3) centred at [0, 0] (wrapped FFT layout): 4 x 4
        sub-samples per cell, the centre cell from the exact disk integral of equal area (never R(0))."""
        from estimation.dipole import cumulative_disk, profile
        ssp, sa = np.asarray(self.sigma_s_prime_per_mm, float), np.asarray(self.sigma_a_per_mm, float)
        i = np.fft.fftfreq(size, 1.0 / size)
        h = self.patch_mm
        sub = (np.arange(4) + 0.5) / 4 - 0.5
        out = np.zeros((size, size, 3))
        for a in sub:
            for b in sub:
                r = np.hypot((i[:, None] + a) * h, (i[None, :] + b) * h)
                out += profile(r[..., None], ssp, sa, self.eta) * (h * h / 16)
        out[0, 0] = cumulative_disk(h / np.sqrt(np.pi), ssp, sa, self.eta)
        return out

    def exitance(self, points_mm: FloatArray, led_positions_mm: FloatArray,
                 emissions: list[FloatArray]) -> list[FloatArray]:
        """Diffuse exitance B (P, 3) at surface ``points_mm`` for each LED emission (N, 3) (FFT convolution)."""
        centers, normals, areas = self.patches()
        m = self.grid().size
        size = int(2 ** np.ceil(np.log2(2 * m)))  # zero padding: linear (not circular) convolution
        kf = np.fft.rfft2(self.kernel(size), axes=(0, 1))
        c, _, e1, e2 = self._frame()
        p = np.asarray(points_mm, float) - c
        g0 = self.grid()[0]
        fu = np.clip((p @ e1 - g0) / self.patch_mm, 0, m - 1.000001)
        fv = np.clip((p @ e2 - g0) / self.patch_mm, 0, m - 1.000001)
        iu, iv = fu.astype(int), fv.astype(int)
        wu, wv = (fu - iu)[:, None], (fv - iv)[:, None]
        out = []
        for em in emissions:
            src = led_irradiance(centers, normals, led_positions_mm, em, self.eta) * (areas / self.patch_mm ** 2)[:, None]
            pad = np.zeros((size, size, 3))
            pad[:m, :m] = src.reshape(m, m, 3)
            b = np.fft.irfft2(np.fft.rfft2(pad, axes=(0, 1)) * kf, s=(size, size), axes=(0, 1))[:m, :m]
            out.append((b[iu, iv] * (1 - wu) * (1 - wv) + b[iu + 1, iv] * wu * (1 - wv)
                        + b[iu, iv + 1] * (1 - wu) * wv + b[iu + 1, iv + 1] * wu * wv))
        return out


@dataclass
class MeshObject:
    """A closed triangle mesh (``trimesh.Trimesh``, outward normals, mm) of homogeneous material.

    Patches: the mesh faces after ``subdivisions`` midpoint subdivisions. Pixel normals: the vertex normals
    interpolated barycentrically over the face the ray hits (a smooth shading normal, like a scanned mesh's).
    Subsurface transport: :func:`estimation.forward.diffuse_exitance` over the patches, as for the sphere.
    ``shadows``: the mesh casts shadows of the LEDs on its patches and pixels (shadow rays,
    :mod:`estimation.shadows`; "fast" render mode — the Monte Carlo mode traces them anyway): "auto" (default) when
    it is not convex (:func:`estimation.shadows.is_convex_mesh`), True, or False (max(0, n.l) only, as before).
    """

    mesh: trimesh.Trimesh
    sigma_s_prime_per_mm: tuple[float, float, float]
    sigma_a_per_mm: tuple[float, float, float]
    eta: float
    subdivisions: int = 0
    specular_roughness: float = 0.15
    shadows: bool | str = "auto"
    _engine: RayEngine | None = field(default=None, repr=False, compare=False)
    _engine_key: int | None = field(default=None, repr=False, compare=False)
    _convex: bool | None = field(default=None, repr=False, compare=False)

    def _ray_engine(self) -> RayEngine:
        key = hash(self.mesh)    # trimesh's hash of the vertex and face data: an edited mesh gets a new engine
        if self._engine is None or self._engine_key != key:
            self._engine = RayEngine(np.asarray(self.mesh.vertices, float), np.asarray(self.mesh.faces))
            self._engine_key = key
            self._convex = None
        return self._engine

    def shadow_engine(self) -> RayEngine | None:
        """The ray engine that casts this mesh's shadows, or None (shadows off, or "auto" on a convex mesh)."""
        if not (self.shadows == "auto" or isinstance(self.shadows, (bool, np.bool_))):
            raise ValueError(f"MeshObject.shadows must be 'auto', True or False; got {self.shadows!r}")
        if self.shadows is False:
            return None
        eng = self._ray_engine()
        if self.shadows == "auto":
            if self._convex is None:
                self._convex = is_convex_mesh(self.mesh.vertices, self.mesh.faces)
            if self._convex:
                return None
        return eng

    def patches(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        m = self.mesh
        for _ in range(self.subdivisions):
            m = m.subdivide()
        return (np.asarray(m.triangles_center, float), np.asarray(m.face_normals, float),
                np.asarray(m.area_faces, float))

    def _hits(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, npt.NDArray[np.intp],
                                                                     FloatArray, FloatArray]:
        """Nearest hit of each ray (M, 3) (unit ``dirs``): t (inf if none), face index (-1 if none), barycentrics
        (b1, b2) of the hit point on that face (0 for a miss); first hits by :class:`estimation.rays.RayEngine`."""
        face, t = self._ray_engine().first_hit(origins, dirs, min_dist=1e-9)
        hit = face >= 0
        tri = np.asarray(self.mesh.triangles, float)[face[hit]]
        p = origins[hit] + t[hit, None] * dirs[hit]
        e1, e2, w = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
        d11, d12, d22 = (np.einsum("ij,ij->i", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
        w1, w2 = np.einsum("ij,ij->i", w, e1), np.einsum("ij,ij->i", w, e2)
        den = d11 * d22 - d12 * d12
        bb1 = np.zeros(len(face))
        bb2 = np.zeros(len(face))
        bb1[hit] = (d22 * w1 - d12 * w2) / den
        bb2[hit] = (d11 * w2 - d12 * w1) / den
        return t, face, bb1, bb2

    def intersect(self, camera: PinholeCamera) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        origins, dirs = camera.pixel_rays()
        shape = dirs.shape[:2]
        t, _, _, _ = self._hits(origins.reshape(-1, 3), dirs.reshape(-1, 3))
        hit = np.isfinite(t).reshape(shape)
        pts = origins + np.where(hit, t.reshape(shape), np.nan)[..., None] * dirs
        return pts, hit

    def normals_at(self, points_mm: FloatArray) -> FloatArray:
        """Interpolated vertex normals at surface points (located by a short ray along the face normal field)."""
        p = np.asarray(points_mm, float).reshape(-1, 3)
        c = np.asarray(self.mesh.centroid, float)
        d = p - c
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        # cast from outside, back towards the centroid: for a star-shaped mesh this finds the point's own face
        t, face, b1, b2 = self._hits(p + 1e-3 * d, -d)
        vn = np.asarray(self.mesh.vertex_normals, float)[np.asarray(self.mesh.faces)[np.maximum(face, 0)]]
        n = (1 - b1 - b2)[:, None] * vn[:, 0] + b1[:, None] * vn[:, 1] + b2[:, None] * vn[:, 2]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return n.reshape(np.shape(points_mm))

    def exitance(self, points_mm: FloatArray, led_positions_mm: FloatArray,
                 emissions: list[FloatArray]) -> list[FloatArray]:
        return patch_exitance(self, points_mm, led_positions_mm, emissions)


def wall_on_slab_mesh(length_mm: float = 30.0, slab_mm: float = 5.0, wall_mm: float = 8.0, height_mm: float = 20.0,
                      depth_mm: float = 20.0, *, max_edge_mm: float | None = None,
                      flat_shading: bool = False) -> trimesh.Trimesh:
    """A non-convex test object: an L-shaped block, a slab (x in [``wall_mm``, ``length_mm``], top at z =
    ``slab_mm``) with a wall (x in [0, ``wall_mm``], up to z = ``height_mm``), over y in +-``depth_mm``/2, outward
    normals. A light beyond the wall (x < 0) casts the wall's shadow on the slab's top. ``max_edge_mm``
    subdivides it (``trimesh.remesh.subdivide_to_size``); ``flat_shading`` gives every planar side its own vertices
    (the vertex normals are then the face normals: no smoothing over the block's edges; the mesh is then not
    watertight, which is fine for rendering and estimation)."""
    poly = np.array([(0, 0), (length_mm, 0), (length_mm, slab_mm), (wall_mm, slab_mm), (wall_mm, height_mm),
                     (0, height_mm)], float)
    if not (0 < slab_mm < height_mm and 0 < wall_mm < length_mm and depth_mm > 0):
        raise ValueError("wall_on_slab_mesh: need 0 < slab_mm < height_mm, 0 < wall_mm < length_mm, depth_mm > 0")
    n = len(poly)
    cap = [(3, 4, 5), (3, 5, 0), (3, 0, 1), (3, 1, 2)]        # a fan from the reflex vertex covers the L
    v = np.vstack([np.c_[poly[:, 0], np.full(n, -depth_mm / 2), poly[:, 1]],
                   np.c_[poly[:, 0], np.full(n, depth_mm / 2), poly[:, 1]]])
    sides = [[(a, c, b) for a, b, c in cap], [(a + n, b + n, c + n) for a, b, c in cap]]
    sides += [[(i, (i + 1) % n, (i + 1) % n + n), (i, (i + 1) % n + n, i + n)] for i in range(n)]
    f = np.array([t for side in sides for t in side])
    # y -> -y mirrors the extrusion (which was wound for +y out of the cap): flip if the volume came out negative
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    if vol < 0:
        f = f[:, ::-1]
    parts = [(v, f)]
    if flat_shading:
        parts = []
        start = 0
        for side in sides:
            ff = f[start:start + len(side)]
            start += len(side)
            used, inv = np.unique(ff, return_inverse=True)
            parts.append((v[used], inv.reshape(-1, 3)))
    out_v, out_f, off = [], [], 0
    for pv, pf in parts:
        if max_edge_mm is not None:
            pv, pf = trimesh.remesh.subdivide_to_size(pv, pf, max_edge=float(max_edge_mm))
        out_v.append(pv)
        out_f.append(pf + off)
        off += len(pv)
    return trimesh.Trimesh(np.vstack(out_v), np.vstack(out_f), process=not flat_shading)


def patch_exitance(obj: SphereObject | MeshObject, points_mm: FloatArray, led_positions_mm: FloatArray,
                    emissions: list[FloatArray]) -> list[FloatArray]:
    centers, normals, areas = obj.patches()
    occ = shadow_engine(obj)
    vis = None
    if occ is not None and emissions:   # once for every LED lit in any emission (independent of the drive)
        lit = np.flatnonzero(np.any([np.any(np.asarray(em) > 0, axis=1) for em in emissions], axis=0))
        vis = np.zeros((len(centers), len(led_positions_mm)), dtype=bool)
        vis[:, lit] = point_light_visibility(occ, centers, normals, np.asarray(led_positions_mm)[lit])
    out = []
    for em in emissions:
        e_t = led_irradiance(centers, normals, led_positions_mm, em, obj.eta, visibility=vis)
        out.append(diffuse_exitance(points_mm, centers, areas, e_t, np.asarray(obj.sigma_s_prime_per_mm),
                                    np.asarray(obj.sigma_a_per_mm), obj.eta))
    return out


SceneObject = SphereObject | BumpySlabObject | MeshObject


def shadow_engine(obj: object) -> RayEngine | None:
    """The engine casting ``obj``'s shadows (a non-convex :class:`MeshObject` with shadows on), else None."""
    return obj.shadow_engine() if isinstance(obj, MeshObject) else None


