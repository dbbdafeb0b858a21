"""Capture folders a user brings from elsewhere -> gradient maps and diffusion (``rig estimate gradients FOLDER``).

A capture folder holds the frames (EXR, float TIFF, 16-bit PNG or camera RAW/DNG) and ``capture.toml`` naming each
frame's pattern, polarization and exposure, the LED calibration (or an ideal-gradient flag), the camera
(orthographic or pinhole), the radiometric scale and optionally an object mask, the object's geometry (a sphere,
for the grounded diffusion estimator) and a seed calibration. The format is documented key by key in
``docs/capture-folder.md``; this module validates it (:func:`load_capture`: every error names the file, the key
and what was expected, as ``rig.config`` does), runs :func:`estimation.gradients.compute_maps` and the diffusion
estimators (:func:`estimate_capture`) and writes the maps with :func:`rig.files.maps_io.write_maps`.

The session path (``rig.estimate.sessions.run_gradients``) and this one call the same estimators with the same conventions:
frames ambient-subtracted and divided by their exposure, ``albedo_scale`` from radiometry
(:func:`estimation.gradients.albedo_scale_from_radiometry`) or from a Lambertian reference
(:func:`estimation.gradients.albedo_scale_from_lambertian`), the LED near field modelled at the sphere, the
grounded sphere estimator (:func:`estimation.diffusion.estimate_sphere`).

References: Ma et al. 2007 (polarized spherical gradients); Zhu, Peers, Debevec, Ghosh, "Estimating diffusion
parameters from polarized spherical gradient illumination" (the seed); Jensen et al. 2001 (dipole);
``docs/gradients.md``; ``shared/reference/science.md`` sec. 3-4, 6.
"""
from __future__ import annotations

from estimation.camera import OrthographicCamera

from .estimate import estimate_capture
from .reading import load_capture
from .report import format_summary, run_cli
from .spec import (CAPTURE_FILE, CAPTURE_FORMAT, CAPTURE_FORMAT_VERSION, Capture, CaptureError, FrameEntry,
                   LedCalibration, Radiometry, ReferenceTarget, SeedSpec, SphereGeometry, missing_frames)


__all__ = [
    "CAPTURE_FILE",
    "CAPTURE_FORMAT",
    "CAPTURE_FORMAT_VERSION",
    "CaptureError",
    "FrameEntry",
    "LedCalibration",
    "OrthographicCamera",
    "ReferenceTarget",
    "Radiometry",
    "SphereGeometry",
    "SeedSpec",
    "Capture",
    "load_capture",
    "missing_frames",
    "estimate_capture",
    "run_cli",
    "format_summary"
]
