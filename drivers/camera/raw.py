"""Load a camera RAW/DNG file as linear float32 RGB for photometry (rawpy / LibRaw).

:func:`load_linear` uses the sensor values as recorded: ``raw_image_visible``, the per-channel black levels,
the white level and the CFA pattern. Each 2x2 CFA cell becomes one RGB pixel (R, mean of the two Gs, B), so
the result has half the sensor's resolution and no interpolated values. No demosaicing, no gamma, no white
balance, no auto-brightness, no clipping: values are ``(raw - black) / (white - black)`` per CFA position, so
the white level maps to 1.0 and read noise below black stays negative (unbiased when averaged).

Only 2x2 CFAs holding one R, two G and one B are supported (any arrangement: RGGB, BGGR, GRBG, GBRG);
X-Trans, CMYG, monochrome and linear-RGB DNGs raise :class:`RawFileError`.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import ProtocolError


class RawFileError(ProtocolError):
    """A RAW file could not be read or is not supported; the message names the file."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        super().__init__(f"{os.fspath(path)}: {reason}")
        self.path = os.fspath(path)
        self.reason = reason


def cfa_cell_indices(colors: npt.NDArray[Any], color_desc: str, path: str | os.PathLike[str] = "<raw>"
                     ) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int], tuple[int, int], str]:
    """Positions in the 2x2 CFA cell of R, G, G, B and the pattern name (e.g. ``"RGGB"``).

    ``colors`` is the per-pixel colour-index array (``raw_colors_visible``), ``color_desc`` maps an index to
    a letter (``"RGBG"``). Raises :class:`RawFileError` unless the CFA repeats every 2x2 with one R, two G
    and one B.
    """
    if colors.ndim != 2 or colors.shape[0] < 2 or colors.shape[1] < 2:
        raise RawFileError(path, f"unsupported sensor layout: colour index array of shape {colors.shape}")
    cell = np.asarray(colors[:2, :2])
    h2, w2 = colors.shape[0] // 2 * 2, colors.shape[1] // 2 * 2
    for i in range(2):
        for j in range(2):
            if not np.all(colors[i:h2:2, j:w2:2] == cell[i, j]):
                raise RawFileError(path, "unsupported CFA: it does not repeat every 2x2 pixels (X-Trans?)")
    try:
        letters = [[color_desc[int(cell[i, j])] for j in range(2)] for i in range(2)]
    except IndexError:
        raise RawFileError(path, f"CFA colour index outside colour description {color_desc!r}") from None
    name = "".join(letters[0] + letters[1])
    if sorted(name) != ["B", "G", "G", "R"]:
        raise RawFileError(path, f"unsupported CFA {name!r}: need one R, two G and one B per 2x2 cell")
    pos = {(i, j): letters[i][j] for i in range(2) for j in range(2)}
    r = next(p for p, c in pos.items() if c == "R")
    b = next(p for p, c in pos.items() if c == "B")
    g1, g2 = (p for p, c in sorted(pos.items()) if c == "G")
    return r, g1, g2, b, name


def superpixel_rgb(raw: npt.NDArray[Any], cell: tuple[tuple[int, int], ...],
                   black_2x2: npt.ArrayLike, white_2x2: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Bin a CFA mosaic into linear RGB at half resolution.

    ``cell`` = positions (R, G1, G2, B) in the 2x2 cell; ``black_2x2`` / ``white_2x2`` are the black and white
    levels at each cell position. An odd last row or column is dropped. Returns float32 (H//2, W//2, 3).
    """
    raw = np.asarray(raw)
    h2, w2 = raw.shape[0] // 2 * 2, raw.shape[1] // 2 * 2
    black = np.asarray(black_2x2, dtype=np.float64).reshape(2, 2)
    white = np.asarray(white_2x2, dtype=np.float64).reshape(2, 2)
    if np.any(white <= black):
        raise ValueError(f"white level {white.tolist()} must exceed black level {black.tolist()}")

    def plane(p: tuple[int, int]) -> npt.NDArray[np.float64]:
        i, j = p
        return (raw[i:h2:2, j:w2:2].astype(np.float64) - black[i, j]) / (white[i, j] - black[i, j])

    r, g1, g2, b = cell
    out = np.empty((h2 // 2, w2 // 2, 3), dtype=np.float32)
    out[..., 0] = plane(r)
    out[..., 1] = 0.5 * (plane(g1) + plane(g2))
    out[..., 2] = plane(b)
    return out


def _tiff_tags(path: Path) -> dict[str, Any]:
    """Make, Model and the exact ExposureTime of TIFF-based RAWs (DNG, most others); {} if not TIFF."""
    try:
        import tifffile

        with tifffile.TiffFile(path) as tf:
            tags = tf.pages[0].tags
            out: dict[str, Any] = {}
            for key in ("Make", "Model"):
                if key in tags:
                    out[key.lower()] = str(tags[key].value).strip("\x00 ")
            if "ExposureTime" in tags:
                num, den = tags["ExposureTime"].value
                if den:
                    out["exposure_s"] = num / den
            return out
    except Exception:  # noqa: BLE001 - metadata is best effort; the pixels came from rawpy
        return {}


def load_linear(path: str | os.PathLike[str]) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
    """Read ``path`` and return ``(rgb, metadata)``.

    ``rgb`` is float32 (H/2, W/2, 3) in sensor units scaled so the white level is 1.0 (see module docstring).
    ``metadata``: ``path``, ``raw_shape``, ``cfa_pattern`` (e.g. ``"RGGB"``), ``black_levels`` and
    ``white_levels`` (at the R, G1, G2, B positions), ``white_level``, ``color_desc``, ``camera_whitebalance``,
    ``exposure_s`` (None if unknown), ``make``, ``model``. Raises :class:`FileNotFoundError` for a missing
    file and :class:`RawFileError` (naming the file) for an unreadable or unsupported one.
    """
    import rawpy

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(2, "RAW file not found", os.fspath(p))
    try:
        with rawpy.imread(os.fspath(p)) as rp:
            raw = rp.raw_image_visible.copy()
            colors = rp.raw_colors_visible.copy()
            color_desc = rp.color_desc.decode("ascii", "replace")
            black_per_channel = list(rp.black_level_per_channel)
            white_level = int(rp.white_level)
            white_per_channel = rp.camera_white_level_per_channel
            wb = [float(x) for x in rp.camera_whitebalance]
            shutter = float(rp.other.shutter_speed) if hasattr(rp, "other") else 0.0
    except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
        raise RawFileError(p, f"cannot decode RAW file ({type(exc).__name__}: {exc})") from exc
    except (OSError, ValueError) as exc:
        raise RawFileError(p, f"cannot read RAW file ({exc})") from exc
    if raw.ndim != 2:
        raise RawFileError(p, f"not a single-plane CFA image (raw array shape {raw.shape})")
    r, g1, g2, b, name = cfa_cell_indices(colors, color_desc, p)
    black = np.empty((2, 2))
    white = np.full((2, 2), float(white_level))
    for i in range(2):
        for j in range(2):
            c = int(colors[i, j])
            black[i, j] = black_per_channel[c]
            if white_per_channel is not None and white_per_channel[c] > 0:
                white[i, j] = white_per_channel[c]
    if np.any(white <= black):
        raise RawFileError(p, f"white level {white.tolist()} not above black level {black.tolist()}")
    rgb = superpixel_rgb(raw, (r, g1, g2, b), black, white)
    tags = _tiff_tags(p)
    exposure = tags.get("exposure_s", shutter if shutter > 0 else None)
    meta: dict[str, Any] = {
        "path": os.fspath(p),
        "raw_shape": tuple(raw.shape),
        "cfa_pattern": name,
        "black_levels": tuple(float(black[q]) for q in (r, g1, g2, b)),
        "white_level": float(white_level),
        "white_levels": tuple(float(white[q]) for q in (r, g1, g2, b)),
        "color_desc": color_desc,
        "camera_whitebalance": wb,
        "exposure_s": exposure,
        "make": tags.get("make", ""),
        "model": tags.get("model", ""),
    }
    return rgb, meta
