"""A zoo scene rendered by the project's Monte Carlo renderer and written as a scene-file folder (docs/scene-file.md).

Folder ``benchmarks/out/zoo/<hash>/``: ``scene.toml``, ``mesh.ply`` (the coarse convex mesh; the estimator
subdivides it to ``[mesh].max_edge_mm``), ``image.exr`` or ``image.png`` (16-bit), ``sky.exr`` (lat-long map, for
``sun``/``sky`` lights) and ``meta.json`` (truth, classes, noise level, render statistics; written last, so its
presence marks a complete folder). ``<hash>`` is the SHA-256 of the scene description, the renderer's sources
(:func:`simulators.mc._cache.sources_hash`) and this file's source: a second run re-renders nothing, and a change of
the renderer or of the noise model re-renders everything.

Frame (:func:`render_frame`): ``simulators.mc.render`` of the coarse mesh (``Mesh``) filled with the material
(``Medium.from_reduced``, one medium per channel, isotropic phase function), no specular reflection (the scene file
says ``specular_free = true``), ``frame_spp`` paths per pixel, seed ``frame_seed`` (the estimator's reference renders
use seed 1: independent random numbers).

Environment maps. The lighting is a function of the z-up world direction (:func:`sky_radiance`). The map file F is
that function at the pixel centres of the map *in the file's convention*: pixel (i, j) is the world direction
M n(i, j), n the native lat-long direction and M the orientation matrix of the file's ``up``, ``phi0``,
``azimuth``, ``rotation_deg`` keys as docs/scene-file.md defines it (:func:`documented_map_rotation`, written
from the documentation, not imported from the loader, so that the loader's convention code is what is checked).
The frame is then rendered with F itself as the renderer's native map, the scene rotated into the map's frame
(a clockwise azimuth: M = M' S with S = diag(1, -1, 1); F's columns reversed, rotation M'): the map written is
exactly the lighting the frame saw, with no resampling.

Noise (:func:`apply_noise`; values v = radiance x ``radiance_scale`` k):
- ``mc``: k = 1, the frame as rendered (float EXR): its own Monte Carlo noise at low spp, fireflies included;
- ``camera``: k = 0.6 / (99th percentile of the object's radiance); electrons ~ Poisson(v g), value = electrons/g
  + N(0, r) (g electrons per value, r read noise in value units = read electrons / g); float EXR (negative values
  kept) or 16-bit PNG (clipped to [0, 1], quantized);
- ``zeros``: as ``camera``, with the black level b = 0.02 added before and subtracted after the read noise and the
  result clipped at 0 (a raw developer's ``max(raw - black, 0)``): dark pixels become exactly 0. The read noise is
  raised to twice the 2nd percentile of the object's values (at most 0.03) so that zeros occur on every scene
  (the class is drawn with point lights only: they leave dark pixels).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
import trimesh

from .scenes import SUN_SIGMA_DEG, SceneSpec, l_d_min_mm

BLACK_LEVEL = 0.02
SKY_RADIANCE = 0.2          # dim sky (radiance units of the lights), ~10x less irradiance than the sun lobe
SUN_IRRADIANCE = 4.0        # the sun lobe's irradiance on a surface facing it
_THIS = Path(__file__).resolve()


def documented_map_rotation(up: Any, phi0: Any, azimuth: str, rotation_deg: float) -> np.ndarray:
    """docs/scene-file.md "Environment maps": w_world = M Rz(rotation_deg) w_native, M = [a | b | u] with u = up,
    a = phi0 made orthogonal to u, b = u x a (counterclockwise) or -(u x a) (clockwise)."""
    u, a = _direction(up), _direction(phi0)
    a = a - (a @ u) * u
    a /= np.linalg.norm(a)
    b = np.cross(u, a) * (1.0 if azimuth == "counterclockwise" else -1.0)
    t = math.radians(rotation_deg)
    rz = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
    return np.stack([a, b, u], axis=1) @ rz


def _direction(v: Any) -> np.ndarray:
    axes = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
    d = np.asarray(axes[v] if isinstance(v, str) else v, float)
    return d / np.linalg.norm(d)


def native_directions(rows: int) -> np.ndarray:
    """(rows, 2 rows, 3) native lat-long directions of the pixel centres (row 0 = up, phi from the first axis)."""
    th = np.pi * (np.arange(rows) + 0.5) / rows
    ph = 2 * np.pi * (np.arange(2 * rows) + 0.5) / (2 * rows)
    t, p = np.meshgrid(th, ph, indexing="ij")
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def sky_radiance(spec: SceneSpec, w: np.ndarray) -> np.ndarray:
    """Radiance towards z-up world directions w (..., 3): ``sun``: a dim sky (brighter towards the zenith, dimmer
    ground) plus a Gaussian sun lobe of SUN_SIGMA_DEG; ``sky``: a smooth sky brighter towards ``sky_tint``."""
    z = w[..., 2]
    if spec.light == "sun":
        sig = math.radians(SUN_SIGMA_DEG)
        peak = SUN_IRRADIANCE / (2 * math.pi * sig * sig)
        sky = SKY_RADIANCE * np.where(z > 0, 0.6 + 0.4 * z, 0.3)
        return sky + peak * np.exp((w @ np.asarray(spec.sun_direction) - 1.0) / (sig * sig))
    tint = w @ np.asarray(spec.sky_tint)
    return 2 * SKY_RADIANCE * np.maximum(0.05, 0.5 + 0.3 * z + 0.25 * tint)


def environment(spec: SceneSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(map file F (rows, 2 rows) in the file's convention, the renderer's native map, the rotation taking the
    z-up world into the renderer's frame)."""
    keys = dict(spec.env_keys)
    t = np.asarray(spec.world_rotation)
    m = documented_map_rotation(keys["up"], keys["phi0"], keys["azimuth"], keys["rotation_deg"])
    file_map = sky_radiance(spec, native_directions(spec.env_rows) @ m.T @ t)   # world z-up = T^T M n
    flip = keys["azimuth"] == "clockwise"
    m_proper = m @ np.diag([1.0, -1.0, 1.0]) if flip else m
    render_map = file_map[:, ::-1] if flip else file_map
    return file_map, np.ascontiguousarray(render_map), m_proper.T @ t


def _camera(spec: SceneSpec, rot: np.ndarray) -> Any:
    from estimation.camera import PinholeCamera

    cam = PinholeCamera.looking_at(width_px=spec.size_px, height_px=spec.size_px, fx_px=spec.fx_px(),
                                   position_mm=spec.camera_position_mm(), target_mm=spec.position_mm)
    r = np.asarray(cam.R) @ rot.T
    return PinholeCamera(cam.width_px, cam.height_px, cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px,
                         tuple(map(tuple, r.tolist())), tuple(float(x) for x in rot @ np.asarray(cam.C)))


def render_frame(spec: SceneSpec) -> dict[str, Any]:
    """The Monte Carlo frame (radiance, stderr (H, W, C), mask) and its statistics."""
    from estimation.single_image import EnvironmentMap, PointLights
    from simulators.mc import Medium, Mesh, render

    rot = np.eye(3)
    lights: list[Any] = []
    if spec.point_lights:
        p = np.array(spec.point_lights)
        lights.append(PointLights(p[:, :3], np.repeat(p[:, 3:4], len(spec.channels), axis=1)))
    else:
        _, render_map, rot = environment(spec)
        lights.append(EnvironmentMap(render_map, max_size=spec.env_rows))
    mesh = spec.mesh()
    shape = Mesh(trimesh.Trimesh(mesh.vertices @ rot.T, mesh.faces, process=False))
    media = [Medium.from_reduced(float(s), float(a), eta=spec.eta)
             for s, a in zip(spec.sigma_s_prime_per_mm, spec.sigma_a_per_mm)]
    img = render(shape, media, _camera(spec, rot), lights, spp=spec.frame_spp, seed=spec.frame_seed)
    return {"radiance": img.radiance, "stderr": img.stderr, "mask": img.mask, "seconds": img.seconds,
            "paths": int(img.mask.sum()) * spec.frame_spp * len(media), "truncated": img.truncated_fraction}


def apply_noise(spec: SceneSpec, radiance: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(image values, radiance_scale k, read noise in value units) for the scene's noise class (module docstring)."""
    obj = radiance[mask]
    if spec.noise == "mc":
        return radiance.astype(np.float32), 1.0, 0.0
    k = 0.6 / float(np.percentile(obj, 99))
    v = radiance * k
    rng = np.random.default_rng(spec.noise_seed)
    gain = spec.gain_e_per_value
    read = spec.read_noise_e / gain
    if spec.noise == "zeros":
        read = float(min(0.03, max(read, 2.0 * np.percentile(v[mask], 2))))
    raw = rng.poisson(np.maximum(v, 0) * gain) / gain + BLACK_LEVEL + rng.normal(0.0, read, v.shape)
    out = raw - BLACK_LEVEL
    if spec.noise == "zeros":
        out = np.maximum(out, 0.0)
    if spec.image_format == "png16":
        out = np.round(np.clip(out, 0.0, 1.0) * 65535.0) / 65535.0
    return out.astype(np.float32), k, read


def max_edge_mm(spec: SceneSpec) -> float:
    """Patch edge for the estimator: a third of the shortest l_d and at most 1/12 of the object's diameter (a few
    patches per face), coarser if the mesh would exceed the patch budget."""
    mesh = spec.mesh()
    edge = min(l_d_min_mm(spec.material, spec.channels) / 3, 2 * spec.bounding_radius_mm() / 12)
    while len(trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=edge)[1]) > spec.patch_budget:
        edge *= 1.2
    return round(edge, 4)


def _file_vec(t: np.ndarray, x: Any) -> list[float]:
    return [round(float(v), 6) for v in t @ np.asarray(x, float)]


def scene_doc(spec: SceneSpec, image_name: str, radiance_scale: float, read_value: float) -> dict[str, Any]:
    t = np.asarray(spec.world_rotation)
    doc: dict[str, Any] = {
        "version": 1, "name": spec.name,
        "mesh": {"path": "mesh.ply", "max_edge_mm": max_edge_mm(spec)},
        "camera": {"width_px": spec.size_px, "height_px": spec.size_px, "fx_px": round(spec.fx_px(), 6),
                   "position_mm": _file_vec(t, spec.camera_position_mm()),
                   "look_at_mm": _file_vec(t, spec.position_mm), "up": _file_vec(t, (0.0, 0.0, 1.0))},
        "image": {"path": image_name, "radiance_scale": radiance_scale, "specular_free": True},
        "material": {"eta": spec.eta},
    }
    if spec.point_lights:
        doc["point_lights"] = [{"position_mm": _file_vec(t, p[:3]), "intensity": p[3]} for p in spec.point_lights]
    else:
        doc["environment"] = {"path": "sky.exr", "max_size": 64, **dict(spec.env_keys)}
    if spec.noise_section:
        doc["noise"] = {"electrons_per_value": spec.gain_e_per_value, "read_noise": read_value}
    return doc


def content_hash(spec: SceneSpec) -> str:
    from simulators.mc._cache import sources_hash

    h = hashlib.sha256(json.dumps(spec.to_json(), sort_keys=True).encode())
    h.update(sources_hash().encode())
    h.update(_THIS.read_bytes())
    return h.hexdigest()[:16]


def build_scene(spec: SceneSpec, root: Path) -> tuple[Path, dict[str, Any]]:
    """The scene folder (rendered now, or found in the cache) and its meta data."""
    from drivers.atomic import atomic_write
    from rig.files.imageio import write_exr, write_png16

    folder = root / content_hash(spec)
    meta_path = folder / "meta.json"
    if meta_path.exists():
        meta = json.loads(meta_path.read_text())
        meta["cached"] = True
        return folder, meta
    folder.mkdir(parents=True, exist_ok=True)
    t = np.asarray(spec.world_rotation)
    mesh = spec.mesh()
    trimesh.Trimesh(mesh.vertices @ t.T, mesh.faces, process=False).export(folder / "mesh.ply")
    t0 = time.perf_counter()
    fr = render_frame(spec)
    seconds = time.perf_counter() - t0
    values, k, read = apply_noise(spec, fr["radiance"], fr["mask"])
    image_name = "image.exr" if spec.image_format == "exr" else "image.png"
    (write_exr if spec.image_format == "exr" else write_png16)(folder / image_name, values)
    if not spec.point_lights:
        write_exr(folder / "sky.exr", environment(spec)[0].astype(np.float32))
    doc = scene_doc(spec, image_name, k, read)
    atomic_write(folder / "scene.toml", lambda p: p.write_text(tomli_w.dumps(doc)))
    obj = fr["radiance"][fr["mask"]]
    vals = values[fr["mask"]]
    rel_se = fr["stderr"][fr["mask"]] / np.maximum(obj, 1e-300)
    meta = {"spec": spec.to_json(), "name": spec.name, "classes": sorted(spec.classes),
            "truth": {"sigma_s_prime_per_mm": spec.sigma_s_prime_per_mm.tolist(),
                      "sigma_a_per_mm": spec.sigma_a_per_mm.tolist()},
            "frame_spp": spec.frame_spp, "render_seconds": seconds, "paths": fr["paths"],
            "truncated_fraction": fr["truncated"], "object_pixels": int(fr["mask"].sum()),
            "radiance_scale": k, "gain_e_per_value": spec.gain_e_per_value if spec.noise != "mc" else None,
            "read_noise_value": read if spec.noise != "mc" else None, "max_edge_mm": doc["mesh"]["max_edge_mm"],
            "mc_rel_stderr_median": float(np.median(rel_se[np.isfinite(rel_se)])),
            "max_over_p99": float(obj.max() / max(np.percentile(obj, 99), 1e-300)),
            "zero_fraction": float(np.mean(vals == 0)), "unlit_faces": spec.unlit_faces,
            "max_observed_view_deg": float(np.nanmax(np.where(spec.view_angles_deg < 70, spec.view_angles_deg,
                                                              np.nan))),
            "noise_section": spec.noise_section, "cached": False}
    atomic_write(meta_path, lambda p: p.write_text(json.dumps(meta, indent=1)))
    return folder, meta


def default_root() -> Path:
    return Path(os.environ.get("SSSRIG_ZOO_DIR", _THIS.parents[1] / "out" / "zoo"))
