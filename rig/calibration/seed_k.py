"""Step 5: the length k of the second seed's D = k R_d / |n_z|, from a reference material in the capture geometry.

A flat homogeneous patch under distant light carries no information about D, so the seed's relation hides an
empirical length k that depends on the geometry (science.md sec. 4); it must be calibrated on a material of
known parameters, shaped and placed like the objects (same rig, similar size), and reported as such.

Captures: a sphere of the reference material (``[calibration.seed_k]``: a row of the material table or explicit
sigma_s', sigma_a; radius of the objects by default) where the objects go, surveyed like an object
(``[object] survey_target``), under the constant and x, y, z gradient patterns plus an ambient frame,
cross-polarized, at the gradient exposure.

Computes: the gradient maps (``estimation.gradients.compute_maps``) exactly as the estimator does, but with
everything calibrated so far — undistorted frames, the calibrated camera, the LED rig (directions, distances,
gains), the albedo scale and the sensor linearization — then ``estimation.diffusion.calibrate_k`` with the
reference's D = 1/(3 sigma_t') over the sphere (eroded outline), per channel, with an order-statistic interval.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from rig.calibration.capture import Captured, Shot, Survey, displayed_drive, exposure_ms
from rig.calibration.context import StepContext, StepOutput

SECTION = "seed_k"
FloatArray = npt.NDArray[np.float64]
GRADIENTS = ("full", "x", "y", "z")

__all__ = ["SECTION", "shots", "compute", "compare", "reference_D_mm", "truth_k_mm"]


def reference_D_mm(sigma_s_prime_per_mm: npt.ArrayLike, sigma_a_per_mm: npt.ArrayLike) -> FloatArray:
    from estimation.dipole import diffusion_coefficient_mm

    return np.asarray(diffusion_coefficient_mm(np.asarray(sigma_s_prime_per_mm, float),
                                               np.asarray(sigma_a_per_mm, float)), float)


def shots(ctx: StepContext) -> list[Shot | Survey]:
    from rig.calibration.simworld import reference_material

    cfg = ctx.config
    name, _, _, _, radius = reference_material(cfg, ctx.settings)
    t = exposure_ms(cfg.camera.exposure_s, cfg)
    items: list[Shot | Survey] = []
    op = {"say": f"place the reference sphere ({name}, radius {radius:g} mm) where the objects go, with its "
                 f"reflector {cfg.object.survey_target!r}", "target": "reference"}
    if cfg.object.survey_target:
        items.append(Survey(cfg.object.survey_target, operator=op))
        op = None
    items.append(Shot("ambient", t, "ambient", polarization="cross", operator=op))
    items += [Shot(p, t, p, polarization="cross") for p in GRADIENTS]
    return items


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    from estimation.diffusion import calibrate_k, sphere_geometry
    from estimation.gradients import LedRig, albedo_scale_from_radiometry, compute_maps
    from scipy.ndimage import binary_erosion

    from rig.acquire.patterns import pattern_values
    from rig.calibration.capture import design_value_per_radiance
    from rig.calibration.simworld import reference_material

    cfg, s = ctx.config, ctx.settings.seed_k
    name, ssp, sa, eta, radius = reference_material(cfg, ctx.settings)
    intr = ctx.intrinsics()
    camera = ctx.camera()
    if cfg.object.survey_target and cfg.object.survey_target in cap.surveys:
        center = np.asarray(cap.surveys[cfg.object.survey_target], float) - np.asarray(cfg.object.target_offset_mm)
        ctx.used["reference_center"] = f"survey of {cfg.object.survey_target!r} - object.target_offset_mm"
    else:
        center = np.asarray(cfg.scene.center_mm, float)
        ctx.used["reference_center"] = "config scene.center_mm (no survey target)"
    t = cap.exposure_s("full")
    raw = {("ambient", "cross"): intr.undistort_image(cap.image("ambient"))}
    for p in GRADIENTS:
        raw[(p, "cross")] = intr.undistort_image(cap.image(p))
        if cap.exposure_s(p) != t:
            raise ValueError(f"{cap.session.root}: gradient frames must share one exposure")
    rig = ctx.led_rig()
    drive = displayed_drive(cfg, ctx.pattern_peak)
    dirs = np.asarray(ctx.geometry.led_directions, float)       # the patterns were computed from the design layout
    shown = {p: np.round(pattern_values(p, dirs) * drive * 65535) / 65535 for p in GRADIENTS}
    leds = LedRig(rig.directions, rig.gains, rig.distances_mm, shown)
    if ctx.prior is not None and ctx.prior.has("radiometry"):
        scale = ctx.prior.albedo_scale(t)
        ctx.used["albedo_scale"] = f"radiometry revision {ctx.prior.section('radiometry')['revision']}"
    else:
        scale = albedo_scale_from_radiometry(np.full(3, design_value_per_radiance(cfg, t)), leds, eta=eta)
        ctx.used["albedo_scale"] = "design camera response (uncalibrated)"
    normals, view, hit = sphere_geometry(camera, center, radius)
    maps = compute_maps(raw, albedo_scale=scale, leds=leds, eta=eta, view_dirs=view,
                        geometry_normals=np.where(hit[..., None], normals, 0.0), object_mask=hit,
                        surface_center_mm=center, surface_radius_mm=radius, lut_size=s.lut_size)
    region = binary_erosion(hit, iterations=s.erode_px)
    D_ref = reference_D_mm(ssp, sa)
    cal = calibrate_k(maps, D_ref, region=region, true_normals=normals,
                      provenance={"reference": name, "radius_mm": radius, "session": str(cap.session.root)})
    if not np.all(np.isfinite(cal.k_mm)) or np.any(cal.k_mm <= 0):
        raise ValueError(f"{cap.session.root}: k could not be calibrated (pixels per channel {cal.n_pixels.tolist()})")
    m = region[..., None] & ~maps.unknown
    alb = [float(np.median(maps.albedo[..., c][m[..., c]])) for c in range(3)]
    from estimation.diffusion.maps import _shortening

    sh = _shortening(maps, normals)
    short = [float(np.median(sh[..., c][m[..., c]])) for c in range(3)]
    result = {"k_mm": cal.k_mm.tolist(), "interval_mm": cal.interval_mm.tolist(), "n_pixels": cal.n_pixels.tolist(),
              "reference": {"material": name, "sigma_s_prime_per_mm": list(ssp), "sigma_a_per_mm": list(sa),
                            "eta": eta, "radius_mm": radius, "D_ref_mm": D_ref.tolist()},
              "geometry": {"center_mm": center.tolist(),
                           "camera_distance_mm": float(np.linalg.norm(camera.C - center))},
              "estimator": "D = k R_d / |n_z| (Zhu et al.; estimation.diffusion.calibrate_k)"}
    residuals = {"median_albedo": alb, "median_shortening": short,
                 "relative_interval": ((cal.interval_mm[:, 1] - cal.interval_mm[:, 0]) / cal.k_mm).tolist()}
    summary = [f"k = {np.round(cal.k_mm, 4).tolist()} mm from {name} (D_ref {np.round(D_ref, 4).tolist()} mm, "
               f"radius {radius:g} mm); median albedo {np.round(alb, 4).tolist()}, shortening "
               f"{np.round(short, 4).tolist()}"]
    return StepOutput(result, residuals, {"albedo_scale_used": np.asarray(scale).tolist()}, summary)


def truth_k_mm(ssp: npt.ArrayLike, sa: npt.ArrayLike, eta: float, radius_mm: float) -> FloatArray:
    """k the simulator's truth implies for the reference sphere: D_ref x S / C, with the sphere's exact apparent
    albedo C(2 rho) and shortening S (``estimation.diffusion.sphere_albedo``, ``sphere_shortening``), which is
    what the maps measure on a sphere under (near-)uniform light."""
    from estimation.diffusion import sphere_albedo, sphere_shortening

    ssp = np.asarray(ssp, float)
    sa = np.asarray(sa, float)
    return reference_D_mm(ssp, sa) * sphere_shortening(radius_mm, ssp, sa, eta) / sphere_albedo(radius_mm, ssp, sa, eta)


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    ref = result["reference"]
    k_t = truth_k_mm(ref["sigma_s_prime_per_mm"], ref["sigma_a_per_mm"], ref["eta"], ref["radius_mm"])
    return {"k_truth_mm": k_t.tolist(), "k_rel_error": (np.asarray(result["k_mm"]) / k_t - 1.0).tolist()}
