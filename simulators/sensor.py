"""The simulated camera's sensor: an RGGB mosaic with Poisson photon noise and Gaussian read noise, 14-bit DN.

Kept apart from :mod:`simulators.camera` (the device that listens to the sphere and the trigger) so that renderers
of whole captures (:func:`simulators.scene.render_gradient_capture`, calibration targets) expose frames through the
same sensor without importing the camera device. Noise model: EMVA 1288's linear camera model (photon shot noise
in electrons, then read noise in DN).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["SensorModel", "signal_mosaic", "expose"]


@dataclass(frozen=True)
class SensorModel:
    gain_dn_per_unit: float      # DN per (radiance unit x second)
    black_level_dn: int
    white_level_dn: int
    read_noise_dn: float
    electrons_per_dn: float


def signal_mosaic(rgb: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(H, W, 3) -> (2H, 2W) RGGB mosaic (each RGB pixel becomes one 2x2 CFA cell)."""
    h, w, _ = rgb.shape
    m = np.empty((2 * h, 2 * w))
    m[0::2, 0::2] = rgb[..., 0]
    m[0::2, 1::2] = rgb[..., 1]
    m[1::2, 0::2] = rgb[..., 1]
    m[1::2, 1::2] = rgb[..., 2]
    return m


def expose(radiance: npt.NDArray[np.float64], exposure_s: float, sensor: SensorModel,
           rng: np.random.Generator) -> npt.NDArray[np.uint16]:
    """Radiance image (H, W, 3) -> noisy raw mosaic (2H, 2W) in DN, clipped at the white level."""
    signal_dn = signal_mosaic(radiance) * sensor.gain_dn_per_unit * exposure_s
    electrons = rng.poisson(np.maximum(signal_dn, 0.0) * sensor.electrons_per_dn)
    dn = electrons / sensor.electrons_per_dn + rng.normal(0.0, sensor.read_noise_dn, signal_dn.shape)
    dn = np.round(dn + sensor.black_level_dn)
    return np.clip(dn, 0, sensor.white_level_dn).astype(np.uint16)
