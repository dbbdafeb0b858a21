"""The virtual scene: a homogeneous translucent object inside the LED sphere, rendered physically.

Diffuse (subsurface) light follows the BSSRDF factorisation of Jensen et al. 2001 as used by
Mukaigawa et al. (seed 000, Eq. 10): L_o(x_o) = F_t(eta, w_o)/pi * sum_k R(|x_o - x_k|) E_t(x_k) A_k, with
E_t the Fresnel-transmitted irradiance from every LED (``estimation.forward``). Surface reflection is a GGX
microfacet lobe with Fresnel reflectance. Polarization after Ma et al. 2007 / science.md §3: subsurface
light is depolarized, specular keeps the source polarization, so cross = diffuse/2 and
parallel = diffuse/2 + specular; without polarizers the camera sees diffuse + specular.

The renderer's tessellation is finer than the estimators' so tests do not commit the inverse crime.

``render_mode="mc"`` (:func:`render_object`, :func:`render_gradient_capture`, ``SimulatedCamera``) replaces the
dipole by a Monte Carlo random walk in the object (:mod:`simulators.mc_capture`; exact transport, seeded, with a
standard error), keeping the cameras, LEDs, polarization and GGX lobe of the fast path.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from estimation.rays import RayEngine
from estimation.fresnel import fresnel_reflectance, fresnel_transmittance
from estimation.shadows import point_light_visibility

from .mc_capture import MCSettings, check_render_mode, render_mc_leds
from .objects import (BumpySlabObject, MeshObject, SceneObject, SphereObject, led_irradiance, patch_exitance,
                      shadow_engine, wall_on_slab_mesh)
from .sensor import expose

FloatArray = npt.NDArray[np.float64]

__all__ = ["SphereObject", "BumpySlabObject", "MeshObject", "SceneObject", "wall_on_slab_mesh", "led_irradiance",
           "specular_radiance", "RenderResult", "render", "render_object", "GradientCapture",
           "render_gradient_capture"]


def specular_radiance(points_mm: FloatArray, normals: FloatArray, view: FloatArray,
                      led_positions_mm: FloatArray, led_radiant_intensity: FloatArray, eta: float,
                      roughness: float, *, occluder: RayEngine | None = None) -> FloatArray:
    """GGX microfacet reflection of the LEDs (Walter et al. 2007), (P, C); LEDs hidden by ``occluder`` (a cast
    shadow, as in :func:`led_irradiance`) reflect nothing."""
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
        w = brdf * cos_i / dist2
        if occluder is not None:
            w = w * point_light_visibility(occluder, points_mm, normals, led_positions_mm[idx])
        out += w @ led_radiant_intensity[idx]
    return out


@dataclass
class RenderResult:
    radiance: FloatArray          # (H, W, 3), camera-side radiance in rig units
    mask: npt.NDArray[np.bool_]   # object pixels
    # render_mode "mc": the Monte Carlo standard error of ``radiance`` (H, W, 3) (the specular lobe is exact);
    # None for "fast"
    stderr: FloatArray | None = None


def render(obj: SphereObject, camera: PinholeCamera, led_positions_mm: FloatArray,
           led_radiant_intensity: FloatArray, polarization: Polarization,
           *, include_specular: bool = True, render_mode: str = "fast",
           mc: "MCSettings | None" = None) -> RenderResult:
    """Radiance image of ``obj`` lit by the LEDs' current emission (N, 3) (:func:`render_object` on a sphere)."""
    return render_object(obj, camera, led_positions_mm, led_radiant_intensity, polarization,
                         include_specular=include_specular, render_mode=render_mode, mc=mc)


# ---------------------------------------------------------------------------------------------------------------
# more objects: a slab with fine relief and a triangle mesh; gradient captures in both polarizations with noise
# ---------------------------------------------------------------------------------------------------------------
def _exitance(obj: SceneObject, points_mm: FloatArray, led_positions_mm: FloatArray,
              emissions: list[FloatArray]) -> list[FloatArray]:
    if isinstance(obj, SphereObject):
        return patch_exitance(obj, points_mm, led_positions_mm, emissions)
    return obj.exitance(points_mm, led_positions_mm, emissions)


def _mc_diffuse(obj: SceneObject, camera: PinholeCamera, led_positions_mm: FloatArray,
                emission: FloatArray, hit: npt.NDArray[np.bool_], mc: "MCSettings | None"
                ) -> tuple[FloatArray, FloatArray]:
    """Monte Carlo subsurface radiance and its standard error at the ``hit`` pixels, (P, 3) each (0 where the
    Monte Carlo shape misses a pixel the analytic intersection hits: a silhouette pixel)."""
    im, _ = render_mc_leds(obj, camera, led_positions_mm, emission, mc or MCSettings())
    return im.radiance[hit], im.stderr[hit]


def render_object(obj: SceneObject, camera: PinholeCamera, led_positions_mm: FloatArray,
                  led_radiant_intensity: FloatArray, polarization: Polarization,
                  *, include_specular: bool = True, render_mode: str = "fast",
                  mc: "MCSettings | None" = None) -> RenderResult:
    """Radiance image of any scene object (sphere, bumpy slab, mesh) lit by the LEDs' current emission (N, 3):
    cross-polarized frames hold half the diffuse light and no specular, parallel ones half the diffuse light
    plus the specular reflection.

    ``render_mode``: "fast" (default) computes the subsurface light with the Jensen dipole and the exit factor
    F_t(eta, w_o)/pi; "mc" renders it by Monte Carlo (:mod:`simulators.mc_capture`, options ``mc``:
    :class:`~simulators.mc_capture.MCSettings`; seeded) and returns its standard error in ``stderr``. The
    specular lobe (GGX) is the same analytic one in both modes."""
    check_render_mode(render_mode)
    H, W = camera.height_px, camera.width_px
    img = np.zeros((H, W, 3))
    se_img = np.zeros((H, W, 3)) if render_mode == "mc" else None
    pts, hit = obj.intersect(camera)
    if not np.any(led_radiant_intensity > 0) or not hit.any():
        return RenderResult(img, hit, se_img)
    p = pts[hit]
    n = obj.normals_at(p)
    v = camera.view_directions(p)
    k = 1.0 if polarization == Polarization.NONE else 0.5
    if render_mode == "mc":
        diffuse, se = _mc_diffuse(obj, camera, np.asarray(led_positions_mm, float),
                                  np.asarray(led_radiant_intensity, float), hit, mc)
        assert se_img is not None
        se_img[hit] = k * se
    else:
        cos_o = np.clip(np.sum(n * v, axis=-1), 0.0, 1.0)
        b = _exitance(obj, p, led_positions_mm, [np.asarray(led_radiant_intensity, float)])[0]
        diffuse = fresnel_transmittance(obj.eta, cos_o)[:, None] / np.pi * b
    spec = 0.0
    if include_specular and polarization != Polarization.CROSS:
        spec = specular_radiance(p, n, v, led_positions_mm, led_radiant_intensity, obj.eta, obj.specular_roughness,
                                 occluder=shadow_engine(obj))
    img[hit] = k * diffuse + spec
    return RenderResult(img, hit, se_img)


@dataclass
class GradientCapture:
    """Frames of one gradient capture and the truth behind them.

    ``frames``: {(pattern, "cross" | "parallel"): (H, W, 3) float32}, linear, black-subtracted, 1.0 = white level
    (the convention of ``drivers.contracts.RawFrame``), patterns "ambient" and those requested.
    ``value_per_radiance``: frame value per unit radiance (gain x exposure / (white - black)), for
    ``estimation.gradients.albedo_scale_from_radiometry``. ``normals``, ``points_mm``, ``view_dirs``: (H, W, 3),
    NaN off the object; ``hit`` (H, W).
    """

    frames: dict[tuple[str, str], npt.NDArray[np.float32]]
    value_per_radiance: float
    normals: FloatArray
    points_mm: FloatArray
    view_dirs: FloatArray
    hit: npt.NDArray[np.bool_]
    render_mode: str = "fast"
    # render_mode "mc": {pattern: (H, W, 3)} Monte Carlo standard error of the *diffuse radiance* (both
    # polarizations see half of it: frame units = 0.5 * value_per_radiance * this); None for "fast"
    diffuse_stderr: dict[str, FloatArray] | None = None
    led_mode: str = ""    # "mc": how the LEDs were rendered ("points" | "distant", simulators.mc_capture)


def render_gradient_capture(obj: SceneObject, camera: PinholeCamera, led_positions_mm: npt.ArrayLike,
                            led_intensity: npt.ArrayLike, patterns: dict[str, npt.ArrayLike], *,
                            polarizations: tuple[str, ...] = ("cross", "parallel"), exposure_s: float = 1.0,
                            sensor: object | None = None, noise: bool = True, rng: np.random.Generator | None = None,
                            ambient_radiance: float = 0.0, render_mode: str = "fast",
                            mc: "MCSettings | None" = None) -> GradientCapture:
    """Render a polarized spherical-gradient capture of ``obj`` (Ma et al. 2007; science.md sec. 3).

    ``patterns``: {name: LED drive values (N,) or (N, 3) in [0, 1]} (e.g. full, x, y, z, x_c, ...), each LED's
    emission being ``led_intensity`` (N, 3) x drive. Per pattern the subsurface exitance is computed once and
    shared by both polarizations: cross = diffuse/2, parallel = diffuse/2 + GGX specular (polarization-preserving).
    An "ambient" frame (all LEDs off, plus ``ambient_radiance``) is added for each polarization.
    ``sensor`` (``simulators.camera.SensorModel``): Poisson-Gaussian noise of the simulated camera on each
    photosite of its RGGB mosaic (``simulators.camera.expose``), read back one RGB pixel per 2 x 2 cell (green:
    the mean of the two sites), black-subtracted and divided by (white - black); ``noise=False`` gives the
    expected values of the same sensor (clipped at white). Without a sensor: radiance x ``exposure_s``, clipped at 1.

    ``render_mode="mc"``: the subsurface light of every pattern is rendered by Monte Carlo
    (:mod:`simulators.mc_capture`; ``mc``: :class:`~simulators.mc_capture.MCSettings`), all patterns with the same
    seed (common random numbers); ``diffuse_stderr`` holds each pattern's standard error. The default LED mode
    renders the lit LEDs as a distant piecewise-constant radiance map (no near field; see that module).
    """
    check_render_mode(render_mode)

    pos = np.asarray(led_positions_mm, float)
    inten = np.asarray(led_intensity, float)
    H, W = camera.height_px, camera.width_px
    pts, hit = obj.intersect(camera)
    p = pts[hit]
    n = obj.normals_at(p)
    v = camera.view_directions(p)
    ft = fresnel_transmittance(obj.eta, np.clip(np.sum(n * v, axis=-1), 0.0, 1.0))[:, None] / np.pi
    names = list(patterns)
    emissions = []
    for name in names:
        drive = np.asarray(patterns[name], float)
        emissions.append(inten * (drive[:, None] if drive.ndim == 1 else drive))
    diffuse_se: dict[str, FloatArray] | None = None
    led_mode = ""
    if render_mode == "mc":
        settings = mc or MCSettings()
        ft = np.full((len(p), 1), 1.0)  # the Monte Carlo radiance already is camera-side radiance
        diffuse, diffuse_se = [], {}
        for name, em in zip(names, emissions):
            se_img = np.zeros((H, W, 3))
            if hit.any() and np.any(em > 0):
                im, led_mode = render_mc_leds(obj, camera, pos, em, settings)
                diffuse.append(im.radiance[hit])
                se_img[hit] = im.stderr[hit]
            else:
                diffuse.append(np.zeros((len(p), 3)))
            diffuse_se[name] = se_img
        # ``val = 0.5 * ft * b`` below: the fast path's b is exitance with ft = F_t/pi; here b is radiance
    else:
        diffuse = _exitance(obj, p, pos, emissions) if hit.any() else [np.zeros((0, 3))] * len(names)
    if sensor is not None:
        gain = float(sensor.gain_dn_per_unit) * exposure_s  # type: ignore[attr-defined]
        span = float(sensor.white_level_dn - sensor.black_level_dn)  # type: ignore[attr-defined]
        k = gain / span
    else:
        k = exposure_s
    rng = rng or np.random.default_rng(0)
    frames: dict[tuple[str, str], npt.NDArray[np.float32]] = {}

    def finish(radiance: FloatArray) -> npt.NDArray[np.float32]:
        if sensor is None or not noise:
            return np.clip(radiance * k, 0.0, 1.0).astype(np.float32)
        raw = expose(radiance, exposure_s, sensor, rng).astype(float)  # type: ignore[arg-type]
        rgb = np.stack([raw[0::2, 0::2], 0.5 * (raw[0::2, 1::2] + raw[1::2, 0::2]), raw[1::2, 1::2]], -1)
        return ((rgb - sensor.black_level_dn) / span).astype(np.float32)  # type: ignore[attr-defined]

    for pol in polarizations:
        if pol not in ("cross", "parallel"):
            raise ValueError(f"unknown polarization {pol!r}; valid: cross, parallel")
        amb = np.full((H, W, 3), float(ambient_radiance))
        frames[("ambient", pol)] = finish(amb)
        for name, em, b in zip(names, emissions, diffuse):
            img = np.zeros((H, W, 3))
            val = 0.5 * ft * b + ambient_radiance
            if pol == "parallel" and hit.any():
                val = val + specular_radiance(p, n, v, pos, em, obj.eta, obj.specular_roughness,
                                              occluder=shadow_engine(obj))
            img[hit] = val
            frames[(name, pol)] = finish(img)
    normals = np.full((H, W, 3), np.nan)
    normals[hit] = n
    view = np.full((H, W, 3), np.nan)
    view[hit] = v
    return GradientCapture(frames, k, normals, pts, view, hit, render_mode, diffuse_se, led_mode)
