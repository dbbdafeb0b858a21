"""Reading a capture folder (:func:`load_capture`): frames, LED table, camera, radiometry, mask, object and seed
sections of ``capture.toml``, each checked with an error that names the file and field (docs/capture-folder.md).
"""
from __future__ import annotations

import csv
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError
from estimation.camera import OrthographicCamera, PinholeCamera, look_at_rotation
from estimation.gradients import PATTERNS, POLARIZATIONS
from rig.files.imageio import ImageFileError, read_image
from rig.files.provenance import sha256_file

from .spec import (_AXES, _REQ, CAPTURE_FILE, CAPTURE_FORMAT, CAPTURE_FORMAT_VERSION, LED_COLUMNS, Capture, FrameEntry,
                   FrameKey, LedCalibration, Radiometry, ReferenceTarget, SeedSpec, SphereGeometry, _rel,
                   _specular_possible, _Table, missing_frames)


# ------------------------------------------------------------------------------------------------ sections
def _read_frames(file: str, folder: Path, data: dict[str, Any], stderr_out: dict[FrameKey, Any] | None = None
                 ) -> tuple[tuple[FrameEntry, ...], dict[FrameKey, NDArray[np.float32]]]:
    raw = data.get("frames")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(file, "frames", "an array of tables [[frames]] (one per frame file)",
                          None if raw is None else type(raw).__name__)
    entries: list[FrameEntry] = []
    images: dict[FrameKey, NDArray[np.float32]] = {}
    seen: dict[FrameKey, int] = {}
    for i, item in enumerate(raw):
        if not isinstance(item, dict):
            raise ConfigError(file, f"frames[{i}]", "a table with file, pattern, polarization, exposure_s",
                              type(item).__name__)
        t = _Table(file, item, f"frames[{i}].", ("file", "pattern", "polarization", "exposure_s", "stderr_file"))
        pattern = t.str("pattern", choices=PATTERNS)
        pol = t.str("polarization", choices=POLARIZATIONS)
        exposure = t.num("exposure_s", positive=True)
        key = (pattern, pol)
        if key in seen:
            raise ConfigError(file, f"frames[{i}]", f"a unique (pattern, polarization); frames[{seen[key]}] "
                              f"already is ({pattern}, {pol})", f"({pattern}, {pol})")
        seen[key] = i
        path = t.path("file", folder, "image")
        try:
            img, meta = read_image(path)
        except ImageFileError as exc:
            raise ConfigError(file, f"frames[{i}].file", f"a readable linear image ({exc.reason})",
                              _rel(path, folder)) from None
        recorded = meta.get("exposure_s")
        if isinstance(recorded, (int, float)) and recorded > 0 and abs(recorded / exposure - 1) > 0.02:
            raise ConfigError(file, f"frames[{i}].exposure_s", f"the exposure recorded in {path.name} "
                              f"({recorded:.6g} s) within 2 %", exposure)
        if img.ndim == 2:  # monochrome camera: the same value in R, G, B
            img = np.repeat(img[..., None], 3, axis=-1)
        shape = (int(img.shape[0]), int(img.shape[1]))
        if entries and shape != entries[0].shape:
            f0 = entries[0]
            raise ConfigError(file, f"frames[{i}].file", f"an image of {f0.shape[1]} x {f0.shape[0]} px (W x H) "
                              f"like frames[0] ({_rel(f0.file, folder)})",
                              f"{_rel(path, folder)}: {shape[1]} x {shape[0]} px")
        entries.append(FrameEntry(i, path, pattern, pol, exposure, sha256_file(path), str(meta.get("format")), shape))
        images[key] = img
        if t.has("stderr_file") and stderr_out is not None:
            from .noise import read_frame_stderr
            stderr_out[key] = read_frame_stderr(t, folder, shape)
    miss = missing_frames(images)
    if miss:
        raise ConfigError(file, "frames", "a sufficient frame set: ambient and, per axis, the gradient with its "
                          "complement or with full (all cross-polarized); missing: " + "; ".join(miss),
                          sorted(f"{p}/{pol}" for p, pol in images))
    return tuple(entries), images


def _led_file(t: _Table, folder: Path) -> tuple[NDArray[np.float64], Path]:
    p = t.path("file", folder, "LED calibration (.csv or .npy)")
    if p.suffix.lower() == ".npy":
        try:
            a = np.load(p, allow_pickle=False)
        except Exception as exc:
            raise t.err("file", f"a readable .npy array of shape (N, 6): {', '.join(LED_COLUMNS)}",
                        f"{p.name} ({exc})") from None
        a = np.asarray(a, dtype=np.float64) if np.issubdtype(np.asarray(a).dtype, np.number) else a
        if not (isinstance(a, np.ndarray) and a.ndim == 2 and a.shape[1] == 6 and a.shape[0] > 0):
            raise t.err("file", f"an .npy array of shape (N, 6): {', '.join(LED_COLUMNS)}",
                        f"{p.name}: shape {getattr(a, 'shape', None)}")
        return a, p
    if p.suffix.lower() != ".csv":
        raise t.err("file", "a .csv or .npy file", p.name)
    rows: list[list[float]] = []
    header: list[str] | None = None
    idx: list[int] = []
    with open(p, newline="") as fh:
        for line_no, line in enumerate(fh, start=1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            row = next(csv.reader([line]))
            if header is None:
                header = [h.strip() for h in row]
                if sorted(header) != sorted(LED_COLUMNS):
                    raise t.err("file", f"a CSV whose header names the columns {','.join(LED_COLUMNS)}",
                                f"{p.name} line {line_no}: {row}")
                idx = [header.index(c) for c in LED_COLUMNS]
                continue
            try:
                rows.append([float(row[j]) for j in idx])
            except (ValueError, IndexError):
                raise t.err("file", "6 numbers per CSV row", f"{p.name} line {line_no}: {row}") from None
    if not rows:
        raise t.err("file", "at least one LED row", p.name)
    return np.asarray(rows, dtype=np.float64), p


def _read_leds(file: str, folder: Path, data: dict[str, Any]) -> LedCalibration:
    if not isinstance(data.get("leds"), dict):
        raise ConfigError(file, "leds", "a table [leds] with ideal = true or an LED calibration",
                          None if data.get("leds") is None else type(data.get("leds")).__name__)
    t = _Table(file, data["leds"], "leds.", ("ideal", "file", "positions_mm", "intensity", "drive_file", "drive_peak"))
    ideal = t.bool("ideal", False)
    if ideal:
        for k in ("file", "positions_mm", "intensity", "drive_file", "drive_peak"):
            if t.has(k):
                raise t.err(k, "nothing: ideal = true uses the continuous gradients and no LED calibration", k)
        return LedCalibration(ideal=True)
    if t.has("file") == t.has("positions_mm"):
        raise t.err("file", "either file = \"leds.csv\" (or .npy) or positions_mm + intensity inline "
                    "(or ideal = true)", "both" if t.has("file") else "neither")
    sha = None
    if t.has("file"):
        if t.has("intensity"):
            raise t.err("intensity", "nothing: the LED file holds the intensities", "intensity")
        a, p = _led_file(t, folder)
        pos, inten, source, sha = a[:, :3], a[:, 3:], _rel(p, folder), sha256_file(p)
        where = f"{p.name}"
    else:
        pos = t.matrix("positions_mm", 3)
        v = t._get("intensity", _REQ)
        if isinstance(v, list) and v and isinstance(v[0], list):
            inten = t.matrix("intensity", 3, rows=len(pos))
        else:
            inten = np.broadcast_to(t.rgb("intensity", nonneg=True), pos.shape).copy()
        source, where = "inline", "leds.positions_mm"
    if not np.all(np.isfinite(pos)) or np.any(np.linalg.norm(pos, axis=1) <= 0):
        raise t.err("file" if t.has("file") else "positions_mm",
                    "finite LED positions away from the rig origin (mm)", where)
    if not np.all(np.isfinite(inten)) or np.any(inten < 0) or not np.any(inten > 0):
        raise t.err("file" if t.has("file") else "intensity", "finite intensities >= 0, not all zero", where)
    drive: dict[str, NDArray[np.float64]] = {}
    if t.has("drive_file"):
        dp = t.path("drive_file", folder, "drive values (.npz)")
        try:
            with np.load(dp, allow_pickle=False) as z:
                for name in z.files:
                    if name not in PATTERNS[1:]:
                        raise t.err("drive_file", "arrays named after gradient patterns (full, x, y, z, x_c, y_c, "
                                    "z_c)", f"{dp.name}: {name}")
                    arr = np.asarray(z[name], dtype=np.float64)
                    if arr.shape not in ((len(pos),), (len(pos), 3)) or not np.all(np.isfinite(arr)) \
                            or np.any(arr < 0):
                        raise t.err("drive_file", f"per pattern (N,) or (N, 3) finite values >= 0, N = {len(pos)}",
                                    f"{dp.name}: {name} of shape {arr.shape}")
                    drive[name] = arr
        except ConfigError:
            raise
        except Exception as exc:
            raise t.err("drive_file", "a readable .npz file", f"{dp.name} ({exc})") from None
    peak = t.num("drive_peak", 1.0, positive=True, hi=1.0)
    return LedCalibration(False, pos, inten, drive, peak, source, sha)


def _rotation(t: _Table, k: str) -> NDArray[np.float64]:
    R = t.matrix(k, 3, rows=3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise t.err(k, "a proper rotation (orthonormal rows: camera right, down, forward in the rig frame; "
                    "det +1)", R.tolist())
    return R


def _default_up(direction: NDArray[np.float64]) -> NDArray[np.float64]:
    """The ``up`` a user did not write: +z, or +y when the camera looks (nearly) along z (docs/capture-folder.md)."""
    n = float(np.linalg.norm(direction))
    if n > 0 and abs(float(direction[2])) / n > 0.99:
        return np.array([0.0, 1.0, 0.0])
    return np.array([0.0, 0.0, 1.0])


def _read_camera(file: str, data: dict[str, Any], shape: tuple[int, int]
                 ) -> tuple[PinholeCamera | OrthographicCamera, dict[str, Any]]:
    H, W = shape
    if not isinstance(data.get("camera"), dict):
        raise ConfigError(file, "camera", "a table [camera] with model = \"pinhole\" or \"orthographic\"",
                          None if data.get("camera") is None else type(data.get("camera")).__name__)
    model = data["camera"].get("model")
    common = ("model", "width_px", "height_px", "cx_px", "cy_px", "rotation", "up")
    if model == "pinhole":
        allowed = common + ("fx_px", "fy_px", "position_mm", "look_at_mm", "translation_mm")
    elif model == "orthographic":
        allowed = common + ("pixel_size_mm", "look_direction", "target_mm")
    else:
        raise ConfigError(file, "camera.model", "one of pinhole, orthographic", model)
    t = _Table(file, data["camera"], "camera.", allowed)
    for k, n in (("width_px", W), ("height_px", H)):
        if t.has(k) and t.num(k) != n:
            raise t.err(k, f"the frames' size ({W} x {H} px), or leave it out", t.data[k])
    cx, cy = t.num("cx_px", (W - 1) / 2.0), t.num("cy_px", (H - 1) / 2.0)
    spec: dict[str, Any] = {"model": model, "width_px": W, "height_px": H, "cx_px": cx, "cy_px": cy}
    if model == "pinhole":
        fx = t.num("fx_px", positive=True)
        fy = t.num("fy_px", fx, positive=True)
        if t.has("rotation"):
            for k in ("position_mm", "look_at_mm", "up"):
                if t.has(k):
                    raise t.err(k, "nothing: give the pose as rotation + translation_mm or as position_mm + "
                                "look_at_mm (+ up), not both", k)
            R = _rotation(t, "rotation")
            tvec = t.vec("translation_mm", 3)
            C = -R.T @ tvec                       # OpenCV: X_cam = R X_rig + t  =>  centre C = -R^T t
        else:
            if t.has("translation_mm"):
                raise t.err("translation_mm", "only with rotation (OpenCV extrinsics R, t)", "translation_mm")
            C = t.vec("position_mm", 3)
            target = t.vec("look_at_mm", 3)
            up = t.vec("up", 3) if t.has("up") else _default_up(target - C)
            try:
                R = look_at_rotation(C, target, up)
            except ValueError:
                raise t.err("look_at_mm", "a target away from position_mm, in a direction not parallel to up "
                            f"{up.tolist()}", target.tolist()) from None
        if np.linalg.norm(C) == 0:
            raise t.err("position_mm" if not t.has("rotation") else "translation_mm",
                        "a camera centre away from the rig origin (the object sits there)", C.tolist())
        cam: PinholeCamera | OrthographicCamera = PinholeCamera(
            W, H, fx, fy, cx, cy, tuple(map(tuple, R.tolist())), tuple(map(float, C)))
        spec.update({"fx_px": fx, "fy_px": fy, "rotation": R.tolist(), "center_mm": C.tolist(),
                     "convention": "OpenCV: X_cam = R (X_rig - center_mm); rows of R = right, down, forward"})
        return cam, spec
    px = t.num("pixel_size_mm", positive=True)
    if t.has("rotation"):
        for k in ("look_direction", "up"):
            if t.has(k):
                raise t.err(k, "nothing: give rotation or look_direction (+ up), not both", k)
        R = _rotation(t, "rotation")
    else:
        d = t.vec("look_direction", 3)
        up = t.vec("up", 3) if t.has("up") else _default_up(d)
        if np.linalg.norm(d) == 0:
            raise t.err("look_direction", "a non-zero direction (from the camera towards the object)", d.tolist())
        try:
            R = look_at_rotation(np.zeros(3), d, up)
        except ValueError:
            raise t.err("up", f"a direction not parallel to look_direction {d.tolist()}", up.tolist()) from None
    target = t.vec("target_mm", 3, [0.0, 0.0, 0.0])
    cam = OrthographicCamera(W, H, px, tuple(map(tuple, R.tolist())), tuple(map(float, target)), cx, cy)
    spec.update({"pixel_size_mm": px, "rotation": R.tolist(), "target_mm": target.tolist(),
                 "convention": "X_cam = R (X_rig - target_mm); (u, v) = X_cam[:2] / pixel_size_mm + (cx, cy)"})
    return cam, spec


def _read_radiometry(file: str, data: dict[str, Any], shape: tuple[int, int]) -> Radiometry:
    if not isinstance(data.get("radiometry"), dict):
        raise ConfigError(file, "radiometry", "a table [radiometry] with albedo_scale, value_per_radiance_per_s "
                          "or [radiometry.reference]", None)
    t = _Table(file, data["radiometry"], "radiometry.",
               ("eta", "albedo_scale", "value_per_radiance_per_s", "reference", "saturation_level", "dark_level"))
    eta = t.num("eta", 1.3, lo=1.0, hi=3.0)
    sources = [k for k in ("albedo_scale", "value_per_radiance_per_s", "reference") if t.has(k)]
    if len(sources) != 1:
        raise t.err("albedo_scale", "exactly one of albedo_scale, value_per_radiance_per_s, [radiometry.reference]",
                    sources or "none")
    scale = t.rgb("albedo_scale", positive=True) if t.has("albedo_scale") else None
    vpr = t.rgb("value_per_radiance_per_s", positive=True) if t.has("value_per_radiance_per_s") else None
    ref = None
    if t.has("reference"):
        r = t.table("reference", ("region_px", "reflectance"))
        assert r is not None
        reg = r.vec("region_px", 4)
        H, W = shape
        x0, y0, x1, y1 = (int(v) for v in reg)
        if not (np.all(reg == np.round(reg)) and 0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
            raise r.err("region_px", f"integers [x0, y0, x1, y1] with 0 <= x0 < x1 <= {W} and 0 <= y0 < y1 <= {H} "
                        "(half-open pixel ranges)", reg.tolist())
        ref = ReferenceTarget((x0, y0, x1, y1), r.rgb("reflectance", positive=True))
    return Radiometry(eta, scale, vpr, ref, t.num("saturation_level", 0.98, positive=True, allow_inf=True),
                      t.num("dark_level", 0.01, lo=0.0))


def _read_mask(t: _Table, folder: Path, shape: tuple[int, int]) -> tuple[NDArray[np.bool_], Path]:
    p = t.path("mask", folder, "mask image (.png, .tif, .exr)")
    suffix = p.suffix.lower()
    try:
        if suffix == ".png":
            import cv2
            a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if a is None:
                raise ValueError("not a readable PNG")
        elif suffix in (".tif", ".tiff"):
            import tifffile
            a = tifffile.imread(str(p))
        elif suffix == ".exr":
            a, _ = read_image(p)
        else:
            raise ValueError(f"unknown suffix {suffix!r}")
    except (ValueError, ImageFileError, OSError) as exc:
        raise t.err("mask", "a PNG (8/16-bit), TIFF or EXR image, non-zero = object", f"{p.name} ({exc})") from None
    a = np.asarray(a)
    if a.ndim == 3:
        a = np.any(a[..., :3] != 0, axis=-1)
    if a.shape != shape:
        raise t.err("mask", f"an image of the frames' size {shape[1]} x {shape[0]} px",
                    f"{p.name}: {a.shape[1] if a.ndim > 1 else '?'} x {a.shape[0]} px")
    return a != 0, p


def _read_object(file: str, folder: Path, data: dict[str, Any], shape: tuple[int, int], camera: Any = None
                 ) -> tuple[NDArray[np.bool_] | None, Path | None, SphereGeometry | None, Any, Any]:
    if "object" not in data:
        return None, None, None, None, None
    if not isinstance(data["object"], dict):
        raise ConfigError(file, "object", "a table [object]", type(data["object"]).__name__)
    t = _Table(file, data["object"], "object.", ("mask", "shape", "center_mm", "radius_mm", "normals_file",
                                                 "height_file", "mesh_file", "mesh_units", "mesh_translation_mm",
                                                 "regions", "region_names"))
    mask, mask_file = _read_mask(t, folder, shape) if t.has("mask") else (None, None)
    shape_kind = t.str("shape", "unknown", choices=("unknown", "sphere", "relief"))
    geo = None
    relief = None
    if shape_kind == "sphere":
        geo = SphereGeometry(t.vec("center_mm", 3), t.num("radius_mm", positive=True))
    else:
        for k in ("center_mm", "radius_mm"):
            if t.has(k):
                raise t.err(k, "nothing unless shape = \"sphere\"", k)
    if shape_kind == "relief":
        from rig.estimate.folder_diffusion import read_relief_geometry
        relief = read_relief_geometry(t, folder, shape, camera)
    else:
        for k in ("normals_file", "height_file", "mesh_file", "mesh_units", "mesh_translation_mm"):
            if t.has(k):
                raise t.err(k, "nothing unless shape = \"relief\"", k)
    from rig.estimate.folder_regions import read_regions
    return mask, mask_file, geo, relief, read_regions(t, folder, shape)


def _read_seed(file: str, data: dict[str, Any]) -> SeedSpec | None:
    if "seed" not in data:
        return None
    if not isinstance(data["seed"], dict):
        raise ConfigError(file, "seed", "a table [seed] with k_mm and provenance", type(data["seed"]).__name__)
    t = _Table(file, data["seed"], "seed.", ("k_mm", "provenance"))
    k = t.rgb("k_mm", positive=True)
    prov = t._get("provenance", _REQ)
    if isinstance(prov, str) and prov.strip():
        prov_d: dict[str, Any] = {"note": prov}
    elif isinstance(prov, dict) and prov:
        prov_d = dict(prov)
    else:
        raise t.err("provenance", "a non-empty string or table: the reference material, its D, the geometry and "
                    "rig it was calibrated on, the date (k is an empirical length, not a constant)", prov)
    return SeedSpec(k, prov_d)


def load_capture(folder: str | Path) -> Capture:
    """Read and validate ``FOLDER/capture.toml`` and decode its frames (``docs/capture-folder.md``).

    Raises :class:`drivers.errors.ConfigError` naming the file, the key and what was expected (missing frame file,
    unknown pattern or polarization, duplicate (pattern, polarization), frames of different sizes, an insufficient
    frame set listing what is missing, an unreadable frame with the reader's reason, a RAW frame whose recorded
    exposure differs from ``exposure_s``, bad calibration / camera / radiometry / object / seed values).
    """
    root = Path(folder)
    cfile = root / CAPTURE_FILE
    file = str(cfile)
    if not root.is_dir():
        raise ConfigError(str(root), "<folder>", "a capture folder holding capture.toml", "no such folder")
    try:
        text = cfile.read_text()
    except OSError as exc:
        raise ConfigError(file, "<file>", "a readable capture.toml", str(exc)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(file, "<syntax>", "valid TOML", str(exc)) from None
    top = _Table(file, data, "", ("format", "format_version", "name", "description", "frames", "leds", "camera",
                                  "radiometry", "object", "seed", "noise"))
    if top.str("format") != CAPTURE_FORMAT:
        raise top.err("format", repr(CAPTURE_FORMAT), data.get("format"))
    v = data.get("format_version")
    if v != CAPTURE_FORMAT_VERSION or isinstance(v, bool):
        raise top.err("format_version", str(CAPTURE_FORMAT_VERSION), v)
    name = top.str("name", root.resolve().name)
    top.str("description", "")
    frame_stderr: dict[FrameKey, Any] = {}
    frames, images = _read_frames(file, root, data, frame_stderr)
    from .noise import read_noise
    noise = read_noise(file, data, frame_stderr, len(frames))
    shape = frames[0].shape
    leds = _read_leds(file, root, data)
    camera, cam_spec = _read_camera(file, data, shape)
    radiometry = _read_radiometry(file, data, shape)
    if radiometry.value_per_radiance_per_s is not None and leds.ideal:
        raise ConfigError(file, "radiometry.value_per_radiance_per_s", "an LED calibration ([leds] file or "
                          "positions_mm + intensity): the irradiance comes from it; with ideal = true give "
                          "albedo_scale or [radiometry.reference]", "leds.ideal = true")
    if radiometry.reference is not None:
        if ("full", "cross") not in images and not any((a, "cross") in images and (a + "_c", "cross") in images
                                                        for a in _AXES):
            raise ConfigError(file, "radiometry.reference", "a cross-polarized full frame, or a gradient with its "
                              "complement (their sum is the full pattern), to measure the reference", None)
    mask, mask_file, geo, relief, regions = _read_object(file, root, data, shape, camera)
    seed = _read_seed(file, data)
    spec_ok, spec_note = _specular_possible(set(images))
    notes = tuple(n for n in (spec_note,) if n)
    return Capture(root, cfile, sha256_file(cfile), name, frames, images, leds, camera, cam_spec, radiometry, mask,
                   mask_file, geo, seed, spec_ok, notes, relief, regions, noise)
