"""Patch decimation through scene files (issue 17): ``[estimation].patches`` and ``rig estimate single-image
--patches`` on a non-convex 5k-face mesh (a sphere with a crater) rendered by the fast simulated camera: patches
from a decimated copy, visibility, the pixel map and cast shadows on the full mesh."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
import trimesh

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from estimation.shadows import point_light_visibility
from estimation.single_image import decimate_mesh, patches_from_decimated
from rig.cli import main as rig_main
from rig.files.imageio import write_exr
from rig.files.scene_file import load_scene
from rig.files.scene_spec import AUTO_PATCHES, SceneFileError, resolve_patches
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
    (folder / "full.toml").write_text(tomli_w.dumps({**doc, "estimation": {}}))
    (folder / "decimated.toml").write_text(tomli_w.dumps({**doc, "estimation": {"patches": PATCHES}}))
    for name, est in (("zero", {"patches": 0}), ("negative", {"patches": -5}), ("many", {"patches": 6000}),
                      ("text", {"patches": "lots"}), ("typo", {"patchs": 512})):
        (folder / f"bad_{name}.toml").write_text(tomli_w.dumps({**doc, "estimation": est}))
    return folder


def _estimate(capsys: pytest.CaptureFixture[str], scene: Path, *extra: str) -> dict[str, Any]:
    code = rig_main(["estimate", "single-image", str(scene), "--json", "--out", str(scene.with_suffix(".json")),
                     *extra])
    out, _ = capsys.readouterr()
    assert code == 0
    return json.loads(out)


def test_decimated_estimate_recovers_sigma_s_and_matches_the_full_mesh(scene_dir: Path, capsys) -> None:
    full = _estimate(capsys, scene_dir / "full.toml")                      # patches = auto: one per face
    dec = _estimate(capsys, scene_dir / "full.toml", "--patches", str(PATCHES))    # the flag beats the file
    assert load_scene(scene_dir / "decimated.toml").estimation.patches == PATCHES  # (the key: as the flag)
    d_full, d_dec = full["observations"]["patch_decimation"], dec["observations"]["patch_decimation"]
    assert d_full["decimated"] is False and "one patch per face" in d_full["reason"]
    assert full["observations"]["patches"] == 5120
    assert d_dec["decimated"] is True and d_dec["mesh_faces"] == 5120
    assert abs(dec["observations"]["patches"] - PATCHES) <= 0.02 * PATCHES
    assert dec["observations"]["cast_shadows"] is True and full["observations"]["cast_shadows"] is True
    assert d_dec["not_snapped"] <= 0.01 * PATCHES and d_dec["deviation_mm_p99"] < 0.05 * RADIUS_MM
    assert dec["observations"]["observed_per_channel"][0] >= 100
    assert "decimation" in dec["seconds_by_stage"] and "fit" in dec["seconds_by_stage"]
    ssp = {k: r["parameters"]["sigma_s_prime_per_mm"]["value"][0] for k, r in (("full", full), ("dec", dec))}
    with capsys.disabled():
        print(f"\ncrater, sigma_s' error: full mesh ({full['observations']['patches']} patches) "
              f"{ssp['full'] / SSP - 1:+.1%}, decimated ({dec['observations']['patches']}) {ssp['dec'] / SSP - 1:+.1%}")
    assert abs(ssp["full"] / SSP - 1) < 0.03
    assert abs(ssp["dec"] / SSP - 1) < 0.05                   # stated tolerance of the decimated estimate
    assert abs(ssp["dec"] / ssp["full"] - 1) < 0.03           # and its distance from the undecimated one


@pytest.mark.parametrize("name, words", [("zero", "an integer >= 10"), ("negative", "an integer >= 10"),
                                         ("many", "at most the mesh's face count (5120 faces)"),
                                         ("text", '"auto" or an integer'), ("typo", "a known key")])
def test_bad_patches_names_file_and_field(scene_dir: Path, name: str, words: str) -> None:
    with pytest.raises(SceneFileError) as ei:
        load_scene(scene_dir / f"bad_{name}.toml")
    msg = str(ei.value)
    key = "estimation.patchs" if name == "typo" else "estimation.patches"
    assert f"bad_{name}.toml" in msg and f"'{key}'" in msg and words in msg, msg
    assert len(msg.splitlines()) == 1


def test_bad_patches_flag_names_the_field(scene_dir: Path, capsys) -> None:
    code = rig_main(["estimate", "single-image", str(scene_dir / "full.toml"), "--patches", "0",
                     "--out", str(scene_dir / "flag.json")])
    err = capsys.readouterr().err
    assert code == 2 and "full.toml" in err and "estimation.patches (--patches)" in err and ">= 10" in err
    assert rig_main(["estimate", "single-image", str(scene_dir / "full.toml"), "--patches", "lots"]) == 2
    assert "expected 'auto' or an integer" in capsys.readouterr().err


def test_auto_patch_budget() -> None:
    target, why = resolve_patches("auto", 102_400, 20_000)
    assert target == AUTO_PATCHES and "decimated to 10000" in why
    assert resolve_patches("auto", 5_000, 20_000)[0] is None
    assert resolve_patches("auto", 30_000, 4_000)[0] == 4_000          # never above max_patches
    assert resolve_patches(5_000, 5_000, 20_000)[0] is None            # as many patches as faces: the mesh itself


def test_decimated_patches_on_the_full_surface_are_not_self_shadowed() -> None:
    """A decimated sphere's faces are chords, inside the full sphere: shadow rays from their own centres are all
    blocked by the full surface. Moved onto it (snap_to_surface), no patch facing the light is shadowed."""
    cam = PinholeCamera.looking_at(width_px=64, height_px=48, fx_px=80.0, position_mm=[0.0, -80.0, 30.0],
                                   target_mm=[0.0, 0.0, 0.0])
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_MM)
    dec = patches_from_decimated(sphere, decimate_mesh(sphere, 512), cam, shadows=True)
    p = dec.patches
    light = np.array([[60.0, -40.0, 50.0]])
    to_light = light[0] - p.centers_mm
    cos_l = np.einsum("kc,kc->k", to_light / np.linalg.norm(to_light, axis=1, keepdims=True), p.normals)
    lit = cos_l > 0.1
    vis = point_light_visibility(p.occluder, p.centers_mm, p.normals, light, own_face=p.face_index)[:, 0]
    chord_centres = np.asarray(decimate_mesh(sphere, 512).triangles_center)
    naive = point_light_visibility(p.occluder, chord_centres, p.normals, light)[:, 0]
    assert dec.snapped.all() and lit.sum() > 100
    assert np.sum(~vis & lit) == 0
    assert np.mean(~naive[lit]) > 0.5                # what the snapping prevents
    assert dec.deviation_mm.max() < 0.02 * RADIUS_MM


def test_decimated_shadows_agree_with_the_full_mesh() -> None:
    """On the crater mesh the point light's shadow at each decimated patch centre equals the full mesh's own
    shadow at the face under it (patches whose light is not grazing)."""
    cam = PinholeCamera.looking_at(width_px=64, height_px=48, fx_px=80.0, position_mm=CAM["position_mm"],
                                   target_mm=CAM["look_at_mm"])
    mesh = crater_mesh()
    dec = patches_from_decimated(mesh, decimate_mesh(mesh, PATCHES), cam, shadows=True)
    p = dec.patches
    light = np.array([LIGHT_MM])
    vis = point_light_visibility(p.occluder, p.centers_mm, p.normals, light, own_face=p.face_index)[:, 0]
    f = np.maximum(p.face_index, 0)
    fn = np.asarray(mesh.face_normals)[f]
    full = point_light_visibility(p.occluder, np.asarray(mesh.triangles_center)[f], fn, light, own_face=f)[:, 0]
    to_light = light[0] - p.centers_mm
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    clear = (np.abs(np.einsum("kc,kc->k", to_light, p.normals)) > 0.15) & dec.snapped
    shadowed = ~full & clear
    assert shadowed.sum() > 20                                        # the crater does cast a shadow
    assert np.mean(vis[clear] == full[clear]) > 0.97


def test_gather_patch_pixels_evaluates_the_plane_at_the_centre() -> None:
    """A radiance linear along the surface: the plane through a patch's pixels gives the value at the patch centre
    exactly, where their mean (at the pixels' centroid) would not; too few pixels give NaN, collinear ones the
    mean."""
    h, w = 20, 24
    v, u = np.mgrid[0:h, 0:w].astype(float)
    points = np.stack([0.1 * u, 0.1 * v, np.zeros_like(u)], axis=-1)
    face = np.zeros((h, w), np.int32)                      # patch 0: the 20 x 20 block
    face[:, 20:] = -1
    face[0, 20:23] = 1                                     # patch 1: 3 pixels
    face[8:17, 22] = 2                                     # patch 2: 9 pixels in a column: collinear
    img = (2.0 + 3.0 * points[..., 0] + 1.0 * points[..., 1])[..., None]
    var = np.full_like(img, 0.01)
    valid = face[..., None] >= 0
    centers = np.array([[0.5, 0.6, 0.0], [2.1, 0.0, 0.0], [2.0, 1.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    from estimation.single_image import gather_patch_pixels

    obs, sig, n = gather_patch_pixels(img, var, valid, face, np.array([0, 1, 2]), points, centers, normals)
    assert n[:, 0].tolist() == [400, 3, 9]
    assert obs[0, 0] == pytest.approx(2.0 + 1.5 + 0.6, abs=1e-9)          # not the mean over the block (5.8)
    assert np.mean(img[:, :20]) == pytest.approx(5.8)
    assert 0.1 / 20 < sig[0, 0] < 0.1                     # between sigma / sqrt(400) and one pixel's sigma
    assert np.isnan(obs[1, 0]) and np.isnan(sig[1, 0])
    sel = face == 2
    assert obs[2, 0] == pytest.approx(float(np.mean(img[sel, 0])))         # no plane through a line: the mean
    assert obs[2, 0] != pytest.approx(2.0 + 3.0 * 2.0 + 1.0 * 1.0)
