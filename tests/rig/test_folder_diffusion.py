"""Diffusion maps of surfaces other than a known sphere through ``rig estimate gradients`` (issue 16).

Frames: ``tests/data/relief_skin1`` -- Monte Carlo frames (the project's renderer, not the estimator's model) of a
skin1 slab (science.md sec. 2, eta 1.3) with a random relief of 1.5-6 mm wavelengths and RMS slope 0.1, 64 x 64
px of 0.2 mm, orthographic, 128 spp, both polarizations, written by ``tests/data/make_relief_capture.py`` (19 min
of Monte Carlo on a shared core: cached, not rendered here). Truth l_d = 3.673 / 1.367 / 0.683 mm,
D = 0.432 / 0.317 / 0.224 mm.

Measured (one 64-px window = the whole 12.8 mm map; specular normals as the true ones):
l_d 31.9 / 1.23 / 0.82 mm (+768 / -10 / +20 %), every channel "weak" with intervals that cover the truth
([1.6, 131], [0.43, 51], [0.30, 3.2] mm). Red's l_d (3.7 mm) exceeds what a 3.2 mm margin can hold, and its
interval says so. With the true normals (normals_file): G / B -8 / +21 %.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from rig.estimate.capture_folder import load_capture
from rig.cli import main
from rig.files.imageio import read_image, write_exr

DATA = Path(__file__).resolve().parents[1] / "data" / "relief_skin1"
SSP, SA = np.array([0.74, 0.88, 1.01]), np.array([0.032, 0.17, 0.48])
L_D = 1 / np.sqrt(3 * SA * (SSP + SA))
D = 1 / (3 * (SSP + SA))


def _copy(tmp_path: Path, extra: str = "") -> Path:
    f = tmp_path / "relief"
    shutil.copytree(DATA, f)
    if extra:
        (f / "capture.toml").write_text((f / "capture.toml").read_text() + "\n" + extra)
    return f


def _run(folder: Path, capsys, *extra: str) -> dict:
    import json
    assert main(["estimate", "gradients", str(folder), "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def _covers(d: dict, k: str, truth: np.ndarray) -> np.ndarray:
    iv = np.asarray(d[k]["interval"], dtype=float)
    return (iv[:, 0] <= truth) & (truth <= iv[:, 1])


def test_relief_slab_unknown_shape_uses_the_specular_normals(tmp_path, capsys) -> None:
    s = _run(_copy(tmp_path), capsys)
    d = s["diffusion"]
    assert d["true_normals"].startswith("specular normals") and d["window_px"] == 64
    assert "unknown" not in d["status"]
    for k, t in (("l_d_mm", L_D), ("D_mm", D)):
        assert _covers(d, k, t).all(), (k, d[k])
    l_d = np.asarray(d["l_d_mm"]["value"])
    assert np.all(np.abs(l_d[1:] / L_D[1:] - 1) < 0.25), l_d          # measured -10 / +20 %
    assert l_d[0] > l_d[1] > l_d[2]                                      # the channel order
    # red's l_d does not fit in the window's margin: the interval is wide and the status weak, not a number
    lo, hi = d["l_d_mm"]["interval"][0]
    assert hi / lo > 10 and d["status"][0] == "weak"
    # the window maps and the status map are written; the apparent albedo sits below R_d by F_t E_t/E
    for name in ("relief_l_d_mm", "relief_l_d_mm_lo", "relief_l_d_mm_hi", "relief_D_mm", "relief_status",
                 "relief_sigma_a_per_mm", "relief_sigma_s_prime_per_mm", "albedo_apparent"):
        assert Path(s["files"][name]).is_file(), name
    st, _ = read_image(Path(s["files"]["relief_status"]))
    assert set(np.unique(st[np.isfinite(st)])) <= {0.0, 1.0, 2.0}
    ratio = np.asarray(s["maps"]["albedo_apparent_median"]) / np.asarray(s["maps"]["R_d_median"])
    assert np.all((ratio > 0.88) & (ratio < 0.95)), ratio              # ~0.983 x 0.939 head-on at eta 1.3


def test_the_seed_beside_the_relief_fit_with_a_disagreement_map(tmp_path, capsys) -> None:
    """Issue 16: the seed's D = k R_d / |n_z| beside the relief fit, and a map of where they disagree. A k that
    reproduces the fitted D agrees in the lit channels; the same k x 20 disagrees in every compared window."""
    s0 = _run(_copy(tmp_path / "a"), capsys)
    d0 = s0["diffusion"]
    k_fit = np.asarray(d0["D_mm"]["value"]) / np.asarray(s0["maps"]["R_d_median"])
    for scale, agree in ((1.0, True), (20.0, False)):
        k = ", ".join(f"{x:.6g}" for x in k_fit * scale)
        s = _run(_copy(tmp_path / f"k{scale:g}", f"[seed]\nk_mm = [{k}]\nprovenance = \"test: k from the fit\"\n"),
                 capsys)
        v = s["seed"]["versus_relief"]
        assert min(v["windows_compared"]) > 0
        frac, ratio = np.asarray(v["fraction_disagree"]), np.asarray(v["median_ratio"])
        if agree:
            assert np.all(frac[1:] < 0.5) and np.all(np.abs(ratio[1:] - 1) < 0.3), v
        else:       # disagree wherever 20 x the fitted D lies outside the (wider) region interval of the fit
            lo, hi = np.asarray(d0["D_mm"]["interval"], dtype=float).T
            outside = 20 * np.asarray(d0["D_mm"]["value"]) > hi
            assert outside.any() and np.all(frac[outside] == 1.0) and np.all(ratio > 5), (v, hi)
        flag, _ = read_image(Path(s["files"]["relief_D_seed_disagree"]))
        assert set(np.unique(flag[np.isfinite(flag)])) <= {0.0, 1.0}
        assert np.nanmean(flag) == pytest.approx(float(np.mean(frac)), abs=0.35)
        assert Path(s["files"]["relief_D_seed_ratio"]).is_file()


def test_relief_slab_with_a_normals_file_and_a_smaller_window(tmp_path, capsys) -> None:
    folder = _copy(tmp_path, '[object]\nshape = "relief"\nnormals_file = "true_normals.npy"\n')
    s = _run(folder, capsys, "--relief-window-px", "32")
    d = s["diffusion"]
    assert d["true_normals"].startswith("normals_file") and d["windows"] == [2, 2]
    assert sum(d["window_status"]["unknown"]) == 0
    assert _covers(d, "D_mm", D).all() and _covers(d, "l_d_mm", L_D).all()


def test_a_flat_height_field_gives_unknown_with_a_wide_interval(tmp_path, capsys) -> None:
    """No relief in the given geometry: no information about a length -> unknown, never a narrow number."""
    folder = _copy(tmp_path, '[object]\nshape = "relief"\nheight_file = "flat.npy"\n')
    np.save(folder / "flat.npy", np.zeros((64, 64)))
    d = _run(folder, capsys)["diffusion"]
    assert d["status"] == ["unknown"] * 3
    assert all(v is None for v in d["l_d_mm"]["value"])
    for lo, hi in d["D_mm"]["interval"]:
        assert hi is None or hi / max(lo, 1e-9) > 100


@pytest.mark.parametrize("extra,key,expected", [
    ('shape = "relief"\nnormals_file = "bad.npy"\n', "object.normals_file", "(64, 64, 3)"),
    ('shape = "relief"\n', "object.normals_file", "exactly one of normals_file"),
    ('shape = "sphere"\ncenter_mm = [0, 0, 0]\nradius_mm = 5\nnormals_file = "bad.npy"\n', "object.normals_file",
     "nothing unless shape"),
])
def test_bad_relief_geometry_names_file_and_key(tmp_path, capsys, extra, key, expected) -> None:
    folder = _copy(tmp_path, "[object]\n" + extra)
    np.save(folder / "bad.npy", np.zeros((10, 10, 3)))
    assert main(["estimate", "gradients", str(folder)]) == 2
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if "error" in ln]   # one line, not progress
    assert len(err) == 1 and str(folder / "capture.toml") in err[0] and f"'{key}'" in err[0] and expected in err[0]


def test_height_file_needs_an_orthographic_camera(tmp_path, capsys) -> None:
    folder = _copy(tmp_path, '[object]\nshape = "relief"\nheight_file = "h.npy"\n')
    np.save(folder / "h.npy", np.zeros((64, 64)))
    t = (folder / "capture.toml").read_text()
    t = t.replace('model = "orthographic"\npixel_size_mm = 0.2\nlook_direction = [0.0, 1.0, 0.0]',
                  'model = "pinhole"\nfx_px = 10000.0\nposition_mm = [0.0, -2000.0, 0.0]\nlook_at_mm = [0, 0, 0]')
    (folder / "capture.toml").write_text(t)
    assert main(["estimate", "gradients", str(folder)]) == 2
    assert "'object.height_file'" in capsys.readouterr().err


def test_look_direction_along_z_needs_no_up(tmp_path) -> None:
    """Issue 16: look_direction = [0, 0, -1] alone used to fail on a default up = +z the user never wrote."""
    folder = _copy(tmp_path)
    p = folder / "capture.toml"
    p.write_text(p.read_text().replace("look_direction = [0.0, 1.0, 0.0]", "look_direction = [0.0, 0.0, -1.0]"))
    cap = load_capture(folder)
    np.testing.assert_allclose(cap.camera.R[2], [0.0, 0.0, -1.0], atol=1e-12)
    p.write_text(p.read_text().replace("look_direction = [0.0, 0.0, -1.0]",
                                       "look_direction = [0.0, 0.0, -1.0]\nup = [0.0, 0.0, 1.0]"))
    with pytest.raises(Exception, match="camera.up"):       # an explicit parallel up is still an error
        load_capture(folder)


def test_a_dark_channel_in_float_frames_is_unknown(tmp_path, capsys) -> None:
    """Float HDR frames with dark_level = 0: the blue channel scaled to 1e-4 of its signal plus noise of ~2x the
    remaining signal. The per-pixel test alone would keep its noise-high pixels and report an albedo; the channel
    must be unknown (and the other channels unaffected)."""
    folder = _copy(tmp_path)
    rng = np.random.default_rng(3)
    for f in sorted((folder / "frames").glob("*.exr")):
        img, _ = read_image(f)
        img = np.array(img, dtype=np.float32)
        img[..., 2] = img[..., 2] * 1e-4 + rng.normal(0.0, 2e-5, img.shape[:2]).astype(np.float32)
        write_exr(f, img)
    p = folder / "capture.toml"
    p.write_text(p.read_text().replace("[radiometry]", "[radiometry]\ndark_level = 0.0"))
    s = _run(folder, capsys)
    assert s["maps"]["albedo_median"][2] is None and s["maps"]["known_pixels"][2] == 0
    assert s["diffusion"]["status"][2] == "unknown"
    assert s["maps"]["known_pixels"][0] > 3000 and s["diffusion"]["status"][0] != "unknown"
    assert any("channel(s) B unknown" in n for n in s["notes"])


def test_ketchup_relief_dark_channels_unknown_and_red_weak(tmp_path, capsys) -> None:
    """tests/data/relief_ketchup: the same relief, ketchup (science.md sec. 2: sigma_s' 0.18 / 0.07 / 0.03, sigma_a
    0.061 / 0.97 / 1.45 per mm; l_d 4.76 / 0.58 / 0.39 mm), 48 x 48 px of 0.25 mm, 64 spp (27 s to render). G and B
    are dark (median full-on value 0.004 / 0.001 < dark_level 0.01): unknown, never a number. Red's l_d (4.8 mm)
    is far beyond what a 12 mm map with a 3 mm margin can measure: measured l_d 0.41 mm (-91 %), but "weak" with
    the interval [0.067, 51] mm that covers the truth."""
    f = tmp_path / "ketchup"
    shutil.copytree(DATA.parent / "relief_ketchup", f)
    s = _run(f, capsys)
    d = s["diffusion"]
    assert d["status"] == ["weak", "unknown", "unknown"]
    assert s["maps"]["albedo_median"][1:] == [None, None] and d["D_mm"]["value"][1:] == [None, None]
    ssp, sa = np.array([0.18, 0.07, 0.03]), np.array([0.061, 0.97, 1.45])
    lo, hi = d["l_d_mm"]["interval"][0]
    assert lo <= 1 / np.sqrt(3 * sa[0] * (ssp[0] + sa[0])) <= hi and hi / lo > 10


def _add_camera_noise(folder: Path, gain: float, read: float, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for f in sorted((folder / "frames").glob("*.exr")):
        img = np.asarray(read_image(f)[0], dtype=np.float64)
        write_exr(f, (img + rng.standard_normal(img.shape) * np.sqrt(np.maximum(img, 0) / gain + read ** 2)
                      ).astype(np.float32))


def test_stated_frame_noise_weights_the_relief_fit(tmp_path, capsys) -> None:
    """Issue 16 item 2 through the CLI: camera noise (5000 e-/value) added to the relief frames and stated in
    [noise]; the maps' standard errors are written, the relief fit weights its residuals by them and its l_d / D
    intervals cover the truth; the summary and the sidecar name the noise source."""
    folder = _copy(tmp_path, '[object]\nshape = "relief"\nnormals_file = "true_normals.npy"\n\n'
                             '[noise]\nelectrons_per_value = 5000\nread_noise = 2e-4\n')
    _add_camera_noise(folder, 5000.0, 2e-4)
    s = _run(folder, capsys, "--relief-window-px", "32")
    d = s["diffusion"]
    assert d["fit"]["residual_weights"].startswith("Hann x 1/sigma^2")
    assert _covers(d, "D_mm", D).all() and _covers(d, "l_d_mm", L_D).all()
    sd = np.asarray(s["noise"]["diffuse_normal_stderr_rad_median"])
    assert np.all((sd > 0.02) & (sd < 0.5)) and sd[0] < sd[1] < sd[2], sd     # fewer photons in G, B
    for name in ("albedo_stderr", "diffuse_normals_stderr_rad", "specular_normals_stderr_rad"):
        assert Path(s["files"][name]).is_file(), name
    import json
    side = json.loads(Path(s["files"]["sidecar"]).read_text())
    assert side["provenance"]["noise"]["source"] == "shot+read"


@pytest.mark.parametrize("extra,frames_edit,key,expected", [
    ("[noise]\nelectrons_per_value = 0\n", None, "noise.electrons_per_value", "> 0"),
    ("[noise]\nread_noise = 1\n", None, "noise.electrons_per_value", "key is missing"),
    ("[noise]\nelectrons_per_value = 10\nshot = 1\n", None, "noise.shot", "documented keys"),
    ("", "one", "frames[].stderr_file", "every frame or on none"),
    ("", "small", "frames[0].stderr_file", "64 x 64"),
    ("[noise]\nelectrons_per_value = 10\n", "all", "noise.electrons_per_value", "not both"),
])
def test_bad_noise_spec_names_file_and_key(tmp_path, extra, frames_edit, key, expected) -> None:
    folder = _copy(tmp_path, extra)
    write_exr(folder / "se.exr", np.full((64, 64, 3), 1e-3, np.float32))
    write_exr(folder / "se_small.exr", np.full((8, 8, 3), 1e-3, np.float32))
    if frames_edit:
        p = folder / "capture.toml"
        t = p.read_text()
        n = 1 if frames_edit in ("one", "small") else -1
        t = t.replace("exposure_s = 0.02\n", "exposure_s = 0.02\nstderr_file = \""
                      + ("se_small.exr" if frames_edit == "small" else "se.exr") + "\"\n", n)
        p.write_text(t)
    with pytest.raises(Exception) as ei:
        load_capture(folder)
    assert f"'{key}'" in str(ei.value) and expected in str(ei.value), str(ei.value)


def test_stderr_files_on_every_frame_are_the_noise_source(tmp_path) -> None:
    folder = _copy(tmp_path)
    write_exr(folder / "se.exr", np.full((64, 64, 3), 1e-3, np.float32))
    p = folder / "capture.toml"
    p.write_text(p.read_text().replace("exposure_s = 0.02\n", "exposure_s = 0.02\nstderr_file = \"se.exr\"\n"))
    cap = load_capture(folder)
    se = cap.noise.stderr_images(cap.images)
    assert cap.noise.source == "stderr_file" and set(se) == set(cap.images)
    np.testing.assert_allclose(se[("full", "cross")], 1e-3)


def _relief_mesh(path: Path, step_mm: float, shift_mm: float = 0.0) -> None:
    """The relief of tests/data/relief_skin1 (make_relief_capture.py's BumpySlabObject, seed 0) as a PLY grid mesh."""
    import trimesh

    from simulators.objects import BumpySlabObject
    slab = BumpySlabObject((0.0, 0.0, 0.0), tuple(SSP), tuple(SA), 1.3, extent_mm=64 * 0.2 + 22.0, patch_mm=0.25,
                           rms_slope=0.1, wavelengths_mm=(1.5, 6.0), n_waves=48, seed=0)
    g = np.arange(-7.0, 7.0 + 1e-9, step_mm)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    c, n, e1, e2 = slab._frame()
    pts = c + uu[..., None] * e1 + vv[..., None] * e2 + slab.height(uu, vv)[0][..., None] * n
    m = len(g)
    idx = np.arange(m * m).reshape(m, m)
    a, b, cc, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
    mesh = trimesh.Trimesh(pts.reshape(-1, 3) + [shift_mm, 0, 0], np.concatenate([np.stack([a, b, d], 1),
                                                                                    np.stack([a, d, cc], 1)]),
                           process=False)
    if np.median(mesh.face_normals @ n) < 0:
        mesh.invert()
    mesh.export(path)


def test_a_mesh_file_gives_the_true_normals(tmp_path) -> None:
    """Issue 16: "a mesh given by the capture folder". The relief as a 0.1 mm grid mesh (39,200 faces), rendered into
    the folder's camera with smooth (barycentric vertex) normals, reproduces the renderer's true normals (measured:
    median 0.06 deg, max 0.19 deg; a 0.2 mm mesh 0.41 / 1.4 deg); the relief fit then reads them like a
    normals_file."""
    folder = _copy(tmp_path, '[object]\nshape = "relief"\nmesh_file = "relief.ply"\n')
    _relief_mesh(folder / "relief.ply", step_mm=0.1)
    cap = load_capture(folder)
    tn = np.load(folder / "true_normals.npy").astype(float)
    ang = np.degrees(np.arccos(np.clip((cap.relief.normals * tn).sum(-1), -1, 1)))
    assert cap.relief.source == "mesh_file" and np.isfinite(ang).all()
    assert np.median(ang) < 0.3 and ang.max() < 1.0, (np.median(ang), ang.max())


@pytest.mark.parametrize("extra,key,expected", [
    ('mesh_file = "far.ply"\n', "object.mesh_file", "a mesh that the camera sees"),
    ('mesh_file = "relief.ply"\nmesh_units = "km"\n', "object.mesh_units", "one of mm"),
    ('normals_file = "true_normals.npy"\nmesh_units = "cm"\n', "object.mesh_units", "nothing unless mesh_file"),
    ('mesh_file = "true_normals.npy"\n', "object.mesh_file", ".ply"),
])
def test_bad_mesh_names_file_and_key(tmp_path, extra, key, expected) -> None:
    folder = _copy(tmp_path, '[object]\nshape = "relief"\n' + extra)
    _relief_mesh(folder / "relief.ply", step_mm=1.0)
    _relief_mesh(folder / "far.ply", step_mm=1.0, shift_mm=500.0)
    with pytest.raises(Exception) as ei:
        load_capture(folder)
    assert f"'{key}'" in str(ei.value) and expected in str(ei.value), str(ei.value)
