"""A Monte Carlo reference renderer for :func:`estimation.model_correction.estimate_with_reference`.

It simulates the measurement: the Monte Carlo renderer (:func:`simulators.mc.render`) draws the object in its
known geometry, seen by the capture's camera under the capture's lights, and the image is sampled at the patch
centres exactly as the observations were (:func:`rig.estimate.sample_at_points`: a 3 x 3 window mean and its
standard error, NaN where a window pixel is off the object or outside ``valid_px``). Sampling effects (windows
that straddle an edge, pixel footprints) therefore enter the reference and the observations alike and cancel in
the correction kappa = reference / fast model.

The renders are not free: one per iteration, ``spp`` paths per pixel of the whole frame. :attr:`renders`
keeps the statistics of each (seconds, paths per second) for the reports.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimation.single_image import Patches

from .estimate import sample_at_points

__all__ = ["MonteCarloReference"]


@dataclass
class MonteCarloReference:
    """``reference(sigma_s', sigma_a, eta, seed) -> (radiance (K, C), stderr (K, C))`` over all patches.

    ``shape``: a :mod:`simulators.mc` shape (Box, Sphere, Slab, Mesh, ...) in the rig frame (mm); ``camera``:
    the capture's camera (PinholeCamera / OrthographicCamera); ``lights``: the capture's lights in the units of
    the observations (PointLights, EnvironmentMap, ...); ``patches``: the estimator's patches; ``valid_px``
    (H, W) bool, optional: pixels the observations were allowed to use (e.g. those a mesh face covers);
    ``g``: Henyey-Greenstein anisotropy of the reference medium (sigma_s' is held, sigma_s = sigma_s'/(1-g)).
    """

    shape: Any
    camera: Any
    lights: Any
    patches: Patches
    spp: int = 128
    window_px: int = 3
    valid_px: NDArray[np.bool_] | None = None
    g: float = 0.0
    renders: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.spp < 2:
            raise ValueError("spp must be >= 2 (the correction needs a standard error)")
        if self.valid_px is not None:
            want = (self.camera.height_px, self.camera.width_px)
            if np.shape(self.valid_px) != want:
                raise ValueError(f"valid_px has shape {np.shape(self.valid_px)}; expected the camera's {want}")

    def __call__(self, sigma_s_prime_per_mm: Any, sigma_a_per_mm: Any, eta: float, seed: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        from simulators.mc import Medium, render

        ssp = np.atleast_1d(np.asarray(sigma_s_prime_per_mm, dtype=np.float64))
        sa = np.atleast_1d(np.asarray(sigma_a_per_mm, dtype=np.float64))
        media = [Medium.from_reduced(float(s), float(a), g=self.g, eta=float(eta)) for s, a in zip(ssp, sa)]
        img = render(self.shape, media, self.camera, self.lights, spp=int(self.spp), seed=int(seed))
        valid = img.mask if self.valid_px is None else img.mask & np.asarray(self.valid_px, dtype=bool)
        valid = np.broadcast_to(valid[..., None], img.radiance.shape)
        obs, sig = sample_at_points(img.radiance, img.stderr ** 2, valid, self.camera, self.patches.centers_mm,
                                    self.window_px)
        paths = int(img.mask.sum()) * int(self.spp) * len(media)
        self.renders.append({"seed": int(seed), "seconds": img.seconds, "paths": paths,
                             "paths_per_s": paths / max(img.seconds, 1e-9),
                             "sigma_s_prime_per_mm": ssp.tolist(), "sigma_a_per_mm": sa.tolist()})
        return obs, sig
