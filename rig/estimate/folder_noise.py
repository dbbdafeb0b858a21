"""The frames' noise of a capture folder through the gradient maps into the diffusion intervals (issue 16, item 2).

With ``[noise]`` (shot + read noise) or a ``stderr_file`` on every frame (``docs/capture-folder.md``), the
per-frame standard errors are propagated to first order through the per-pixel formulas of
:func:`estimation.gradients.compute_maps` (:func:`estimation.gradients.uncertainty.propagate_frame_noise`, bands of
rows) and used by the diffusion estimators:

- the relief fit (:func:`estimation.relief.fit_relief_windows`) weights each pixel's residual by
  1 / (sigma_diffuse^2 + sigma_true^2) (sigma_true: the specular normals' standard error when they stand in for
  the true normals, 0 for a given normals / height file) and sizes its profile interval from that noise (or the
  residual where larger);
- the sphere summary (:func:`estimation.diffusion.summarize`) makes the observables' intervals at least the
  median's standard error under the stated noise.

Written maps: ``albedo_stderr``, ``diffuse_normals_stderr_rad`` (R, G, B: per tangential component),
``specular_normals_stderr_rad`` (with parallel frames) and ``shortening_stderr`` (with a sphere).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["propagate_capture_noise", "noise_summary", "write_noise_maps", "relief_residual_stderr",
           "reference_scale_rel_stderr"]


def reference_scale_rel_stderr(cap: Any) -> NDArray[np.float64] | None:
    """Relative standard error (3,) of the albedo scale measured on ``[radiometry.reference]`` (None without a
    reference target): the median over the region of the ambient-subtracted full-on signal per second has the
    standard error sqrt(pi/2) sqrt(mean var / n), var = (sigma_full / e_full)^2 + (sigma_ambient / e_ambient)^2
    (or the gradient + complement pair's), and the scale is its inverse. Shared by every pixel of the albedo map,
    it is not reduced by pooling pixels (:func:`estimation.diffusion.summarize`, ``albedo_rel_common``)."""
    ref = cap.radiometry.reference
    if ref is None or cap.noise is None:
        return None
    x0, y0, x1, y1 = ref.region_px
    exp = {f.key: f.exposure_s for f in cap.frames}
    keys = [("full", "cross")] if ("full", "cross") in cap.images else next(
        [(a, "cross"), (a + "_c", "cross")] for a in "xyz" if (a, "cross") in cap.images
        and (a + "_c", "cross") in cap.images)
    se = cap.noise.stderr_images({k: cap.images[k] for k in keys + [("ambient", "cross")]})
    sig = sum(cap.images[k][y0:y1, x0:x1].astype(np.float64) / exp[k] for k in keys) \
        - len(keys) * cap.images[("ambient", "cross")][y0:y1, x0:x1].astype(np.float64) / exp[("ambient", "cross")]
    var = sum((se[k][y0:y1, x0:x1].astype(np.float64) / exp[k]) ** 2 for k in keys) \
        + len(keys) ** 2 * (se[("ambient", "cross")][y0:y1, x0:x1].astype(np.float64) / exp[("ambient", "cross")]) ** 2
    n = sig.shape[0] * sig.shape[1]
    med = np.median(sig.reshape(-1, 3), axis=0)
    return np.sqrt(np.pi / 2 * var.reshape(-1, 3).mean(axis=0) / n) / med


def propagate_capture_noise(cap: Any, maps: Any, dark: list[bool], *, folder_maps_kwargs: dict[str, Any],
                            view: Any, obj: Any, geo_normals: Any, true_normals: Any,
                            rows_per_band: int = 256) -> Any:
    """:class:`estimation.gradients.uncertainty.MapNoise` of the capture ``cap`` (its ``noise`` spec) for the maps
    computed with ``folder_maps_kwargs`` (the capture's :func:`compute_maps` arguments except the per-pixel ones:
    ``view``, ``obj``, ``geo_normals`` are sliced per band); channels in ``dark`` stay NaN."""
    from estimation.gradients import compute_maps, tau_ratio
    from estimation.gradients.uncertainty import propagate_frame_noise

    H, W = cap.shape
    view_a = np.asarray(view)
    per_pixel_view = view_a.shape == (H, W, 3)

    def band_maps(fb: dict[Any, NDArray[np.float32]], rows: slice) -> Any:
        return compute_maps(fb, view_dirs=view_a[rows] if per_pixel_view else view_a, tile_rows=rows_per_band,
                            object_mask=None if obj is None else np.asarray(obj)[rows],
                            geometry_normals=None if geo_normals is None else np.asarray(geo_normals)[rows],
                            out_dir=None, **folder_maps_kwargs)

    stderr = cap.noise.stderr_images(cap.images)
    tn = None
    if true_normals is not None:
        tn = np.asarray(true_normals)
    noise = propagate_frame_noise(band_maps, cap.images, stderr, true_normals=tn,
                                  tau_ratio=tau_ratio(float(cap.radiometry.eta)) if tn is not None else None,
                                  rows_per_band=rows_per_band)
    unknown = np.asarray(maps.unknown)
    for a in (noise.albedo, noise.diffuse_normal_rad, noise.shortening):
        if a is not None:
            a[unknown] = np.nan
    for c, d in enumerate(dark):
        if d:
            noise.albedo[..., c] = np.nan
            noise.diffuse_normal_rad[..., c] = np.nan
    noise.provenance["source"] = cap.noise.provenance(cap.folder)
    return noise


def relief_residual_stderr(noise: Any, true_from_specular: bool) -> NDArray[np.float32]:
    """(H, W, 3) sqrt(sigma_diffuse^2 + sigma_true^2) per tangential component (radians) for the relief fit."""
    s = np.asarray(noise.diffuse_normal_rad, dtype=np.float32)
    if true_from_specular and noise.specular_normal_rad is not None:
        t = np.asarray(noise.specular_normal_rad, dtype=np.float32)[..., None]
        s = np.sqrt(s * s + t * t)
    return s


def noise_summary(cap: Any, noise: Any, known: Any) -> dict[str, Any]:
    """The summary's ``noise`` entry: the source and per-channel medians over the known pixels."""
    reg = np.asarray(known).any(axis=-1)
    return {"source": cap.noise.provenance(cap.folder), **noise.summary(reg),
            "method": noise.provenance["method"], "map_calls": noise.provenance["map_calls"],
            "used_by": "relief fit residual weights and intervals; sphere summary intervals (docs/gradients.md "
                       "sec. 9, 'Noise')"}


def write_noise_maps(noise: Any, out_dir: Path, fmt: str) -> dict[str, Path]:
    """Write the standard-error maps (EXR or float TIFF) and return their paths by name."""
    from rig.files.imageio import write_exr, write_float_tiff

    writer = write_exr if fmt == "exr" else write_float_tiff
    ext = ".exr" if fmt == "exr" else ".tif"
    out: dict[str, Path] = {}
    items = {"albedo_stderr": noise.albedo, "diffuse_normals_stderr_rad": noise.diffuse_normal_rad,
             "specular_normals_stderr_rad": noise.specular_normal_rad, "shortening_stderr": noise.shortening}
    for name, a in items.items():
        if a is not None:           # every float map has 3 channels (docs/capture-folder.md sec. 5)
            a = np.asarray(a, dtype=np.float32)
            out[name] = writer(out_dir / f"{name}{ext}", np.repeat(a[..., None], 3, axis=-1) if a.ndim == 2 else a)
    return out
