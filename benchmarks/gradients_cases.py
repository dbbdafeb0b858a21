"""The cases of issue 16's acceptance (benchmarks/gradients_acceptance.py): Monte Carlo gradient captures written as
capture folders (docs/capture-folder.md), rendered once and cached by content hash.

Folder ``benchmarks/out/gradients_acceptance/<hash>/`` (``SSSRIG_GRADIENTS_CASES_DIR`` overrides the root):
``capture.toml``, ``frames/*.exr``, ``leds.npy`` and ``meta.json`` (the case, its truth, render seconds; written
last, so its presence marks a complete folder). ``<hash>``: SHA-256 of the case, the Monte Carlo renderer's sources
(:func:`simulators.mc._cache.sources_hash`), ``simulators/scene.py``, ``simulators/mc_capture.py`` and this file:
a second run renders nothing; a change of the renderer or of a case renders again.

Common to every case: 362 LEDs at 1 m (``rig.acquire.geometry.led_layout(6, 1000, -60)``, intensity 1000 per channel) seen
by the Monte Carlo renderer as a distant map (``simulators.mc_capture``), full + x + y + z gradients, eta 1.3,
reduced sigma_s', sigma_a of science.md sec. 2 (``rig.config.MATERIALS``), isotropic phase function; camera noise
of a 14-bit sensor (``simulators.camera.SensorModel``: Poisson shot noise at 1.5 electrons/DN, read noise 2 DN,
Bayer mosaic averaged to RGB; ``noise=True``, seeded) on top of the Monte Carlo error of ``spp`` paths per pixel.

Families:

- ``relief``: a slab (``simulators.scene.BumpySlabObject``) whose top carries a relief of a single period P (three
  plane waves of wavelength P in seeded directions, RMS slope 0.15), seen by an orthographic camera along +y
  (``size_px`` pixels of ``pixel_mm``), both polarizations, no geometry in ``capture.toml`` (shape "unknown": the
  user path through the specular normals) and the rendered normals in ``true_normals.npy`` (H, W, 3, rig frame;
  :func:`with_normals_file` makes a copy of the folder whose ``[object]`` names them: the user path of a relief
  whose geometry is known). The relief mesh is sampled every ``pixel_mm``. Size: a slab only needs to
  be a few diffusion lengths l_d wide and thick around what the camera sees -- light that would have come back
  from farther is lost at the sides and bottom. Margin and thickness are ``MARGIN_L_D`` = 2.75 x the material's
  largest l_d (skimmilk 51 mm, marble 23 mm, apple 19 mm, ketchup 13 mm, skin1 10 mm): by the dipole's tail
  (R_d beyond r ~ 2.5 l' e^(-r/l_d) / r) that loses <~ 1 % of the reflectance per face, a few per cent of 1 - R_d
  and so of l_d, small against the 25 % rule. The relief only needs several pixels per period: 0.25 mm pixels
  give 10 and 16 per period at P = 2.5 and 4 mm, 40 px (10 mm) 2.5-4 periods.
  The slab lies on a black backing (``RELIEF_BLACK_BACKING``): the LEDs of the rear hemisphere (w . n_slab <= 0)
  are blocked while rendering (``leds.npy`` still lists every LED: the rig's calibration), as for a real sample on
  a holder. Lit from behind as well, a slab 2.75 l_d thick is no half-space: light entering its back adds to the
  front's exitance. Measured on flat boxes of the case's size under these LEDs (docs/model-error.md, "Issue 16
  acceptance, measured"): the R_d map over the table's R_d is +25 / +6 / +4 % (skin1) and +9 / +7 / +7 % (marble)
  lit from all sides, +8 / +5 / +3 % and +6 / +6 / +5 % with the rear hemisphere blocked, +6 % on a half-space
  (the exit normalization 1/c(1.3), which estimation.relief now divides out).
- ``sphere``: a sphere of ``radius_mm`` at the origin, pinhole camera 400 mm away on -y that the sphere just fills
  (``size_px`` square), cross-polarized frames, ``[object] shape = "sphere"`` in the folder (estimated plain or
  with ``--reference``).

Truth per channel: l_d = 1 / sqrt(3 sigma_a (sigma_s' + sigma_a)), D = 1 / (3 (sigma_s' + sigma_a)).
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

_THIS = Path(__file__).resolve()
ROOT = _THIS.parents[1]
ETA = 1.3
GAIN_DN_PER_UNIT, BLACK_DN, WHITE_DN, EXPOSURE_S = 4.5e7, 512, 16383, 0.02
MARGIN_L_D = 2.75          # slab margin and thickness in units of the material's largest l_d
RELIEF_BLACK_BACKING = True   # relief slabs: rear-hemisphere LEDs blocked (a black backing plate)
RELIEF_RMS_SLOPE = 0.15
RELIEF_WAVES = 3
CAMERA_DISTANCE_MM = 400.0


def materials() -> dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]]:
    from rig.config import MATERIALS
    return {k: (tuple(map(float, v[0])), tuple(map(float, v[1]))) for k, v in MATERIALS.items()}  # type: ignore


def truth(material: str) -> dict[str, list[float]]:
    ssp, sa = (np.asarray(x, dtype=np.float64) for x in materials()[material])
    return {"sigma_s_prime_per_mm": ssp.tolist(), "sigma_a_per_mm": sa.tolist(),
            "l_d_mm": (1.0 / np.sqrt(3.0 * sa * (ssp + sa))).tolist(), "D_mm": (1.0 / (3.0 * (ssp + sa))).tolist()}


@dataclass(frozen=True)
class Case:
    """One capture: ``family`` "relief" (``period_mm``, ``pixel_mm``) or "sphere" (``radius_mm``); ``reference``:
    estimate the sphere with ``--reference`` (its renders: ``reference_spp``, ``reference_iterations``)."""

    family: str
    material: str
    size_px: int
    spp: int
    seed: int = 0
    period_mm: float = 0.0
    pixel_mm: float = 0.0
    radius_mm: float = 0.0
    reference: bool = False
    reference_spp: int = 64
    reference_iterations: int = 4

    @property
    def name(self) -> str:
        if self.family == "relief":
            return f"relief P{self.period_mm:g}mm {self.material}"
        return f"sphere r{self.radius_mm:g}mm {self.material}" + (" --reference" if self.reference else "")

    def render_key(self) -> dict[str, Any]:
        """What the frames depend on (the estimate options are not part of the cache key)."""
        d = asdict(self)
        for k in ("reference", "reference_spp", "reference_iterations"):
            d.pop(k)
        return d

    def margin_mm(self) -> float:
        return MARGIN_L_D * float(max(truth(self.material)["l_d_mm"]))


def content_hash(case: Case) -> str:
    from simulators.mc._cache import sources_hash

    h = hashlib.sha256(json.dumps(case.render_key(), sort_keys=True).encode())
    h.update(sources_hash().encode())
    for p in (ROOT / "simulators" / "scene.py", ROOT / "simulators" / "mc_capture.py", _THIS):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def default_root() -> Path:
    return Path(os.environ.get("SSSRIG_GRADIENTS_CASES_DIR", ROOT / "benchmarks" / "out" / "gradients_acceptance"))


def _leds() -> tuple[np.ndarray, np.ndarray, Any]:
    from estimation.gradients import LedRig
    from rig.acquire.geometry import led_layout

    pos, _ = led_layout(6, 1000.0, -60.0)
    inten = np.full((len(pos), 3), 1000.0)
    return pos, inten, LedRig.from_positions(pos, inten)


def _sensor() -> Any:
    from simulators.camera import SensorModel
    return SensorModel(gain_dn_per_unit=GAIN_DN_PER_UNIT, black_level_dn=BLACK_DN, white_level_dn=WHITE_DN,
                       read_noise_dn=2.0, electrons_per_dn=1.5)


def _render(case: Case) -> tuple[Any, list[str], dict[str, Any]]:
    """The capture (simulators.scene.GradientCapture), the folder's [camera]/[object] lines and render facts."""
    from estimation.camera import OrthographicCamera, PinholeCamera
    from rig.estimate.reference.folder_reference import renderable_camera
    from simulators.mc_capture import MCSettings
    from simulators.scene import BumpySlabObject, SphereObject, render_gradient_capture

    ssp, sa = materials()[case.material]
    pos, inten, rig = _leds()
    patterns = {p: rig.pattern_values(p) for p in ("full", "x", "y", "z")}
    facts: dict[str, Any] = {}
    if case.family == "relief":
        margin = case.margin_mm()
        view = case.size_px * case.pixel_mm
        cam = renderable_camera(OrthographicCamera.looking_at(width_px=case.size_px, height_px=case.size_px,
                                                              pixel_size_mm=case.pixel_mm, direction=(0.0, 1.0, 0.0)))
        obj = BumpySlabObject((0.0, 0.0, 0.0), ssp, sa, ETA, extent_mm=view + 2.0 * margin, patch_mm=case.pixel_mm,
                              rms_slope=RELIEF_RMS_SLOPE, wavelengths_mm=(case.period_mm, case.period_mm),
                              n_waves=RELIEF_WAVES, seed=case.seed)
        mc = MCSettings(spp=case.spp, seed=case.seed, leds="distant", relief_step_mm=case.pixel_mm,
                        slab_thickness_mm=margin)
        pols: tuple[str, ...] = ("cross", "parallel")
        lines = ["[camera]", 'model = "orthographic"', f"pixel_size_mm = {case.pixel_mm!r}",
                 "look_direction = [0.0, 1.0, 0.0]", ""]
        facts.update(slab_extent_mm=view + 2.0 * margin, slab_thickness_mm=margin, view_mm=view)
    elif case.family == "sphere":
        fx = case.size_px * CAMERA_DISTANCE_MM / (2.0 * case.radius_mm)
        cam = PinholeCamera.looking_at(width_px=case.size_px, height_px=case.size_px, fx_px=fx,
                                       position_mm=(0.0, -CAMERA_DISTANCE_MM, 0.0), target_mm=(0.0, 0.0, 0.0))
        obj = SphereObject((0.0, 0.0, 0.0), case.radius_mm, ssp, sa, ETA, tessellation=3)
        mc = MCSettings(spp=case.spp, seed=case.seed, leds="distant")
        pols = ("cross",)
        lines = ["[camera]", 'model = "pinhole"', f"fx_px = {fx!r}", f"position_mm = [0.0, {-CAMERA_DISTANCE_MM}, 0.0]",
                 "look_at_mm = [0.0, 0.0, 0.0]", "", "[object]", 'shape = "sphere"', "center_mm = [0.0, 0.0, 0.0]",
                 f"radius_mm = {case.radius_mm!r}", ""]
    else:
        raise ValueError(f"unknown case family {case.family!r}")
    lit = inten
    if case.family == "relief" and RELIEF_BLACK_BACKING:      # the slab faces -y; its backing hides y >= 0
        lit = inten * (pos[:, 1] < 0.0)[:, None]
        facts.update(black_backing=True, leds_blocked=int(np.sum(pos[:, 1] >= 0.0)))
    cap = render_gradient_capture(obj, cam, pos, lit, patterns, polarizations=pols, exposure_s=EXPOSURE_S,
                                  sensor=_sensor(), noise=True, rng=np.random.default_rng(1000 + case.seed),
                                  render_mode="mc", mc=mc)
    return cap, lines, facts


def build_case(case: Case, root: Path | None = None) -> tuple[Path, dict[str, Any]]:
    """The case's capture folder (rendered now, or found in the cache) and its meta data."""
    from drivers.atomic import atomic_write
    from rig.estimate.capture_folder.write import write_frames_and_leds

    folder = (root or default_root()) / content_hash(case)
    meta_path = folder / "meta.json"
    if meta_path.exists():
        meta = json.loads(meta_path.read_text())
        meta["cached"] = True
        return folder, meta
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cap, cam_lines, facts = _render(case)
    seconds = time.perf_counter() - t0
    pos, inten, _ = _leds()
    lines = ['format = "sssrig-capture"', "format_version = 1", f'name = "{case.name}"',
             f'description = "benchmarks/gradients_cases.py: {case.name}, {case.size_px} px, {case.spp} spp, '
             f'seed {case.seed}, camera noise"', ""]
    fr = np.stack([np.asarray(f) for (p, _), f in cap.frames.items() if p != "ambient"])
    lines += write_frames_and_leds(folder, cap.frames, EXPOSURE_S, np.hstack([pos, inten]))
    if case.family == "relief":
        np.save(folder / "true_normals.npy", np.nan_to_num(cap.normals).astype(np.float32))
    lines += [*cam_lines, "[radiometry]", f"eta = {ETA}",
              f"value_per_radiance_per_s = {GAIN_DN_PER_UNIT / (WHITE_DN - BLACK_DN)!r}", ""]
    atomic_write(folder / "capture.toml", lambda p: p.write_text("\n".join(lines)))
    hit = np.asarray(cap.hit, dtype=bool)
    meta = {"case": asdict(case), "name": case.name, "truth": truth(case.material), "render_seconds": seconds,
            "object_pixels": int(hit.sum()), "frame_max": float(np.nanmax(fr)),
            "saturated_px": int(np.sum(np.any(fr >= 1.0, axis=(0, -1)) & hit)), "led_mode": cap.led_mode,
            **facts, "cached": False}
    atomic_write(meta_path, lambda p: p.write_text(json.dumps(meta, indent=1)))
    return folder, meta


def with_normals_file(folder: Path, dest: Path) -> Path:
    """A copy of a relief case's folder whose ``[object]`` is ``shape = "relief"`` with ``normals_file =
    "true_normals.npy"`` (docs/capture-folder.md)."""
    import shutil

    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(folder, dest)
    toml = dest / "capture.toml"
    toml.write_text(toml.read_text() + '\n[object]\nshape = "relief"\nnormals_file = "true_normals.npy"\n')
    return dest


def camera_noise_toml() -> str:
    """The cases' camera noise as a capture folder's ``[noise]`` table (docs/capture-folder.md): frame values are
    (DN - black) / (white - black), so electrons per value = 1.5 e-/DN x (white - black) and the read noise is
    2 DN / (white - black)."""
    span = float(WHITE_DN - BLACK_DN)
    return f"\n[noise]\nelectrons_per_value = {1.5 * span!r}\nread_noise = {2.0 / span!r}\n"


def with_noise(folder: Path, dest: Path) -> Path:
    """``folder`` (or, when ``dest`` already holds a copy, that copy) with the cases' camera noise stated in
    ``[noise]`` (:func:`camera_noise_toml`): the estimate then propagates it into its intervals."""
    import shutil

    if folder != dest:
        if dest.exists():
            shutil.rmtree(dest)
        shutil.copytree(folder, dest)
    toml = dest / "capture.toml"
    toml.write_text(toml.read_text() + camera_noise_toml())
    return dest
