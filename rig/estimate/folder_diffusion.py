"""Diffusion maps of surfaces other than a known sphere, for ``rig estimate gradients FOLDER`` (issue 16).

Where the capture has relief or curvature but no sphere, the diffuse normal field is the true one blurred by the
subsurface transport (:mod:`estimation.relief`). The true normals come from the capture folder:

- ``[object] shape = "relief"`` with ``normals_file`` (an .npy (H, W, 3) of rig-frame unit normals, NaN where
  unknown), ``height_file`` (an .npy (H, W) height in mm towards the camera on the pixel grid; orthographic
  camera only) or ``mesh_file`` (a mesh rendered into the camera: :mod:`rig.estimate.folder_mesh`), or
- ``shape = "unknown"`` (or no ``[object]``) with parallel-polarized frames: the specular normals of the same
  capture (Ma et al. 2007) stand in for the true ones.

Per window of ``window_px`` pixels and per channel: l', l_d, D, sigma_s', sigma_a, alpha' with intervals and a
status (ok / weak / unknown), written as maps (``relief_<param>.exr`` and ``_lo`` / ``_hi``, ``relief_status``),
and a region summary over the object mask. Documented in ``docs/gradients.md`` sec. 9 and
``docs/capture-folder.md``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimation.camera import OrthographicCamera, PinholeCamera
from estimation.relief import (RELIEF_PARAMS, compare_seed, fit_relief_windows, normals_from_height,
                              summarize_relief)

__all__ = ["ReliefGeometry", "read_relief_geometry", "pixel_footprint_mm", "relief_estimate", "RELIEF_WINDOW_PX"]

RELIEF_WINDOW_PX = 64
"""Default window (pixels) of the per-window relief fit; the region summary pools the windows."""


@dataclass(frozen=True)
class ReliefGeometry:
    """``[object] shape = "relief"``: true normals (H, W, 3, rig frame) read from ``source`` (a file)."""

    normals: NDArray[np.float64]
    source: str
    file: Path


def read_relief_geometry(t: Any, folder: Path, shape: tuple[int, int], camera: Any) -> ReliefGeometry:
    """Read ``normals_file`` or ``height_file`` of an ``[object]`` table ``t`` (``rig.estimate.capture_folder._Table``);
    errors name the file and the key."""
    H, W = shape
    keys = [k for k in ("normals_file", "height_file", "mesh_file") if t.has(k)]
    if len(keys) != 1:
        raise t.err("normals_file", "exactly one of normals_file (.npy, H x W x 3 rig-frame unit normals), "
                    "height_file (.npy, H x W heights in mm) or mesh_file (PLY / OBJ / STL in the rig frame) with "
                    "shape = \"relief\"", keys or "neither")
    k = keys[0]
    if k != "mesh_file":
        for extra in ("mesh_units", "mesh_translation_mm"):
            if t.has(extra):
                raise t.err(extra, "nothing unless mesh_file is given", extra)
    if k == "mesh_file":
        from rig.estimate.folder_mesh import read_mesh_normals
        normals, path = read_mesh_normals(t, folder, shape, camera)
        return ReliefGeometry(normals, "mesh_file", path)
    p = t.path(k, folder, ".npy array")
    try:
        a = np.asarray(np.load(p, allow_pickle=False), dtype=np.float64)
    except Exception as exc:
        raise t.err(k, "a readable .npy array of numbers", f"{p.name} ({exc})") from None
    if k == "normals_file":
        if a.shape != (H, W, 3):
            raise t.err(k, f"an array of shape ({H}, {W}, 3) (the frames' size)", f"{p.name}: shape {a.shape}")
        fin = np.isfinite(a).all(-1)
        if not fin.any() or np.any(np.abs(np.linalg.norm(a[fin], axis=-1) - 1.0) > 1e-3):
            raise t.err(k, "unit normals (NaN where unknown), at least one finite", p.name)
        return ReliefGeometry(a, "normals_file", p)
    if not isinstance(camera, OrthographicCamera):
        raise t.err(k, "an orthographic [camera] (a height field is sampled on its pixel grid); give normals_file "
                    "for a pinhole camera", p.name)
    if a.shape != (H, W) or not np.isfinite(a).all():
        raise t.err(k, f"a finite array of shape ({H}, {W}) (heights in mm)", f"{p.name}: shape {a.shape}")
    return ReliefGeometry(normals_from_height(a, camera.pixel_size_mm, camera.R), "height_file", p)


def pixel_footprint_mm(camera: PinholeCamera | OrthographicCamera) -> float:
    """Pixel size on the object: the orthographic pixel, or (pinhole) the distance from the camera centre to the
    rig origin divided by the focal length (exact at the origin, a fronto-parallel approximation elsewhere)."""
    if isinstance(camera, OrthographicCamera):
        return float(camera.pixel_size_mm)
    return float(np.linalg.norm(np.asarray(camera.C, dtype=np.float64)) / camera.fx_px)


class _Known:
    """~unknown, computed per slice (a full-frame boolean copy is not made): what ``fit_relief_windows`` reads
    band by band as ``valid``."""

    def __init__(self, unknown: Any) -> None:
        self.unknown = unknown
        self.shape = tuple(unknown.shape)

    def __getitem__(self, key: Any) -> NDArray[np.bool_]:
        return ~np.asarray(self.unknown[key], dtype=bool)


def relief_estimate(maps: Any, true_normals: NDArray[np.float64], source: str, camera: Any,
                    region: NDArray[np.bool_] | None, out_dir: Path, fmt: str, window_px: int,
                    seed_D_mm: Any = None, residual_stderr_rad: Any = None
                    ) -> tuple[dict[str, Any], dict[str, Path], Any]:
    """The per-window relief fit and its region summary; writes the window maps. With the seed's D map
    (``seed_D_mm``, (H, W, 3)) also the seed beside the fit (:func:`estimation.relief.compare_seed`): the maps
    ``relief_D_seed_ratio`` (window median seed D / fitted D) and ``relief_D_seed_disagree`` (1 where the seed lies
    outside the fit's interval, 0 where it agrees, NaN where not compared) and ``versus_seed`` in the summary.
    ``residual_stderr_rad`` (H, W, 3): the frames' noise propagated to the residual (:mod:`rig.estimate.folder_noise`;
    the fit's weights and intervals). Returns (summary, files, fit): ``fit`` the :class:`estimation.relief.ReliefFit` (None when the image is
    smaller than a window), for the per-region summaries (:mod:`rig.estimate.folder_regions`)."""
    from rig.files.imageio import write_exr, write_float_tiff

    H, W = maps.shape
    px = pixel_footprint_mm(camera)
    if window_px > min(H, W):
        window_px = min(H, W)
    if window_px < 16:
        return ({"estimator": "relief blur (estimation.relief)", "status": ["unknown"] * 3,
                 "reason": f"the image ({W} x {H} px) is smaller than the smallest relief window (16 px)"}, {}, None)
    reg = None if region is None else np.asarray(region, dtype=bool)
    # every input is read one band of window rows at a time (memory maps, derived maps, float32 normals): no
    # full-frame float64 copy; the region masks the true normals and the pixels inside the fit
    fit = fit_relief_windows(maps.diffuse_normals, true_normals, maps.albedo, px, float(maps.eta),
                             window_px=window_px, valid=_Known(maps.unknown), region=reg,
                             residual_stderr_rad=residual_stderr_rad)
    reg = summarize_relief(fit, region)
    files: dict[str, Path] = {}
    out = Path(out_dir)
    ext = ".exr" if fmt == "exr" else ".tif"
    writer = write_exr if fmt == "exr" else write_float_tiff
    for name in RELIEF_PARAMS:
        for which, suffix in (("value", ""), ("lo", "_lo"), ("hi", "_hi")):
            key = f"relief_{name}{suffix}"
            files[key] = writer(out / f"{key}{ext}", fit.pixel_map(name, (H, W), which))
    files["relief_status"] = writer(out / f"relief_status{ext}", fit.pixel_map("status", (H, W)))
    versus_seed = None
    if seed_D_mm is not None:
        cmp = compare_seed(seed_D_mm, fit)
        files["relief_D_seed_ratio"] = writer(out / f"relief_D_seed_ratio{ext}", fit.window_map(cmp.ratio, (H, W)))
        flag = np.where(cmp.compared, cmp.disagree.astype(np.float32), np.nan)
        files["relief_D_seed_disagree"] = writer(out / f"relief_D_seed_disagree{ext}", fit.window_map(flag, (H, W)))
        versus_seed = cmp.as_dict()
    counts = {s: [int((fit.status[..., c] == s).sum()) for c in range(3)] for s in ("ok", "weak", "unknown")}
    summary = {"estimator": "relief blur (estimation.relief; docs/gradients.md sec. 9)",
               "true_normals": source, "pixel_mm": px, "window_px": fit.window_px,
               "windows": [int(fit.origins_px.shape[0]), int(fit.origins_px.shape[1])], "window_status": counts,
               "relief_rms_rad_median": float(np.nanmedian(fit.relief_rms_rad))
               if np.isfinite(fit.relief_rms_rad).any() else None,
               "relief_noise_rad_median": float(np.nanmedian(fit.relief_noise_rad))
               if np.isfinite(fit.relief_noise_rad).any() else None,
               **reg.as_dict(), "fit": fit.provenance}
    if versus_seed is not None:
        summary["versus_seed"] = versus_seed
    return summary, files, fit


def dark_channels(images: Any, exposure_s: Any, region: NDArray[np.bool_], dark_level: float,
                  noise_sigmas: float = 1.0) -> tuple[list[bool], dict[str, Any]]:
    """Channels whose full-on signal over ``region`` is not above its noise: unknown as a whole (issue 16).

    The ambient-subtracted cross-polarized full-on signal (``full``, else ``a + a_c`` of an axis) is expressed in
    frame values at the full pattern's exposure; a channel is dark when its median over the region is below
    max(``dark_level``, ``noise_sigmas`` x its per-pixel noise) (default 1: the signal within its noise). The
    noise is the robust standard deviation of
    horizontal neighbour differences / sqrt 2 (a smooth signal contributes little). The per-pixel dark test of
    :func:`estimation.gradients.compute_maps` alone keeps the noise-high pixels of a dark channel and so reports
    an albedo biased high; this test removes the whole channel instead. Returns (dark per channel, details).
    """
    e = {k: float(v) for k, v in exposure_s.items()}
    amb = np.asarray(images[("ambient", "cross")], dtype=np.float64) / e[("ambient", "cross")]
    if ("full", "cross") in images:
        e_ref = e[("full", "cross")]
        sig = np.asarray(images[("full", "cross")], dtype=np.float64) / e_ref - amb
    else:
        a = next(a for a in ("x", "y", "z") if (a, "cross") in images and (a + "_c", "cross") in images)
        e_ref = e[(a, "cross")]
        sig = (np.asarray(images[(a, "cross")], dtype=np.float64) / e_ref
               + np.asarray(images[(a + "_c", "cross")], dtype=np.float64) / e[(a + "_c", "cross")] - 2 * amb)
    sig = sig * e_ref
    reg = np.asarray(region, dtype=bool)
    pair = reg[:, 1:] & reg[:, :-1]
    dark: list[bool] = []
    med_l: list[float | None] = []
    noise_l: list[float | None] = []
    for c in range(3):
        v = sig[..., c][reg]
        v = v[np.isfinite(v)]
        if v.size == 0:
            dark.append(False)
            med_l.append(None)
            noise_l.append(None)
            continue
        d = (sig[:, 1:, c] - sig[:, :-1, c])[pair]
        d = d[np.isfinite(d)]
        noise = float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0)) if d.size else 0.0
        med = float(np.median(v))
        dark.append(bool(med < max(dark_level, noise_sigmas * noise)))
        med_l.append(med)
        noise_l.append(noise)
    return dark, {"median_full_signal": med_l, "pixel_noise": noise_l, "dark_level": dark_level,
                  "noise_sigmas": noise_sigmas}


def mark_channels_unknown(maps: Any, channels: list[bool]) -> None:
    """Set the dark mask of whole channels and NaN their float maps (in place; RAM or memory-mapped maps)."""
    for c, d in enumerate(channels):
        if not d:
            continue
        maps.masks.dark[..., c] = True
        maps.albedo[..., c] = np.nan
        maps.diffuse_vectors[..., c, :] = np.nan
        if isinstance(maps.diffuse_normals, np.ndarray):      # else derived from diffuse_vectors on access
            maps.diffuse_normals[..., c, :] = np.nan


def albedo_apparent(maps: Any, normals: Any, eta: float, leds: Any, reference_normal: Any, rows: int = 256
                    ) -> NDArray[np.float32]:
    """The apparent diffuse albedo pi L / E (H, W, 3) beside the maps' R_d (issue 16; docs/gradients.md sec. 3).

    With Jensen's boundary terms the diffuse radiance is L = F_t(eta, n.v) R_d E_t / pi, so
    ``albedo_apparent = R_d * F_t(eta, n.v) * E_t/E``: what Ma et al. 2007 call the diffuse albedo and what a
    renderer takes as a diffuse texture (8-10 % below R_d at eta 1.3 viewed head-on). E_t/E is the full pattern's
    Fresnel-transmitted over plain irradiance at ``reference_normal`` (exact for ideal gradients; for LEDs exact
    at n_ref), n the given ``normals`` (H, W, 3) (sphere or relief geometry, else the specular normals), else each
    channel's diffuse normal; v the maps' view directions.
    """
    from estimation.fresnel import fresnel_transmittance
    from estimation.gradients.response import _full_transmitted_over_plain

    ratio = _full_transmitted_over_plain(eta, leds, reference_normal)
    H = maps.albedo.shape[0]
    out = np.empty(maps.albedo.shape, np.float32)
    for r0 in range(0, H, rows):        # row blocks: a 24 MP capture never holds a float64 copy of a full map
        r1 = min(H, r0 + rows)
        view = np.asarray(maps.view_dirs[r0:r1], dtype=np.float64)
        for c in range(3):
            n = np.asarray((normals[r0:r1] if normals is not None else maps.diffuse_normals[r0:r1, :, c, :]),
                           dtype=np.float64)
            cos = np.clip(np.sum(n * view, axis=-1), 0.0, 1.0)
            out[r0:r1, :, c] = np.asarray(maps.albedo[r0:r1, :, c], dtype=np.float64) * fresnel_transmittance(
                eta, cos) * ratio[c]
    return out


IDEAL_REFERENCE_FREQUENCY = 14
IDEAL_REFERENCE_DISTANCE_MM = 1.0e5


def ideal_reference_leds(frequency: int = IDEAL_REFERENCE_FREQUENCY, distance_mm: float = IDEAL_REFERENCE_DISTANCE_MM
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A dense synthetic LED set standing in for ideal continuous gradients in ``--reference`` renders: a full
    geodesic sphere (10 f^2 + 2 LEDs: 1962, ~4.6 deg apart for f = 14) at 100 m (no near field), equal
    intensities giving each LED the irradiance 4 pi / N (uniform radiance 1 over the sphere). The Monte Carlo
    renderer reads them as a distant map of 2-degree cells (:mod:`simulators.mc_capture`), i.e. a piecewise-constant
    approximation of the continuous gradients; the rendered frames are then reduced with the folder's ideal model."""
    from rig.acquire.geometry import led_layout

    pos, _ = led_layout(int(frequency), float(distance_mm), -90.0)
    inten = np.full((len(pos), 3), 4.0 * np.pi / len(pos) * float(distance_mm) ** 2)
    return pos, inten


# --------------------------------------------------------------------------------------------------------------
# the steps rig.estimate.capture_folder.estimate_capture calls
# --------------------------------------------------------------------------------------------------------------
def apply_dark_channels(cap: Any, maps: Any, obj: Any, exposure: Any, notes: list[str]) -> list[bool]:
    """:func:`dark_channels` over the object (else the non-background pixels) and :func:`mark_channels_unknown`;
    appends a note naming the channels. Returns the dark flags."""
    region = ~np.asarray(maps.masks.background) if obj is None else np.asarray(obj, dtype=bool)
    dark, info = dark_channels(cap.images, exposure, region, cap.radiometry.dark_level)
    if any(dark):
        mark_channels_unknown(maps, dark)
        notes.append("channel(s) " + ", ".join("RGB"[c] for c in range(3) if dark[c]) + " unknown: the median "
                     "full-on signal over the object is below max(dark_level, its pixel noise) "
                     f"({info['median_full_signal']} vs noise {info['pixel_noise']})")
    return dark


def relief_branch(cap: Any, maps: Any, obj: Any, out_dir: Path, fmt: str, window_px: int | None,
                  notes: list[str], seed_D_mm: Any = None, noise: Any = None
                  ) -> tuple[dict[str, Any], dict[str, Path], Any]:
    """The relief estimate with the folder's relief geometry, else the specular normals (shape unknown); with the
    seed's D map, the seed beside it (:func:`relief_estimate`); with the frames' ``noise``
    (:class:`estimation.gradients.uncertainty.MapNoise`), noise-weighted residuals and intervals."""
    if cap.relief is not None:
        try:
            rel = cap.relief.file.relative_to(cap.folder)
        except ValueError:
            rel = cap.relief.file
        tn, source = cap.relief.normals, f"{cap.relief.source} {rel}"
    else:
        tn, source = np.asarray(maps.specular_normals, dtype=np.float64), "specular normals (shape unknown)"
    se = None
    if noise is not None:
        from rig.estimate.folder_noise import relief_residual_stderr
        se = relief_residual_stderr(noise, true_from_specular=cap.relief is None)
    out = relief_estimate(maps, tn, source, cap.camera, obj, out_dir, fmt, window_px or RELIEF_WINDOW_PX,
                          seed_D_mm=seed_D_mm, residual_stderr_rad=se)
    notes.append("diffusion from the relief blur of the diffuse normals against the " + source
                 + " (docs/gradients.md sec. 9)")
    return out


def write_albedo_apparent(cap: Any, maps: Any, geo_normals: Any, leds: Any, n_ref: Any, out_dir: Path, fmt: str
                          ) -> tuple[NDArray[np.float32], Any]:
    """The apparent albedo (NaN where the maps are unknown) and a function writing it as ``albedo_apparent``."""
    from rig.files.imageio import write_exr, write_float_tiff

    n = geo_normals if geo_normals is not None else (
        cap.relief.normals if cap.relief is not None else maps.specular_normals)
    alb = albedo_apparent(maps, n, cap.radiometry.eta, leds, n_ref)
    alb[np.asarray(maps.unknown)] = np.nan
    path = out_dir / ("albedo_apparent" + (".exr" if fmt == "exr" else ".tif"))

    def write() -> Path:
        return (write_exr if fmt == "exr" else write_float_tiff)(path, alb)
    return alb, write


def sphere_seed_disagreement(seed_D_mm: Any, grounded: dict[str, Any], region: Any, *, albedo: Any = None,
                             shortening: Any = None, albedo_stderr: Any = None, shortening_stderr: Any = None,
                             confidence: float = 0.95
                             ) -> tuple[NDArray[np.float32], NDArray[np.float32], dict[str, Any]]:
    """The seed's per-pixel D against the grounded sphere summary's D interval (issue 16: "where the two disagree,
    a map of that"): ``ratio`` (H, W, 3) seed D / the summary's D, ``disagree`` (H, W, 3) 1 where the seed's
    interval lies wholly outside the summary's, 0 where they overlap, NaN where either is unknown (outside
    ``region``, an unknown channel). The seed's interval is its point without standard errors, else
    D_seed (1 +- z sqrt((sigma_A / A)^2 + (sigma_S / S)^2)): D_seed = k R_d / |n_z| and on a sphere n_z is the
    shortening S (the diffuse vector along the true normal over tau1/tau0), so the frames' noise reaches it through
    the albedo's and the shortening's standard errors (:mod:`rig.estimate.folder_noise`). Returns (ratio, disagree,
    per-channel fractions of compared pixels that disagree and the rule)."""
    from scipy import stats

    sd = np.asarray(seed_D_mm, dtype=np.float64)
    reg = np.asarray(region, dtype=bool)[..., None] if region is not None else np.ones(sd.shape[:2] + (1,), bool)
    d = grounded.get("D_mm", {})
    val = np.array([np.nan if v is None else float(v) for v in d.get("value", [None] * 3)])
    iv = np.array([[np.nan, np.nan] if p is None else [np.nan if x is None else float(x) for x in p]
                   for p in d.get("interval", [None] * 3)])
    rel = np.zeros_like(sd)
    if albedo_stderr is not None and shortening_stderr is not None:
        z = float(stats.norm.ppf(0.5 + confidence / 2))
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = z * np.sqrt((np.asarray(albedo_stderr, np.float64) / np.asarray(albedo, np.float64)) ** 2
                              + (np.asarray(shortening_stderr, np.float64) / np.asarray(shortening, np.float64)) ** 2)
        rel = np.where(np.isfinite(rel), rel, np.inf)
    lo, hi = sd * (1 - rel), sd * (1 + rel)
    known = reg & np.isfinite(sd) & np.isfinite(val)[None, None, :] & np.isfinite(iv).all(-1)[None, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(known, sd / val[None, None, :], np.nan)
        outside = (hi < iv[None, None, :, 0]) | (lo > iv[None, None, :, 1])
    dis = np.where(known, outside.astype(np.float64), np.nan)
    n = known.sum(axis=(0, 1))
    frac = [float(np.nansum(dis[..., c]) / n[c]) if n[c] else None for c in range(3)]
    return ratio.astype(np.float32), dis.astype(np.float32), {
        "fraction_outside_interval": frac, "pixels_compared": n.tolist(),
        "rule": "disagree: the seed's per-pixel D (with its noise interval when the frames' noise is stated) wholly "
                "outside the grounded sphere summary's D interval"}
