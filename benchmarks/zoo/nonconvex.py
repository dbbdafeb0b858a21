"""The zoo's non-convex family (issue 17 part 5): self-shadowing objects under a point light and under a sky.

Separate from the 24 drawn scenes (:func:`.scenes.draw_zoo`, seed 15, unchanged: their specs, hashes and the CI
``--quick`` subset do not move); indices from :data:`FIRST_INDEX` on, chosen by ``scene_zoo.py --family
nonconvex`` (or ``all``). The scenes are designed, not drawn: each one has a part of an observed face in the
object's own cast shadow, which is what the estimator's shadow rays (docs/visibility.md) must model.

Shapes (:func:`nonconvex_mesh`, z-up, centred on the bounding box, outward winding, coarse: the estimator subdivides
them to ``[mesh].max_edge_mm``):

- ``lblock``: :func:`simulators.scene.wall_on_slab_mesh` -- a 30 x 20 mm slab 5 mm thick with an 8 mm wall up to
  20 mm at one end; a light beyond the wall shades the slab's top;
- ``ushape``: a U-channel extruded along y: two posts ``post`` mm thick rising to ``height`` over a floor ``floor``
  mm thick, ``width`` across; a light from one side shades the channel's floor and the inner face of a post.

Frames are rendered by the Monte Carlo renderer like the other zoo scenes (benchmarks/zoo/frames.py): point lights
at eta != 1 through a non-convex mesh use its shadow-ray connections (simulators.mc.nee
``nonconvex_mesh_connections``); the sky by escaping walks (exact inter-reflection through the notch).
"""
from __future__ import annotations

import numpy as np
import trimesh

from .scenes import SceneSpec

FIRST_INDEX = 24
NONCONVEX_SHAPES = ("lblock", "ushape")
_Z_UP = (("up", "+z"), ("phi0", "+x"), ("azimuth", "counterclockwise"), ("rotation_deg", 0.0))
_EYE = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _extrude(poly: np.ndarray, cap: list[tuple[int, int, int]], depth_mm: float) -> trimesh.Trimesh:
    """The prism of the polygon ``poly`` (x, z) (K, 2) over y in +-depth/2; ``cap`` triangulates the polygon."""
    n = len(poly)
    v = np.vstack([np.c_[poly[:, 0], np.full(n, -depth_mm / 2), poly[:, 1]],
                   np.c_[poly[:, 0], np.full(n, depth_mm / 2), poly[:, 1]]])
    f = [(a, c, b) for a, b, c in cap] + [(a + n, b + n, c + n) for a, b, c in cap]
    f += [t for i in range(n) for t in ((i, (i + 1) % n, (i + 1) % n + n), (i, (i + 1) % n + n, i + n))]
    f = np.array(f)
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    if vol < 0:
        f = f[:, ::-1]
    return trimesh.Trimesh(v, f, process=True)


def u_channel_mesh(width_mm: float = 24.0, height_mm: float = 14.0, floor_mm: float = 4.0, post_mm: float = 6.0,
                   depth_mm: float = 20.0) -> trimesh.Trimesh:
    """A U-channel (x across, z up, extruded along y): floor z in [0, floor], posts x in [0, post] and
    [width - post, width] up to ``height``."""
    w, h, b, t = width_mm, height_mm, floor_mm, post_mm
    if not (0 < b < h and 0 < 2 * t < w and depth_mm > 0):
        raise ValueError("u_channel_mesh: need 0 < floor < height, 0 < 2 post < width, depth > 0")
    poly = np.array([(0, 0), (w, 0), (w, h), (w - t, h), (w - t, b), (t, b), (t, h), (0, h)], float)
    cap = [(0, 1, 4), (0, 4, 5), (0, 5, 6), (0, 6, 7), (1, 2, 3), (1, 3, 4)]
    return _extrude(poly, cap, depth_mm)


def nonconvex_mesh(shape: str, dims_mm: tuple[float, float, float]) -> trimesh.Trimesh:
    """The family's shape centred on its bounding box (before the scene's yaw and position); ``dims_mm``: the
    extents along x, y, z."""
    from simulators.scene import wall_on_slab_mesh

    lx, ly, lz = dims_mm
    if shape == "lblock":
        m = wall_on_slab_mesh(length_mm=lx, slab_mm=0.25 * lz, wall_mm=0.27 * lx, height_mm=lz, depth_mm=ly)
    elif shape == "ushape":
        m = u_channel_mesh(width_mm=lx, height_mm=lz, floor_mm=0.3 * lz, post_mm=0.25 * lx, depth_mm=ly)
    else:
        raise ValueError(f"unknown non-convex shape {shape!r}; valid: {', '.join(NONCONVEX_SHAPES)}")
    m.apply_translation(-m.bounds.mean(axis=0))
    return m


def _spec(index: int, shape: str, dims: tuple[float, float, float], light: str, material: str,
          channels: tuple[str, ...], eta: float, camera_azimuth_deg: float, camera_elevation_deg: float,
          light_azimuth_deg: float = 0.0, light_elevation_deg: float = 0.0, size_px: int = 64,
          frame_spp: int = 256) -> SceneSpec:
    pts: tuple[tuple[float, float, float, float], ...] = ()
    if light == "point1":
        d = 400.0
        a, e = np.radians(light_azimuth_deg), np.radians(light_elevation_deg)
        u = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        pts = (tuple(float(x) for x in d * u) + (d * d,),)
    return SceneSpec(
        index=index, shape=shape, size_mm=float(max(dims)), dims_mm=dims, yaw_deg=0.0,
        position_mm=(0.0, 0.0, 0.0), camera_distance_mm=300.0, camera_elevation_deg=camera_elevation_deg,
        camera_azimuth_deg=camera_azimuth_deg, size_px=size_px, light=light, point_lights=pts,
        sun_direction=(0.0, 0.0, 1.0), sky_tint=(-1.0, 0.0, 0.0), env_rows=64, env_keys=_Z_UP, world="z-up",
        world_rotation=_EYE, material=material, channels=channels, eta=eta, noise="camera", noise_section=True,
        gain_e_per_value=20000.0, read_noise_e=4.0, image_format="exr", frame_spp=frame_spp,
        frame_seed=1000 + index, noise_seed=2000 + index, patch_budget=6000)


def draw_nonconvex() -> list[SceneSpec]:
    """The non-convex family (module docstring), indices FIRST_INDEX.. in this order:

    24 L-block under a point light beyond the wall (azimuth 180 deg, elevation 50 deg: the wall shades the slab's
       top over ~2/3 of it), eta 1.3, skin1-R; camera from the slab's side;
    25 L-block under the smooth sky brighter towards -x (the wall's outer side), eta 1.3, potato-B;
    26 U-channel under a point light from +x at 55 deg: the right post shades the floor and the left post's inner
       face is lit, eta 1.5, skin1-R;
    27 U-channel under the sky, eta 1.3, skin1-R.
    """
    i = FIRST_INDEX
    return [
        _spec(i, "lblock", (30.0, 20.0, 20.0), "point1", "skin1", ("R",), 1.3, -35.0, 45.0, 180.0, 50.0),
        _spec(i + 1, "lblock", (30.0, 20.0, 20.0), "sky", "potato", ("B",), 1.3, -35.0, 45.0),
        _spec(i + 2, "ushape", (24.0, 20.0, 14.0), "point1", "skin1", ("R",), 1.5, -60.0, 55.0, 0.0, 55.0),
        _spec(i + 3, "ushape", (24.0, 20.0, 14.0), "sky", "skin1", ("R",), 1.3, -60.0, 55.0),
    ]
