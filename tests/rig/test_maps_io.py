"""Round trips of rig.files.maps_io: float maps (EXR / TIFF) with NaN = unknown, the mask bit field, the JSON sidecar,
the preview sheet (matplotlib and the OpenCV fallback), and the reader's refusals.

The maps come from estimation.gradients.compute_maps on continuous-gradient frames of a sphere (Ma et al. 2007
closed forms; tests/estimation/test_gradients.py's ``continuous_frames`` pattern) plus a specular lobe in the
parallel frames, and from estimation.diffusion on the same sphere, so every field is a real estimator output.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from estimation.diffusion import diffusion_seed, estimate_diffusion
from estimation.fresnel import fresnel_transmittance
from estimation.gradients import compute_maps, tau_ratio
from rig.files.maps_io import (MASK_BITS, PREVIEW_TILE_PX, MapsError, preview_size_px, read_maps, write_maps)

ETA = 1.3


def sphere_normals(size: int) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size]
    u = (xx - size / 2 + 0.5) / (size / 2) * 1.1
    w = -(yy - size / 2 + 0.5) / (size / 2) * 1.1
    r2 = u * u + w * w
    n = np.full((size, size, 3), np.nan)
    hit = r2 < 1
    n[hit, 0], n[hit, 2], n[hit, 1] = u[hit], w[hit], -np.sqrt(1 - r2[hit])
    return n


@pytest.fixture(scope="module")
def estimates():
    """(GradientMaps with specular maps, DiffusionMaps, SeedEstimate, true normals) of a 20 px sphere."""
    n = sphere_normals(20)
    hit = np.isfinite(n).all(-1)
    nn = np.where(hit[..., None], n, 0.0)
    rho = np.array([0.8, 0.5, 0.3])
    tau = tau_ratio(ETA)
    ft = fresnel_transmittance(ETA, np.clip(-nn[..., 1], 0, 1))[..., None]
    base = 0.4 * rho * ft * hit[..., None]
    base[3, 10, 0] = 0.99          # one saturated red pixel
    view = np.array([0.0, -1.0, 0.0])          # towards the camera
    r = 2 * np.sum(nn * view, -1, keepdims=True) * nn - view   # mirror reflection of the view direction
    frames = {("ambient", "cross"): np.zeros((20, 20, 3), np.float32),
              ("ambient", "parallel"): np.zeros((20, 20, 3), np.float32)}
    for p in ("full", "x", "y", "z", "x_c", "y_c", "z_c"):
        if p == "full":
            e, s = np.ones_like(base), np.ones((20, 20, 1))
        else:
            i, sign = "xyz".index(p[0]), (-1 if p.endswith("_c") else 1)
            e = 0.5 * (1 + sign * tau * nn[..., i:i + 1])
            s = 0.5 * (1 + sign * r[..., i:i + 1])
        frames[(p, "cross")] = (base * e).astype(np.float32)
        frames[(p, "parallel")] = (base * e + 0.05 * s * hit[..., None]).astype(np.float32)
    maps = compute_maps(frames, albedo_scale=2.5, ideal=True, eta=ETA, geometry_normals=nn, object_mask=hit)
    dm = estimate_diffusion(maps, n, sphere_radius_mm=5.0)
    seed = diffusion_seed(maps, [0.16, 0.15, 0.13], {"reference": "test"}, true_normals=n)
    return maps, dm, seed, n


PROV = {"name": "unit", "capture": {"folder": "/somewhere"}, "frames": [{"file": "a.exr", "sha256": "0" * 64}],
        "parameters": {"eta": 1.3, "weird": float("nan")}}


@pytest.mark.parametrize("fmt,suffix", [("exr", ".exr"), ("tiff", ".tif")])
def test_round_trip_is_exact_including_nan(tmp_path, estimates, fmt, suffix) -> None:
    maps, dm, seed, _ = estimates
    files = write_maps(tmp_path, maps, dm, fmt=fmt, provenance=PROV, seed=seed)
    got = read_maps(tmp_path)
    expected = {"albedo_diffuse": maps.albedo, "diffuse_length": maps.diffuse_length(),
                "albedo_specular": maps.specular_albedo, "normals_specular": maps.specular_normals,
                "R_d": dm.R_d, "alpha_prime": dm.alpha_prime, "D_mm": dm.D_mm,
                "sigma_s_prime_per_mm": dm.sigma_s_prime_per_mm, "sigma_a_per_mm": dm.sigma_a_per_mm,
                "shortening": dm.shortening, "D_seed_mm": seed.D_mm,
                **{f"normals_diffuse_{ch}": maps.diffuse_normals[..., c, :] for c, ch in enumerate("RGB")}}
    assert set(got.arrays) == set(expected)
    for k, v in expected.items():
        assert files[k].suffix == suffix
        assert got.arrays[k].dtype == np.float32
        np.testing.assert_array_equal(got.arrays[k], v, err_msg=k)   # NaN positions must match too
    assert np.isnan(got.arrays["albedo_diffuse"][0, 0]).all()       # background
    assert np.isnan(got.arrays["albedo_diffuse"][3, 10, 0])          # the saturated channel only
    assert np.isfinite(got.arrays["albedo_diffuse"][3, 10, 1:]).all()


def test_masks_round_trip_as_bit_field(tmp_path, estimates) -> None:
    maps, dm, seed, _ = estimates
    write_maps(tmp_path, maps, dm, provenance=PROV)
    got = read_maps(tmp_path)
    m = maps.masks
    np.testing.assert_array_equal(got.masks["saturated"], m.saturated)
    np.testing.assert_array_equal(got.masks["dark"], m.dark)
    np.testing.assert_array_equal(got.masks["inconsistent"], m.inconsistent)
    np.testing.assert_array_equal(got.masks["grazing"], np.repeat(m.grazing[..., None], 3, -1))
    np.testing.assert_array_equal(got.masks["background"], np.repeat(m.background[..., None], 3, -1))
    np.testing.assert_array_equal(got.masks["specular_unknown"][..., 0], maps.specular_unknown)
    np.testing.assert_array_equal(got.masks["diffusion_unknown"], dm.unknown)
    assert got.masks["saturated"][3, 10].tolist() == [True, False, False]
    raw = cv2.imread(str(tmp_path / "masks.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and raw[0, 0, 0] & MASK_BITS["background"]


def test_sidecar_describes_every_file(tmp_path, estimates) -> None:
    maps, dm, seed, _ = estimates
    files = write_maps(tmp_path, maps, dm, fmt="exr", provenance=PROV, seed=seed,
                       extra_sidecar={"summary": {"ok": True}})
    text = (tmp_path / "maps.json").read_text()
    side = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c} in maps.json"))
    assert side["format"] == "sssrig-maps" and side["format_version"] == 1
    assert side["image"] == {"width_px": 20, "height_px": 20, "pixel_convention": side["image"]["pixel_convention"]}
    units = {k: v["unit"] for k, v in side["files"].items()}
    assert units["D_mm"] == "mm" and units["sigma_s_prime_per_mm"] == "1/mm" and units["sigma_a_per_mm"] == "1/mm"
    assert units["normals_diffuse_G"] == "unit vector" and units["albedo_diffuse"] == "1"
    assert side["files"]["albedo_diffuse"]["channels"] == ["R", "G", "B"]
    assert side["files"]["normals_specular"]["channels"] == ["x", "y", "z"]
    assert all("unknown" in v["nan"] and "rig frame" in v["frame"] for v in side["files"].values())
    assert side["provenance"]["frames"][0]["sha256"] == "0" * 64
    assert side["provenance"]["parameters"]["weird"] is None       # NaN in provenance becomes null
    assert side["summary"] == {"ok": True}
    import hashlib
    assert side["files"]["D_mm"]["sha256"] == hashlib.sha256(files["D_mm"].read_bytes()).hexdigest()
    frac = side["files"]["albedo_diffuse"]["known_fraction"]
    assert frac[0] == pytest.approx(np.isfinite(maps.albedo[..., 0]).mean())


@pytest.mark.parametrize("backend", ["matplotlib", "opencv"])
def test_preview_sheet_size_and_unknown_grey(tmp_path, estimates, backend) -> None:
    maps, dm, seed, _ = estimates
    write_maps(tmp_path, maps, dm, provenance=PROV, seed=seed, preview=backend)
    img = cv2.imread(str(tmp_path / "preview.png"))
    rows = 6   # albedo row, normals row, D, sigma_s', sigma_a, D seed
    assert img.shape[:2] == preview_size_px(rows) == (rows * PREVIEW_TILE_PX[1], 3 * PREVIEW_TILE_PX[0])
    side = json.loads((tmp_path / "maps.json").read_text())
    assert side["preview"]["backend"] == backend and len(side["preview"]["tiles"]) == rows
    # the normals tile (row 1, column 0) shows the background (unknown) as neutral grey
    tw, th = PREVIEW_TILE_PX
    tile = img[th:2 * th, :tw].reshape(-1, 3).astype(int)
    grey = np.all(np.abs(tile - 128) <= 1, axis=-1)
    assert grey.sum() > 200
    assert len(np.unique(tile, axis=0)) > 50      # and real colours elsewhere


def test_without_diffusion_or_specular(tmp_path, estimates) -> None:
    maps, *_ = estimates
    from dataclasses import replace
    plain = replace(maps, specular_albedo=None, specular_normals=None, reflection_vectors=None,
                    specular_unknown=None)
    files = write_maps(tmp_path, plain, None, fmt="tiff", provenance=PROV)
    assert not any(k in files for k in ("D_mm", "sigma_a_per_mm", "albedo_specular", "D_seed_mm"))
    assert not (tmp_path / "D_mm.tif").exists()
    got = read_maps(tmp_path)
    assert got.masks["diffusion_unknown"].all() and got.masks["specular_unknown"].all()
    assert cv2.imread(str(tmp_path / "preview.png")).shape[:2] == preview_size_px(2)


def test_reader_refuses_altered_missing_or_foreign_folders(tmp_path, estimates) -> None:
    maps, dm, *_ = estimates
    write_maps(tmp_path, maps, dm, fmt="exr", provenance=PROV)
    from rig.files.imageio import write_exr
    write_exr(tmp_path / "D_mm.exr", np.ones((20, 20, 3), np.float32))
    with pytest.raises(MapsError, match=r"D_mm\.exr: sha256 differs from maps\.json"):
        read_maps(tmp_path)
    assert read_maps(tmp_path, verify=False).arrays["D_mm"].max() == 1.0
    (tmp_path / "D_mm.exr").unlink()
    with pytest.raises(MapsError, match=r"D_mm\.exr: no such file"):
        read_maps(tmp_path)
    side = json.loads((tmp_path / "maps.json").read_text())
    side["format_version"] = 7
    (tmp_path / "maps.json").write_text(json.dumps(side))
    with pytest.raises(MapsError, match=r"maps\.json: field 'format_version': expected 1, got 7"):
        read_maps(tmp_path)
    with pytest.raises(MapsError, match="maps.json: no such file"):
        read_maps(tmp_path / "elsewhere")


def test_writer_rejects_unknown_format(tmp_path, estimates) -> None:
    maps, *_ = estimates
    with pytest.raises(ValueError, match="'exr' or 'tiff'"):
        write_maps(tmp_path, maps, None, fmt="png", provenance=PROV)
    assert not list(Path(tmp_path).iterdir())


def test_selection_lists_what_was_left_out_and_how_to_derive_it(tmp_path, estimates) -> None:
    """``select`` writes only the named maps; maps.json names every left-out map with its derivation from the
    written files, and the derivation reproduces the estimator's own map (float32 rounding)."""
    from rig.files.maps_io import DERIVATIONS, select_maps

    maps, dm, seed, _ = estimates
    sel = select_maps("albedo_diffuse,normals_diffuse,alpha_prime,D_mm")
    assert sel[:4] == ["albedo_diffuse", "normals_diffuse_R", "normals_diffuse_G", "normals_diffuse_B"]
    with pytest.raises(ValueError, match="unknown map"):
        select_maps("albedo,D")
    assert select_maps("all") is None and select_maps(None) is None
    files = write_maps(tmp_path, maps, dm, provenance=PROV, seed=seed, select=sel)
    got = read_maps(tmp_path)
    assert set(got.arrays) == set(sel) and not (tmp_path / "sigma_a_per_mm.exr").exists()
    nw = got.sidecar["not_written"]
    assert set(nw) == {"diffuse_length", "albedo_specular", "normals_specular", "R_d", "sigma_s_prime_per_mm",
                       "sigma_a_per_mm", "shortening", "D_seed_mm"}
    assert nw["sigma_a_per_mm"] == {"derive": DERIVATIONS["sigma_a_per_mm"][0], "from": ["alpha_prime", "D_mm"]}
    assert nw["shortening"]["derive"] is None
    a, D = got.arrays["alpha_prime"].astype(np.float64), got.arrays["D_mm"].astype(np.float64)
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose((1 - a) / (3 * D), np.asarray(dm.sigma_a_per_mm), rtol=1e-3, equal_nan=True)
        np.testing.assert_allclose(a / (3 * D), np.asarray(dm.sigma_s_prime_per_mm), rtol=1e-5, equal_nan=True)
    assert "sidecar" in files and "preview" in files


def test_half_precision_for_normals_and_albedo_only(tmp_path, estimates) -> None:
    """EXR HALF for unit vectors and albedos (< 0.03 deg, 4.9e-4 relative), refused for the diffusion maps."""
    maps, dm, seed, _ = estimates
    write_maps(tmp_path, maps, dm, provenance=PROV, half=True)
    got = read_maps(tmp_path)
    side = got.sidecar["files"]
    assert side["normals_diffuse_R"]["dtype"] == "float16" and side["albedo_diffuse"]["dtype"] == "float16"
    assert side["D_mm"]["dtype"] == "float32" and side["shortening"]["dtype"] == "float32"
    n = got.arrays["normals_diffuse_G"]
    ref = np.asarray(maps.diffuse_normals[..., 1, :])
    assert np.array_equal(np.isnan(n), np.isnan(ref))
    ok = np.isfinite(ref).all(-1)
    cos = np.clip(np.sum(n[ok].astype(np.float64) * ref[ok], -1) / np.linalg.norm(n[ok], axis=-1), -1, 1)
    assert np.degrees(np.arccos(cos)).max() < 0.03
    np.testing.assert_allclose(got.arrays["albedo_diffuse"], maps.albedo, rtol=5e-4)
    np.testing.assert_array_equal(got.arrays["D_mm"], np.asarray(dm.D_mm))
    with pytest.raises(ValueError, match="must stay float32"):
        write_maps(tmp_path / "x", maps, dm, provenance=PROV, half=["D_mm"])
    with pytest.raises(ValueError, match="fmt='exr'"):
        write_maps(tmp_path / "y", maps, dm, provenance=PROV, fmt="tiff", half=True)
