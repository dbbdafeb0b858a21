"""Patch decimation through scene files (issue 17): ``[estimation].patches`` and ``rig estimate single-image
--patches`` on a non-convex 5k-face mesh (a sphere with a crater) rendered by the fast simulated camera: patches
from a decimated copy, visibility, the pixel map and cast shadows on the full mesh."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from estimation.shadows import point_light_visibility
from estimation.single_image import decimate_mesh, patches_from_decimated
from rig.cli import main as rig_main
from rig.imageio import write_exr
from rig.scene_file import load_scene
from rig.scene_spec import AUTO_PATCHES, SceneFileError, resolve_patches
from simulators.scene import MeshObject, render_object

SSP, SA, ETA = 2.0, 0.005, 1.3
RADIUS_MM = 15.0
LIGHT_MM = [-60.0, -90.0, 70.0]
INTENSITY = 2e4
CAM = dict(width_px=128, height_px=96, fx_px=150.0, position_mm=[20.0, -80.0, 40.0], look_at_mm=[0.0, 0.0, 0.0],
           up=[0.0, 0.0, 1.0])
PATCHES = 512


def crater_mesh(subdivisions: int = 4) -> trimesh.Trimesh:
    """An icosphere (radius 15 mm; 5,120 faces at 4 subdivisions) with a Gaussian pit 0.4 R deep facing the camera
    and the light: concave, it shadows itself."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    u = np.asarray(s.vertices)
    axis = np.array([-0.2, -1.0, 0.45])
    axis /= np.linalg.norm(axis)
    ang = np.arccos(np.clip(u @ axis, -1, 1))
    r = 1.0 - 0.4 * np.exp(-(ang / 0.4) ** 2)
    return trimesh.Trimesh(u * r[:, None] * RADIUS_MM, s.faces, process=False)


def _toml(doc: dict[str, Any]) -> str:
    def val(v: Any) -> str:
        return json.dumps(v) if not isinstance(v, bool) else ("true" if v else "false")
    lines = [f"{k} = {val(v)}" for k, v in doc.items() if not isinstance(v, (dict, list))]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines += [f"\n[{k}]"] + [f"{kk} = {val(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list):
            for item in v:
                lines += [f"\n[[{k}]]"] + [f"{kk} = {val(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Image (fast renderer, shadows on, diffuse only), the 20k-face mesh and scene files."""
    folder = tmp_path_factory.mktemp("decimation_scene")
    cam = PinholeCamera.looking_at(width_px=CAM["width_px"], height_px=CAM["height_px"], fx_px=CAM["fx_px"],
                                   position_mm=CAM["position_mm"], target_mm=CAM["look_at_mm"], up=CAM["up"])
    mesh = crater_mesh()
    obj = MeshObject(mesh, (SSP,) * 3, (SA,) * 3, ETA)
    img = render_object(obj, cam, np.array([LIGHT_MM]), np.full((1, 3), INTENSITY), Polarization.NONE,
                        include_specular=False)
    write_exr(folder / "img.exr", img.radiance[..., :1].astype(np.float32))
    mesh.export(folder / "crater.ply")
    sigma = 1e-3 * float(np.median(img.radiance[img.mask, 0]))
    doc = {"version": 1, "mesh": {"path": "crater.ply", "units": "mm"}, "camera": CAM,
           "image": {"path": "img.exr", "specular_free": True},
           "point_lights": [{"position_mm": LIGHT_MM, "intensity": [INTENSITY]}],
           "material": {"eta": ETA}, "noise": {"sigma": [sigma]}}
    (folder / "full.toml").write_text(_toml({**doc, "estimation": {}}))
    (folder / "decimated.toml").write_text(_toml({**doc, "estimation": {"patches": PATCHES}}))
    for name, est in (("zero", {"patches": 0}), ("negative", {"patches": -5}), ("many", {"patches": 6000}),
                      ("text", {"patches": "lots"}), ("typo", {"patchs": 512})):
        (folder / f"bad_{name}.toml").write_text(_toml({**doc, "estimation": est}))
    return folder


def _estimate(capsys: pytest.CaptureFixture[str], scene: Path, *extra: str) -> dict[str, Any]:
    code = rig_main(["estimate", "single-image", str(scene), "--json", "--out", str(scene.with_suffix(".json")),
                     *extra])
    out, _ = capsys.readouterr()
    assert code == 0
    return json.loads(out)
