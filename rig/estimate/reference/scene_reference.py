"""The Monte Carlo reference of a scene file: ``--model mc-table+reference`` (docs/scene-file.md).

:func:`scene_reference` turns a loaded :class:`rig.files.scene_spec.Scene` into a
:class:`rig.estimate.reference.mc_reference.MonteCarloReference` for :func:`estimation.model_correction.estimate_with_reference`:

- shape: the mesh as read (mm, world frame, before ``max_edge_mm`` subdivision, which only adds coplanar faces)
  as a :class:`simulators.mc.Mesh`; it must be closed (watertight) to bound a medium;
- camera: the estimator's camera (``scene.camera.model``): a pinhole, or with lens distortion a camera whose
  pixel rays pass through the *undistorted* position of every pixel centre (OpenCV's iterative undistortion,
  checked to reproject within 1e-3 px), so the render is the recorded, distorted image and is sampled at the
  same distorted patch projections as the observations — no approximation;
- lights, in the observations' units (radiance = value / radiance_scale, x2 when cross-polarized, which the
  estimator applies to the observations): point lights as given; the environment map at full resolution (the
  estimator box-downsamples it to ``max_size`` rows; that difference is a model error the correction absorbs);
  each directional light as a point light 1e6 x the object's size away with intensity E d^2 (irradiance
  uniform over the object to ~1e-6);
- pixels: ``valid_px`` = the pixels the observations could use (on the mesh, in the mask, unsaturated, finite),
  sampled with the scene's ``window_px``.

Frame. The renderer reads a lat-long map in its native convention (+z up, phi from +x towards +y). The scene
gives the map's orientation as the matrix M of :attr:`rig.files.scene_spec.EnvironmentSpec.rotation` (native -> world,
the one the estimator uses through :func:`rig.files.scene_spec.environment_directions`). Instead of resampling the
map, the whole scene (mesh, camera, lights, patch centres) is rotated into the map's frame by M^T, which is exact
and leaves every projection unchanged. A clockwise azimuth makes M a reflection; then the map's columns are
reversed (j -> W - 1 - j maps pixel centres onto pixel centres) and the remaining rotation is proper.

Point lights (and directional lights, rendered as point lights) through a refracting boundary (eta != 1) need a
convex mesh (:func:`simulators.mc.render`); a non-convex mesh is refused up front with that advice.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimation.camera import PinholeCamera
from estimation.single_image import Patches

__all__ = ["ReferenceFrame", "reference_frame", "scene_reference", "check_reference_scene"]

DIRECTIONAL_DISTANCE_FACTOR = 1e6  # directional light -> point light this many object sizes away

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ReferenceFrame:
    """World -> render frame: x_render = rotation_world_to_render @ x_world; ``flip_map_columns``: the map's
    columns are reversed (clockwise azimuth)."""

    rotation_world_to_render: Array
    flip_map_columns: bool


def reference_frame(scene: Any) -> ReferenceFrame:
    """The frame in which the scene's environment map is in the renderer's native convention (identity without
    a map). M = frame(a, +-b, up) Rz(rotation_deg); for "clockwise", M = frame(a, b, up) Rz(-rotation_deg) S with
    S = diag(1, -1, 1), i.e. the map with reversed columns seen through a proper rotation."""
    env = scene.environment
    if env is None:
        return ReferenceFrame(np.eye(3), False)
    m = np.asarray(env.rotation, float)
    flip = env.azimuth == "clockwise"
    if flip:
        m = m @ np.diag([1.0, -1.0, 1.0])  # M S: proper (S Rz(t) = Rz(-t) S)
    assert np.linalg.det(m) > 0.999
    return ReferenceFrame(m.T, flip)


def _rotate_camera(cam: Any, rot: Array) -> Any:
    """The same camera in the render frame: R' = R rot^T, C' = rot C (projections of rotated points unchanged)."""
    from rig.files.scene_spec import DistortedCamera

    pin = cam.pinhole if isinstance(cam, DistortedCamera) else cam
    r_new = np.asarray(pin.R) @ rot.T
    c_new = rot @ np.asarray(pin.C)
    pin2 = PinholeCamera(pin.width_px, pin.height_px, pin.fx_px, pin.fy_px, pin.cx_px, pin.cy_px,
                         tuple(map(tuple, r_new.tolist())), tuple(float(x) for x in c_new))
    if isinstance(cam, DistortedCamera):
        return DistortedCamera(pin2, cam.distortion, cam.max_radius)
    return pin2


def _lights(scene: Any, frame: ReferenceFrame, center_mm: Array, size_mm: float) -> list[Any]:
    from estimation.single_image import EnvironmentMap, PointLights

    rot = frame.rotation_world_to_render
    pos: list[Array] = []
    inten: list[Array] = []
    for p in scene.point_lights:
        pos.append(rot @ np.asarray(p.position_mm, float))
        inten.append(np.asarray(p.intensity, float))
    dist = DIRECTIONAL_DISTANCE_FACTOR * size_mm
    for d in scene.directional_lights:
        pos.append(rot @ (center_mm + dist * np.asarray(d.direction, float)))
        inten.append(np.asarray(d.irradiance, float) * dist ** 2)
    out: list[Any] = []
    if pos:
        out.append(PointLights(np.array(pos), np.array(inten)))
    if scene.environment is not None and scene.environment_data is not None:
        env = np.asarray(scene.environment_data, float)
        if frame.flip_map_columns:
            env = env[:, ::-1]
        out.append(EnvironmentMap(np.ascontiguousarray(env), max_size=scene.environment.max_size))
    return out


def check_reference_scene(scene: Any) -> Any:
    """Refuse what the Monte Carlo reference cannot render (:class:`rig.files.scene_spec.SceneFileError` naming the
    key); return the :class:`simulators.mc.Mesh` of the scene's surface (world frame)."""
    from simulators.mc import Mesh

    from rig.files.scene_spec import SceneFileError

    file = str(scene.path)
    mesh = scene.render_mesh_data if scene.render_mesh_data is not None else scene.mesh_data
    if not bool(mesh.is_watertight):
        raise SceneFileError(file, "mesh.path", "a closed (watertight) mesh for the model mc-table+reference: the "
                             "Monte Carlo reference needs the surface to bound the medium (close the holes, or "
                             "use model mc-table without the reference)", str(scene.mesh.path.name))
    shape = Mesh(mesh)   # point lights through any mesh at any eta (simulators.mc.nee; issue 17)
    if scene.point_lights:
        inside = shape.contains(np.array([p.position_mm for p in scene.point_lights]))
        if inside.any():
            i = int(np.flatnonzero(inside)[0])
            raise SceneFileError(file, f"point_lights[{i}].position_mm", "a light position outside the object",
                                 list(scene.point_lights[i].position_mm))
    return shape


def scene_reference(scene: Any, patches: Patches, valid_px: NDArray[np.bool_], *, spp: int,
                    spp_levels: tuple[int, ...] = ()) -> tuple[Any, dict[str, Any]]:
    """A :class:`rig.estimate.reference.mc_reference.MonteCarloReference` of the scene (module docstring) and a JSON-able
    description of what it renders (frame, lights, approximations); ``spp_levels``: its adaptive sample counts
    (ascending, ending at ``spp``; () = ``spp`` alone)."""
    import trimesh
    from simulators.mc import Mesh

    from rig.estimate.reference.mc_reference import MonteCarloReference
    from rig.files.scene_spec import DistortedCamera, SceneFileError

    check_reference_scene(scene)
    frame = reference_frame(scene)
    rot = frame.rotation_world_to_render
    mesh = scene.render_mesh_data if scene.render_mesh_data is not None else scene.mesh_data
    verts = np.asarray(mesh.vertices, float)
    rotated = trimesh.Trimesh(verts @ rot.T, np.asarray(mesh.faces), process=False)
    shape = Mesh(rotated)
    cam = _rotate_camera(scene.camera.model, rot)
    if isinstance(cam, DistortedCamera):
        try:
            cam.pixel_rays()  # checks the undistortion once, before any render
        except ValueError as exc:
            raise SceneFileError(str(scene.path), "camera.distortion", "a distortion that OpenCV can invert at "
                                 f"every pixel for the Monte Carlo reference ({exc})", list(cam.distortion)) from None
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    lights = _lights(scene, frame, 0.5 * (lo + hi), float(np.linalg.norm(hi - lo)))
    # rotated into the render frame: the world-frame shadow caster no longer fits them (only sampled here)
    pat = replace(patches, centers_mm=patches.centers_mm @ rot.T, normals=patches.normals @ rot.T, occluder=None,
                  face_index=None)
    ref = MonteCarloReference(shape, cam, lights, pat, spp=int(spp), window_px=scene.estimation.window_px,
                              valid_px=np.asarray(valid_px, bool), spp_levels=tuple(spp_levels))
    notes = []
    if scene.directional_lights:
        notes.append(f"directional lights rendered as point lights {DIRECTIONAL_DISTANCE_FACTOR:.0e} object sizes "
                     "away (irradiance uniform over the object to ~1e-6)")
    if scene.environment is not None:
        notes.append("environment map rendered at full resolution (the estimator uses it box-downsampled to "
                     f"max_size = {scene.environment.max_size} rows; the correction absorbs the difference)")
    if isinstance(cam, DistortedCamera):
        notes.append("lens distortion: rays through the undistorted pixel centres (the render is the distorted "
                     "image, sampled at the same distorted projections as the observations)")
    info = {"renderer": "simulators.mc (Monte Carlo, full light transport in the scene's mesh)",
            "spp": int(spp), "window_px": scene.estimation.window_px, "valid_pixels": int(np.sum(valid_px)),
            "mesh_faces": int(len(mesh.faces)), "convex": bool(shape.geometry().convex),
            "render_frame_rotation": rot.tolist(), "map_columns_reversed": frame.flip_map_columns,
            "notes": notes}
    return ref, info
