"""Linear image files in and out: OpenEXR, float TIFF, camera RAW/DNG and 16-bit PNG.

One reader for every image a user brings (scene files, capture folders) and one writer per format for the
maps we produce. Everything is **linear**: no format here is gamma-decoded or tone-mapped, so

- EXR (half or float) and float32/float64 TIFF are taken as they are;
- integer TIFF and 16-bit PNG are divided by their full scale (65535 for 16 bit, 255 for 8-bit TIFF) and are
  assumed to hold *linear* values (as written by RAW converters with a linear profile); an 8-bit PNG is
  refused because it is almost always sRGB-encoded display output;
- RAW/DNG go through :func:`drivers.camera.raw.load_linear` (black/white level, 2x2 superpixel, half size).

Arrays are ``(H, W)`` or ``(H, W, C)`` float32, channels in **RGB** order (OpenCV's BGR is swapped on the
way in and out). Row 0 is the top of the image, column 0 the left (the pixel convention of
:class:`estimation.camera.PinholeCamera`).

Writers are atomic (temporary file in the same folder, fsync, rename), so a crash never leaves half a map.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.atomic import atomic_write
from drivers.errors import RigError

__all__ = ["ImageFileError", "IMAGE_SUFFIXES", "RAW_SUFFIXES", "read_image", "write_exr", "write_float_tiff",
           "write_png16", "write_png8", "atomic_write"]

RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw")
IMAGE_SUFFIXES = (".exr", ".tif", ".tiff", ".png") + RAW_SUFFIXES


class ImageFileError(RigError, ValueError):
    """An image file could not be read or written; the message names the file and what was expected."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        super().__init__(f"{os.fspath(path)}: {reason}")
        self.path = os.fspath(path)
        self.reason = reason


def _check_array(path: Path, a: NDArray[Any]) -> NDArray[np.float32]:
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)) or min(a.shape[:2]) < 1:
        raise ImageFileError(path, f"expected an image of shape (H, W), (H, W, 3) or (H, W, 4); got {a.shape}")
    if a.ndim == 3 and a.shape[2] == 4:
        a = a[..., :3]  # alpha is not radiance
    return np.ascontiguousarray(a, dtype=np.float32)


def _read_exr(path: Path) -> tuple[NDArray[np.float32], dict[str, Any]]:
    try:
        import OpenEXR
    except ImportError as exc:  # pragma: no cover - a dependency
        raise ImageFileError(path, "reading EXR needs the 'openexr' package") from exc
    try:
        with OpenEXR.File(str(path)) as f:
            ch = f.channels()
            if "RGB" in ch:
                a = np.asarray(ch["RGB"].pixels)
            elif "RGBA" in ch:
                a = np.asarray(ch["RGBA"].pixels)[..., :3]
            elif all(k in ch for k in "RGB"):
                a = np.stack([np.asarray(ch[k].pixels) for k in "RGB"], axis=-1)
            elif "Y" in ch:
                a = np.asarray(ch["Y"].pixels)
            elif len(ch) == 1:
                a = np.asarray(next(iter(ch.values())).pixels)
            else:
                raise ImageFileError(path, f"expected channels R,G,B (or RGB, or Y); found {sorted(ch)}")
    except ImageFileError:
        raise
    except Exception as exc:  # OpenEXR raises plain exceptions on bad files
        raise ImageFileError(path, f"not a readable OpenEXR file ({exc})") from None
    return _check_array(path, a), {"format": "exr", "source_dtype": str(a.dtype)}


def _read_tiff(path: Path) -> tuple[NDArray[np.float32], dict[str, Any]]:
    import tifffile
    try:
        a = tifffile.imread(str(path))
    except Exception as exc:
        raise ImageFileError(path, f"not a readable TIFF file ({exc})") from None
    dtype = a.dtype
    if np.issubdtype(dtype, np.floating):
        out = a
    elif dtype == np.uint16:
        out = a.astype(np.float32) / 65535.0
    elif dtype == np.uint8:
        out = a.astype(np.float32) / 255.0
    else:
        raise ImageFileError(path, f"unsupported TIFF sample type {dtype}; expected float16/32/64, uint16 or uint8")
    return _check_array(path, out), {"format": "tiff", "source_dtype": str(dtype)}


def _read_png(path: Path) -> tuple[NDArray[np.float32], dict[str, Any]]:
    import cv2
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if a is None:
        raise ImageFileError(path, "not a readable PNG file")
    if a.dtype != np.uint16:
        raise ImageFileError(path, f"PNG with {a.dtype} samples: expected a 16-bit linear PNG (8-bit PNGs are "
                                   "display-encoded; export 16-bit linear, EXR or float TIFF)")
    if a.ndim == 3:
        a = a[..., [2, 1, 0] + ([3] if a.shape[2] == 4 else [])]
    return _check_array(path, a.astype(np.float32) / 65535.0), {"format": "png16", "source_dtype": "uint16"}


def _read_raw(path: Path) -> tuple[NDArray[np.float32], dict[str, Any]]:
    from drivers.camera.raw import RawFileError, load_linear
    try:
        a, meta = load_linear(path)
    except RawFileError as exc:
        raise ImageFileError(path, exc.reason) from None
    return _check_array(path, a), {"format": "raw", **meta}


def read_image(path: str | os.PathLike[str], *, allow_nonfinite: bool = False
               ) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Read a linear image: ``(array float32 (H, W[, 3]) RGB, metadata)``; the format comes from the suffix.

    Raises :class:`ImageFileError` naming the file for a missing file, an unknown suffix, an unreadable or
    non-linear (8-bit PNG) file, a wrong shape or (unless ``allow_nonfinite``: then ``metadata["nonfinite"]``
    counts them and the caller excludes them) NaN/inf samples.
    """
    img, meta = _read_any(path)
    bad = int(np.count_nonzero(~np.isfinite(img)))
    if bad and not allow_nonfinite:
        raise ImageFileError(path, f"{bad} pixel values are NaN or infinite; expected finite linear radiance")
    return img, {**meta, "nonfinite": bad}


def _read_any(path: str | os.PathLike[str]) -> tuple[NDArray[np.float32], dict[str, Any]]:
    p = Path(path)
    if not p.is_file():
        raise ImageFileError(p, "no such file")
    suffix = p.suffix.lower()
    readers: dict[str, Callable[[Path], tuple[NDArray[np.float32], dict[str, Any]]]] = {
        ".exr": _read_exr, ".tif": _read_tiff, ".tiff": _read_tiff, ".png": _read_png}
    if suffix in readers:
        return readers[suffix](p)
    if suffix in RAW_SUFFIXES:
        return _read_raw(p)
    raise ImageFileError(p, f"unknown image suffix {suffix!r}; expected one of {', '.join(IMAGE_SUFFIXES)}")


# ---------------------------------------------------------------------------------------------- writers
def _as_image(a: ArrayLike, name: str) -> NDArray[np.float32]:
    arr = np.asarray(a, dtype=np.float32)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
        raise ValueError(f"{name}: expected an image of shape (H, W), (H, W, 3) or (H, W, 4); got {arr.shape}")
    return np.ascontiguousarray(arr)


def write_exr(path: str | os.PathLike[str], image: ArrayLike, *, attributes: dict[str, str] | None = None,
              half: bool = False) -> Path:
    """Write a float image as OpenEXR (ZIP compression; float32, or half with ``half=True``); NaN is kept
    (EXR stores it), which is how maps mark "unknown". ``attributes`` become string header attributes."""
    import OpenEXR
    arr = _as_image(image, os.fspath(path))
    if half:
        arr = arr.astype(np.float16)
    key = "Y" if arr.ndim == 2 else ("RGB" if arr.shape[2] == 3 else "RGBA")
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        header[k] = str(v)

    def write(tmp: Path) -> None:
        with OpenEXR.File(header, {key: arr}) as f:
            f.write(str(tmp))
    return atomic_write(path, write)


def write_float_tiff(path: str | os.PathLike[str], image: ArrayLike, *, description: str | None = None) -> Path:
    """Write a float32 TIFF (zlib-compressed, RGB photometric for 3 channels, minisblack for 1)."""
    import tifffile
    arr = _as_image(image, os.fspath(path))
    photometric = "minisblack" if arr.ndim == 2 else "rgb"

    def write(tmp: Path) -> None:
        tifffile.imwrite(str(tmp), arr, photometric=photometric, compression="zlib",
                         description=description, metadata=None)
    return atomic_write(path, write)


def _write_png(path: str | os.PathLike[str], arr: NDArray[Any]) -> Path:
    import cv2
    if arr.ndim == 3:
        arr = arr[..., [2, 1, 0] + ([3] if arr.shape[2] == 4 else [])]

    def write(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(arr)):
            raise ImageFileError(path, "OpenCV could not write the PNG")
    return atomic_write(path, write)


def write_png16(path: str | os.PathLike[str], image: ArrayLike) -> Path:
    """Write linear values in [0, 1] as a 16-bit PNG (clipped, rounded; NaN written as 0)."""
    arr = _as_image(image, os.fspath(path))
    q = np.round(np.clip(np.nan_to_num(arr, nan=0.0), 0.0, 1.0) * 65535.0).astype(np.uint16)
    return _write_png(path, q)


def write_png8(path: str | os.PathLike[str], image: ArrayLike) -> Path:
    """Write display values in [0, 1] as an 8-bit PNG (for previews only; no transfer curve is applied)."""
    arr = _as_image(image, os.fspath(path))
    q = np.round(np.clip(np.nan_to_num(arr, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    return _write_png(path, q)
