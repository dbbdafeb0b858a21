"""Write and read the maps of a gradient estimate: one float image per quantity, a JSON sidecar, a PNG preview.

Layout of an output folder (``docs/capture-folder.md``, section "Outputs"):

    maps.json                 sidecar: per file quantity, unit, channel order, frame, NaN meaning, sha256;
                              the provenance (capture folder, frames + sha256, calibration, software, parameters)
    albedo_diffuse.exr        (H, W, 3) R,G,B   measured diffuse albedo (R_d convention of docs/gradients.md sec. 3)
    normals_diffuse_R.exr     (H, W, 3) x,y,z   unit diffuse normal of the red channel, rig frame
    normals_diffuse_G.exr, normals_diffuse_B.exr
    diffuse_length.exr        (H, W, 3) R,G,B   |v| / (tau1/tau0): 1 = no subsurface blur
    albedo_specular.exr       (H, W, 3) R,G,B   with parallel-polarized frames only
    normals_specular.exr      (H, W, 3) x,y,z   with parallel-polarized frames only
    R_d.exr, alpha_prime.exr, D_mm.exr, sigma_s_prime_per_mm.exr, sigma_a_per_mm.exr, shortening.exr
                              (H, W, 3) R,G,B   grounded diffusion estimate (with geometry only)
    D_seed_mm.exr             (H, W, 3) R,G,B   the seed's D = k R_d/|n_z| (with a seed calibration only)
    masks.png                 8-bit RGB bit field per channel (MASK_BITS)
    preview.png               contact sheet for people (display-encoded; never for measurement)

Float files are EXR (float32, ZIP) or float32 TIFF (zlib), written atomically by :mod:`rig.files.imageio`. **NaN means
unknown** (masked: saturated, dark, inconsistent, grazing, background, outside the model's validity); nothing is
ever written as a number where it is not known. Row 0 is the top of the image, column 0 the left, as in the input
frames (the pixel convention of :class:`estimation.camera.PinholeCamera`). Vectors are in the rig frame
(right-handed, +z up, docs/architecture.md).

References: Ma et al. 2007 (maps), Jensen et al. 2001 (R_d, alpha', D, sigma_s', sigma_a), Zhu et al. (the seed's
D ~ R_d/|n_z|); ``docs/gradients.md`` for every quantity's definition.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from drivers.errors import RigError
from estimation.diffusion import DiffusionMaps, SeedEstimate
from estimation.gradients import DerivedMap, GradientMaps

from rig.files.imageio import write_exr, write_float_tiff, write_png8
from rig.files.provenance import sha256_file, write_json

__all__ = ["MAPS_FORMAT", "MAPS_FORMAT_VERSION", "SIDECAR", "PREVIEW", "MASKS", "MASK_BITS", "MAP_SPECS",
           "PREVIEW_TILE_PX", "MapSpec", "MapsError", "LoadedMaps", "write_maps", "read_maps", "preview_size_px",
           "DERIVATIONS", "HALF_OK", "select_maps"]

MAPS_FORMAT = "sssrig-maps"
MAPS_FORMAT_VERSION = 1
SIDECAR = "maps.json"
PREVIEW = "preview.png"
MASKS = "masks.png"
PREVIEW_TILE_PX = (320, 300)       # (width, height) of one preview tile; the sheet is 3 tiles wide
PREVIEW_COLUMNS = 3
_DPI = 100

# bits of masks.png, per colour channel (per-pixel masks are set in all three channels)
MASK_BITS: dict[str, int] = {
    "saturated": 1,            # a used frame reached the saturation level in this channel
    "dark": 2,                 # full-on signal below the dark level in this channel
    "inconsistent": 4,         # non-finite input, rho <= 0 or |v|/tau above max_length
    "grazing": 8,              # n.v below cos(grazing angle) (per pixel)
    "background": 16,          # all channels dark, or outside the object mask (per pixel)
    "specular_unknown": 32,    # no specular estimate here (per pixel; set everywhere without parallel frames)
    "diffusion_unknown": 64,   # no grounded diffusion estimate in this channel (everywhere without geometry)
}

FRAME = ("image grid of the input frames (row 0 top, column 0 left); vectors in the rig frame: right-handed, "
         "mm, +z up (docs/architecture.md)")
_NAN_DIFFUSE = "unknown: saturated, dark, inconsistent, grazing or background pixel (see masks.png)"


class MapsError(RigError, ValueError):
    """A maps folder is missing, malformed or does not match its sidecar; the message names the file."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        super().__init__(f"{os.fspath(path)}: {reason}")
        self.path = os.fspath(path)
        self.reason = reason


@dataclass(frozen=True)
class MapSpec:
    """What one map file holds (copied into the sidecar)."""

    name: str
    quantity: str
    unit: str
    channels: tuple[str, str, str]
    nan: str
    definition: str

    def sidecar(self) -> dict[str, Any]:
        return {"quantity": self.quantity, "unit": self.unit, "channels": list(self.channels),
                "frame": FRAME, "nan": self.nan, "definition": self.definition, "dtype": "float32"}


_RGB = ("R", "G", "B")
_XYZ = ("x", "y", "z")
_DIFF_NAN = ("unknown: no grounded estimate (maps unknown there, outside the sphere region, grazing, or the "
             "(albedo, shortening) pair could not be inverted)")
MAP_SPECS: dict[str, MapSpec] = {s.name: s for s in [
    MapSpec("albedo_diffuse", "diffuse albedo (total diffuse reflectance R_d, apparent on curved objects)", "1",
            _RGB, _NAN_DIFFUSE,
            "cross-polarized full-on signal x albedo_scale, exit Fresnel divided out (docs/gradients.md sec. 3)"),
    *[MapSpec(f"normals_diffuse_{c}", f"diffuse normal of the {c} channel", "unit vector", _XYZ, _NAN_DIFFUSE,
              "direction of the ideal-equivalent gradient vector v (Ma et al. 2007; docs/gradients.md sec. 2)")
      for c in _RGB],
    MapSpec("diffuse_length", "diffuse gradient length |v| / (tau1/tau0)", "1", _RGB, _NAN_DIFFUSE,
            "1 for an unblurred Fresnel-Lambertian surface; < 1 where subsurface blur averages curved normals"),
    MapSpec("albedo_specular", "specular albedo", "1", _RGB,
            "unknown: no specular signal (dark, saturated, background) or no parallel-polarized frames",
            "albedo_scale x (parallel - cross full-on) / 2 (docs/gradients.md sec. 3)"),
    MapSpec("normals_specular", "specular normal", "unit vector", _XYZ,
            "unknown: no specular signal (dark, saturated, background)",
            "normalize(reflection vector + view direction) from the channel-summed specular gradients"),
    MapSpec("R_d", "half-space total diffuse reflectance of the estimated alpha'", "1", _RGB, _DIFF_NAN,
            "R_d(alpha', eta) of the Jensen dipole (science.md sec. 1)"),
    MapSpec("alpha_prime", "reduced scattering albedo alpha' = sigma_s'/sigma_t'", "1", _RGB, _DIFF_NAN,
            "from the inversion of (apparent albedo, shortening) on the sphere (docs/gradients.md sec. 5)"),
    MapSpec("D_mm", "diffusion coefficient D = 1/(3 sigma_t')", "mm", _RGB, _DIFF_NAN,
            "grounded estimator (docs/gradients.md sec. 5), no fitted constant"),
    MapSpec("sigma_s_prime_per_mm", "reduced scattering coefficient sigma_s'", "1/mm", _RGB, _DIFF_NAN,
            "alpha' sigma_t'"),
    MapSpec("sigma_a_per_mm", "absorption coefficient sigma_a", "1/mm", _RGB, _DIFF_NAN,
            "(1 - alpha') sigma_t'; poorly conditioned when sigma_a << sigma_s' (science.md sec. 6)"),
    MapSpec("shortening", "shortening S = v.n_true / (tau1/tau0)", "1", _RGB, _DIFF_NAN,
            "the observable of the grounded estimator: 1 - S grows with the diffusion length"),
    MapSpec("D_seed_mm", "the seed's D = k R_d / |n_z| (Zhu et al.)", "mm", _RGB,
            "unknown: maps unknown there or |n_z| below the floor",
            "k is an empirical length calibrated on a reference (see provenance.seed): a relative map"),
]}


#: how a map that was left out (``write_maps(select=...)``) follows from the others; recorded in the sidecar's
#: ``not_written`` with the files it needs (a map whose sources were left out too is marked not derivable).
DERIVATIONS: dict[str, tuple[str, tuple[str, ...]]] = {
    "sigma_s_prime_per_mm": ("alpha_prime / (3 D_mm)", ("alpha_prime", "D_mm")),
    "sigma_a_per_mm": ("(1 - alpha_prime) / (3 D_mm)", ("alpha_prime", "D_mm")),
    "D_mm": ("1 / (3 (sigma_s_prime_per_mm + sigma_a_per_mm))", ("sigma_s_prime_per_mm", "sigma_a_per_mm")),
    "alpha_prime": ("sigma_s_prime_per_mm / (sigma_s_prime_per_mm + sigma_a_per_mm)",
                    ("sigma_s_prime_per_mm", "sigma_a_per_mm")),
    "R_d": ("half-space R_d(alpha_prime, eta) of the model in provenance.diffusion.model (Jensen: "
            "0.5 a (1 + exp(-4/3 A s)) exp(-s), s = sqrt(3 (1 - a)), A = boundary_A(eta))", ("alpha_prime",)),
}
#: maps whose precision allows EXR HALF (``write_maps(half=...)``): unit vectors (half: < 0.03 deg) and albedos
#: (relative 4.9e-4). The diffusion parameters, the shortening and |v|/tau stay float32: 1 - S ~ 1e-2..1e-1
#: carries the length scale and half would quantize it by ~5e-4 absolute.
HALF_OK: tuple[str, ...] = ("albedo_diffuse", "normals_diffuse_R", "normals_diffuse_G", "normals_diffuse_B",
                            "albedo_specular", "normals_specular")


def select_maps(spec: str | None) -> list[str] | None:
    """Parse a ``--maps`` value: None / "all" -> None (every available map); else comma-separated names of
    :data:`MAP_SPECS`, where "normals_diffuse" stands for the three channels. Unknown names raise ValueError."""
    if spec is None or spec.strip() in ("", "all"):
        return None
    out: list[str] = []
    for name in (t.strip() for t in spec.split(",") if t.strip()):
        names = [f"normals_diffuse_{c}" for c in _RGB] if name == "normals_diffuse" else [name]
        for n in names:
            if n not in MAP_SPECS:
                raise ValueError(f"unknown map {name!r}; valid: normals_diffuse, {', '.join(MAP_SPECS)}")
            out.append(n)
    return out


# ---------------------------------------------------------------------------------------------- helpers


def _write_json(path: Path, data: Mapping[str, Any]) -> Path:
    return write_json(path, data, strict=True)


def _read_float(path: Path) -> NDArray[np.float32]:
    """Read a float map (EXR or TIFF) keeping NaN (``rig.files.imageio.read_image`` refuses NaN in *frames*)."""
    if not path.is_file():
        raise MapsError(path, "no such file (listed in maps.json)")
    try:
        if path.suffix.lower() == ".exr":
            import OpenEXR
            with OpenEXR.File(str(path)) as f:
                ch = f.channels()
                if "RGB" in ch:
                    a = np.asarray(ch["RGB"].pixels)
                elif all(k in ch for k in "RGB"):
                    a = np.stack([np.asarray(ch[k].pixels) for k in "RGB"], axis=-1)
                else:
                    raise MapsError(path, f"expected channels R,G,B; found {sorted(ch)}")
        else:
            import tifffile
            a = tifffile.imread(str(path))
    except MapsError:
        raise
    except Exception as exc:
        raise MapsError(path, f"not a readable float map ({exc})") from None
    return np.ascontiguousarray(a, dtype=np.float32)


def _rgb(a: NDArray[Any] | None, name: str, shape: tuple[int, int]) -> NDArray[np.float32] | None:
    if a is None:
        return None
    if isinstance(a, DerivedMap):  # computed when written (one map at a time in memory)
        if a.shape != (*shape, 3):
            raise ValueError(f"{name}: expected shape {(*shape, 3)}, got {a.shape}")
        return a  # type: ignore[return-value]
    arr = np.asarray(a, dtype=np.float32)
    if arr.shape != (*shape, 3):
        raise ValueError(f"{name}: expected shape {(*shape, 3)}, got {arr.shape}")
    return arr


def _collect(maps: GradientMaps, diffusion: DiffusionMaps | None,
             seed: SeedEstimate | None) -> dict[str, NDArray[np.float32]]:
    shape = maps.shape
    out: dict[str, NDArray[np.float32] | None] = {"albedo_diffuse": _rgb(maps.albedo, "albedo", shape)}
    for c, ch in enumerate(_RGB):
        out[f"normals_diffuse_{ch}"] = _rgb(maps.diffuse_normals[..., c, :], "diffuse_normals", shape)
    out["diffuse_length"] = _rgb(maps.diffuse_length(), "diffuse_length", shape)
    out["albedo_specular"] = _rgb(maps.specular_albedo, "specular_albedo", shape)
    out["normals_specular"] = _rgb(maps.specular_normals, "specular_normals", shape)
    if diffusion is not None:
        for k in ("R_d", "alpha_prime", "D_mm", "sigma_s_prime_per_mm", "sigma_a_per_mm", "shortening"):
            out[k] = _rgb(getattr(diffusion, k), k, shape)
    if seed is not None:
        out["D_seed_mm"] = _rgb(seed.D_mm, "seed D_mm", shape)
    return {k: v for k, v in out.items() if v is not None}


def _mask_field(maps: GradientMaps, diffusion: DiffusionMaps | None) -> NDArray[np.uint8]:
    m = maps.masks
    H, W = maps.shape
    bits = np.zeros((H, W, 3), np.uint8)
    bits |= np.where(m.saturated, MASK_BITS["saturated"], 0).astype(np.uint8)
    bits |= np.where(m.dark, MASK_BITS["dark"], 0).astype(np.uint8)
    bits |= np.where(m.inconsistent, MASK_BITS["inconsistent"], 0).astype(np.uint8)
    bits |= np.where(m.grazing[..., None], MASK_BITS["grazing"], 0).astype(np.uint8)
    bits |= np.where(m.background[..., None], MASK_BITS["background"], 0).astype(np.uint8)
    spec_unknown = np.ones((H, W), bool) if maps.specular_unknown is None else maps.specular_unknown
    bits |= np.where(spec_unknown[..., None], MASK_BITS["specular_unknown"], 0).astype(np.uint8)
    d_unknown = np.ones((H, W, 3), bool) if diffusion is None else diffusion.unknown
    bits |= np.where(d_unknown, MASK_BITS["diffusion_unknown"], 0).astype(np.uint8)
    return bits


# ---------------------------------------------------------------------------------------------- preview
def _tiles(arrays: Mapping[str, NDArray[np.float32]]) -> list[list[dict[str, Any]]]:
    """Rows of tiles: each tile {title, kind ('rgb'|'normal'|'scalar'), data, unit, group}."""
    def alb(name: str, title: str) -> dict[str, Any]:
        return {"title": title, "kind": "rgb", "data": arrays.get(name), "unit": ""}
    rows = [[alb("albedo_diffuse", "diffuse albedo"), alb("albedo_specular", "specular albedo"),
             {"title": "specular normals", "kind": "normal", "data": arrays.get("normals_specular"), "unit": ""}],
            [{"title": f"diffuse normals {c}", "kind": "normal", "data": arrays.get(f"normals_diffuse_{c}"),
              "unit": ""}
             for c in _RGB]]
    for name, label, unit in (("D_mm", "D", "mm"), ("sigma_s_prime_per_mm", "sigma_s'", "1/mm"),
                              ("sigma_a_per_mm", "sigma_a", "1/mm"), ("D_seed_mm", "D seed (relative)", "mm")):
        if name in arrays:
            rows.append([{"title": f"{label} {c}", "kind": "scalar", "data": arrays[name][..., i], "unit": unit,
                          "group": name} for i, c in enumerate(_RGB)])
    return rows


def preview_size_px(n_rows: int) -> tuple[int, int]:
    """(height, width) in pixels of a preview sheet with ``n_rows`` rows of tiles."""
    return n_rows * PREVIEW_TILE_PX[1], PREVIEW_COLUMNS * PREVIEW_TILE_PX[0]


def _srgb(linear: NDArray[Any]) -> NDArray[np.float64]:
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _display_rgb(tile: dict[str, Any]) -> tuple[NDArray[np.float64], str]:
    """Display RGB in [0, 1] with unknown = neutral grey, and a note on the scaling used."""
    a = np.asarray(tile["data"], dtype=np.float64)
    unknown = ~np.isfinite(a).all(-1)
    if tile["kind"] == "normal":
        rgb, note = (np.nan_to_num(a) + 1.0) / 2.0, "(n+1)/2"
    else:
        fin = a[np.isfinite(a)]
        top = float(np.percentile(fin, 99.5)) if fin.size else 1.0
        gain = 1.0 / top if top > 1.0 or (tile["title"].startswith("specular") and top > 0) else 1.0
        rgb, note = _srgb(np.nan_to_num(a) * gain), ("sRGB display" + (f", x{gain:.3g}" if gain != 1.0 else ""))
    rgb = np.clip(rgb, 0.0, 1.0)
    rgb[unknown] = 0.5
    return rgb, note


def _scalar_ranges(rows: list[list[dict[str, Any]]]) -> dict[str, tuple[float, float]]:
    """Shared colour range per quantity (1-99 % over its three channels), so channels compare by colour."""
    out: dict[str, tuple[float, float]] = {}
    for row in rows:
        for t in row:
            if t["kind"] != "scalar":
                continue
            vals = np.concatenate([np.asarray(u["data"], dtype=np.float64).ravel() for u in row])
            vals = vals[np.isfinite(vals)]
            if vals.size:
                lo, hi = (float(v) for v in np.percentile(vals, [1, 99]))
                if hi <= lo:
                    lo, hi = lo - 0.5 * abs(lo) - 1e-12, hi + 0.5 * abs(hi) + 1e-12
            else:
                lo, hi = 0.0, 1.0
            out[t["group"]] = (lo, hi)
            break
    return out


def _compose_sheet(rows: list[list[dict[str, Any]]]) -> tuple[NDArray[np.uint8], list[tuple[int, int, str, float]]]:
    """The preview sheet's pixels (h, w, 3) uint8 — tiles in a grid, scalars in viridis with a colour strip per
    tile, unknown grey — and its labels as (x_px, baseline_px, text, size) for either text renderer."""
    import cv2

    tw, th = PREVIEW_TILE_PX
    h_px, w_px = preview_size_px(len(rows))
    sheet = np.full((h_px, w_px, 3), 255, np.uint8)
    ranges = _scalar_ranges(rows)
    band, bar = 22, 26
    texts: list[tuple[int, int, str, float]] = []
    for r, row in enumerate(rows):
        for c, t in enumerate(row):
            y0, x0 = r * th, c * tw
            tile = sheet[y0:y0 + th, x0:x0 + tw]
            label = t["title"]
            area_h = th - band - bar
            if t["data"] is None:
                tile[band:th - bar] = 128
                label += ": not measured"
            else:
                if t["kind"] == "scalar":
                    lo, hi = ranges[t["group"]]
                    a = np.asarray(t["data"], dtype=np.float64)
                    u8 = np.round(np.clip((np.nan_to_num(a, nan=lo) - lo) / (hi - lo), 0, 1) * 255).astype(np.uint8)
                    img = cv2.applyColorMap(u8, cv2.COLORMAP_VIRIDIS)[..., ::-1]  # BGR -> RGB
                    img[~np.isfinite(a)] = 128
                    label += f" [{t['unit']}]"
                    ramp = np.round(np.linspace(0, 255, tw - 80)).astype(np.uint8)[None, :].repeat(8, 0)
                    strip = cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS)[..., ::-1]
                    tile[th - bar + 2:th - bar + 10, 40:tw - 40] = strip
                    for txt, xx in ((f"{lo:.3g}", 2), (f"{hi:.3g}", tw - 78)):
                        texts.append((x0 + xx, y0 + th - 4, txt, 0.35))
                else:
                    rgb, note = _display_rgb(t)
                    img = np.round(rgb * 255).astype(np.uint8)
                    label += f" ({note})"
                h, w = img.shape[:2]
                s = min(area_h / h, (tw - 4) / w)
                nh, nw = max(1, int(h * s)), max(1, int(w * s))
                img = cv2.resize(np.ascontiguousarray(img), (nw, nh), interpolation=cv2.INTER_NEAREST)
                oy, ox = band + (area_h - nh) // 2, (tw - nw) // 2
                tile[oy:oy + nh, ox:ox + nw] = img
            texts.append((x0 + 4, y0 + 15, label[:48], 0.4))
    return sheet, texts


def _preview_matplotlib(path: Path, rows: list[list[dict[str, Any]]], title: str) -> None:
    """The sheet of :func:`_compose_sheet` as one figure image with matplotlib's text (issue 19: one image and a few
    text artists instead of an Axes and a colour bar per tile: measured 1.2 -> ~0.1 CPU s per capture)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    sheet, texts = _compose_sheet(rows)
    h_px, w_px = sheet.shape[:2]
    fig = Figure(figsize=(w_px / _DPI, h_px / _DPI), dpi=_DPI)
    fig.patch.set_alpha(0.0)
    canvas = FigureCanvasAgg(fig)
    for x, y, txt, size in texts:
        fig.text(x / w_px, 1.0 - y / h_px, txt, fontsize=7 if size >= 0.4 else 6, va="baseline", ha="left")
    canvas.draw()       # the text alone (transparent elsewhere), laid over the sheet: black ink with its coverage
    ink = np.asarray(canvas.buffer_rgba())[:h_px, :w_px, 3:4].astype(np.float32) / 255.0
    del title  # the sidecar describes the sheet; tiles carry their own labels
    write_png8(path, sheet.astype(np.float32) / 255.0 * (1.0 - ink))


def _preview_opencv(path: Path, rows: list[list[dict[str, Any]]], title: str) -> None:
    """numpy + OpenCV fallback (no matplotlib): the same sheet (:func:`_compose_sheet`), labels drawn by OpenCV."""
    import cv2

    sheet, texts = _compose_sheet(rows)
    for x, y, txt, size in texts:
        cv2.putText(sheet, txt, (x, y), cv2.FONT_HERSHEY_SIMPLEX, size, (0, 0, 0), 1, cv2.LINE_AA)
    del title  # the sidecar describes the sheet; tiles carry their own labels
    write_png8(path, sheet.astype(np.float32) / 255.0)


def _write_preview(path: Path, arrays: Mapping[str, NDArray[np.float32]], title: str,
                   backend: str) -> tuple[str, list[list[str]], tuple[int, int]]:
    rows = _tiles(arrays)
    if backend not in ("auto", "matplotlib", "opencv"):
        raise ValueError(f"preview backend must be auto, matplotlib or opencv, got {backend!r}")
    used = backend
    if backend == "auto":  # matplotlib is the optional 'plots' extra
        import importlib.util
        used = "matplotlib" if importlib.util.find_spec("matplotlib") is not None else "opencv"
    (_preview_matplotlib if used == "matplotlib" else _preview_opencv)(path, rows, title)
    return used, [[t["title"] for t in row] for row in rows], preview_size_px(len(rows))


# ---------------------------------------------------------------------------------------------- API
def write_maps(out_dir: str | os.PathLike[str], maps: GradientMaps, diffusion: DiffusionMaps | None, *,
               fmt: str = "exr", provenance: Mapping[str, Any], seed: SeedEstimate | None = None,
               preview: str = "auto", extra_sidecar: Mapping[str, Any] | None = None,
               select: Any = None, half: Any = ()) -> dict[str, Path]:
    """Write every available map as one float file, ``masks.png``, ``preview.png`` and ``maps.json``.

    ``fmt``: "exr" (float32 OpenEXR, ZIP) or "tiff" (float32 TIFF, zlib). ``diffusion``: the grounded per-pixel
    estimate (:func:`estimation.diffusion.estimate_diffusion` / ``estimate_sphere(...).maps``) or None (no
    geometry: no diffusion files, ``diffusion_unknown`` set everywhere in ``masks.png``). ``seed``: the seed's
    estimate (:func:`estimation.diffusion.diffusion_seed`) or None. ``provenance`` is stored verbatim in the
    sidecar (capture folder, frames with sha256, calibration, parameters); ``extra_sidecar`` adds top-level keys
    (e.g. a summary). ``preview``: "auto" (matplotlib if installed, else OpenCV), "matplotlib" or "opencv".

    ``select``: names of :data:`MAP_SPECS` to write (None: every available map); the sidecar's ``not_written``
    lists each available map that was left out with how it follows from the written ones (:data:`DERIVATIONS`)
    or that it does not. ``half``: names (or True for all of :data:`HALF_OK`) written as EXR HALF (float16;
    only maps in :data:`HALF_OK`, EXR only); the sidecar's per-file ``dtype`` says which.

    Returns {name: path} for every file written (map names of :data:`MAP_SPECS`, plus "masks", "preview",
    "sidecar"). Existing files of the same names are replaced atomically; others in ``out_dir`` are left alone.
    """
    if fmt not in ("exr", "tiff"):
        raise ValueError(f"fmt must be 'exr' or 'tiff', got {fmt!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    H, W = maps.shape
    available = _collect(maps, diffusion, seed)
    if select is not None:
        chosen = list(select)
        unknown = [n for n in chosen if n not in MAP_SPECS]
        if unknown:
            raise ValueError(f"unknown map names {unknown}; valid: {', '.join(MAP_SPECS)}")
        arrays = {k: v for k, v in available.items() if k in chosen}
    else:
        arrays = available
    half_set = set(HALF_OK) if half is True else set(half or ())
    bad_half = sorted(half_set - set(HALF_OK))
    if bad_half:
        raise ValueError(f"maps {bad_half} must stay float32; half precision is allowed for {', '.join(HALF_OK)}")
    if half_set and fmt != "exr":
        raise ValueError("half precision needs fmt='exr' (the TIFF writer is float32 only)")
    ext = ".exr" if fmt == "exr" else ".tif"
    written: dict[str, Path] = {}
    files: dict[str, Any] = {}
    for name, lazy in arrays.items():
        arr = np.asarray(lazy, dtype=np.float32)
        spec = MAP_SPECS[name]
        p = out / f"{name}{ext}"
        meta = {"quantity": spec.quantity, "unit": spec.unit, "channels": ",".join(spec.channels),
                "nan": "unknown", "software": "sssrig", "sidecar": SIDECAR}
        is_half = name in half_set
        if fmt == "exr":
            write_exr(p, arr, attributes={f"sssrig_{k}": v for k, v in meta.items()}, half=is_half)
        else:
            write_float_tiff(p, arr, description=json.dumps(meta))
        written[name] = p
        files[name] = {"file": p.name, **spec.sidecar(), "dtype": "float16" if is_half else "float32",
                       "sha256": sha256_file(p),
                       "known_fraction": [float(np.isfinite(arr[..., c]).mean()) for c in range(3)]}
    bits = _mask_field(maps, diffusion)
    pm = write_png8(out / MASKS, bits.astype(np.float32) / 255.0)
    written["masks"] = pm
    title = f"sssrig maps: {provenance.get('name', '')}".rstrip(": ")
    backend, tiles, (ph, pw) = _write_preview(out / PREVIEW, arrays, title, preview)
    written["preview"] = out / PREVIEW
    sidecar: dict[str, Any] = {
        "format": MAPS_FORMAT, "format_version": MAPS_FORMAT_VERSION,
        "image": {"width_px": W, "height_px": H, "pixel_convention": "row 0 top, column 0 left, pixel centres at "
                  "integer coordinates (estimation.camera)"},
        "nan": "NaN (in every float file) = unknown; never a number where nothing is known",
        "file_format": {"exr": "OpenEXR float32, ZIP, channels R,G,B (vectors: x,y,z stored as R,G,B)",
                        "tiff": "TIFF float32, zlib, 3 samples per pixel (RGB photometric; vectors: x,y,z)"}[fmt],
        "files": files,
        "not_written": {k: ({"derive": DERIVATIONS[k][0], "from": list(DERIVATIONS[k][1])}
                            if k in DERIVATIONS and all(s in arrays for s in DERIVATIONS[k][1])
                            else {"derive": None, "note": "left out (write_maps select); not derivable from the "
                                                          "written files"})
                        for k in available if k not in arrays},
        "masks": {"file": MASKS, "sha256": sha256_file(pm), "encoding": "8-bit RGB PNG; per colour channel a bit "
                  "field (per-pixel masks are set in all three channels)", "bits": dict(MASK_BITS)},
        "preview": {"file": PREVIEW, "backend": backend, "width_px": pw, "height_px": ph, "tiles": tiles,
                    "note": "display-encoded for viewing only (sRGB albedo, (n+1)/2 normals, viridis scalars with "
                            "a shared range per quantity); grey = unknown"},
        "provenance": dict(provenance),
    }
    if extra_sidecar:
        sidecar.update(dict(extra_sidecar))
    written["sidecar"] = _write_json(out / SIDECAR, sidecar)
    return written


@dataclass(frozen=True)
class LoadedMaps:
    """Maps read back by :func:`read_maps`: float arrays (H, W, 3) by name, boolean masks by name (H, W, 3),
    and the parsed sidecar."""

    arrays: dict[str, NDArray[np.float32]]
    masks: dict[str, NDArray[np.bool_]]
    sidecar: dict[str, Any]

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.sidecar["image"]["height_px"]), int(self.sidecar["image"]["width_px"])


def read_maps(out_dir: str | os.PathLike[str], *, verify: bool = True) -> LoadedMaps:
    """Read a folder written by :func:`write_maps`. With ``verify`` every file's sha256 must match the sidecar.

    Raises :class:`MapsError` naming the file for a missing/foreign sidecar, a missing or altered file, or a
    shape that differs from the sidecar's image size.
    """
    out = Path(out_dir)
    side_p = out / SIDECAR
    if not side_p.is_file():
        raise MapsError(side_p, "no such file: not a maps folder written by sssrig")
    try:
        side = json.loads(side_p.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise MapsError(side_p, f"not readable JSON ({exc})") from None
    if side.get("format") != MAPS_FORMAT:
        raise MapsError(side_p, f"field 'format': expected {MAPS_FORMAT!r}, got {side.get('format')!r}")
    if side.get("format_version") != MAPS_FORMAT_VERSION:
        raise MapsError(side_p, f"field 'format_version': expected {MAPS_FORMAT_VERSION}, "
                                f"got {side.get('format_version')!r}")
    shape = (int(side["image"]["height_px"]), int(side["image"]["width_px"]))
    arrays: dict[str, NDArray[np.float32]] = {}
    for name, entry in side["files"].items():
        p = out / entry["file"]
        a = _read_float(p)
        if a.shape != (*shape, 3):
            raise MapsError(p, f"shape {a.shape}, expected {(*shape, 3)} from maps.json")
        if verify and sha256_file(p) != entry["sha256"]:
            raise MapsError(p, "sha256 differs from maps.json: the file was changed after it was written")
        arrays[name] = a
    import cv2
    mp = out / side["masks"]["file"]
    raw = cv2.imread(str(mp), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.shape != (*shape, 3):
        raise MapsError(mp, f"expected an 8-bit RGB PNG of {shape[1]} x {shape[0]} px")
    if verify and sha256_file(mp) != side["masks"]["sha256"]:
        raise MapsError(mp, "sha256 differs from maps.json: the file was changed after it was written")
    bits = raw[..., ::-1]
    masks = {k: (bits & b) != 0 for k, b in side["masks"]["bits"].items()}
    return LoadedMaps(arrays, masks, side)
