"""Cast shadows through scene files: ``[estimation].shadows`` and ``rig estimate single-image --shadows`` on a
non-convex mesh (an L-shaped block) whose image the simulated camera rendered with the wall's shadow."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from rig.cli import main as rig_main
from rig.files.imageio import write_exr
from rig.files.scene_file import load_scene
from rig.files.scene_spec import SceneFileError
from simulators.scene import MeshObject, render_object, wall_on_slab_mesh

SSP, SA, ETA = 2.0, 0.05, 1.3
LIGHT_MM = [-40.0, 0.0, 100.0]
INTENSITY = 2e4
CAM = dict(width_px=80, height_px=60, fx_px=100.0, position_mm=[70.0, -40.0, 80.0], look_at_mm=[18.0, 0.0, 6.0],
           up=[0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Image (fast renderer, shadows on, diffuse only), the estimator's mesh (3 mm faces) and a scene file."""
    folder = tmp_path_factory.mktemp("shadow_scene")
    cam = PinholeCamera.looking_at(width_px=CAM["width_px"], height_px=CAM["height_px"], fx_px=CAM["fx_px"],
                                   position_mm=CAM["position_mm"], target_mm=CAM["look_at_mm"], up=CAM["up"])
    obj = MeshObject(wall_on_slab_mesh(max_edge_mm=2.0, flat_shading=True), (SSP,) * 3, (SA,) * 3, ETA)
    img = render_object(obj, cam, np.array([LIGHT_MM]), np.full((1, 3), INTENSITY), Polarization.NONE,
                        include_specular=False)
    write_exr(folder / "img.exr", img.radiance[..., :1].astype(np.float32))
    wall_on_slab_mesh(max_edge_mm=3.0).export(folder / "block.ply")
    sigma = 1e-3 * float(np.median(img.radiance[img.mask, 0]))
    doc = {"version": 1, "mesh": {"path": "block.ply", "units": "mm"}, "camera": CAM,
           "image": {"path": "img.exr", "specular_free": True},
           "point_lights": [{"position_mm": LIGHT_MM, "intensity": [INTENSITY]}],
           "material": {"eta": ETA}, "noise": {"sigma": [sigma]}}
    (folder / "scene.toml").write_text(tomli_w.dumps(doc))
    (folder / "scene_off.toml").write_text(tomli_w.dumps({**doc, "estimation": {"shadows": False}}))
    (folder / "scene_bad.toml").write_text(tomli_w.dumps({**doc, "estimation": {"shadows": "yes"}}))
    return folder


def _estimate(capsys: pytest.CaptureFixture[str], scene: Path, *extra: str) -> dict[str, Any]:
    code = rig_main(["estimate", "single-image", str(scene), "--json", "--out", str(scene.with_suffix(".json")),
                     *extra])
    out, _ = capsys.readouterr()
    assert code == 0
    return json.loads(out)


def test_scene_file_shadows_on_recover_sigma_s_and_off_do_not(scene_dir: Path, capsys) -> None:
    on = _estimate(capsys, scene_dir / "scene.toml")                        # default: auto (mesh not convex)
    off = _estimate(capsys, scene_dir / "scene.toml", "--shadows", "off")
    off_file = _estimate(capsys, scene_dir / "scene_off.toml")
    assert on["observations"]["cast_shadows"] is True and on["scene"]["estimation"]["shadows"] == "auto"
    assert off["observations"]["cast_shadows"] is False and off_file["observations"]["cast_shadows"] is False
    err = {k: r["parameters"]["sigma_s_prime_per_mm"]["value"][0] / SSP - 1.0
           for k, r in (("on", on), ("off", off), ("off_file", off_file))}
    with capsys.disabled():
        print(f"\nscene file, sigma_s' error: shadows on {err['on']:+.1%}, off {err['off']:+.1%}")
    assert abs(err["on"]) < 0.05
    assert abs(err["off"]) > 0.15 and err["off_file"] == err["off"]
    forced = _estimate(capsys, scene_dir / "scene_off.toml", "--shadows", "on")   # the flag beats the file
    assert forced["observations"]["cast_shadows"] is True
    assert forced["parameters"]["sigma_s_prime_per_mm"]["value"] == on["parameters"]["sigma_s_prime_per_mm"]["value"]


def test_bad_shadows_key_names_file_and_field(scene_dir: Path) -> None:
    with pytest.raises(SceneFileError) as ei:
        load_scene(scene_dir / "scene_bad.toml")
    msg = str(ei.value)
    assert "scene_bad.toml" in msg and "'estimation.shadows'" in msg and '"auto", true or false' in msg
    assert len(msg.splitlines()) == 1
