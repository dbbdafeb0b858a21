"""Write simulated camera frames as DNG files that rawpy/LibRaw decodes bit-exactly.

:func:`write_dng` turns a linear RGB rendering (H, W, 3) into an RGGB Bayer mosaic of (2H, 2W) sensor values
- every rendered pixel becomes one 2x2 CFA cell, so ``drivers.camera.raw.load_linear`` (2x2 superpixel
binning) returns the rendering back up to quantization - and writes an uncompressed 16-bit CFA DNG with
tifffile. Noise is the caller's business (add it to ``rgb_linear`` before, seeded). The file appears
atomically (temporary file, fsync, rename), so a folder watcher never sees half a frame.
"""
from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path
from typing import Sequence

import numpy as np
import numpy.typing as npt

from drivers.atomic import atomic_write

# XYZ (D65) -> linear sRGB: the simulated sensor's native RGB is linear sRGB.
XYZ_TO_SRGB = ((3.2404542, -1.5371385, -0.4985314),
               (-0.9692660, 1.8760108, 0.0415560),
               (0.0556434, -0.2040259, 1.0572252))
MIN_CELLS = 11        # LibRaw refuses images narrower or lower than 22 sensor pixels

# TIFF / EXIF / DNG tag numbers
TAG_MAKE, TAG_MODEL = 271, 272
TAG_CFA_REPEAT_PATTERN_DIM, TAG_CFA_PATTERN, TAG_EXPOSURE_TIME = 33421, 33422, 33434
TAG_DNG_VERSION, TAG_DNG_BACKWARD_VERSION, TAG_UNIQUE_CAMERA_MODEL = 50706, 50707, 50708
TAG_BLACK_LEVEL_REPEAT_DIM, TAG_BLACK_LEVEL, TAG_WHITE_LEVEL = 50713, 50714, 50717
TAG_COLOR_MATRIX_1, TAG_AS_SHOT_NEUTRAL, TAG_CALIBRATION_ILLUMINANT_1 = 50721, 50728, 50778
CFA_RGGB = (0, 1, 1, 2)          # TIFF/EP colour codes: 0 red, 1 green, 2 blue, row by row
D65 = 21


def _black_2x2(black_level: int | Sequence[int]) -> npt.NDArray[np.int64]:
    arr = np.asarray(black_level, dtype=np.int64)
    if arr.ndim == 0:
        return np.full((2, 2), int(arr))
    if arr.shape == (4,):
        return arr.reshape(2, 2)
    raise ValueError(f"black_level must be an int or 4 ints (R, Gr, Gb, B), got shape {arr.shape}")


def mosaic_rggb(rgb_linear: npt.ArrayLike, *, black_level: int | Sequence[int] = 512,
                white_level: int = 16383) -> npt.NDArray[np.uint16]:
    """Sensor values of an RGGB mosaic (2H, 2W) for a linear rendering (H, W, 3).

    Each pixel becomes a cell ``[[R, G], [G, B]]`` with ``DN = round(black + value * (white - black))``
    clipped to ``[0, white]``: values above 1 saturate at the white level; slightly negative values (read
    noise below black) are kept down to DN 0. ``black_level`` is one int or four (R, Gr, Gb, B).
    """
    rgb = np.asarray(rgb_linear, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb_linear must have shape (H, W, 3), got {rgb.shape}")
    if not np.all(np.isfinite(rgb)):
        raise ValueError("rgb_linear holds NaN or infinite values")
    black = _black_2x2(black_level)
    if np.any(black < 0) or np.any(black >= white_level):
        raise ValueError(f"black level {black.ravel().tolist()} must be in [0, white_level={white_level})")
    h, w, _ = rgb.shape
    mosaic = np.empty((2 * h, 2 * w), dtype=np.uint16)
    channel = ((0, 1), (1, 2))          # RGGB: colour channel at each cell position
    for i in range(2):
        for j in range(2):
            b = float(black[i, j])
            dn = np.rint(b + rgb[..., channel[i][j]] * (white_level - b))
            mosaic[i::2, j::2] = np.clip(dn, 0, white_level).astype(np.uint16)
    return mosaic


def _rational(x: float, what: str) -> tuple[int, int]:
    frac = Fraction(x).limit_denominator(1_000_000)
    if frac.numerator < 0 or frac.numerator > 0xFFFF_FFFF or frac.denominator > 0xFFFF_FFFF:
        raise ValueError(f"{what} {x!r} does not fit an unsigned rational")
    return frac.numerator, frac.denominator


def _srational(x: float) -> tuple[int, int]:
    return round(x * 10000), 10000


def write_dng(path: str | os.PathLike[str], rgb_linear: npt.ArrayLike, *, exposure_s: float,
              black_level: int | Sequence[int] = 512, white_level: int | None = None, bits: int = 14,
              make: str = "sssrig", model: str = "SimCam",
              as_shot_neutral: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> npt.NDArray[np.uint16]:
    """Write ``rgb_linear`` (H, W, 3, linear, white = 1.0) as an RGGB CFA DNG at ``path``; return the mosaic.

    ``bits`` is the sensor's bit depth (samples are stored in 16 bits); ``white_level`` defaults to
    ``2**bits - 1``; ``black_level`` is one int or four (R, Gr, Gb, B, written with BlackLevelRepeatDim 2x2).
    H and W must be at least 11 (LibRaw refuses images under 22 sensor pixels). ColorMatrix1 is
    XYZ -> linear sRGB (the simulated sensor is linear sRGB), AsShotNeutral defaults to (1, 1, 1).
    The file is written to a hidden temporary file in the same folder, fsynced and renamed into place.
    """
    if not 8 <= bits <= 16:
        raise ValueError(f"bits must be 8..16, got {bits}")
    if white_level is None:
        white_level = (1 << bits) - 1
    if not 0 < white_level < (1 << bits):
        raise ValueError(f"white_level must be in (0, {1 << bits}) for {bits}-bit samples, got {white_level}")
    if not (np.isfinite(exposure_s) and exposure_s > 0):
        raise ValueError(f"exposure_s must be a positive number, got {exposure_s!r}")
    rgb = np.asarray(rgb_linear)
    if rgb.ndim == 3 and (rgb.shape[0] < MIN_CELLS or rgb.shape[1] < MIN_CELLS):
        raise ValueError(f"rgb_linear of shape {rgb.shape} is too small: LibRaw needs at least "
                         f"{2 * MIN_CELLS} sensor pixels, i.e. H, W >= {MIN_CELLS}")
    mosaic = mosaic_rggb(rgb, black_level=black_level, white_level=white_level)
    write_cfa_dng(path, mosaic, exposure_s=exposure_s, black_level=black_level, white_level=white_level,
                  make=make, model=model, as_shot_neutral=as_shot_neutral)
    return mosaic


def write_cfa_dng(path: str | os.PathLike[str], mosaic: npt.ArrayLike, *, exposure_s: float,
                  black_level: int | Sequence[int], white_level: int, make: str = "sssrig",
                  model: str = "SimCam", as_shot_neutral: tuple[float, float, float] = (1.0, 1.0, 1.0)
                  ) -> None:
    """Write an RGGB sensor mosaic (2H, 2W) of uint16 DN values as a CFA DNG, atomically.

    Used directly by the simulated camera, which adds photon and read noise per photosite.
    """
    import tifffile

    mosaic = np.asarray(mosaic)
    if mosaic.ndim != 2 or mosaic.dtype != np.uint16 or mosaic.shape[0] % 2 or mosaic.shape[1] % 2:
        raise ValueError(f"mosaic: expected a 2-D uint16 array of even shape, got {mosaic.dtype} "
                         f"{mosaic.shape}")
    if min(mosaic.shape) < 2 * MIN_CELLS:
        raise ValueError(f"mosaic of shape {mosaic.shape} is too small: LibRaw needs >= {2 * MIN_CELLS} px")
    black = _black_2x2(black_level)

    tags: list[tuple[int, str, int, object, bool]] = [
        (TAG_MAKE, "s", 0, make, True),
        (TAG_MODEL, "s", 0, model, True),
        (TAG_CFA_REPEAT_PATTERN_DIM, "H", 2, (2, 2), True),
        (TAG_CFA_PATTERN, "B", 4, CFA_RGGB, True),
        (TAG_EXPOSURE_TIME, "2I", 1, _rational(float(exposure_s), "exposure_s"), True),
        (TAG_DNG_VERSION, "B", 4, (1, 4, 0, 0), True),
        (TAG_DNG_BACKWARD_VERSION, "B", 4, (1, 1, 0, 0), True),
        (TAG_UNIQUE_CAMERA_MODEL, "s", 0, f"{make} {model}", True),
    ]
    if np.all(black == black[0, 0]):
        tags.append((TAG_BLACK_LEVEL, "H", 1, int(black[0, 0]), True))
    else:
        tags.append((TAG_BLACK_LEVEL_REPEAT_DIM, "H", 2, (2, 2), True))
        tags.append((TAG_BLACK_LEVEL, "H", 4, tuple(int(b) for b in black.ravel()), True))
    cm = tuple(v for row in XYZ_TO_SRGB for x in row for v in _srational(x))
    neutral = tuple(v for x in as_shot_neutral for v in _rational(float(x), "as_shot_neutral"))
    tags += [
        (TAG_WHITE_LEVEL, "H", 1, int(white_level), True),
        (TAG_COLOR_MATRIX_1, "2i", 9, cm, True),
        (TAG_CALIBRATION_ILLUMINANT_1, "H", 1, D65, True),
        (TAG_AS_SHOT_NEUTRAL, "2I", 3, neutral, True),
    ]

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            tifffile.imwrite(fh, mosaic, photometric="cfa", subfiletype=0, metadata=None, software="sssrig",
                             extratags=tags)

    atomic_write(path, write)
    return mosaic
