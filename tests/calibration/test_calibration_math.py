"""Unit tests of the calibration math, the plan builder and the settings (no devices)."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.errors import ConfigError, LimitError
from estimation.camera import PinholeCamera
from rig.calibration.capture import Shot, Survey, build_plan, exposure_and_peak
from rig.files.camera_intrinsics import Intrinsics
from rig.calibration.common import fit_transform, reflect, sphere_from_silhouette
from rig.calibration.led_directions import highlight_centroid, led_direction_from_highlight
from rig.calibration.radiometry import fit_linearity, linearize
from rig.calibration.rig_frame import camera_pose_pnp, refine_leds
from rig.config.calibration_settings import load_settings
from simulators.targets import DiffuseSphereTarget, LensCamera, distort_normalized, rotation_about

DIST = (-0.18, 0.22, 6e-4, -4e-4, 0.0)


def _cam(distortion=DIST):
    pin = PinholeCamera.looking_at(width_px=200, height_px=150, fx_px=650.0, position_mm=(0, -400, 0),
                                   target_mm=(0, 0, 0))
    pin = PinholeCamera(200, 150, 650.0, 652.0, 101.3, 73.9, pin.rotation, pin.center_mm)
    return LensCamera(pin, distortion), Intrinsics(200, 150, 650.0, 652.0, 101.3, 73.9, distortion)


def test_intrinsics_undistortion_inverts_the_simulator_lens():
    lens, intr = _cam()
    xy = np.random.default_rng(1).uniform(-0.2, 0.2, (200, 2))
    d = distort_normalized(xy, DIST)
    uv = np.stack([d[:, 0] * 650.0 + 101.3, d[:, 1] * 652.0 + 73.9], -1)
    assert np.abs(intr.normalized(uv) - xy).max() < 1e-9
    assert np.abs(intr.project(np.c_[xy, np.ones(len(xy))]) - uv).max() < 1e-9
    # and the simulator's ray through a pixel is the calibration's (same OpenCV model, independent code)
    rays = lens.pixel_directions(uv) @ lens.pinhole.R.T
    assert np.abs(rays - intr.rays(uv)).max() < 1e-12


@pytest.mark.parametrize("scale", [False, True])
def test_fit_transform_recovers_a_known_motion(scale):
    rng = np.random.default_rng(2)
    src = rng.normal(0, 500, (12, 3))
    R = rotation_about((1, 2, 3), 0.01)
    t = np.array([1.5, -2.0, 0.7])
    s = 1.002 if scale else 1.0
    dst = s * src @ R.T + t
    R2, t2, s2 = fit_transform(src, dst, scale=scale)
    assert np.allclose(R2, R, atol=1e-12) and np.allclose(t2, t, atol=1e-9) and abs(s2 - s) < 1e-12


def test_refine_leds_moves_the_design_and_keeps_surveys():
    rng = np.random.default_rng(3)
    design = rng.normal(size=(30, 3))
    design *= 1000.0 / np.linalg.norm(design, axis=1, keepdims=True)
    R = rotation_about((0, 0, 1), np.radians(0.3))
    true = design @ R.T + [2.0, 0, -1.0]
    surveyed = {i: true[i] + rng.normal(0, 0.1, 3) for i in (0, 5, 9, 17, 22)}
    pos, source, fit = refine_leds(design, surveyed)
    assert np.abs(pos - true).max() < 0.5 < np.abs(design - true).max()
    assert source[5] == "survey" and source[1] == "design+fit"
    assert np.allclose(pos[5], surveyed[5]) and fit["rms_mm"] < 0.3
    assert abs(fit["rotation_deg"] - 0.3) < 0.02


def test_camera_pose_pnp_exact_points():
    lens, intr = _cam((0, 0, 0, 0, 0))
    pts = np.random.default_rng(4).uniform(-40, 40, (8, 3))
    uv, _ = lens.project(pts)
    R, C, err = camera_pose_pnp(pts, intr.normalized(uv), intr.fx_px)
    assert np.allclose(R, lens.pinhole.R, atol=1e-9) and np.allclose(C, lens.pinhole.C, atol=1e-6)
    assert err.max() < 1e-6
    with pytest.raises(ValueError, match="at least 4"):
        camera_pose_pnp(pts[:3], intr.normalized(uv[:3]), 650.0)


def test_sphere_from_silhouette_of_a_rendered_ball():
    from scipy.ndimage import gaussian_filter

    lens, intr = _cam()
    center = np.array([3.0, 5.0, -2.0])
    target = DiffuseSphereTarget(tuple(center), 20.0)
    from rig.acquire.geometry import led_layout

    leds, _ = led_layout(4, 1000.0, -60.0)                   # every LED on: the whole visible side is lit
    img = target.render(lens, leds, np.full((len(leds), 3), 1000.0), 0)[..., 1]
    img = gaussian_filter(img, 0.7)
    fit = sphere_from_silhouette(img, intr, 20.0)
    found = lens.pinhole.C + lens.pinhole.R.T @ fit.center_cam_mm
    view = (center - lens.pinhole.C) / np.linalg.norm(center - lens.pinhole.C)
    err = found - center
    # across the view the outline pins the centre to ~0.01 px; along it the distance comes from the outline's
    # angular size (r / sin alpha): a 0.02 px radius error at 32 px radius is 0.25 mm at 400 mm
    assert np.linalg.norm(err - (err @ view) * view) < 0.05
    assert abs(err @ view) < 0.6
    assert fit.rms_px < 0.2 and fit.inliers > 300


def test_mirror_reflection_round_trip():
    lens, intr = _cam()
    ball, radius, led = np.array([0.5, -0.5, 0.3]), 20.0, np.array([300.0, -700.0, 650.0])
    led = led / np.linalg.norm(led) * 1000.0
    from simulators.targets import _reflection_points

    p, ok = _reflection_points(lens.pinhole.C, ball, radius, led[None, :])
    uv, _ = lens.project(p)
    w = led_direction_from_highlight(uv[0], intr, lens.pinhole.R, lens.pinhole.C, ball, radius, 1000.0)
    assert ok[0] and np.degrees(np.arccos(np.clip(w @ led / 1000.0, -1, 1))) < 1e-6
    n = np.array([0.0, 0.0, 1.0])
    assert np.allclose(reflect([[1.0, 0.0, -1.0]], n), [[1.0, 0.0, 1.0]])


def test_highlight_centroid_subpixel():
    img = np.zeros((40, 40))
    v, u = np.mgrid[0:40, 0:40]
    img += np.exp(-((u - 17.3) ** 2 + (v - 22.6) ** 2) / (2 * 0.8 ** 2)) + 0.01
    uv, peak = highlight_centroid(img)
    assert np.allclose(uv, [17.3, 22.6], atol=0.01) and peak > 0.8


def test_linearity_fit_and_inverse():
    t = np.array([0.002, 0.004, 0.008, 0.016, 0.03])
    a = np.array([20.0, 25.0, 30.0])
    beta = np.array([0.02, 0.0, -0.01])
    x = np.outer(t, a)
    v = x * (1 - beta * x)
    a2, b2, dev = fit_linearity(t, v)
    assert np.allclose(a2, a, rtol=1e-9) and np.allclose(b2, beta, atol=1e-9)
    assert dev[1] < 1e-12 < dev[0]
    res = {"black_offset_dn": [0.0] * 3, "span_dn": 1000.0, "nonlinearity": beta.tolist()}
    assert np.allclose(linearize(v, res), x, atol=1e-12)


def test_build_plan_slots_polarization_operator_and_limits(cal_config):
    dirs = np.eye(3)[[0, 1, 2, 0, 1, 2, 0, 1, 2, 0]]
    dirs = dirs + 0.01 * np.arange(10)[:, None]
    items = [Shot("a", 0.01, "full", operator={"say": "put the ball", "target": "mirror_ball"}),
             Shot("amb", 0.01, "ambient", polarization="parallel")]
    items += [Shot(f"l{i}", 0.01, "key", led=i, polarization="parallel") for i in range(10)]
    items += [Shot("again", 0.01, "key", led=3, polarization="parallel"), Survey("object_top")]
    import dataclasses

    cfg = dataclasses.replace(cal_config, sphere=dataclasses.replace(cal_config.sphere, slots=4))
    steps = build_plan(items, cfg, dirs)
    kinds = [s.kind for s in steps]
    assert kinds[0] == "checkpoint" and steps[0].params["operator"]["target"] == "mirror_ball"
    assert kinds.count("fetch") == 13 and kinds.count("survey") == 1 and kinds[-1] == "all_off"
    assert [s.params["state"] for s in steps if s.kind == "polarization"] == ["cross", "parallel"]
    uploads = [s for s in steps if s.kind == "upload"]
    assert {s.params["slot"] for s in uploads} == {0, 1, 2, 3}                 # round-robin over 4 slots
    assert len(uploads) == 12                # full + 10 LEDs + LED 3 again (its slot was reused meanwhile)
    fetch = {s.params["pattern"]: s for s in steps if s.kind == "fetch"}
    assert fetch["l7"].params["led"] == 7 and fetch["amb"].params["polarization"] == "parallel"
    for s in uploads:                          # each upload serves the frames that use it
        assert s.serves and all(steps[i].kind == "fetch" for i in s.serves)
    with pytest.raises(LimitError, match="watchdog"):
        build_plan([Shot("long", 6.0, "full")], cfg, dirs)
    with pytest.raises(ValueError, match="duplicate"):
        build_plan([Shot("x", 0.01), Shot("x", 0.01)], cfg, dirs)
    with pytest.raises(ValueError, match="LED index"):
        Shot("k", 0.01, "key")


def test_exposure_and_peak_dims_leds_instead_of_overexposing(cal_config):
    t, peak = exposure_and_peak(cal_config, 1.0, 0.5)             # 1 radiance unit: far too bright for 1 ms
    assert t == 0.001 and peak < cal_config.sphere.pattern_peak
    t, peak = exposure_and_peak(cal_config, 1e-3, 0.5)
    assert t > 0.001 and peak == cal_config.sphere.pattern_peak and round(t * 1000) == t * 1000


def test_settings_from_toml_and_errors(cal_config):
    s = load_settings(cal_config)
    assert s.mirror_ball.count == 8 and s.seed_k.lut_size == 33
    assert s.board.square_mm > 0 and s.mirror_ball.radius_mm > 0          # auto sizes resolved
    with pytest.raises(ConfigError, match=r"calibration\.board\.viewz"):
        load_settings(cal_config, {"board": {"viewz": 3}})
    with pytest.raises(ConfigError, match=r"calibration\.mirror_ball\.leds"):
        load_settings(cal_config, {"mirror_ball": {"leds": [1.5]}})
    with pytest.raises(ConfigError, match=r"calibration\.pose_targets\.first_id"):
        load_settings(cal_config, {"pose_targets": {"first_id": 10}})       # overlaps the board's markers
    with pytest.raises(ConfigError, match=r"calibration\.board\.dictionary"):
        load_settings(cal_config, {"board": {"dictionary": "DICT_9X9_1"}})
