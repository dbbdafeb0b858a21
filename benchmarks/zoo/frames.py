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

The frame rule (``camera`` / ``zeros``, :func:`frame_spp_needed`): these classes claim the camera's noise and
nothing else, so the frame's own Monte Carlo noise must be well below it. The ``frame_spp`` render is a pilot; from
the renderer's per-pixel standard error (``MCImage.stderr``, scaled by k) and the camera's sd at the pilot's values
(sqrt(v / g + r^2)) the spp is raised so that the Monte Carlo sd is at most 1/3 of the camera sd at 95 % of the
object's pixel-channels (stderr ~ 1/sqrt(spp); a multiple of the pilot spp, at most 16x under a sky, 4x under a
sun — whose pilot is already 1024 spp —, 2x under point lights: :data:`MAX_SPP_FACTOR`, the zoo's cost), and a
second render adds the missing paths (seed ``frame_seed`` + 500). At 1/3 the Monte Carlo part adds at most ~5 % to
the noise sd the scene file states. Where the cap binds (the rule holds at < 95 % of the pixel-channels) and the
scene has a ``[noise]`` section, the section is a ``stderr_path`` image instead (:func:`stated_stderr`: the camera
part from the observed values, as ``electrons_per_value`` + ``read_noise`` would give it, plus k x the renderer's
stderr), so that every stated noise is the frame's noise; without a section the estimator fits the noise to the
image (docs/scene-file.md). ``meta.json`` records the spp rendered and the achieved ratio (median, 95th percentile, the
fraction of pixel-channels within 1/3). The ``mc`` class keeps its 32-spp frame (heavy tails by design).
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
MC_SD_RATIO = 1.0 / 3.0     # frame rule: Monte Carlo sd <= this x the camera sd ...
MC_SD_QUANTILE = 0.95       # ... at this fraction of the object's pixel-channels
#: ... rendering at most this x the pilot's spp, by light (beyond it the scene file states the rest, module docstring):
#: the zoo's cost on 2 shared cores. Measured per collision (32-spp renders, 1 thread): sky 0.7-1.0 us, sun 2.6-3.9
#: us, point lights 1.9-4.4 us (the refracted connections); a 256-spp point-lit pilot takes 2.5-93 s (z18), the
#: sun's 1024-spp pilots 6-36 s, a sky's 2-5 s
MAX_SPP_FACTOR = {"sky": 16, "sun": 4, "point1": 2, "point2": 2}
TOP_UP_SEED_OFFSET = 500    # seed of the frame's second render: frame_seed + this (frame seeds are 1000 + index)
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
    """The Monte Carlo frame (radiance, stderr (H, W, C), mask) and its statistics. ``camera`` / ``zeros``: rendered
    until the frame's Monte Carlo noise is below the camera's (:func:`frame_spp_needed`, module docstring): the
    ``frame_spp`` render is the pilot, a second render (seed ``frame_seed`` + :data:`TOP_UP_SEED_OFFSET`) adds the
    missing paths and the two are averaged with weights spp / total."""
    from simulators.mc import render

    shape, media, camera, lights = _render_setup(spec)
    img = render(shape, media, camera, lights, spp=spec.frame_spp, seed=spec.frame_seed)
    rad, se, seconds, trunc = img.radiance, img.stderr, img.seconds, img.truncated_fraction
    spp = spec.frame_spp
    needed = frame_spp_needed(spec, rad, se, img.mask)
    if needed > spp:
        extra = needed - spp
        top = render(shape, media, camera, lights, spp=extra, seed=spec.frame_seed + TOP_UP_SEED_OFFSET)
        w = spp / needed
        rad = w * rad + (1 - w) * top.radiance
        se = np.sqrt(np.square(w * se) + np.square((1 - w) * top.stderr))
        seconds += top.seconds
        trunc = w * trunc + (1 - w) * top.truncated_fraction
        spp = needed
    return {"radiance": rad, "stderr": se, "mask": img.mask, "seconds": seconds, "spp": spp,
            "pilot_spp": spec.frame_spp, "paths": int(img.mask.sum()) * spp * len(media), "truncated": trunc}


def _render_setup(spec: SceneSpec) -> tuple[Any, list[Any], Any, list[Any]]:
    """(shape, media, camera, lights) of the frame render (module docstring)."""
    from estimation.single_image import EnvironmentMap, PointLights
    from simulators.mc import Medium, Mesh

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
    return shape, media, _camera(spec, rot), lights


def noise_levels(spec: SceneSpec, radiance: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """(radiance_scale k, gain g in electrons per value, read noise r in value units) of the ``camera`` /
    ``zeros`` classes (module docstring), from the frame's radiance."""
    k = 0.6 / float(np.percentile(radiance[mask], 99))
    gain = spec.gain_e_per_value
    read = spec.read_noise_e / gain
    if spec.noise == "zeros":
        read = float(min(0.03, max(read, 2.0 * np.percentile(radiance[mask] * k, 2))))
    return k, gain, read


def camera_sd(values: np.ndarray, gain: float, read: float) -> np.ndarray:
    """The camera's standard deviation at noise-free values v: sqrt(max(v, 0) / g + r^2) (value units)."""
    return np.sqrt(np.maximum(values, 0.0) / gain + read * read)


def mc_to_camera_sd(spec: SceneSpec, radiance: np.ndarray, stderr: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per object pixel and channel: the frame's Monte Carlo standard error over the camera's standard deviation
    (both in value units; the renderer's own per-pixel stderr, :class:`simulators.mc.render.MCImage`)."""
    k, gain, read = noise_levels(spec, radiance, mask)
    return (k * stderr[mask]) / camera_sd(k * radiance[mask], gain, read)


def frame_spp_needed(spec: SceneSpec, radiance: np.ndarray, stderr: np.ndarray, mask: np.ndarray) -> int:
    """The frame rule (module docstring): the spp at which the Monte Carlo sd is at most :data:`MC_SD_RATIO` of
    the camera sd at :data:`MC_SD_QUANTILE` of the object's pixel-channels, from a pilot render at
    ``spec.frame_spp`` (stderr ~ 1/sqrt(spp)); rounded up to a multiple of the pilot spp and capped at
    :data:`MAX_SPP_FACTOR` [light] x the pilot. The pilot's spp for the ``mc`` class, and when ``spec.frame_rule`` is off."""
    if spec.noise == "mc" or not spec.frame_rule:
        return spec.frame_spp
    ratio = mc_to_camera_sd(spec, radiance, stderr, mask)
    q = float(np.quantile(ratio[np.isfinite(ratio)], MC_SD_QUANTILE))
    factor = min(MAX_SPP_FACTOR[spec.light], max(1, math.ceil((q / MC_SD_RATIO) ** 2)))
    return spec.frame_spp * factor


def apply_noise(spec: SceneSpec, radiance: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(image values, radiance_scale k, read noise in value units) for the scene's noise class (module docstring)."""
    if spec.noise == "mc":
        return radiance.astype(np.float32), 1.0, 0.0
    k, gain, read = noise_levels(spec, radiance, mask)
    v = radiance * k
    rng = np.random.default_rng(spec.noise_seed)
    raw = rng.poisson(np.maximum(v, 0) * gain) / gain + BLACK_LEVEL + rng.normal(0.0, read, v.shape)
    out = raw - BLACK_LEVEL
    if spec.noise == "zeros":
        out = np.maximum(out, 0.0)
    if spec.image_format == "png16":
        out = np.round(np.clip(out, 0.0, 1.0) * 65535.0) / 65535.0
    return out.astype(np.float32), k, read


def stated_stderr(values: np.ndarray, mc_sd_values: np.ndarray, gain: float, read: float) -> np.ndarray:
    """The ``[noise] stderr_path`` image of a frame whose Monte Carlo noise is not negligible (value units):
    sqrt(max(value, 0) / g + r^2 + mc_sd^2) — the camera part exactly as ``electrons_per_value`` + ``read_noise``
    would state it from the observed values (docs/scene-file.md), plus the renderer's own standard error x k."""
    return np.sqrt(np.maximum(values, 0.0) / gain + read * read + np.square(mc_sd_values)).astype(np.float32)


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


def scene_doc(spec: SceneSpec, image_name: str, radiance_scale: float, read_value: float,
              stderr_name: str | None = None) -> dict[str, Any]:
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
    if spec.noise_section and stderr_name is not None:
        doc["noise"] = {"stderr_path": stderr_name}
    elif spec.noise_section:
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
    ratio = None if spec.noise == "mc" else mc_to_camera_sd(spec, fr["radiance"], fr["stderr"], fr["mask"])
    ratio = None if ratio is None else ratio[np.isfinite(ratio)]
    rule_met = ratio is None or float(np.mean(ratio <= MC_SD_RATIO)) >= MC_SD_QUANTILE
    stderr_name = None
    if spec.noise_section and not rule_met:   # the frame still carries Monte Carlo noise: state all of it
        stderr_name = "stderr.exr"
        write_exr(folder / stderr_name, stated_stderr(values, k * fr["stderr"], spec.gain_e_per_value, read))
    if not spec.point_lights:
        write_exr(folder / "sky.exr", environment(spec)[0].astype(np.float32))
    doc = scene_doc(spec, image_name, k, read, stderr_name)
    atomic_write(folder / "scene.toml", lambda p: p.write_text(tomli_w.dumps(doc)))
    obj = fr["radiance"][fr["mask"]]
    vals = values[fr["mask"]]
    rel_se = fr["stderr"][fr["mask"]] / np.maximum(obj, 1e-300)
    meta = {"spec": spec.to_json(), "name": spec.name, "classes": sorted(spec.classes),
            "truth": {"sigma_s_prime_per_mm": spec.sigma_s_prime_per_mm.tolist(),
                      "sigma_a_per_mm": spec.sigma_a_per_mm.tolist()},
            "frame_spp": spec.frame_spp, "frame_spp_rendered": fr["spp"], "render_seconds": seconds,
            "mc_over_camera_sd": None if ratio is None else
            {"median": float(np.median(ratio)), "p95": float(np.quantile(ratio, MC_SD_QUANTILE)),
             "fraction_within_rule": float(np.mean(ratio <= MC_SD_RATIO))},
            "noise_stated": None if not spec.noise_section else
            ("stderr image: camera + Monte Carlo" if stderr_name else "camera: electrons_per_value + read_noise"), "paths": fr["paths"],
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
