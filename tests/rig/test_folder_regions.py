"""Per-region summaries from a labelled region image (``[object] regions``; rig.estimate.folder_regions; issue 16 item 1).

Captures reused, nothing new rendered: the 10 mm marble sphere of tests/rig/test_capture_folder.py (dipole render,
84 x 80 px, one material: simulators.scene has no per-region materials) and the cached Monte Carlo relief slab
tests/data/relief_skin1 (64 x 64 px). On one material every region must recover the whole object's material, each
with a wider interval than the whole object's (fewer pixels / windows).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import test_capture_folder as _tcf

from rig.estimate.capture_folder import format_summary
from rig.cli import main
from rig.estimate.folder_regions import MIN_REGION_PIXELS
from rig.files.imageio import read_image
from rig.files.maps_io import read_maps

marble_scene = _tcf.marble_scene              # the module-scoped fixture of test_capture_folder
write_marble_capture = _tcf.write_marble_capture

RELIEF = Path(__file__).resolve().parents[1] / "data" / "relief_skin1"
SKIN1_D = 1 / (3 * (np.array([0.74, 0.88, 1.01]) + np.array([0.032, 0.17, 0.48])))
H, W = 80, 84


def _run(folder: Path, capsys, *extra: str) -> dict:
    rc = main(["estimate", "gradients", str(folder), "--json", *extra])
    out = capsys.readouterr().out
    assert rc == 0, out
    return json.loads(out)


def _halves(h: int, w: int, dtype=np.uint16) -> np.ndarray:
    lab = np.ones((h, w), dtype)
    lab[:, w // 2:] = 2
    return lab


@pytest.fixture
def sphere_folder(tmp_path, marble_scene) -> Path:
    """The marble sphere (cross frames only) with a label image: left half 1, right half 2, a 2 x 2 px region 3 at
    the sphere's centre (too few pixels for an interval)."""
    lab = _halves(H, W)
    lab[39:41, 41:43] = 3
    folder = write_marble_capture(tmp_path / "cap", marble_scene, "exr", parallel=False, seed=False,
                                  extra='regions = "regions.png"\n\n[object.region_names]\n1 = "left"\n2 = "right"\n')
    cv2.imwrite(str(folder / "regions.png"), lab)
    return folder


def test_sphere_regions_recover_the_material_with_wider_intervals(sphere_folder, capsys, marble_scene) -> None:
    """Each half of a one-material sphere recovers its D / sigma_s' / R_d like the whole object (within 1 %, the
    whole-object test's tolerance), with plain (order-statistic) D intervals that hold the truth and are wider than
    the whole object's; the 2 x 2 px region is unknown with the reason. Also JSON = sidecar, the provenance and the
    table output."""
    s = _run(sphere_folder, capsys)
    tr = marble_scene["truth"]
    whole = s["diffusion"]
    regs = s["regions"]
    assert [(r["label"], r["name"]) for r in regs] == [(1, "left"), (2, "right"), (3, "region 3")]
    assert [r["n_pixels_label"] for r in regs] == [H * W // 2 - 2, H * W // 2 - 2, 4]
    w_plain = np.asarray(whole["model_shortening_bias"]["plain_intervals"]["D_mm"])
    for r in regs[:2]:
        d = r["diffusion"]
        widths = np.ptp(d["model_shortening_bias"]["plain_intervals"]["D_mm"], axis=1) / np.ptp(w_plain, axis=1)
        print(f"\n{r['name']}: D / truth - 1 {np.round(np.asarray(d['D_mm']['value']) / tr['D_mm'] - 1, 4)}, plain D "
              f"interval width / whole object's {np.round(widths, 2)}, status {d['status']}, pixels "
              f"{d['n_pixels']} of {whole['n_pixels']}")
        assert d["estimator"].startswith("grounded sphere") and set(d["status"]) <= {"ok", "weak"}
        assert 0.4 * np.sum(whole["n_pixels"]) < np.sum(d["n_pixels"]) < 0.6 * np.sum(whole["n_pixels"])
        for k in ("D_mm", "sigma_s_prime_per_mm", "R_d"):
            np.testing.assert_allclose(d[k]["value"], tr[k], rtol=1e-2, err_msg=f"{r['name']} {k}")
        plain = np.asarray(d["model_shortening_bias"]["plain_intervals"]["D_mm"])
        assert np.all(plain[:, 0] <= tr["D_mm"] * 1.005) and np.all(tr["D_mm"] * 0.995 <= plain[:, 1]), plain
        assert np.all(plain[:, 1] - plain[:, 0] > w_plain[:, 1] - w_plain[:, 0]), (r["name"], plain, w_plain)
        lo, hi = np.asarray(d["D_mm"]["interval"]).T           # the reported (widened) interval holds the truth
        assert np.all(lo <= tr["D_mm"]) and np.all(tr["D_mm"] <= hi)
        np.testing.assert_allclose(r["maps"]["R_d_median"], s["maps"]["R_d_median"], rtol=5e-3)
        assert all(a < b for a, b in zip(r["maps"]["albedo_apparent_median"], r["maps"]["R_d_median"]))
    tiny = regs[2]["diffusion"]
    assert tiny["status"] == ["unknown"] * 3 and all(v is None for v in tiny["D_mm"]["value"])
    assert all(n < MIN_REGION_PIXELS for n in tiny["n_pixels"]) and all("< 6" in x for x in tiny["reason"])
    side = read_maps(sphere_folder / "maps").sidecar
    assert side["summary"]["regions"] == regs
    prov = side["provenance"]["object"]["regions"]
    assert prov["file"] == "regions.png" and len(prov["sha256"]) == 64 and prov["names"]["2"] == "right"
    table = format_summary(s)
    assert "regions (3)" in table and "left" in table and "right" in table
    assert sum(1 for line in table.splitlines() if line.rstrip().endswith("unknown")) >= 3


def test_relief_regions_pool_the_windows_inside_each_region(tmp_path, capsys) -> None:
    """The relief slab in 32-px windows (2 x 2): each half (an .npy label file) pools its 2 windows, its D lies
    between its windows' values and its interval holds the truth, as the whole object's does; a 4 x 4 px region
    holds no window >= 50 % and is unknown with the reason."""
    folder = tmp_path / "relief"
    shutil.copytree(RELIEF, folder)
    lab = _halves(64, 64, np.int32)
    lab[30:34, 30:34] = 3
    np.save(folder / "labels.npy", lab)
    (folder / "capture.toml").write_text((folder / "capture.toml").read_text()
                                         + '\n[object]\nregions = "labels.npy"\n')
    s = _run(folder, capsys, "--relief-window-px", "32")
    assert s["diffusion"]["windows"] == [2, 2]
    Dmap, _ = read_image(Path(s["files"]["relief_D_mm"]))
    for r, cols in zip(s["regions"][:2], (slice(0, 32), slice(32, 64))):
        d = r["diffusion"]
        assert d["windows_in_region"] == 2 and ">= 50%" in d["window_rule"]
        assert "unknown" not in d["status"] and all(n >= 1 for n in d["n_windows"])
        win = Dmap[:, cols].reshape(-1, 3)
        for c in range(3):
            vals = win[np.isfinite(win[:, c]), c]
            assert vals.min() * 0.999 <= d["D_mm"]["value"][c] <= vals.max() * 1.001, (r["label"], c)
        lo, hi = np.asarray(d["D_mm"]["interval"], dtype=float).T
        assert np.all((lo <= SKIN1_D) & (SKIN1_D <= hi)), (r["label"], lo, hi)
    tiny = s["regions"][2]["diffusion"]
    assert tiny["status"] == ["unknown"] * 3 and tiny["windows_in_region"] == 0
    assert all("no window of 32 px" in x for x in tiny["reason"])


def _err(folder: Path, capsys) -> str:
    rc = main(["estimate", "gradients", str(folder), "--json"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("write,extra,expected", [
    (lambda f: cv2.imwrite(str(f / "r.png"), np.ones((10, 12), np.uint8)), "",
     "a label image of the frames' size 84 x 80 px (W x H), got 'r.png: 12 x 10 px'"),
    (lambda f: cv2.imwrite(str(f / "r.png"), np.ones((H, W, 3), np.uint8)), "",
     "an 8- or 16-bit single-channel PNG"),
    (lambda f: np.save(f / "r.npy", np.ones((H, W))), "", "integer dtype"),
    (lambda f: cv2.imwrite(str(f / "r.png"), np.where(_halves(H, W) == 2, 3, 1).astype(np.uint16)), "",
     "every label 1..3 present"),
    (lambda f: cv2.imwrite(str(f / "r.png"), np.zeros((H, W), np.uint8)), "", "at least one region"),
    (lambda f: cv2.imwrite(str(f / "r.png"), _halves(H, W)), '\n[object.region_names]\n1 = "a"\n5 = "ghost"\n',
     "field 'object.region_names.5': expected a label present in r.png (1..2), got '5'"),
    (lambda f: cv2.imwrite(str(f / "r.png"), _halves(H, W)), '\n[object.region_names]\n1 = 7\n',
     "field 'object.region_names.1': expected a non-empty string"),
])
def test_bad_region_files_name_file_field_and_expectation(tmp_path, capsys, marble_scene, write, extra,
                                                          expected) -> None:
    folder = write_marble_capture(tmp_path / "bad", marble_scene, "exr", parallel=False, seed=False)
    write(folder)
    name = "r.npy" if (folder / "r.npy").exists() else "r.png"
    (folder / "capture.toml").write_text((folder / "capture.toml").read_text() + f'regions = "{name}"\n' + extra)
    err = _err(folder, capsys)
    assert str(folder / "capture.toml") in err and "object.region" in err and expected in err, err
    if "region_names" not in expected:
        assert "field 'object.regions'" in err and name in err


def test_region_names_without_regions_and_a_missing_file(tmp_path, capsys, marble_scene) -> None:
    folder = write_marble_capture(tmp_path / "bad", marble_scene, "exr", parallel=False, seed=False,
                                  extra='\n[object.region_names]\n1 = "a"\n')
    err = _err(folder, capsys)
    assert "field 'object.region_names'" in err and "nothing unless regions" in err
    toml = (folder / "capture.toml").read_text().replace("[object.region_names]",
                                                          'regions = "nope.png"\n[object.region_names]')
    (folder / "capture.toml").write_text(toml)
    err = _err(folder, capsys)
    assert "field 'object.regions'" in err and "an existing label image" in err and "nope.png" in err
    assert not (folder / "maps").exists()        # refused while loading, before any map


def test_a_channel_with_too_few_pixels_is_unknown_and_leaves_the_others() -> None:
    """Synthetic grounded maps of a 10 mm marble sphere (exact albedo and shortening in every pixel): green and blue
    known in only 5 and 3 pixels of the region -> "unknown" with the reason, values None, no model bias for them;
    red recovers marble's D as the whole-object path would (the same summarize + widening)."""
    from estimation.diffusion import DiffusionMaps, sphere_albedo, sphere_shortening
    from rig.estimate.folder_regions import _sphere_region
    from rig.files.provenance import jsonable

    ssp, sa, eta, rho, n = _tcf.MARBLE[0], _tcf.MARBLE[1], _tcf.ETA, _tcf.RADIUS, 8
    A = np.broadcast_to(sphere_albedo(rho, ssp, sa, eta), (n, n, 3)).astype(np.float32)
    S = np.broadcast_to(sphere_shortening(rho, ssp, sa, eta), (n, n, 3)).astype(np.float32)
    nan = np.full((n, n, 3), np.nan, np.float32)
    unknown = np.zeros((n, n, 3), bool)
    unknown[..., 1:] = True
    unknown[0, :5, 1] = unknown[0, :3, 2] = False
    dm = DiffusionMaps(A, S, np.full((n, n), rho, np.float32), *(nan,) * 9, unknown=unknown,
                       censored=np.zeros((n, n, 3), bool), method="sphere", eta=eta)
    d = jsonable(_sphere_region(dm, np.ones((n, n), bool), rho, eta, MIN_REGION_PIXELS))
    assert d["status"][1:] == ["unknown"] * 2 and d["status"][0] != "unknown" and d["n_pixels"] == [64, 5, 3]
    assert d["reason"][0] is None and "5 usable pixel(s) < 6" in d["reason"][1] and "3 usable" in d["reason"][2]
    assert d["D_mm"]["value"][1:] == [None, None] and d["model_bias"]["channels_evaluated"] == [True, False, False]
    np.testing.assert_allclose(d["D_mm"]["value"][0], 1 / (3 * (ssp[0] + sa[0])), rtol=2e-3)


def test_regions_without_geometry_give_map_medians_and_unknown_diffusion(tmp_path, capsys) -> None:
    """The unblurred ideal-gradient sphere of test_capture_folder (no geometry: diffusion unknown): each region's R_d
    median is the sphere's albedo (to float32 precision, as the whole object), its diffusion unknown with the whole
    object's reason; a region wholly on the background has no known pixel and no median."""
    folder = tmp_path / "ortho"
    tr = _tcf._ideal_ortho_capture(folder)
    h, w = tr["hit"].shape
    lab = _halves(h, w, np.uint8)
    lab[0:2, 0:2] = 3                                     # a corner: background
    cv2.imwrite(str(folder / "r.png"), lab)
    (folder / "capture.toml").write_text((folder / "capture.toml").read_text() + 'regions = "r.png"\n')
    s = _run(folder, capsys, "--format", "tiff")
    left, right, corner = s["regions"]
    for r in (left, right):
        np.testing.assert_allclose(r["maps"]["R_d_median"], tr["albedo"], rtol=1e-4)
        assert min(r["maps"]["known_pixels"]) > 0.4 * tr["hit"].sum()
        assert r["diffusion"]["status"] == ["unknown"] * 3 and "no geometry" in r["diffusion"]["reason"]
    assert corner["maps"]["known_pixels"] == [0, 0, 0] and corner["maps"]["R_d_median"] == [None] * 3


def test_tiff_label_images_are_read_and_float_tiffs_refused(tmp_path) -> None:
    """A 16-bit single-channel TIFF label image (e.g. from an image editor) is read like a PNG; a float TIFF is
    refused naming the field and the file."""
    import tifffile

    from rig.estimate.capture_folder import load_capture
    folder = tmp_path / "relief"
    shutil.copytree(RELIEF, folder)
    lab = np.zeros((64, 64), np.uint16)
    lab[:, :32], lab[:, 32:] = 1, 2
    tifffile.imwrite(folder / "regions.tif", lab)
    tifffile.imwrite(folder / "bad.tif", lab.astype(np.float32))
    toml = folder / "capture.toml"
    base = toml.read_text()
    toml.write_text(base + '\n[object]\nregions = "regions.tif"\n')
    cap = load_capture(folder)
    np.testing.assert_array_equal(cap.regions.labels, lab)
    toml.write_text(base + '\n[object]\nregions = "bad.tif"\n')
    with pytest.raises(Exception) as ei:
        load_capture(folder)
    assert "'object.regions'" in str(ei.value) and "bad.tif: dtype float32" in str(ei.value), str(ei.value)
