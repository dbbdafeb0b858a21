"""Monte Carlo reference of a capture folder's known sphere (``rig estimate gradients FOLDER --reference``).

The grounded sphere estimator is biased on a sphere of the size of the diffusion length (real transport in a small
convex body is not the truncated half-space dipole; :mod:`estimation.gradient_correction`). This module renders
*the capture the folder describes* by Monte Carlo and lets
:func:`estimation.gradient_correction.estimate_sphere_with_reference` correct the sphere summary with it:

- the same camera (pinhole as calibrated; an orthographic camera gets the view direction the simulator needs),
  the same LEDs (calibrated positions and intensities, the displayed drive values of every pattern), the frames
  the folder holds (patterns x polarizations; ambient frames are zero, the observed ones are subtracted), the
  known sphere (center_mm, radius_mm) and eta;
- the render is converted into the folder's frame units before the maps: frame value = rendered radiance x V x
  exposure_s of that frame, with V (value per unit radiance per second, per channel) the one implied by the
  folder's albedo scale and LED calibration, V = albedo_scale_from_radiometry(1, leds) / albedo_scale (exactly
  ``radiometry.value_per_radiance_per_s`` when the folder gives it). The saturation and dark thresholds, the
  exposures, the albedo scale, the LUT and the LED near-field model of :func:`estimation.gradients.compute_maps`
  therefore see the rendered capture exactly as they see the folder's frames;
- both the observed maps and every render are reduced by the same region summary
  (:meth:`FolderSphereReference.estimate_maps`: :func:`estimation.diffusion.estimate_sphere`, exact sphere method,
  the folder's region = sphere pixels x object mask, minus pixels saturated in the observed frames).

Limits: the Monte Carlo renderer sees the LEDs as a distant piecewise-constant map centred on the sphere
(:mod:`simulators.mc_capture`, ``leds="distant"``): the LEDs' near field (order 2 r / d, 2 % for a 10 mm sphere
at 1 m) is in the folder's frames and in the maps' LED model, but not in the reference. Surface reflection in
parallel-polarized reference frames is the simulator's GGX lobe (it only enters the specular maps).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import Any, Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from estimation.camera import OrthographicCamera, PinholeCamera
from estimation.diffusion import SphereEstimate, estimate_sphere
from estimation.gradient_correction import SphereObservables, estimate_sphere_with_reference
from estimation.gradients import GradientMaps, LedRig, albedo_scale_from_radiometry

from rig.estimate.reference.mc_reference import GradientsMonteCarloReference

__all__ = ["REFERENCE_SPP", "REFERENCE_ITERATIONS", "REFERENCE_SEED", "REFERENCE_REL_TOL", "FolderSphereReference",
           "renderable_camera", "implied_value_per_radiance_per_s", "render_exposure_s", "reference_corrected_sphere"]

REFERENCE_SPP = 64
REFERENCE_ITERATIONS = 8
REFERENCE_SEED = 1
#: reference_mode "adaptive" (issue 19, the default): sample-count levels spp / these (at least REFERENCE_MIN_SPP),
#: the loop stopping at the cheapest one that meets its stop rule with "ok"-narrow intervals
#: (estimation.gradient_correction); "legacy": every render at spp (the loop as at the start of issue 19)
REFERENCE_SPP_LEVEL_DIVISORS, REFERENCE_MIN_SPP = (8, 1), 8
REFERENCE_MODES = ("adaptive", "legacy")
REFERENCE_REL_TOL = 0.02   # the stop rule used in tests/simulators/test_mc_frames_gradients.py
FrameKey = tuple[str, str]


@dataclass(frozen=True)
class _ViewOrthographic(OrthographicCamera):
    """An :class:`OrthographicCamera` with the ``view_directions`` the scene simulator asks of a camera."""

    def view_directions(self, points_mm: Any) -> NDArray[np.float64]:
        shape = np.shape(points_mm)
        return np.broadcast_to(-self.R[2], shape).copy()


def renderable_camera(camera: PinholeCamera | OrthographicCamera) -> PinholeCamera | OrthographicCamera:
    """The folder's camera as the simulator renders it (same rays; orthographic gets ``view_directions``)."""
    if isinstance(camera, OrthographicCamera):
        return _ViewOrthographic(**{f.name: getattr(camera, f.name) for f in fields(camera)})
    return camera


def implied_value_per_radiance_per_s(albedo_scale: Any, leds: LedRig, eta: float,
                                     reference_normal: Any) -> NDArray[np.float64]:
    """Frame value per unit (cross-polarized) radiance per second (3,) that ``albedo_scale`` implies for these
    LEDs: the inverse of :func:`estimation.gradients.albedo_scale_from_radiometry` (which is 1 / V)."""
    unit = albedo_scale_from_radiometry(np.ones(3), leds, eta=eta, reference_normal=reference_normal)
    return np.asarray(unit, dtype=np.float64) / np.asarray(albedo_scale, dtype=np.float64)


def render_exposure_s(led_positions_mm: Any, led_intensity: Any, drives: Mapping[str, Any],
                      center_mm: Any, radius_mm: float) -> float:
    """Exposure of the reference render (simulator units: frame = radiance x exposure, clipped at 1) chosen so
    that no pixel clips: 0.05 / the largest irradiance any pattern can put on the sphere (radiance <= E)."""
    pos = np.asarray(led_positions_mm, dtype=np.float64)
    inten = np.asarray(led_intensity, dtype=np.float64)
    d = np.maximum(np.linalg.norm(pos - np.asarray(center_mm, dtype=np.float64), axis=1) - float(radius_mm), 1e-6)
    e_max = 0.0
    for drv in drives.values():
        v = np.asarray(drv, dtype=np.float64)
        v = v[:, None] if v.ndim == 1 else v
        e_max = max(e_max, float(np.max(np.sum(inten * v / (d * d)[:, None], axis=0))))
    if not e_max > 0:
        raise ValueError("the LED patterns put no light on the sphere")
    return 0.05 / e_max


@dataclass
class FolderSphereReference(GradientsMonteCarloReference):
    """:class:`rig.estimate.reference.mc_reference.GradientsMonteCarloReference` reduced with a capture folder's region summary:
    ``true_normals`` (H, W, 3) and ``region`` (H, W) of the folder's sphere, ``tile_rows`` as the folder's
    estimate. ``maps_fn`` receives the rendered :class:`simulators.scene.GradientCapture`."""

    true_normals: NDArray[np.float64] | None = None
    region: NDArray[np.bool_] | None = None
    tile_rows: int = 256
    #: the summary's observables only (albedo, shortening: all the correction reads), not its parameter inversions
    observables_only: bool = False
    #: render only the summary's pixels (``region`` eroded by ``erode_px``; the maps and the summary are per pixel, so
    #: the observables are bit-identical to those of a whole-frame render: issue 19)
    render_region_only: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.render_region_only and self.region is not None and self.render_mask is None:
            from scipy import ndimage

            reg = np.asarray(self.region, dtype=bool)
            self.render_mask = ndimage.binary_erosion(reg, iterations=int(self.erode_px)) if self.erode_px else reg

    def estimate_maps(self, maps: GradientMaps) -> SphereEstimate:
        """The sphere summary of maps (observed or rendered): exact sphere method, the folder's region."""
        return estimate_sphere(maps, radius_mm=float(self.radius_mm), true_normals=self.true_normals,
                               region=self.region, erode_px=int(self.erode_px), tile_rows=int(self.tile_rows),
                               invert_summary=not self.observables_only)

    def estimate(self, capture: Any) -> SphereEstimate:
        return self.estimate_maps(self.maps_fn(capture))


def _span(value: Any, interval: Any) -> dict[str, list[float]]:
    return {"value": np.asarray(value, dtype=np.float64).tolist(),
            "interval": np.asarray(interval, dtype=np.float64).tolist()}


def reference_corrected_sphere(*, camera: PinholeCamera | OrthographicCamera, leds: LedRig,
                               led_positions_mm: Any, led_intensity: Any, frame_keys: list[FrameKey],
                               exposure_s: Mapping[FrameKey, float], albedo_scale: Any, eta: float,
                               reference_normal: Any, center_mm: Any, radius_mm: float,
                               true_normals: NDArray[np.float64], region: NDArray[np.bool_],
                               folder_maps: Callable[[Mapping[FrameKey, NDArray[np.float32]]], GradientMaps],
                               observed_maps: GradientMaps, spp: int = REFERENCE_SPP,
                               iterations: int = REFERENCE_ITERATIONS, seed: int = REFERENCE_SEED,
                               tile_rows: int = 256, render_mode: str = "mc", reference_mode: str = "adaptive"
                               ) -> tuple[dict[str, Any], Any]:
    """The reference-corrected sphere summary of a capture folder (JSON-ready dict) and the reference object.

    ``folder_maps(images) -> GradientMaps``: the folder's own ``compute_maps`` call (same albedo scale, LUT, LED
    model, thresholds, exposures, object mask) on frames keyed like the folder's; ``frame_keys``: the folder's
    (pattern, polarization) keys; ``observed_maps``: ``folder_maps`` of the folder's frames. Raises ``ValueError``
    when the correction cannot run (see :func:`estimate_sphere_with_reference`). ``reference_mode``: "adaptive"
    (issue 19: sample-count levels spp / :data:`REFERENCE_SPP_LEVEL_DIVISORS`, the renders reduced to the two
    observables the correction reads, without the summary's parameter inversions) or "legacy" (every render at
    ``spp`` with full summaries, as at the start of issue 19).
    """
    if reference_mode not in REFERENCE_MODES:
        raise ValueError(f"reference_mode must be one of {REFERENCE_MODES}; got {reference_mode!r}")
    t0, c0 = time.perf_counter(), time.process_time()
    drives = {p: leds.pattern_values(p) for p in sorted({p for p, _ in frame_keys if p != "ambient"})}
    pols = tuple(pol for pol in ("cross", "parallel") if any(k[1] == pol for k in frame_keys))
    V = implied_value_per_radiance_per_s(albedo_scale, leds, eta, reference_normal)
    k_render = render_exposure_s(led_positions_mm, led_intensity, drives, center_mm, radius_mm)
    H, W = region.shape

    def maps_fn(capture: Any) -> GradientMaps:
        images: dict[FrameKey, NDArray[np.float32]] = {}
        for key in frame_keys:
            if key[0] == "ambient":
                images[key] = np.zeros((H, W, 3), np.float32)
                continue
            frame = np.asarray(capture.frames[key], dtype=np.float64)
            if frame.max(initial=0.0) >= 1.0:
                raise ValueError(f"reference frame {key[0]}/{key[1]} clipped in the simulator (render exposure "
                                 f"{k_render:.3g} s too long)")
            images[key] = (frame * (V * float(exposure_s[key]) / float(capture.value_per_radiance))
                           ).astype(np.float32)
        return folder_maps(images)

    from simulators.mc_capture import MCSettings

    ref = FolderSphereReference(renderable_camera(camera), np.asarray(led_positions_mm, dtype=np.float64),
                                np.asarray(led_intensity, dtype=np.float64), drives, maps_fn, float(radius_mm),
                                tuple(float(c) for c in np.asarray(center_mm, dtype=np.float64)), spp=int(spp),
                                polarizations=pols, exposure_s=k_render, sensor=None,
                                mc=MCSettings(spp=int(spp), seed=int(seed), leds="distant"), render_mode=render_mode,
                                true_normals=true_normals, region=region, tile_rows=int(tile_rows),
                                spp_levels=tuple(sorted({min(int(spp), max(REFERENCE_MIN_SPP, int(spp) // k))
                                                         for k in REFERENCE_SPP_LEVEL_DIVISORS}))
                                if reference_mode == "adaptive" and render_mode == "mc" else (),
                                observables_only=reference_mode == "adaptive",
                                render_region_only=reference_mode == "adaptive")
    observed = SphereObservables.from_summary(ref.estimate_maps(observed_maps).summary)
    res = estimate_sphere_with_reference(observed, ref, float(radius_mm), float(eta), seed=int(seed),
                                         max_iterations=int(iterations), rel_tol=REFERENCE_REL_TOL)
    unc = res.uncorrected
    mc = MCSettings(spp=int(spp), seed=int(seed), leds="distant")
    summary: dict[str, Any] = {
        "estimator": "grounded sphere (dipole-jensen, exact sphere integrals) corrected by Monte Carlo reference "
                     "renders of this capture (estimation.gradient_correction.estimate_sphere_with_reference)",
        "applies_to": "the region summary only; the per-pixel maps written to the output folder are uncorrected",
        "D_mm": _span(res.D_mm, res.intervals["D_mm"]),
        "sigma_s_prime_per_mm": _span(res.sigma_s_prime_per_mm, res.intervals["sigma_s_prime_per_mm"]),
        "sigma_a_per_mm": _span(res.sigma_a_per_mm, res.intervals["sigma_a_per_mm"]),
        "alpha_prime": res.alpha_prime.tolist(), "l_prime_mm": res.l_prime_mm.tolist(),
        "censored": res.censored.tolist(), "status": list(res.status),
        "channel_converged": np.asarray(res.channel_converged).tolist(),
        "albedo": {"observed": observed.albedo.tolist(), "corrected": res.corrected.albedo.tolist(),
                   "note": "median apparent albedo of the sphere; corrected = observed / kappa_albedo"},
        "shortening": {"observed": observed.shortening.tolist(), "corrected": res.corrected.shortening.tolist()},
        "kappa_albedo": res.kappa_albedo.tolist(), "kappa_blur": res.kappa_blur.tolist(),
        "kappa_albedo_rel_stderr": res.kappa_albedo_rel_stderr.tolist(),
        "kappa_blur_rel_stderr": res.kappa_blur_rel_stderr.tolist(),
        "uncorrected": {k: np.asarray(v).tolist() for k, v in unc.items()},
        "steps": [s.as_dict() for s in res.steps], "iterations": res.iterations, "converged": res.converged,
        "message": res.message,
        "scan": res.provenance.get("scan"),
        "reference": {"renderer": "simulators.scene.render_gradient_capture (render_mode "
                                  f"\"{render_mode}\", simulators.mc_capture)",
                      "spp": int(spp), "max_iterations": int(iterations), "seed": int(seed),
                      "rel_tol": REFERENCE_REL_TOL, "led_mode": mc.leds, "env_rows": mc.env_rows,
                      "reference_mode": reference_mode, "spp_levels": list(ref.spp_levels) or [int(spp)],
                      "render_spp": [r.get("spp") for r in ref.renders],
                      "patterns": sorted(drives), "polarizations": list(pols),
                      "value_per_radiance_per_s": V.tolist(), "render_exposure_s": k_render,
                      "region_px": int(np.count_nonzero(region)),
                      "rendered_px": int(region.size) if ref.render_mask is None
                      else int(np.count_nonzero(ref.render_mask)),
                      "render_seconds": [r["render_seconds"] for r in ref.renders],
                      "limits": "LEDs rendered as a distant map centred on the sphere (no near field); "
                                "the sphere is taken as exactly known (center_mm, radius_mm, eta)"},
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,   # this process's CPU (load-independent; issue 19's benchmark)
    }
    return summary, ref
