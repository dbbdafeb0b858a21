"""The simulated calibration targets (``simulators.targets``) render what their truth says."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from simulators.camera import SensorModel
from simulators.targets import (CalibrationTruth, CharucoBoardTarget, DiffuseSphereTarget, LensCamera, MarkerPlate,
                                MarkerPlatesTarget, MirrorBallTarget, TargetWorld, TileTarget, charuco_poses,
                                distort_normalized, expose_raw, undistort_normalized)

DIST = (-0.18, 0.22, 6e-4, -4e-4, 0.0)


@pytest.fixture(scope="module")
def lens():
    pin = PinholeCamera.looking_at(width_px=320, height_px=240, fx_px=1000.0, position_mm=(0, -400, 0),
                                   target_mm=(0, 0, 0))
    pin = PinholeCamera(320, 240, 1000.0, 1002.0, 162.1, 118.3, pin.rotation, pin.center_mm)
    return LensCamera(pin, DIST)


@pytest.fixture(scope="module")
def leds():
    from rig.acquire.geometry import led_layout

    return led_layout(4, 1000.0, -60.0)[0]


def test_lens_model_round_trip(lens):
    xy = np.random.default_rng(0).uniform(-0.2, 0.2, (500, 2))
    assert np.abs(undistort_normalized(distort_normalized(xy, DIST), DIST) - xy).max() < 1e-12
    pts = np.random.default_rng(1).uniform(-50, 50, (100, 3))
    uv, z = lens.project(pts)
    d = lens.pixel_directions(uv)
    back = (pts - lens.pinhole.C) / np.linalg.norm(pts - lens.pinhole.C, axis=1, keepdims=True)
    assert np.all(z > 0) and np.abs(d - back).max() < 1e-12
    with pytest.raises(ValueError, match="did not converge"):
        undistort_normalized(np.array([[3.0, 3.0]]), (-0.9, 0.0, 0.0, 0.0, 0.0), iterations=5)


def test_charuco_render_puts_corners_at_their_true_projections(lens, leds):
    from rig.calibration.intrinsics import detect_charuco

    poses = charuco_poses(lens.pinhole, 9 * 8.0, 7 * 8.0, 3, seed=1)
    board = CharucoBoardTarget(9, 7, 8.0, 5.8, 0, poses)         # DICT_4X4_50 is OpenCV id 0
    em = np.full((len(leds), 3), 800.0)
    for k in range(3):
        board.pose_index = k
        img = board.render(lens, leds, em, Polarization.CROSS)
        from scipy.ndimage import gaussian_filter

        img = gaussian_filter(img[..., 1], 0.7)
        corners, ids = detect_charuco(img, board.board())
        assert len(ids) >= 20
        truth = lens.project(board.corners_world(k))[0][ids]
        assert np.abs(corners - truth).max() < 0.25          # the detector's sub-pixel accuracy on a clean render
    # white squares: rho/pi E/2 (cross-polarized) with the plate's albedo
    assert 0 < img.max() <= 0.5 * 0.85 / np.pi * 800.0 * len(leds) / 1000.0 ** 2 + 1e-9


def test_plate_centres_project_where_the_reflector_is(lens, leds):
    from scipy.ndimage import gaussian_filter

    from rig.files.camera_intrinsics import Intrinsics
    from rig.calibration.rig_frame import detect_marker_centers

    plates = [MarkerPlate(32 + i, (x, y, z), (0.0, -1.0, 0.2), marker_mm=8.0, target_mm=8.0, margin_mm=2.4)
              for i, (x, y, z) in enumerate([(-35, -50, 20), (25, 0, -15), (0, 60, 25), (-40, 90, -30)])]
    target = MarkerPlatesTarget(plates, 0)
    img = gaussian_filter(target.render(lens, leds, np.full((len(leds), 3), 800.0), Polarization.CROSS)[..., 1],
                          0.7)
    p = lens.pinhole
    intr = Intrinsics(p.width_px, p.height_px, p.fx_px, p.fy_px, p.cx_px, p.cy_px, DIST)
    centers = detect_marker_centers(img, "DICT_4X4_50", intr, marker_mm=8.0, target_mm=8.0, margin_mm=2.4)
    assert sorted(centers) == [32, 33, 34, 35]
    for pl in plates:
        xc = (np.asarray(pl.center_mm) - p.C) @ p.R.T
        assert np.abs(centers[pl.marker_id] - xc[:2] / xc[2]).max() * p.fx_px < 0.05


def test_mirror_ball_highlight_at_the_reflection_point(lens, leds):
    from scipy.ndimage import gaussian_filter

    from rig.calibration.led_directions import highlight_centroid

    ball = MirrorBallTarget((1.0, -0.5, 0.5), 20.0, extinction_ratio=0.01)
    truth_uv = ball.true_highlights(lens, leds)
    for i in (3, 40, 77):
        em = np.zeros((len(leds), 3))
        em[i] = 800.0
        par = gaussian_filter(ball.render(lens, leds, em, Polarization.PARALLEL).sum(-1), 0.7)
        crs = gaussian_filter(ball.render(lens, leds, em, Polarization.CROSS).sum(-1), 0.7)
        if not np.all(np.isfinite(truth_uv[i])) or not (0 < truth_uv[i][0] < 319 and 0 < truth_uv[i][1] < 239):
            continue
        uv, _ = highlight_centroid(par)
        assert np.linalg.norm(uv - truth_uv[i]) < 0.05          # a finite LED disc: centroid ~ its centre's image
        # crossed polarizers pass the extinction ratio of the specular energy (the diffuse residue is tiny here)
        spot = np.hypot(*(np.mgrid[0:240, 0:320][::-1] - uv[:, None, None])) < 4
        assert abs(crs[spot].sum() / par[spot].sum() - 0.01) < 0.002


def test_diffuse_sphere_and_tile_radiance_match_closed_form(lens, leds):
    em = np.zeros((len(leds), 3))
    i = int(np.argmin(np.linalg.norm(leds / 1000.0 - [0, -1, 0], axis=1)))      # the LED behind the camera
    em[i] = (900.0, 1000.0, 1100.0)
    sphere = DiffuseSphereTarget((0.0, 0.0, 0.0), 20.0, (0.5, 0.6, 0.7))
    img = sphere.render(lens, leds, em, Polarization.NONE)
    p = lens.pinhole
    uv, _ = lens.project(np.array([0.0, -20.0, 0.0]))            # the sphere's point facing the camera
    x = np.array([0.0, -20.0, 0.0])
    d = leds[i] - x
    expected = np.array([0.5, 0.6, 0.7]) / np.pi * em[i] * (d @ [0, -1, 0]) / np.linalg.norm(d) ** 3
    got = img[int(round(uv[1])), int(round(uv[0]))]
    assert np.allclose(got, expected, rtol=0.01)
    tile = TileTarget((0.0, 0.0, 0.0), (0.0, -1.0, 0.0), 40.0, (0.99, 0.99, 0.99))
    t_img = tile.render(lens, leds, em, Polarization.CROSS)
    uv0, _ = lens.project(np.zeros(3))
    d = leds[i]
    e = em[i] * (d @ [0, -1, 0]) / np.linalg.norm(d) ** 3
    assert np.allclose(t_img[int(round(uv0[1])), int(round(uv0[0]))], 0.5 * 0.99 / np.pi * e, rtol=0.005)
    assert p.width_px == img.shape[1]


def test_expose_raw_pedestal_and_nonlinearity():
    sensor = SensorModel(1e4, 512, 16383, 0.0, 1e6)           # no read noise, negligible photon noise
    rng = np.random.default_rng(0)
    rad = np.full((4, 4, 3), 0.5)
    lin = expose_raw(rad, 1.0, sensor, rng).astype(float)
    assert np.allclose(lin - 512, 5000, atol=1)
    raw = expose_raw(rad, 1.0, sensor, rng, black_offset_dn=3.0, nonlinearity=0.02).astype(float)
    span = 16383 - 512
    assert np.allclose(raw - 515, 5000 * (1 - 0.02 * 5000 / span), atol=1)
    assert expose_raw(rad * 10, 1.0, sensor, rng).max() == 16383          # clipped at white


def test_world_attaches_to_a_simulated_camera(lens, leds, tmp_path):
    from simulators.camera import SimulatedCamera
    from simulators.scene import SphereObject

    truth = CalibrationTruth.perturbed(lens.pinhole, leds, seed=0)
    obj = SphereObject((0, 0, 0), 10.0, (2.19, 2.62, 3.0), (0.0021, 0.0041, 0.0071), 1.3, tessellation=1)
    cam = SimulatedCamera(obj, lens.pinhole, leds, (1000.0, 1000.0, 1000.0), tmp_path,
                          SensorModel(4.5e7, 512, 16383, 0.0, 1.5))
    try:
        world = TargetWorld(truth, DiffuseSphereTarget((0, 0, 0), 20.0))
        world.attach(cam)
        em = np.zeros((len(leds), 3))
        em[5] = 800.0
        raw = cam.render_raw(em, Polarization.CROSS, 0.5)
        assert raw.shape == (480, 640) and raw.max() > 600 and world.renders == 1
        # the truth differs from the design: gains around 1, LEDs moved by ~1 mm, a distorted lens
        assert 0.7 < truth.led_gains.min() and truth.led_gains.max() < 1.4 and truth.led_gains.std() > 0.03
        moved = np.linalg.norm(truth.led_positions_mm - leds, axis=1)
        assert 0.3 < np.median(moved) < 5.0 and any(truth.camera.distortion)
    finally:
        cam.close()
