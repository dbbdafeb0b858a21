"""Step 3c: polarizer extinction check — a cross-polarized mirror ball must be dark.

Captures: the mirror ball; for a few LEDs with central highlights, one parallel-polarized frame at the highlight
exposure and one cross-polarized frame ``exposure_ratio`` times longer, with an ambient frame for each state.

Computes: per LED the highlight's energy in an aperture (the annulus around it subtracted: the ball's diffuse
residue and stray light) in both states, per unit exposure; the ratio cross/parallel is the fraction of the
specular reflection that leaks through crossed polarizers (Ma et al. 2007 separate diffuse and specular light
by this very extinction). The check passes when the median ratio is at most ``max_ratio``; the report also gives
it in dB (-10 log10 ratio).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from rig.calibration.capture import Captured, Shot, exposure_ms
from rig.calibration.context import StepContext, StepOutput
from rig.calibration.led_directions import _highlight_exposure, _spread, highlight_centroid, visible_leds

SECTION = "extinction"
FloatArray = npt.NDArray[np.float64]

__all__ = ["SECTION", "shots", "compute", "compare", "aperture_energy"]


def _leds(ctx: StepContext) -> list[int]:
    e, b = ctx.settings.extinction, ctx.settings.mirror_ball
    n = len(ctx.geometry.led_positions_mm)
    if e.leds:
        bad = [i for i in e.leds if not 0 <= i < n]
        if bad:
            raise ValueError(f"calibration.extinction.leds: LED indices {bad} outside [0, {n})")
        return list(e.leds)
    pos, cam = ctx.geometry.led_positions_mm, ctx.geometry.camera.C
    central = set(visible_leds(pos, b.center_mm, cam, 40.0)) - set(visible_leds(pos, b.center_mm, cam, 12.0))
    return _spread(ctx.geometry.led_directions, sorted(central), e.count)


def shots(ctx: StepContext) -> list[Shot]:
    e = ctx.settings.extinction
    t_p, ctx.pattern_peak = _highlight_exposure(ctx)
    t_c = exposure_ms(t_p * e.exposure_ratio, ctx.config)
    leds = _leds(ctx)
    items = [Shot("ambient_parallel", t_p, "ambient", polarization="parallel",
                  operator={"say": "place the mirror ball at the sphere's centre", "target": "mirror_ball"})]
    items += [Shot(f"par{i:04d}", t_p, "key", led=i, polarization="parallel") for i in leds]
    items += [Shot("ambient_cross", t_c, "ambient", polarization="cross")]
    items += [Shot(f"crs{i:04d}", t_c, "key", led=i, polarization="cross") for i in leds]
    return items


def aperture_energy(image: npt.ArrayLike, center_uv: npt.ArrayLike, radius_px: float) -> float:
    """Sum of ``image`` (H, W) within ``radius_px`` of ``center_uv`` minus the median of the annulus
    1.5-2.5 radii out times the aperture's pixel count."""
    img = np.asarray(image, float)
    v, u = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    r = np.hypot(u - center_uv[0], v - center_uv[1])
    inside = r <= radius_px
    ring = (r >= 1.5 * radius_px) & (r <= 2.5 * radius_px)
    return float(img[inside].sum() - np.median(img[ring]) * inside.sum())


def compute(ctx: StepContext, cap: Captured) -> StepOutput:
    e = ctx.settings.extinction
    amb_p, amb_c = cap.image("ambient_parallel"), cap.image("ambient_cross")
    ratios, energies, saturated = {}, {}, []
    for label in sorted(l for l in cap.frames if l.startswith("par")):
        i = int(label[3:])
        par_raw = cap.image(label)
        par = (par_raw - amb_p).sum(axis=2)
        crs = (cap.image(f"crs{i:04d}") - amb_c).sum(axis=2)
        uv, _ = highlight_centroid(par)
        if par_raw[int(round(uv[1])), int(round(uv[0]))].max() >= 0.98:
            saturated.append(i)
        t_p, t_c = cap.exposure_s(label), cap.exposure_s(f"crs{i:04d}")
        ep = aperture_energy(par, uv, e.aperture_px) / t_p
        ec = aperture_energy(crs, uv, e.aperture_px) / t_c
        ratios[str(i)] = ec / ep
        energies[str(i)] = {"parallel_per_s": ep, "cross_per_s": ec}
    if not ratios:
        raise ValueError(f"{cap.session.root}: no extinction frames")
    if saturated:
        raise ValueError(f"{cap.session.root}: parallel-polarized highlights saturated for LEDs {saturated}; the "
                         "ratio would be overestimated (lower calibration.mirror_ball.highlight_fraction)")
    r = np.asarray(list(ratios.values()))
    med = float(np.median(r))
    passed = bool(med <= e.max_ratio)
    result = {"median_ratio": med, "ratio_by_led": ratios, "extinction_db": float(-10 * np.log10(max(med, 1e-12))),
              "max_ratio": e.max_ratio, "passed": passed}
    residuals = {"spread": float(r.max() - r.min()), "energies": energies}
    summary = [f"cross/parallel specular ratio {med:.5f} ({result['extinction_db']:.1f} dB) over {len(r)} LEDs: "
               + ("PASS" if passed else f"FAIL (> {e.max_ratio:g}): check the polarizer orientation")]
    return StepOutput(result, residuals, {}, summary)


def compare(ctx: StepContext, result: dict[str, Any]) -> dict[str, Any]:
    truth = ctx.world.truth.extinction_ratio
    return {"truth_ratio": truth, "ratio_rel_error": result["median_ratio"] / truth - 1.0}
