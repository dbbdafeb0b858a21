"""The virtual scene: a homogeneous translucent object inside the LED sphere, rendered physically.

Diffuse (subsurface) light follows the BSSRDF factorisation of Jensen et al. 2001 as used by
Mukaigawa et al. (seed 000, Eq. 10): L_o(x_o) = F_t(eta, w_o)/pi * sum_k R(|x_o - x_k|) E_t(x_k) A_k, with
E_t the Fresnel-transmitted irradiance from every LED (``estimation.forward``). Surface reflection is a GGX
microfacet lobe with Fresnel reflectance. Polarization after Ma et al. 2007 / science.md §3: subsurface
light is depolarized, specular keeps the source polarization, so cross = diffuse/2 and
parallel = diffuse/2 + specular; without polarizers the camera sees diffuse + specular.

The renderer's tessellation is finer than the estimators' so tests do not commit the inverse crime.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import trimesh

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera, intersect_sphere
from estimation.forward import diffuse_exitance
from estimation.fresnel import fresnel_reflectance, fresnel_transmittance

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
                   led_radiant_intensity: FloatArray, eta: float, *, transmitted: bool = True
                   ) -> FloatArray:
    """Irradiance (K, C) from point-like LEDs: sum_l I_l max(0, n.w) / d^2, times F_t(eta, n.w) if
    ``transmitted`` (the seed's c_k per unit area). Convex object: no self-shadowing beyond n.w."""
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
        out += w @ led_radiant_intensity[idx]
    return out


def specular_radiance(points_mm: FloatArray, normals: FloatArray, view: FloatArray,
                      led_positions_mm: FloatArray, led_radiant_intensity: FloatArray, eta: float,
                      roughness: float) -> FloatArray:
    """GGX microfacet reflection of the LEDs (Walter et al. 2007), (P, C)."""
    a2 = roughness ** 4  # alpha = roughness^2
    lit = np.flatnonzero(np.any(led_radiant_intensity > 0, axis=1))
    out = np.zeros((len(points_mm), led_radiant_intensity.shape[1]))
    cos_o = np.clip(np.sum(normals * view, axis=-1), 1e-6, 1.0)
    for start in range(0, len(lit), 64):
        idx = lit[start:start + 64]
        d = led_positions_mm[idx][None, :, :] - points_mm[:, None, :]
        dist2 = np.sum(d * d, axis=-1)
        wi = d / np.sqrt(dist2)[..., None]
        cos_i = np.maximum(np.sum(wi * normals[:, None, :], axis=-1), 0.0)
        h = wi + view[:, None, :]
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        nh = np.clip(np.sum(h * normals[:, None, :], axis=-1), 0.0, 1.0)
        D = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
        k = a2 ** 0.5 / 2.0
        G = (cos_i / (cos_i * (1 - k) + k)) * (cos_o / (cos_o * (1 - k) + k))[:, None]
        F = fresnel_reflectance(eta, np.clip(np.sum(h * view[:, None, :], axis=-1), 0.0, 1.0))
        brdf = D * G * F / (4.0 * cos_o[:, None] * np.maximum(cos_i, 1e-9))
        out += (brdf * cos_i / dist2) @ led_radiant_intensity[idx]
    return out


@dataclass
class RenderResult:
    radiance: FloatArray          # (H, W, 3), camera-side radiance in rig units
    mask: npt.NDArray[np.bool_]   # object pixels


def render(obj: SphereObject, camera: PinholeCamera, led_positions_mm: FloatArray,
           led_radiant_intensity: FloatArray, polarization: Polarization,
           *, include_specular: bool = True) -> RenderResult:
    """Radiance image of ``obj`` lit by the LEDs' current emission (N, 3)."""
    H, W = camera.height_px, camera.width_px
    img = np.zeros((H, W, 3))
    pts, hit = obj.intersect(camera)
    if not np.any(led_radiant_intensity > 0) or not hit.any():
        return RenderResult(img, hit)
    p = pts[hit]
    n = obj.normals_at(p)
    v = camera.view_directions(p)
    cos_o = np.clip(np.sum(n * v, axis=-1), 0.0, 1.0)
    centers, normals, areas = obj.patches()
    e_t = led_irradiance(centers, normals, led_positions_mm, led_radiant_intensity, obj.eta)
    b = diffuse_exitance(p, centers, areas, e_t, np.asarray(obj.sigma_s_prime_per_mm),
                         np.asarray(obj.sigma_a_per_mm), obj.eta)
    diffuse = fresnel_transmittance(obj.eta, cos_o)[:, None] / np.pi * b
    spec = 0.0
    if include_specular and polarization != Polarization.CROSS:
        spec = specular_radiance(p, n, v, led_positions_mm, led_radiant_intensity, obj.eta,
                                 obj.specular_roughness)
    scale = 1.0 if polarization == Polarization.NONE else 0.5
    img[hit] = scale * diffuse + spec
    return RenderResult(img, hit)
