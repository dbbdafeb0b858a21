"""Capture folders (docs/capture-folder.md) -> ``rig estimate gradients FOLDER``: synthesize frames of objects of
known truth, write them as EXR / float TIFF / 16-bit PNG / DNG with a capture.toml, run the CLI, compare.

Scenes (truth known exactly):
- a 10 mm marble sphere (Jensen 2001 Table 2) under 252 point LEDs at 1 m with 5 % intensity spread, seen by a
  pinhole camera at 400 mm: rendered with the independent dipole-over-the-sphere renderer of
  tests/estimation/test_diffusion.py (copied here in compact form: the diffuse exitance at the point with normal
  n0 is sum_j g_j p_j H(n0.w_j), H tabulated by quadrature of R(chord) over the sphere with the LED near field),
  plus a glossy specular lobe in the parallel-polarized frames. Truth: normals, the apparent albedo C(2 rho)
  (estimation.diffusion.sphere_albedo) and D, sigma_s', sigma_a of marble.
- an unblurred Fresnel-Lambertian sphere under ideal continuous gradients (Ma et al. 2007: I_i = rho F_t E_i,
  E_i = (tau0 + tau1 n_i)/2), seen orthographically, with a Spectralon-like reference patch in the corner.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimation.diffusion import sphere_albedo, sphere_geometry
from estimation.dipole import dipole_coefficients, profile_from_coefficients, total_diffuse_reflectance
from estimation.fresnel import fresnel_moment, fresnel_transmittance
from estimation.gradients import GRADIENT_PATTERNS, LedRig, albedo_scale_from_radiometry, tau_ratio
from rig.estimate.capture_folder import OrthographicCamera, estimate_capture, load_capture, missing_frames
from rig.cli import main
from rig.files.imageio import write_exr, write_float_tiff, write_png16
from rig.files.maps_io import PREVIEW_TILE_PX, read_maps
from simulators.dng import write_dng

ETA = 1.3
MARBLE = (np.array([2.19, 2.62, 3.00]), np.array([0.0021, 0.0041, 0.0071]))
R_LED = 1000.0
RADIUS = 10.0
K_PER_S = 30.0          # frame value per unit radiance per second
EXPOSURE = {"ambient": 0.02, "full": 0.01, "x": 0.02, "y": 0.02, "z": 0.02, "x_c": 0.02, "y_c": 0.02, "z_c": 0.02}
AMBIENT_PER_S = 0.3     # ambient light: 0.006 at 0.02 s
SPEC_PER_S = 8.0        # glossy lobe strength in the parallel frames


# ---------------------------------------------------------------------------------------------------- renderer
def geodesic(freq: int) -> np.ndarray:
    t = (1 + 5 ** 0.5) / 2
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    F = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    pts = [(i * V[a] + j * V[b] + (freq - i - j) * V[c]) / freq
           for a, b, c in F for i in range(freq + 1) for j in range(freq + 1 - i)]
    P = np.asarray(pts)
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    return np.unique(np.round(P, 9), axis=0)


def _h_table(ssp, sa, rho: float, nt: int = 401, nphi: int = 72):
    """H(t) = int_sphere R(|x0 - x|) k(n.w) dA for t = n0.w (test_diffusion.h_table, near field at R_LED)."""
    co = [dipole_coefficients(a, b, ETA) for a, b in zip(ssp, sa)]
    gx, gw = np.polynomial.legendre.leggauss(16)
    edges = [0.0]
    e = min(c.z_r_mm for c in co)
    while e < 2 * rho:
        edges.append(e)
        e *= 2.5
    edges.append(2 * rho)
    dn = np.concatenate([0.5 * (a + b) + 0.5 * (b - a) * gx for a, b in zip(edges[:-1], edges[1:])])
    dw = np.concatenate([0.5 * (b - a) * gw for a, b in zip(edges[:-1], edges[1:])])
    th = 2 * np.arcsin(np.clip(dn / (2 * rho), 0, 1))
    phi = (np.arange(nphi) + 0.5) * 2 * np.pi / nphi
    w_prof = np.stack([profile_from_coefficients(c, dn) for c in co], 1) * (dw * dn)[:, None]
    t = np.linspace(-1, 1, nt)
    u = (t[:, None, None] * np.cos(th)[None, :, None]
         + np.sqrt(1 - t * t)[:, None, None] * np.sin(th)[None, :, None] * np.cos(phi)[None, None, :])
    d2 = R_LED ** 2 + rho * rho - 2 * R_LED * rho * u
    c = np.clip((R_LED * u - rho) / np.sqrt(d2), 0, 1)
    k = (fresnel_transmittance(ETA, c) * c * R_LED ** 2 / d2).mean(-1) * 2 * np.pi
    return t, k @ w_prof


def _interp(x, t, y):
    n = t.size - 1
    g = (np.clip(x, -1, 1) + 1) * 0.5 * n
    i = np.minimum(g.astype(np.intp), n - 1)
    f = g - i
    return y[i] * (1 - f) + y[i + 1] * f


def _continuous(p: str, w: np.ndarray) -> np.ndarray:
    if p == "full":
        return np.ones(w.shape[:-1])
    c = w[..., "xyz".index(p[0])]
    return 0.5 * (1 - c) if p.endswith("_c") else 0.5 * (1 + c)


@pytest.fixture(scope="module")
def marble_scene() -> dict:
    """Per-second signal rates of the marble sphere, cross (diffuse/2) and parallel (+ specular lobe), + truth."""
    d = geodesic(5)
    rng = np.random.default_rng(11)
    inten = (R_LED ** 2) * (4 * np.pi / len(d)) * (1 + 0.05 * rng.standard_normal((len(d), 3)))
    pos = d * R_LED
    leds = LedRig.from_positions(pos, inten)
    from estimation.camera import PinholeCamera
    cam = PinholeCamera.looking_at(width_px=84, height_px=80, fx_px=1500.0, position_mm=(0.0, -400.0, 0.0),
                                   target_mm=(0.0, 0.0, 0.0))
    normals, view, hit = sphere_geometry(cam, np.zeros(3), RADIUS)
    t, Ht = _h_table(*MARBLE, RADIUS)
    n = normals[hit]
    tt = n @ leds.directions.T
    ft = fresnel_transmittance(ETA, np.clip(np.sum(n * view[hit], -1), 0, 1))
    v = view[hit]
    refl = 2 * np.sum(n * v, -1, keepdims=True) * n - v
    cross, par = {}, {}
    for p in GRADIENT_PATTERNS:
        w = leds.gains * leds.pattern_values(p)
        B = np.stack([_interp(tt, t, Ht[:, c]) @ w[:, c] for c in range(3)], -1)
        img = np.zeros(hit.shape + (3,))
        img[hit] = K_PER_S * 0.5 * ft[:, None] / np.pi * B
        cross[p] = img
        spec = np.zeros(hit.shape + (3,))
        spec[hit] = SPEC_PER_S * _continuous(p, refl)[:, None] * np.array([1.0, 1.0, 1.0])
        par[p] = img + spec
    ssp, sa = MARBLE
    truth = {"normals": normals, "hit": hit, "albedo": sphere_albedo(RADIUS, ssp, sa, ETA),
             "R_d": total_diffuse_reflectance(ssp, sa, ETA), "D_mm": 1 / (3 * (ssp + sa)),
             "sigma_s_prime_per_mm": ssp, "sigma_a_per_mm": sa}
    return {"leds": (pos, inten), "camera": cam, "cross": cross, "parallel": par, "truth": truth}


def _toml(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(float(v))


def _writer(fmt: str):
    return {"exr": (".exr", lambda p, a, e: write_exr(p, a)),
            "tiff": (".tif", lambda p, a, e: write_float_tiff(p, a)),
            "png16": (".png", lambda p, a, e: write_png16(p, a)),
            "dng": (".dng", lambda p, a, e: write_dng(p, a, exposure_s=e, black_level=512, bits=14))}[fmt]


def write_marble_capture(folder: Path, scene: dict, fmt: str, *, leds: str = "csv", radiometry: str = "radiance",
                         geometry: bool = True, seed: bool = True, parallel: bool = True, mask: bool = False,
                         drop: tuple[str, ...] = (), extra: str = "") -> Path:
    """The marble scene as a capture folder in ``fmt``; returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "frames").mkdir(exist_ok=True)
    suffix, write = _writer(fmt)
    frames = []
    H, W = scene["truth"]["hit"].shape
    for pol in ("cross", "parallel") if parallel else ("cross",):
        for p in ("ambient", *GRADIENT_PATTERNS):
            if p in drop:
                continue
            e = EXPOSURE[p]
            rate = np.zeros((H, W, 3)) if p == "ambient" else scene[pol][p]
            img = (e * (rate + AMBIENT_PER_S)).astype(np.float32)
            name = f"frames/{p}_{pol}{suffix}"
            write(folder / name, img, e)
            frames.append((name, p, pol, e))
    lines = ['format = "sssrig-capture"', "format_version = 1", f'name = "marble-{fmt}"', ""]
    for name, p, pol, e in frames:
        lines += ["[[frames]]", f'file = "{name}"', f'pattern = "{p}"', f'polarization = "{pol}"',
                  f"exposure_s = {e}", ""]
    pos, inten = scene["leds"]
    lines.append("[leds]")
    if leds == "csv":
        with open(folder / "leds.csv", "w") as fh:
            fh.write("# LED calibration\nx_mm,y_mm,z_mm,intensity_r,intensity_g,intensity_b\n")
            for a, b in zip(pos, inten):
                fh.write(",".join(repr(float(x)) for x in (*a, *b)) + "\n")
        lines.append('file = "leds.csv"')
    elif leds == "npy":
        np.save(folder / "leds.npy", np.hstack([pos, inten]))
        lines.append('file = "leds.npy"')
    else:
        lines += [f"positions_mm = {_toml(pos.tolist())}", f"intensity = {_toml(inten.tolist())}"]
    cam = scene["camera"]
    lines += ["", "[camera]", 'model = "pinhole"', f"fx_px = {cam.fx_px}", f"width_px = {W}", f"height_px = {H}"]
    if leds == "npy":  # exercise the OpenCV extrinsics form: X_cam = R X + t
        R = cam.R
        lines += [f"rotation = {_toml(R.tolist())}", f"translation_mm = {_toml((-R @ cam.C).tolist())}"]
    else:
        lines += [f"position_mm = {_toml(list(cam.center_mm))}", "look_at_mm = [0.0, 0.0, 0.0]"]
    lines += ["", "[radiometry]", f"eta = {ETA}"]
    if radiometry == "radiance":
        lines.append(f"value_per_radiance_per_s = {K_PER_S}")
    else:  # the equivalent explicit scale (what albedo_scale_from_radiometry gives for this rig)
        from estimation.gradients import albedo_scale_from_radiometry
        scale = albedo_scale_from_radiometry([K_PER_S] * 3, LedRig.from_positions(pos, inten), eta=ETA)
        lines.append(f"albedo_scale = {_toml(scale.tolist())}")
    if geometry or mask:
        lines += ["", "[object]"]
    if mask:
        m = np.zeros((H, W), np.uint16)
        m[:, : W // 2] = 65535  # left half only
        import cv2
        cv2.imwrite(str(folder / "mask.png"), m)
        lines.append('mask = "mask.png"')
    if geometry:
        lines += ['shape = "sphere"', "center_mm = [0.0, 0.0, 0.0]", f"radius_mm = {RADIUS}"]
    if seed:
        lines += ["", "[seed]", "k_mm = [0.164, 0.145, 0.134]",
                  'provenance = { reference = "marble", geometry = "10 mm sphere", '
                  'source = "docs/gradients.md sec. 6" }']
    (folder / "capture.toml").write_text("\n".join(lines) + "\n" + extra)
    return folder


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors via atan2(|a x b|, a.b): accurate for float32 maps at tiny angles (arccos is not)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def run_json(folder: Path, capsys, *extra: str) -> dict:
    rc = main(["estimate", "gradients", str(folder), "--json", *extra])
    out = capsys.readouterr().out
    assert rc == 0, out
    return json.loads(out)


# ---------------------------------------------------------------------------------------------------- end to end
@pytest.mark.parametrize("fmt,leds,radiometry,out_fmt", [("exr", "csv", "radiance", "exr"),
                                                         ("png16", "inline", "scale", "tiff"),
                                                         ("dng", "npy", "radiance", "exr")])
def test_marble_capture_recovers_truth(tmp_path, capsys, marble_scene, fmt, leds, radiometry, out_fmt) -> None:
    """Tolerances: with this renderer and rig, noise-free maps give R_d within 0.07-0.11 %, D and sigma_s' within
    0.2 % and sigma_a within 1.2-1.7 % (docs/gradients.md sec. 7); the file formats add quantization (14-bit DNG:
    6e-5 of white per value, ~3e-4 relative at the limb, averaged over ~3900 pixels by the medians). So: albedo
    and R_d 0.2 %, D and sigma_s' 1 %, sigma_a 3 % (it enters through 1 - alpha' ~ (1 - R_d)^2, science.md sec.
    6). Diffuse normals are the blurred true normals: on a sphere the blur only shortens them, so their direction
    matches the truth up to the near-field / LED-discreteness residual of the affine LUT (~0.1 deg in red, the
    widest profile): median < 0.2 deg, 99th percentile < 0.5 deg. The specular lobe follows the continuous
    gradients exactly, so specular normals are exact up to quantization. The seed's k (docs/gradients.md sec. 6)
    was calibrated on this very rig, sphere and material, so D_seed/D_grounded must be 1 within 2 %."""
    folder = write_marble_capture(tmp_path / "cap", marble_scene, fmt, leds=leds, radiometry=radiometry)
    s = run_json(folder, capsys, "--format", out_fmt)
    tr = marble_scene["truth"]
    out = folder / "maps"
    assert s["out_dir"] == str(out) and s["mode"] == "leds" and s["maps"]["specular"]
    # issue 16: the reported intervals include the dipole's measured shortening bias against real transport
    # (estimation.sphere_bias), which on a 10 mm marble sphere spans > 3x in D: "weak", pointing to --reference;
    # the plain order-statistic intervals (this render IS the dipole) are kept in model_shortening_bias
    assert set(s["diffusion"]["status"]) <= {"ok", "weak"}
    d = s["diffusion"]
    plain = d["model_shortening_bias"]["plain_intervals"]
    for k in ("D_mm", "sigma_s_prime_per_mm"):
        lo, hi = np.asarray(plain[k]).T
        assert np.all(lo <= np.asarray(tr[k]) * 1.005) and np.all(np.asarray(tr[k]) * 0.995 <= hi), k
        assert np.all(hi / lo < 1.1), k
    np.testing.assert_allclose(d["albedo"]["value"], tr["albedo"], rtol=2e-3)
    np.testing.assert_allclose(d["R_d"]["value"], tr["R_d"], rtol=2e-3)
    np.testing.assert_allclose(d["D_mm"]["value"], tr["D_mm"], rtol=1e-2)
    np.testing.assert_allclose(d["sigma_s_prime_per_mm"]["value"], tr["sigma_s_prime_per_mm"], rtol=1e-2)
    np.testing.assert_allclose(d["sigma_a_per_mm"]["value"], tr["sigma_a_per_mm"], rtol=3e-2)
    for k in ("D_mm", "sigma_s_prime_per_mm", "R_d"):   # the reported interval holds the truth
        lo, hi = np.asarray(d[k]["interval"]).T
        assert np.all(lo <= np.asarray(tr[k]) * 1.005) and np.all(np.asarray(tr[k]) * 0.995 <= hi), k
    # per-pixel maps read back from disk
    got = read_maps(out)
    assert got.shape == tr["hit"].shape
    alb = got.arrays["albedo_diffuse"]
    known = np.isfinite(alb)
    assert known[..., 1].sum() > 0.85 * tr["hit"].sum()
    assert not known[~tr["hit"]].any()                           # background is NaN
    np.testing.assert_allclose(np.nanmedian(alb.reshape(-1, 3), axis=0), tr["albedo"], rtol=5e-3)
    for c, ch in enumerate("RGB"):
        n = got.arrays[f"normals_diffuse_{ch}"]
        ok = known[..., c]
        ang = angle_deg(n[ok], tr["normals"][ok])
        assert np.median(ang) < 0.2 and np.percentile(ang, 99) < 0.5, (ch, np.median(ang), ang.max())
    spec_ok = np.isfinite(got.arrays["normals_specular"]).all(-1)
    assert spec_ok.sum() > 0.8 * tr["hit"].sum()
    assert np.percentile(angle_deg(got.arrays["normals_specular"][spec_ok], tr["normals"][spec_ok]), 99) < 0.1
    D = got.arrays["D_mm"]
    np.testing.assert_allclose(np.nanmedian(D.reshape(-1, 3), axis=0), tr["D_mm"], rtol=3e-2)
    assert np.array_equal(np.isnan(D), got.masks["diffusion_unknown"])
    assert "D_seed_mm" in got.arrays
    np.testing.assert_allclose(s["seed"]["versus_grounded"]["median_ratio"], 1.0, atol=0.02)
    assert max(s["seed"]["versus_grounded"]["fraction_outside_interval"]) < 0.05      # the seed's own sphere
    assert Path(s["files"]["D_seed_disagree"]).is_file() and Path(s["files"]["D_seed_ratio"]).is_file()
    # the preview exists with the documented size: 6 rows (albedo, normals, D, sigma_s', sigma_a, D seed)
    import cv2
    prev = cv2.imread(str(out / "preview.png"))
    assert prev.shape[:2] == (6 * PREVIEW_TILE_PX[1], 3 * PREVIEW_TILE_PX[0])
    side = got.sidecar
    assert (side["preview"]["height_px"], side["preview"]["width_px"]) == prev.shape[:2]
    # sidecar: units, channel order, provenance with frame hashes
    assert side["files"]["D_mm"]["unit"] == "mm" and side["files"]["sigma_a_per_mm"]["unit"] == "1/mm"
    assert side["files"]["normals_diffuse_R"]["channels"] == ["x", "y", "z"]
    assert side["files"]["albedo_diffuse"]["file"].endswith(".exr" if out_fmt == "exr" else ".tif")
    prov = side["provenance"]
    assert len(prov["frames"]) == 16 and all(len(f["sha256"]) == 64 for f in prov["frames"])
    import hashlib
    f0 = prov["frames"][0]
    assert hashlib.sha256((folder / f0["file"]).read_bytes()).hexdigest() == f0["sha256"]
    assert prov["leds"]["count"] == 252 and prov["camera"]["model"] == "pinhole"
    assert prov["software"]["name"] == "sssrig" and prov["parameters"]["format"] == out_fmt
    assert prov["gradients"]["mode"] == "leds" and prov["gradients"]["exposure_s"]["full/cross"] == 0.01


def _ideal_ortho_capture(folder: Path, *, px_mm: float = 0.25, size: tuple[int, int] = (64, 72)) -> dict:
    """Unblurred sphere (radius 6 mm at the origin) under continuous gradients, orthographic view along +y, with a
    Lambertian reference (reflectance 0.9) facing the camera in the top-left corner; float TIFF frames."""
    H, W = size
    rho_sph = 6.0
    alb = np.array([0.7, 0.5, 0.3])
    v, u = np.mgrid[0:H, 0:W].astype(float)
    x = (u - (W - 1) / 2) * px_mm
    z = -(v - (H - 1) / 2) * px_mm
    r2 = x * x + z * z
    hit = r2 < rho_sph ** 2
    n = np.full((H, W, 3), np.nan)
    n[hit, 0], n[hit, 2] = x[hit] / rho_sph, z[hit] / rho_sph
    n[hit, 1] = -np.sqrt(1 - r2[hit] / rho_sph ** 2)
    tau = tau_ratio(ETA)
    t0 = 2 * (0.5 - fresnel_moment(ETA, 1, side="external"))   # tau0/pi: E_t/E of continuous light
    k = 0.5      # value per second at R_d = 1 facing the camera (the inverse of the albedo scale)
    refl = 0.9
    ft = fresnel_transmittance(ETA, np.clip(-np.nan_to_num(n[..., 1]), 0, 1))
    frames = {}
    exposure = 0.5
    for p in ("ambient", "full", "x", "y", "z", "x_c", "y_c", "z_c"):
        img = np.zeros((H, W, 3))
        if p != "ambient":
            e = np.ones((H, W)) if p == "full" else 0.5 * (1 + (-1 if p.endswith("_c") else 1) * tau
                                                             * np.nan_to_num(n[..., "xyz".index(p[0])]))
            img[hit] = (k * alb[None, :] * (ft * e)[hit][:, None])
            # Lambertian reference facing -y: sees plain irradiance; E_P/E_full = 1/2 (x, z), (1 -+ 2/3)/2 (y)
            lam = 1.0 if p == "full" else 0.5 * (1 + (-1 if p.endswith("_c") else 1) * (2 / 3)
                                                 * (-1.0 if p[0] == "y" else 0.0))
            img[2:8, 2:10] = k * refl / t0 * lam   # a Lambertian target of reflectance refl gives refl/(tau0/pi)
        frames[p] = (exposure * (img + 0.01)).astype(np.float32)
    (folder / "frames").mkdir(parents=True)
    lines = ['format = "sssrig-capture"', "format_version = 1", ""]
    for p, img in frames.items():
        write_float_tiff(folder / f"frames/{p}.tif", img)
        lines += ["[[frames]]", f'file = "frames/{p}.tif"', f'pattern = "{p}"', 'polarization = "cross"',
                  f"exposure_s = {exposure}", ""]
    mask = np.zeros((H, W), np.uint8)
    mask[hit] = 255
    import cv2
    cv2.imwrite(str(folder / "object_mask.png"), mask)
    lines += ["[leds]", "ideal = true", "", "[camera]", 'model = "orthographic"', f"pixel_size_mm = {px_mm}",
              "look_direction = [0.0, 1.0, 0.0]", "", "[radiometry]", f"eta = {ETA}",
              "reference = { region_px = [2, 2, 10, 8], reflectance = 0.9 }", "", "[object]",
              'mask = "object_mask.png"', ""]
    (folder / "capture.toml").write_text("\n".join(lines))
    return {"normals": n, "hit": hit, "albedo": alb}


def test_ideal_orthographic_tiff_capture_with_reference_target(tmp_path, capsys) -> None:
    """Continuous gradients and an unblurred sphere: the closed forms are exact, so the albedo (made absolute by
    the reference patch through albedo_scale_from_lambertian) is recovered to float32 precision (1e-4) and the
    normals to < 0.01 deg. No geometry is given: diffusion is unknown (no curvature information), not a number."""
    folder = tmp_path / "ortho"
    tr = _ideal_ortho_capture(folder)
    s = run_json(folder, capsys, "--format", "tiff", "--tile-rows", "7", "--out", str(tmp_path / "out"))
    assert s["mode"] == "ideal" and s["diffusion"]["status"] == ["unknown"] * 3
    assert "no geometry" in s["diffusion"]["reason"] and not s["maps"]["specular"]
    np.testing.assert_allclose(s["maps"]["albedo_median"], tr["albedo"], rtol=1e-4)
    got = read_maps(tmp_path / "out")
    assert "D_mm" not in got.arrays and got.masks["diffusion_unknown"].all()
    ok = np.isfinite(got.arrays["albedo_diffuse"]).all(-1)
    assert not ok[~tr["hit"]].any() and ok.sum() > 0.8 * tr["hit"].sum()   # reference patch masked out
    np.testing.assert_allclose(got.arrays["albedo_diffuse"][ok], np.broadcast_to(tr["albedo"], (ok.sum(), 3)),
                               rtol=1e-4)
    for ch in "RGB":
        assert angle_deg(got.arrays[f"normals_diffuse_{ch}"][ok], tr["normals"][ok]).max() < 0.01
    assert got.sidecar["provenance"]["parameters"]["tile_rows"] == 7
    assert got.sidecar["provenance"]["radiometry"]["source"].startswith("Lambertian reference")
    import cv2
    assert cv2.imread(str(tmp_path / "out" / "preview.png")).shape[:2] == (2 * PREVIEW_TILE_PX[1],
                                                                          3 * PREVIEW_TILE_PX[0])


def test_orthographic_camera_rays_match_the_analytic_sphere() -> None:
    cam = OrthographicCamera(20, 16, 0.5, ((1.0, 0, 0), (0, 0, -1.0), (0, 1.0, 0)), (1.0, 0.0, 0.5), 9.5, 7.5)
    n, view, hit = sphere_geometry(cam, np.array([1.0, 0.0, 0.5]), 3.0)
    v, u = np.mgrid[0:16, 0:20].astype(float)
    x, z = (u - 9.5) * 0.5, -(v - 7.5) * 0.5
    inside = x * x + z * z < 9.0
    assert np.array_equal(hit, inside)
    np.testing.assert_allclose(n[hit][:, 0], x[hit] / 3, atol=1e-9)
    np.testing.assert_allclose(n[hit][:, 2], z[hit] / 3, atol=1e-9)
    assert np.all(n[hit][:, 1] < 0) and np.allclose(view, [0.0, -1.0, 0.0])
    uv, _ = cam.project(np.array([1.0 + 2.0, 0.0, 0.5 - 1.0]))
    np.testing.assert_allclose(uv, [9.5 + 4, 7.5 + 2])


def test_no_geometry_and_mask_limit_the_maps_table_output(tmp_path, capsys, marble_scene) -> None:
    """Without geometry the diffusion is unknown (never a number); the mask keeps only its half of the sphere.
    Also the human-readable table (no --json) and --out."""
    folder = write_marble_capture(tmp_path / "cap", marble_scene, "exr", geometry=False, seed=False,
                                  parallel=False, mask=True)
    assert main(["estimate", "gradients", str(folder), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "D [mm]" in out and out.count("unknown") >= 3 and "note: diffusion unknown" in out
    got = read_maps(tmp_path / "o")
    assert got.sidecar["summary"]["diffusion"]["status"] == ["unknown"] * 3
    assert not got.sidecar["summary"]["maps"]["specular"] and "D_mm" not in got.arrays
    W = got.shape[1]
    assert not np.isfinite(got.arrays["albedo_diffuse"][:, W // 2:]).any()
    assert np.isfinite(got.arrays["albedo_diffuse"][:, : W // 2]).sum() > 1500
    assert got.masks["background"][:, W // 2:].all()


# ---------------------------------------------------------------------------------------------------- bad input
def _err(folder: Path, capsys) -> str:
    rc = main(["estimate", "gradients", str(folder), "--json"])
    err = capsys.readouterr().err
    assert rc == 2
    return err


@pytest.fixture
def small_capture(tmp_path, marble_scene) -> Path:
    return write_marble_capture(tmp_path / "bad", marble_scene, "exr", parallel=False, seed=False)


def _edit(folder: Path, old: str, new: str) -> None:
    p = folder / "capture.toml"
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))


def test_missing_frame_file_names_file_and_key(small_capture, capsys) -> None:
    (small_capture / "frames/y_c_cross.exr").unlink()
    err = _err(small_capture, capsys)
    assert "capture.toml" in err and "frames[6].file" in err and "frames/y_c_cross.exr" in err
    assert "existing image file" in err


def test_unknown_pattern_and_polarization(small_capture, capsys) -> None:
    _edit(small_capture, 'pattern = "x_c"', 'pattern = "xc"')
    err = _err(small_capture, capsys)
    assert "frames[5].pattern" in err and "one of ambient, full, x, y, z, x_c, y_c, z_c" in err and "'xc'" in err
    _edit(small_capture, 'pattern = "xc"', 'pattern = "x_c"')
    _edit(small_capture, 'polarization = "cross"', 'polarization = "circular"')
    err = _err(small_capture, capsys)
    assert "frames[0].polarization" in err and "one of cross, parallel" in err


def test_duplicate_pattern_polarization(small_capture, capsys) -> None:
    _edit(small_capture, 'pattern = "y"', 'pattern = "x"')
    err = _err(small_capture, capsys)
    assert "frames[3]" in err and "unique (pattern, polarization)" in err and "frames[2] already is (x, cross)" in err


def test_frames_of_different_sizes(small_capture, capsys) -> None:
    write_exr(small_capture / "frames/z_cross.exr", np.zeros((10, 12, 3), np.float32))
    err = _err(small_capture, capsys)
    assert "frames[4].file" in err and "84 x 80 px" in err and "12 x 10 px" in err


def test_unreadable_frame_names_key_and_reason(small_capture, capsys) -> None:
    (small_capture / "frames/full_cross.exr").write_bytes(b"not an exr")
    err = _err(small_capture, capsys)
    assert "frames[1].file" in err and "not a readable OpenEXR file" in err and "frames/full_cross.exr" in err


def test_raw_exposure_must_match_the_recorded_one(tmp_path, capsys, marble_scene) -> None:
    folder = write_marble_capture(tmp_path / "dng", marble_scene, "dng", parallel=False, seed=False)
    _edit(folder, "exposure_s = 0.01", "exposure_s = 0.0125")        # full: the DNG says 0.01 s
    err = _err(folder, capsys)
    assert "frames[1].exposure_s" in err and "full_cross.dng (0.01 s) within 2 %" in err


def test_insufficient_frame_set_lists_what_is_missing(tmp_path, capsys, marble_scene) -> None:
    folder = write_marble_capture(tmp_path / "ins", marble_scene, "exr", parallel=False, seed=False,
                                  drop=("full", "y_c", "ambient"))
    err = _err(folder, capsys)
    assert "field 'frames'" in err and "ambient (cross)" in err
    assert "axis y: y + y_c, or y + full, or y_c + full (cross); have y" in err
    assert "axis x" not in err                      # x and x_c are both there
    assert missing_frames({("ambient", "cross"), ("x", "cross"), ("full", "cross"), ("y_c", "cross"),
                           ("z", "cross"), ("z_c", "cross")}) == []


@pytest.mark.parametrize("old,new,key,expected", [
    ('model = "pinhole"', 'model = "fisheye"', "camera.model", "one of pinhole, orthographic"),
    ("fx_px = 1500.0", "fx_px = -1.0", "camera.fx_px", "a number > 0"),
    ("width_px = 84", "width_px = 100", "camera.width_px", "the frames' size (84 x 80 px)"),
    ("value_per_radiance_per_s = 30.0", "", "radiometry.albedo_scale", "exactly one of albedo_scale"),
    ("eta = 1.3", "eta = 0.9", "radiometry.eta", "a number >= 1.0"),
    ('file = "leds.csv"', 'file = "nope.csv"', "leds.file", "an existing LED calibration"),
    ('shape = "sphere"', 'shape = "cube"', "object.shape", "one of unknown, sphere"),
    ("format_version = 1", "format_version = 2", "format_version", "1"),
    ('name = "marble-exr"', 'nmae = "x"', "nmae", "one of the documented keys"),
])
def test_bad_values_name_file_key_and_expectation(small_capture, capsys, old, new, key, expected) -> None:
    _edit(small_capture, old, new)
    err = _err(small_capture, capsys)
    assert str(small_capture / "capture.toml") in err and f"field '{key}'" in err and expected in err, err


def test_bad_led_csv_row_names_the_row(small_capture, capsys) -> None:
    p = small_capture / "leds.csv"
    lines = p.read_text().splitlines()
    lines[5] = "1.0,2.0,oops,1,1,1"
    p.write_text("\n".join(lines) + "\n")
    err = _err(small_capture, capsys)
    assert "leds.file" in err and "leds.csv line 6" in err and "oops" in err


def test_load_capture_exposes_the_validated_capture(small_capture) -> None:
    cap = load_capture(small_capture)
    assert cap.shape == (80, 84) and len(cap.frames) == 8 and cap.leds.positions_mm.shape == (252, 3)
    assert cap.geometry is not None and cap.geometry.radius_mm == RADIUS and not cap.specular
    assert cap.frames[1].key == ("full", "cross") and cap.frames[1].exposure_s == 0.01


def test_drive_values_reach_the_led_model(small_capture) -> None:
    """Displayed drive values (drive_file) and drive_peak define the pattern values of the LED model."""
    cap = load_capture(small_capture)
    ideal_x = cap.leds.rig(cap.gradient_patterns).pattern_values("x")
    quantized = np.round(ideal_x[:, 0] * 255) / 255
    np.savez(small_capture / "drive.npz", x=quantized)
    _edit(small_capture, 'file = "leds.csv"', 'file = "leds.csv"\ndrive_file = "drive.npz"\ndrive_peak = 0.5')
    cap = load_capture(small_capture)
    rig = cap.leds.rig(cap.gradient_patterns)
    np.testing.assert_array_equal(rig.pattern_values("x")[:, 1], quantized)      # from the file
    np.testing.assert_allclose(rig.pattern_values("full"), 0.5)                    # ideal x drive_peak
    np.testing.assert_allclose(rig.pattern_values("y_c"), 0.5 * LedRig(rig.directions, rig.gains)
                               .pattern_values("y_c"))
    np.savez(small_capture / "drive.npz", q=quantized)
    with pytest.raises(Exception, match=r"leds\.drive_file.*arrays named after gradient patterns"):
        load_capture(small_capture)


def test_memory_mapped_intermediates_give_the_same_maps(small_capture, tmp_path) -> None:
    """Large captures keep their full-size intermediate maps in memory maps (MEMMAP_MIN_PX); forcing that path
    on a small capture gives the same files, and the scratch folder is gone afterwards."""
    from rig.estimate.capture_folder import estimate_capture
    from rig.files.maps_io import read_maps

    cap = load_capture(small_capture)
    ram = estimate_capture(cap, tmp_path / "ram", "exr", 32, preview="opencv", memmap_min_px=10 ** 12)
    mm = estimate_capture(cap, tmp_path / "mm", "exr", 32, preview="opencv", memmap_min_px=0)
    a, b = read_maps(tmp_path / "ram"), read_maps(tmp_path / "mm")
    assert set(a.arrays) == set(b.arrays) and "D_mm" in a.arrays
    for name in a.arrays:
        np.testing.assert_array_equal(a.arrays[name], b.arrays[name], err_msg=name)
    for name in a.masks:
        np.testing.assert_array_equal(a.masks[name], b.masks[name], err_msg=name)
    assert ram["diffusion"] == mm["diffusion"]
    assert not list((tmp_path / "mm").glob(".scratch-*"))


@pytest.mark.parametrize("model", ["dipole-jensen", "mc-table"])
def test_model_option_reaches_the_estimate_and_the_sidecar(small_capture, tmp_path, capsys, model) -> None:
    """``--model`` selects the grounded estimator's profile model; the summary and the sidecar name it and report
    its bias against the Monte Carlo table at the fitted parameters (1 for the table itself)."""
    from rig.files.maps_io import read_maps

    s = run_json(small_capture, capsys, "--model", model, "--out", str(tmp_path / "m"))
    d = s["diffusion"]
    assert d["model"] == model and d["method"] == ("sphere" if model == "dipole-jensen" else "small_blur")
    bias = d["model_bias"]
    assert bias["model"] == model and bias["available"]
    if model == "mc-table":
        assert all(r is None or r == pytest.approx(1.0) for r in bias["r2_ratio"])
    else:
        assert all(r is None or r > 1.0 for r in bias["r2_ratio"])   # Jensen's <r^2> exceeds the table's
    side = read_maps(tmp_path / "m").sidecar
    assert side["provenance"]["parameters"]["model"] == model
    assert side["summary"]["diffusion"]["model"] == model


def test_unknown_model_is_rejected(small_capture, capsys) -> None:
    from rig.cli import main

    assert main(["estimate", "gradients", str(small_capture), "--model", "dipole-foo"]) == 2
    assert "invalid choice: 'dipole-foo'" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------------- --reference
# A capture folder whose frames are a simulated gradient capture (simulators.scene.render_gradient_capture) of a 10 mm
# skin1 sphere (science.md sec. 2, eta 1.3): 362 LEDs at 1 m (rig.acquire.geometry.led_layout), full + x, y, z
# cross-polarized, 32 x 32 px pinhole at 400 mm, a 14-bit sensor's expected values (no noise) written as EXR with
# value_per_radiance_per_s = gain / (white - black).
SKIN1 = (np.array([0.74, 0.88, 1.01]), np.array([0.032, 0.17, 0.48]))
SIM_GAIN, SIM_BLACK, SIM_WHITE, SIM_EXPOSURE = 4.5e7, 512, 16383, 0.02
SIM_PX = 32
SIM_SPP = 128
SIM_FRAME_SEED = 0       # the observation's Monte Carlo realisation
SIM_REF_SEED = 100       # the reference's (independent of the observation's, as for a real capture)


def write_simulated_capture(folder: Path, render_mode: str, *, seed: int = SIM_FRAME_SEED, spp: int = SIM_SPP,
                            geometry: bool = True, camera: str = "pinhole", ideal: bool = False, px: int = SIM_PX
                            ) -> Path:
    from estimation.camera import PinholeCamera
    from rig.acquire.geometry import led_layout
    from simulators.camera import SensorModel
    from simulators.mc_capture import MCSettings
    from simulators.scene import SphereObject, render_gradient_capture

    pos, _ = led_layout(6, 1000.0, -60.0)
    inten = np.full((len(pos), 3), 1000.0)
    if ideal:       # continuous gradients, as the folder's --reference approximates them
        from rig.estimate.folder_diffusion import ideal_reference_leds
        pos, inten = ideal_reference_leds()
        inten = inten * 0.03          # radiance 0.03: the 14-bit sensor's range at this exposure
    rig = LedRig.from_positions(pos, inten)
    patterns = {p: rig.pattern_values(p) for p in ("full", "x", "y", "z")}   # what the folder's LED model drives
    SIM_PX = px
    if camera == "pinhole":
        cam = PinholeCamera.looking_at(width_px=SIM_PX, height_px=SIM_PX, fx_px=SIM_PX * 20.0,
                                       position_mm=(0.0, -400.0, 0.0), target_mm=(0.0, 0.0, 0.0))
        cam_toml = ['model = "pinhole"', f"fx_px = {cam.fx_px}", "position_mm = [0.0, -400.0, 0.0]",
                    "look_at_mm = [0.0, 0.0, 0.0]"]
    else:   # the same field of view, orthographic (the simulator needs view_directions: rig.estimate.reference.folder_reference)
        from rig.estimate.reference.folder_reference import renderable_camera
        cam = renderable_camera(OrthographicCamera.looking_at(width_px=SIM_PX, height_px=SIM_PX,
                                                              pixel_size_mm=20.0 / SIM_PX, direction=(0.0, 1.0, 0.0)))
        cam_toml = ['model = "orthographic"', f"pixel_size_mm = {20.0 / SIM_PX!r}", "look_direction = [0.0, 1.0, 0.0]"]
    sensor = SensorModel(gain_dn_per_unit=SIM_GAIN, black_level_dn=SIM_BLACK, white_level_dn=SIM_WHITE,
                         read_noise_dn=2.0, electrons_per_dn=1.5)
    obj = SphereObject((0.0, 0.0, 0.0), RADIUS, tuple(SKIN1[0]), tuple(SKIN1[1]), ETA, tessellation=3)
    cap = render_gradient_capture(obj, cam, pos, inten, patterns, polarizations=("cross",), exposure_s=SIM_EXPOSURE,
                                  sensor=sensor, noise=False, render_mode=render_mode,
                                  mc=MCSettings(spp=spp, seed=seed))
    (folder / "frames").mkdir(parents=True)
    lines = ['format = "sssrig-capture"', "format_version = 1", f'name = "skin1-{render_mode}"', ""]
    for (p, pol), img in cap.frames.items():
        write_exr(folder / f"frames/{p}_{pol}.exr", img)
        lines += ["[[frames]]", f'file = "frames/{p}_{pol}.exr"', f'pattern = "{p}"', f'polarization = "{pol}"',
                  f"exposure_s = {SIM_EXPOSURE}", ""]
    if ideal:
        scale = albedo_scale_from_radiometry([SIM_GAIN / (SIM_WHITE - SIM_BLACK)] * 3, rig, eta=ETA)
        lines += ["[leds]", "ideal = true", "", "[camera]", *cam_toml, "", "[radiometry]", f"eta = {ETA}",
                  f"albedo_scale = {[float(v) for v in scale]!r}", ""]
    else:
        np.save(folder / "leds.npy", np.hstack([pos, inten]))
        lines += ["[leds]", 'file = "leds.npy"', "", "[camera]", *cam_toml, "", "[radiometry]", f"eta = {ETA}",
                  f"value_per_radiance_per_s = {SIM_GAIN / (SIM_WHITE - SIM_BLACK)!r}", ""]
    if geometry:
        lines += ["[object]", 'shape = "sphere"', "center_mm = [0.0, 0.0, 0.0]", f"radius_mm = {RADIUS}", ""]
    (folder / "capture.toml").write_text("\n".join(lines))
    return folder


def _rel_err(values, truth) -> np.ndarray:
    return np.asarray(values, dtype=float) / np.asarray(truth, dtype=float) - 1.0


@pytest.mark.parametrize("camera", ["pinhole", "orthographic"])
def test_reference_units_fast_render_of_the_folder_sphere_is_a_fixed_point(tmp_path, camera) -> None:
    """Units and plumbing of the reference, without Monte Carlo noise: frames written from a FAST render, reference
    renders FAST too (the same renderer). The reference capture is rendered in simulator units and converted to
    the folder's frame units (value_per_radiance_per_s x exposure) before the folder's own compute_maps, so at the
    truth its observables are the folder's frames' observables and the truth is the correction's fixed point:
    measured corrected sigma_s', sigma_a, D within 4e-4 of the truth (plain sphere inversion: D +0.4..+0.9 %, the
    fast renderer's patch quadrature), kappa_albedo 0.9994-1.0002. A wrong scale (e.g. a missing exposure or
    value_per_radiance) would shift the fixed point by that factor in the albedo. Pinhole and orthographic
    (rendered through rig.estimate.reference.folder_reference.renderable_camera) cameras."""
    from rig.estimate.capture_folder import estimate_capture
    from rig.estimate.reference.folder_reference import implied_value_per_radiance_per_s

    folder = write_simulated_capture(tmp_path / "fast", "fast", camera=camera)
    cap = load_capture(folder)
    assert cap.camera_spec["model"] == camera
    s = estimate_capture(cap, tmp_path / "maps", reference={"spp": 2, "iterations": 3, "seed": 0,
                                                            "render_mode": "fast"})
    ssp, sa = SKIN1
    r = s["diffusion_reference_corrected"]
    assert r["reference"]["renderer"].endswith('(render_mode "fast", simulators.mc_capture)')
    np.testing.assert_allclose(r["reference"]["value_per_radiance_per_s"], SIM_GAIN / (SIM_WHITE - SIM_BLACK),
                               rtol=1e-12)
    leds = cap.leds.rig(cap.gradient_patterns)
    from rig.estimate.capture_folder.estimate import _reference_normal
    np.testing.assert_allclose(implied_value_per_radiance_per_s(s["albedo_scale"], leds, ETA,
                                                                _reference_normal(cap.camera)),
                               SIM_GAIN / (SIM_WHITE - SIM_BLACK), rtol=1e-12)
    np.testing.assert_allclose(r["uncorrected"]["D_mm"], s["diffusion"]["D_mm"]["value"], rtol=1e-9)
    np.testing.assert_allclose(r["sigma_s_prime_per_mm"]["value"], ssp, rtol=2e-3)
    np.testing.assert_allclose(r["sigma_a_per_mm"]["value"], sa, rtol=2e-3)
    np.testing.assert_allclose(r["D_mm"]["value"], 1 / (3 * (ssp + sa)), rtol=2e-3)
    np.testing.assert_allclose(r["kappa_albedo"], 1.0, atol=2e-3)


# corrected D / true - 1 allowed for red / green (measured: module docstring of the test below)
REF_D_TOL_RG = 0.08


def test_reference_corrects_a_monte_carlo_skin1_sphere_end_to_end(tmp_path, capsys) -> None:
    """``rig estimate gradients FOLDER --reference`` on Monte Carlo frames of a 10 mm skin1 sphere (32 x 32 px,
    128 spp, frame seed 0; reference seed 100, 128 spp, at most 4 renders).

    Measured (frame seeds 0-3, reference seed = frame seed + 100; corrected D / true - 1, R / G / B):
    plain +23..+25 / +107..+110 / +210..+240 %; corrected +0.2 / -1.4 / -9.1 % (seed 0), +0.7 / +4.6 / +17.7 %
    (seed 1), +0.5 / -4.3 / +9.0 % (seed 2), +1.2 / +0.2 / +1.2 % (seed 3); none met the 2 % stop rule within 4
    renders (last change 9-13 %, the blue channel). Red and green asserted within 8 % (~1.7 x the largest
    measured), blue (Monte-Carlo-noise-limited blur, kappa_blur 8-12) within 35 % as in
    tests/simulators/test_mc_frames_gradients.py. Also: the summary keeps the uncorrected diffusion beside the
    corrected one and says the per-pixel maps are uncorrected; the table output shows both."""
    folder = write_simulated_capture(tmp_path / "mc", "mc")
    s = run_json(folder, capsys, "--reference", "--reference-spp", str(SIM_SPP), "--reference-seed",
                 str(SIM_REF_SEED), "--reference-iterations", "4")     # below the default 8: CI time
    ssp, sa = SKIN1
    D_true = 1 / (3 * (ssp + sa))
    r = s["diffusion_reference_corrected"]
    plain = _rel_err(s["diffusion"]["D_mm"]["value"], D_true)
    corr = _rel_err(r["D_mm"]["value"], D_true)
    print(f"\nskin1 sphere, capture folder --reference ({r['iterations']} renders, {r['seconds']:.1f} s, "
          f"renders {np.round(r['reference']['render_seconds'], 2).tolist()} s; {r['message']})\n"
          f"  D plain {np.round(plain, 3)} -> corrected {np.round(corr, 3)}; sigma_s' "
          f"{np.round(_rel_err(r['sigma_s_prime_per_mm']['value'], ssp), 3)}, sigma_a "
          f"{np.round(_rel_err(r['sigma_a_per_mm']['value'], sa), 3)}; kappa_albedo "
          f"{np.round(r['kappa_albedo'], 3)}, kappa_blur {np.round(r['kappa_blur'], 2)}")
    assert r["reference"]["spp"] == SIM_SPP and r["reference"]["seed"] == SIM_REF_SEED
    # one render per step; the loop stops before the budget of 4 full-spp renders only when it has converged
    # (issue 19's adaptive sample counts: cheaper renders first, which the budget does not count)
    assert len(r["steps"]) == r["iterations"] == len(r["reference"]["render_seconds"])
    full = sum(n == SIM_SPP for n in r["reference"]["render_spp"])
    assert r["converged"] or full == 4, (r["iterations"], r["reference"]["render_spp"], r["message"])
    assert r["reference"]["render_spp"][0] == SIM_SPP // 8 and r["reference"]["reference_mode"] == "adaptive"
    assert [st["spp"] for st in r["steps"]] == r["reference"]["render_spp"]
    assert "uncorrected" in r["applies_to"] and any("per-pixel maps are uncorrected" in n for n in s["notes"])
    np.testing.assert_allclose(r["uncorrected"]["D_mm"], s["diffusion"]["D_mm"]["value"], rtol=1e-9)
    assert np.all(plain[:2] > 0.15)                               # the bias the reference removes
    assert np.all(np.abs(corr[:2]) <= REF_D_TOL_RG), corr
    assert abs(corr[2]) <= 0.35, corr
    assert np.all(np.array(r["kappa_albedo"]) > 1.04) and not any(r["censored"])
    lo, hi = np.asarray(r["D_mm"]["interval"]).T
    assert np.all(lo < r["D_mm"]["value"]) and np.all(np.asarray(r["D_mm"]["value"]) < hi)
    side = read_maps(folder / "maps").sidecar
    assert side["summary"]["diffusion_reference_corrected"]["D_mm"] == r["D_mm"]
    assert side["provenance"]["parameters"]["reference"]["spp"] == SIM_SPP


def test_reference_needs_a_sphere_and_is_refused_clearly(tmp_path, capsys) -> None:
    """--reference without [object] shape = "sphere": exit 2 naming the file, the key and why (before any maps);
    --reference-spp without --reference is refused too."""
    folder = write_simulated_capture(tmp_path / "nosphere", "fast", geometry=False)
    rc = main(["estimate", "gradients", str(folder), "--reference"])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(folder / "capture.toml") in err and "field 'object.shape'" in err
    assert "--reference renders the known sphere" in err
    assert not (folder / "maps").exists()
    rc = main(["estimate", "gradients", str(folder), "--reference-spp", "16"])
    err = capsys.readouterr().err
    assert rc == 2 and "--reference-spp" in err and "only together with --reference" in err


def test_reference_with_ideal_gradients_renders_a_dense_led_set(tmp_path) -> None:
    """Issue 16: --reference is no longer refused for ideal (continuous) gradients: the reference renders a dense
    synthetic LED set (rig.estimate.folder_diffusion.ideal_reference_leds; the renderer reads LEDs as a distant map anyway)
    and reduces the renders with the folder's ideal model. Fast renders (the dipole), one iteration: the plumbing,
    not the accuracy."""
    from rig.estimate.folder_diffusion import ideal_reference_leds

    pos, inten = ideal_reference_leds()
    assert len(pos) == 1962 and np.allclose(np.linalg.norm(pos, axis=1), 1e5)
    assert abs(pos[:, 2].mean()) < 1e-3 * 1e5          # a full sphere: no floor cut-off
    folder = write_simulated_capture(tmp_path / "ideal", "fast", ideal=True, px=16)
    assert "ideal = true" in (folder / "capture.toml").read_text()
    s = estimate_capture(load_capture(folder), tmp_path / "o", reference={"spp": 2, "iterations": 1, "seed": 1,
                                                                           "render_mode": "fast"})
    r = s["diffusion_reference_corrected"]
    assert r["reference"]["spp"] == 2 and len(r["D_mm"]["value"]) == 3

