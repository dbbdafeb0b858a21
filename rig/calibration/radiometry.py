"""Step 4: radiometry — black level and linearity from RAW, and the absolute albedo scale from a reference target.

Captures: a flat Lambertian reference of known reflectance (99% Spectralon tile, or a ColorChecker patch with
its measured reflectance) at the sphere's centre facing the camera; ``dark_frames`` frames with the sphere dark;
an exposure series of the reference under every LED (cross-polarized), geometric in exposure, its longest frame
past saturation; and one frame at the gradient frames' exposure (``[camera] exposure_s``).

Computes (all from RAW through ``drivers.camera.raw.load_linear``, i.e. values (raw - black_tag) / (white -
black_tag)):

- the black-level offset: the dark frames' mean, in DN, relative to the black level the file declares (a
  pedestal the DNG does not know about biases every ratio), and the read noise from the difference of two dark
  frames;
- the linearity: the reference's mean value v(t) (offset removed) over the unsaturated frames, fitted as
  v = a t (1 - beta a t) per channel (a: the linear response per second; beta: the quadratic nonlinearity at
  full scale); saturation where the series stops rising. :func:`linearize` inverts it,
  x = (1 - sqrt(1 - 4 beta v)) / (2 beta);
- the albedo scale (``estimation.gradients.albedo_scale_from_lambertian``) at the gradient exposure, from the
  linear signal a t_g and the reference's reflectance: the factor that makes a translucent surface's
  ambient-subtracted cross-polarized full-on value its diffuse reflectance R_d (Ma et al. 2007; science.md 3).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from .capture import Captured, Shot, design_irradiance, displayed_drive, exposure_ms
from .context import StepContext, StepOutput
from .linearity import fit_linearity, linearize

SECTION = "radiometry"
FloatArray = npt.NDArray[np.float64]

__all__ = ["SECTION", "shots", "compute", "compare", "linearize", "fit_linearity"]


def _tile_radiance(ctx: StepContext) -> float:
    r = ctx.settings.radiometry
    e = design_irradiance(ctx.config, r.tile_center_mm, r.tile_normal, geometry=ctx.geometry)
    return 0.5 * float(np.mean(r.reflectance)) / np.pi * e


def shots(ctx: StepContext) -> list[Shot]:
    r, cfg = ctx.settings.radiometry, ctx.config
    from .capture import design_value_per_radiance

    per_s = design_value_per_radiance(cfg, 1.0) * _tile_radiance(ctx)
    t_top = r.series_top_fraction / per_s
    series = sorted({exposure_ms(t_top / r.series_factor ** k, cfg) for k in range(r.series)})
    t_g = exposure_ms(cfg.camera.exposure_s, cfg)
    items = [Shot(f"dark{k}", t_g, "ambient", polarization="cross",
                  operator={"say": "place the reflectance reference (Spectralon) at the centre, facing the camera; "
                                   "room lights off", "target": "tile"} if k == 0 else None)
             for k in range(max(2, r.dark_frames))]
    items += [Shot(f"series{k:02d}", t, "full", polarization="cross") for k, t in enumerate(series)]
    items.append(Shot("reference", t_g, "full", polarization="cross"))
    return items


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    from estimation.gradients import albedo_scale_from_lambertian

    r, cfg = ctx.settings.radiometry, ctx.config
    span = float(cfg.camera.white_level_dn - cfg.camera.black_level_dn)
    darks = [cap.image(l) for l in sorted(cap.frames) if l.startswith("dark")]
    offset_dn = np.mean([d.reshape(-1, 3).mean(axis=0) for d in darks], axis=0) * span
    diff = (darks[0] - darks[1]).reshape(-1, 3) * span
    read_noise = diff.std(axis=0) / np.sqrt(2.0) * np.sqrt([1.0, 2.0, 1.0])   # per photosite (G averages 2)
    cam = ctx.camera()
    intr = ctx.intrinsics()
    uv = intr.project(((np.asarray(r.tile_center_mm, float) - cam.C) @ cam.R.T)[None, :])[0]   # distorted px
    h = r.roi_px // 2
    u0, v0 = int(round(uv[0])), int(round(uv[1]))
    if not (h <= u0 < intr.width_px - h and h <= v0 < intr.height_px - h):
        raise ValueError(f"the reference tile's centre projects to {uv.round(1).tolist()} px, outside the image")
    roi = (slice(v0 - h, v0 + h + 1), slice(u0 - h, u0 + h + 1))
    off_v = offset_dn / span
    ts, vs, sat = [], [], []
    for label in sorted(l for l in cap.frames if l.startswith("series")):
        img = cap.image(label)[roi]
        if np.any(img >= 0.98):
            sat.append(cap.exposure_s(label))
            continue
        ts.append(cap.exposure_s(label))
        vs.append(img.reshape(-1, 3).mean(axis=0) - off_v)
    if len(ts) < 3:
        raise ValueError(f"{cap.session.root}: only {len(ts)} unsaturated frames in the exposure series (need 3)")
    a, beta, dev = fit_linearity(ts, vs)
    t_g = cap.exposure_s("reference")
    signal = a * t_g                                    # linear signal of the reference at the gradient exposure
    from estimation.gradients import LedRig

    leds = ctx.led_rig()
    leds = LedRig(leds.directions, leds.gains, leds.distances_mm,
                  {"full": np.full(leds.count, displayed_drive(cfg, ctx.pattern_peak))})
    eta = float(cfg.estimation.eta)
    scale = albedo_scale_from_lambertian(signal, np.asarray(r.reflectance), eta=eta, leds=leds,
                                         reference_normal=r.tile_normal)
    ref_direct = cap.image("reference")[roi].reshape(-1, 3).mean(axis=0)
    lin = {"black_offset_dn": offset_dn.tolist(), "span_dn": span, "nonlinearity": beta.tolist()}
    direct = linearize(ref_direct, lin)
    result = {**lin, "read_noise_dn": read_noise.tolist(), "response_per_s": a.tolist(),
              "saturation_exposure_s": min(sat) if sat else None,
              "albedo_scale": scale.tolist(), "albedo_scale_exposure_s": t_g, "eta": eta,
              "pattern_drive": displayed_drive(cfg, ctx.pattern_peak),    # the full pattern's drive (0..1)
              "reference": {"reflectance": list(r.reflectance), "normal": list(r.tile_normal),
                            "center_mm": list(r.tile_center_mm)}}
    residuals = {"linearity_max_deviation": dev.tolist(), "series_exposures_s": ts, "saturated_exposures_s": sat,
                 "reference_frame_vs_fit": (direct / signal - 1.0).tolist(), "roi_px": [u0, v0, r.roi_px]}
    summary = [f"black offset {np.round(offset_dn, 2).tolist()} DN over the declared level, read noise "
               f"{np.round(read_noise, 2).tolist()} DN; nonlinearity beta {np.round(beta, 4).tolist()} "
               f"(max deviation {100 * dev.max():.2f}%); albedo scale {np.round(scale, 4).tolist()} at {t_g:g} s"]
    return StepOutput(result, residuals, {"reference_frame_exposure_s": t_g}, summary)


def truth_albedo_scale(ctx: StepContext, exposure_s: float, pattern_peak: float | None = None) -> FloatArray:
    """The albedo scale the simulator's truth implies (``albedo_scale_from_radiometry`` with the true camera
    response, true LED positions and gains, and the displayed drive)."""
    from estimation.gradients import LedRig, albedo_scale_from_radiometry

    truth, cfg = ctx.world.truth, ctx.config
    inten = np.asarray(cfg.sphere.led_intensity, float) * truth.led_gains
    leds = LedRig.from_positions(truth.led_positions_mm, inten,
                                 patterns={"full": np.full(len(inten), displayed_drive(cfg, pattern_peak))})
    c = cfg.camera
    k = c.gain_dn_per_unit * exposure_s / (c.white_level_dn - c.black_level_dn)
    return albedo_scale_from_radiometry(np.full(3, k), leds, eta=float(cfg.estimation.eta),
                                        reference_normal=ctx.settings.radiometry.tile_normal)


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    truth = ctx.world.truth
    scale_t = truth_albedo_scale(ctx, result["albedo_scale_exposure_s"])
    return {"black_offset_error_dn": (np.asarray(result["black_offset_dn"]) - truth.black_offset_dn).tolist(),
            "nonlinearity_error": (np.asarray(result["nonlinearity"]) - truth.nonlinearity).tolist(),
            "albedo_scale_rel_error": (np.asarray(result["albedo_scale"]) / scale_t - 1.0).tolist(),
            "truth": {"black_offset_dn": truth.black_offset_dn, "nonlinearity": truth.nonlinearity,
                      "albedo_scale": scale_t.tolist()}}
