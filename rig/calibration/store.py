"""The versioned calibration file: one JSON document per rig, one section per calibration step.

Layout (``docs/calibration.md``)::

    {"format": "sssrig-calibration", "schema_version": 1, "rig": "<rig name>", "revision": 7,
     "updated": "<ISO time>",
     "steps": {"intrinsics": {"result": {...}, "residuals": {...}, "provenance": {...}, "revision": 3},
               "rig_frame": {...}, "led_directions": {...}, "gains": {...}, "extinction": {...},
               "radiometry": {...}, "seed_k": {...}}}

Every section carries ``provenance``: ``created`` (ISO time), ``session`` (the capture session folder the
frames are in), ``software_version``, ``config`` (the rig config file), ``inputs`` (which earlier sections and
design values it used) and, for simulated runs, ``simulated: true``. ``revision`` counts writes of the file;
each section records the revision that wrote it, and the previous file is kept as
``<name>.history/rNNNN.json`` (four-digit revision, ``r0001.json``). Writes are atomic (temporary file, fsync, rename).

:func:`load_calibration` validates the document and raises :class:`CalibrationError` naming the file and the
dotted field; :class:`Calibration` gives the estimators what they consume (a ``PinholeCamera``, the lens
distortion, an ``estimation.gradients.LedRig``, the albedo scale, the seed's ``k``, a RAW linearizer).
"""
from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import numpy.typing as npt

from drivers.atomic import atomic_write_bytes
from drivers.errors import RigError

from ..provenance import json_default
from .linearity import linearize

FORMAT = "sssrig-calibration"
SCHEMA_VERSION = 1
STEP_SECTIONS = ("intrinsics", "rig_frame", "led_directions", "gains", "extinction", "radiometry", "seed_k")

__all__ = ["FORMAT", "SCHEMA_VERSION", "STEP_SECTIONS", "CalibrationError", "Calibration", "load_calibration",
           "write_section", "new_document"]


class CalibrationError(RigError, ValueError):
    """A calibration file is missing, malformed, or lacks a section the caller needs. The message names the
    file and the dotted field."""

    def __init__(self, file: str | os.PathLike[str], field: str, expected: str, got: Any = None) -> None:
        self.file, self.field, self.expected, self.got = os.fspath(file), field, expected, got
        msg = f"{self.file}: field '{field}': expected {expected}"
        if got is not None:
            text = repr(got)
            msg += f", got {text if len(text) < 80 else text[:77] + '...'}"
        super().__init__(msg)


# ---------------------------------------------------------------------------------------------- validation
def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


class _V:
    """Field checks with errors naming the file and the dotted path."""

    def __init__(self, file: str, data: Any, path: str) -> None:
        self.file, self.data, self.path = file, data, path

    def _name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def get(self, key: str, kind: str = "table") -> Any:
        if not isinstance(self.data, dict) or key not in self.data:
            raise CalibrationError(self.file, self._name(key), f"a {kind} (field is missing)")
        return self.data[key]

    def table(self, key: str) -> "_V":
        v = self.get(key)
        if not isinstance(v, dict):
            raise CalibrationError(self.file, self._name(key), "a JSON object", type(v).__name__)
        return _V(self.file, v, self._name(key))

    def num(self, key: str, *, positive: bool = False, lo: float | None = None) -> float:
        v = self.get(key, "number")
        if not _is_num(v):
            raise CalibrationError(self.file, self._name(key), "a finite number", v)
        if positive and v <= 0:
            raise CalibrationError(self.file, self._name(key), "a number > 0", v)
        if lo is not None and v < lo:
            raise CalibrationError(self.file, self._name(key), f"a number >= {lo}", v)
        return float(v)

    def array(self, key: str, shape: tuple[int | None, ...], *, positive: bool = False, unit: bool = False,
              allow_nan: bool = False) -> np.ndarray:
        v = self.get(key, "array")
        name = self._name(key)
        want = "x".join("N" if s is None else str(s) for s in shape)
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise CalibrationError(self.file, name, f"a numeric array of shape {want}", v) from None
        if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
            raise CalibrationError(self.file, name, f"a numeric array of shape {want}", f"shape {a.shape}")
        finite = np.isfinite(a) | (np.isnan(a) if allow_nan else False)
        if not np.all(finite):
            raise CalibrationError(self.file, name, "finite numbers", v)
        if positive and np.any(a[np.isfinite(a)] <= 0):
            raise CalibrationError(self.file, name, "numbers > 0", v)
        if unit:
            n = np.linalg.norm(a, axis=-1)
            if np.any(np.abs(n - 1.0) > 1e-6):
                raise CalibrationError(self.file, name, "unit vectors", f"norms {n.min():.6g}..{n.max():.6g}")
        return a


def _validate_section(file: str, name: str, sec: Any) -> None:
    v = _V(file, {name: sec}, "steps")
    s = v.table(name)
    for key in ("result", "residuals", "provenance"):
        s.table(key)
    p = s.table("provenance")
    for key in ("created", "session", "software_version"):
        if not isinstance(p.get(key, "string"), str):
            raise CalibrationError(file, p._name(key), "a string", p.data[key])
    r = s.table("result")
    if name == "intrinsics":
        r.num("width_px", positive=True), r.num("height_px", positive=True)
        for k in ("fx_px", "fy_px"):
            r.num(k, positive=True)
        r.num("cx_px"), r.num("cy_px")
        r.array("distortion", (5,))
    elif name == "rig_frame":
        cam = r.table("camera")
        R = cam.array("rotation", (3, 3))
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise CalibrationError(file, cam._name("rotation"), "a proper rotation matrix (orthonormal, det +1)",
                                   R.tolist())
        cam.array("center_mm", (3,))
        r.array("led_positions_mm", (None, 3))
    elif name == "led_directions":
        idx = r.array("led_indices", (None,))
        d = r.array("directions", (None, 3), unit=True)
        if len(idx) != len(d):
            raise CalibrationError(file, r._name("directions"), f"one direction per LED index ({len(idx)})",
                                   f"{len(d)} directions")
    elif name == "gains":
        idx = r.array("led_indices", (None,))
        g = r.array("gains", (None, 3), positive=True)
        if len(idx) != len(g):
            raise CalibrationError(file, r._name("gains"), f"one gain row per LED index ({len(idx)})",
                                   f"{len(g)} rows")
        r.array("design_intensity", (3,), positive=True)
    elif name == "extinction":
        r.num("median_ratio", lo=0.0)
    elif name == "radiometry":
        r.array("black_offset_dn", (3,))
        r.array("nonlinearity", (3,))
        r.array("albedo_scale", (3,), positive=True)
        r.num("albedo_scale_exposure_s", positive=True)
    elif name == "seed_k":
        r.array("k_mm", (3,), positive=True)


def _validate(file: str, doc: Any) -> dict[str, Any]:
    if not isinstance(doc, dict):
        raise CalibrationError(file, "<document>", "a JSON object", type(doc).__name__)
    if doc.get("format") != FORMAT:
        raise CalibrationError(file, "format", f'"{FORMAT}"', doc.get("format"))
    ver = doc.get("schema_version")
    if ver != SCHEMA_VERSION:
        raise CalibrationError(file, "schema_version", f"{SCHEMA_VERSION} (this software's calibration schema)",
                               ver)
    from ..schema import did_you_mean

    for key in doc:
        if key not in _TOP_KEYS:
            raise CalibrationError(file, key, "a key of a calibration file" + did_you_mean(key, _TOP_KEYS) + " ("
                                   + ", ".join(_TOP_KEYS) + ")", key)
    v = _V(file, doc, "")
    v.num("revision", lo=0)
    steps = v.table("steps")
    for name, sec in steps.data.items():
        if name not in STEP_SECTIONS:
            raise CalibrationError(file, f"steps.{name}", "a calibration step" + did_you_mean(name, STEP_SECTIONS)
                                   + " (" + ", ".join(STEP_SECTIONS) + ")", name)
        if isinstance(sec, dict):
            for key in sec:
                if key not in _SECTION_KEYS:
                    raise CalibrationError(file, f"steps.{name}.{key}", "a key of a calibration section"
                                           + did_you_mean(key, _SECTION_KEYS) + " (" + ", ".join(_SECTION_KEYS) + ")",
                                           key)
        _validate_section(file, name, sec)
    return doc


_TOP_KEYS = ("format", "schema_version", "rig", "revision", "updated", "steps")
_SECTION_KEYS = ("result", "residuals", "provenance", "revision")


# ---------------------------------------------------------------------------------------------- I/O
def new_document(rig_name: str) -> dict[str, Any]:
    return {"format": FORMAT, "schema_version": SCHEMA_VERSION, "rig": rig_name, "revision": 0,
            "updated": None, "steps": {}}


def _atomic_write(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode(), overwrite=True)


def read_document(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Parse and validate a calibration file (no section required)."""
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(p, "<file>", "an existing calibration file (run `rig calibrate STEP` first)")
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise CalibrationError(p, "<syntax>", "valid JSON", str(exc)) from exc
    except OSError as exc:
        raise CalibrationError(p, "<file>", "a readable file", str(exc)) from exc
    return _validate(str(p), doc)


def write_section(path: str | os.PathLike[str], name: str, *, result: Mapping[str, Any],
                  residuals: Mapping[str, Any], provenance: Mapping[str, Any], rig_name: str) -> dict[str, Any]:
    """Add or replace section ``name`` of the calibration file at ``path`` (created if missing); bump the
    revision, keep the previous file in ``<name>.history/``, write atomically. Returns the new document.

    The section is validated before anything is written (a bad result never reaches the file)."""
    if name not in STEP_SECTIONS:
        raise ValueError(f"unknown calibration section {name!r}; expected one of {', '.join(STEP_SECTIONS)}")
    from ..session import now_iso

    p = Path(path)
    doc = read_document(p) if p.exists() else new_document(rig_name)
    if doc.get("rig") != rig_name:
        raise CalibrationError(p, "rig", f"the rig this calibration belongs to ({rig_name!r}); use another --out",
                               doc.get("rig"))
    rev = int(doc["revision"]) + 1
    section = json.loads(json.dumps({"result": dict(result), "residuals": dict(residuals),
                                     "provenance": dict(provenance), "revision": rev}, default=json_default))
    _validate_section(str(p), name, section)
    if p.exists():
        hist = p.parent / f"{p.name}.history"
        hist.mkdir(exist_ok=True)
        shutil.copy2(p, hist / f"r{int(doc['revision']):04d}.json")
    doc["steps"][name] = section
    doc["revision"] = rev
    doc["updated"] = now_iso()
    p.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(p, json.dumps(doc, indent=2, default=json_default) + "\n")
    return doc


# ---------------------------------------------------------------------------------------------- consumer
@dataclass(frozen=True)
class Calibration:
    """A validated calibration document and what the estimators take from it."""

    path: Path
    doc: dict[str, Any]

    def has(self, name: str) -> bool:
        return name in self.doc["steps"]

    def section(self, name: str) -> dict[str, Any]:
        if name not in self.doc["steps"]:
            raise CalibrationError(self.path, f"steps.{name}",
                                   f"a '{name}' section (run `rig calibrate {name.replace('_', '-')}`)")
        return self.doc["steps"][name]

    def result(self, name: str) -> dict[str, Any]:
        return self.section(name)["result"]

    def provenance(self) -> dict[str, Any]:
        """Per section: revision, when, which session, whether simulated (for an estimate's ``inputs``)."""
        return {"file": str(self.path), "revision": self.doc["revision"],
                "sections": {k: {"revision": s["revision"], "created": s["provenance"]["created"],
                                 "session": s["provenance"]["session"],
                                 "simulated": bool(s["provenance"].get("simulated", False))}
                             for k, s in self.doc["steps"].items()}}

    # -- camera -------------------------------------------------------------------------------------------
    def intrinsics(self) -> Any:
        from .common import Intrinsics

        r = self.result("intrinsics")
        return Intrinsics(int(r["width_px"]), int(r["height_px"]), float(r["fx_px"]), float(r["fy_px"]),
                          float(r["cx_px"]), float(r["cy_px"]), tuple(float(x) for x in r["distortion"]))

    def distortion(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.result("intrinsics")["distortion"], float)

    def camera(self) -> Any:
        """The calibrated ``estimation.camera.PinholeCamera`` (intrinsics + rig-frame pose) for undistorted
        frames (:meth:`undistort`)."""
        r = self.result("rig_frame")["camera"]
        return self.intrinsics().pinhole(np.asarray(r["rotation"], float), np.asarray(r["center_mm"], float))

    def undistort(self, image: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """A frame (H, W, C) resampled to the ideal pinhole of :meth:`camera` (bilinear)."""
        return self.intrinsics().undistort_image(np.asarray(image, float))

    # -- LEDs -------------------------------------------------------------------------------------------
    def led_positions_mm(self, design_positions_mm: npt.ArrayLike | None = None) -> npt.NDArray[np.float64]:
        """Survey-refined LED positions (N, 3); the design positions if the rig frame is not calibrated."""
        if self.has("rig_frame"):
            return np.asarray(self.result("rig_frame")["led_positions_mm"], float)
        if design_positions_mm is None:
            self.section("rig_frame")
        return np.asarray(design_positions_mm, float)

    def led_rig(self, design_positions_mm: npt.ArrayLike, design_intensity: npt.ArrayLike, *,
                patterns: Mapping[str, npt.ArrayLike] | None = None) -> Any:
        """``estimation.gradients.LedRig``: directions from the mirror ball where measured (else from the
        refined positions), distances from the positions, gains I_design x gain / d^2 (gain 1 for LEDs the
        gain step did not measure). Missing sections fall back to the design values."""
        from estimation.gradients import LedRig

        pos = self.led_positions_mm(design_positions_mm)
        n = len(pos)
        if len(np.asarray(design_positions_mm)) != n:
            raise CalibrationError(self.path, "steps.rig_frame.result.led_positions_mm",
                                   f"{len(np.asarray(design_positions_mm))} LEDs (the config's layout)", f"{n} LEDs")
        dist = np.linalg.norm(pos, axis=1)
        dirs = pos / dist[:, None]
        if self.has("led_directions"):
            r = self.result("led_directions")
            idx = np.asarray(r["led_indices"], int)
            self._check_indices("led_directions", idx, n)
            dirs[idx] = np.asarray(r["directions"], float)
        gain = np.ones((n, 3))
        if self.has("gains"):
            r = self.result("gains")
            idx = np.asarray(r["led_indices"], int)
            self._check_indices("gains", idx, n)
            gain[idx] = np.asarray(r["gains"], float)
        inten = np.broadcast_to(np.asarray(design_intensity, float), (n, 3)) * gain
        return LedRig(dirs, inten / (dist * dist)[:, None], dist, patterns)

    def _check_indices(self, name: str, idx: np.ndarray, n: int) -> None:
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise CalibrationError(self.path, f"steps.{name}.result.led_indices", f"LED indices in [0, {n})",
                                   idx.tolist())

    # -- radiometry -------------------------------------------------------------------------------------
    def albedo_scale(self, exposure_s: float) -> npt.NDArray[np.float64]:
        """``albedo_scale`` (3,) for gradient frames of ``exposure_s`` (frame values scale with exposure)."""
        r = self.result("radiometry")
        return np.asarray(r["albedo_scale"], float) * float(r["albedo_scale_exposure_s"]) / float(exposure_s)

    def linearizer(self) -> Callable[[npt.ArrayLike], npt.NDArray[np.float64]]:
        """A function mapping ``load_linear`` values (white = 1) to black-corrected, linearized values."""
        if not self.has("radiometry"):
            return lambda v: np.asarray(v, float)
        r = self.result("radiometry")
        return lambda v: linearize(v, r)

    def k_mm(self) -> npt.NDArray[np.float64]:
        """The seed's calibrated length k (3,) in mm, for ``estimation.diffusion.diffusion_seed``."""
        return np.asarray(self.result("seed_k")["k_mm"], float)


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read and validate a calibration file (:class:`CalibrationError` names the file and the field)."""
    p = Path(path)
    return Calibration(p, read_document(p))
