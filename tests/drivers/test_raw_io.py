"""RAW I/O: simulated DNGs written with tifffile decode bit-exactly in rawpy; ``load_linear`` recovers the
rendered linear RGB up to quantization; ``FolderCamera`` picks up new files and times out without one."""
from __future__ import annotations

import math
import os
import threading
import time

import numpy as np
import pytest
import rawpy
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from drivers.camera import FolderCamera, RawFileError, load_linear
from drivers.camera.raw import cfa_cell_indices, superpixel_rgb
from drivers.contracts import Camera, RawFrame
from drivers.errors import DeviceTimeout
from simulators.dng import mosaic_rggb, write_dng

WHITE = 16383
BLACK4 = (500, 510, 520, 530)          # R, Gr, Gb, B


def rendering(h: int = 12, w: int = 14, seed: int = 0) -> np.ndarray:
    rgb = np.random.default_rng(seed).uniform(0.0, 1.0, (h, w, 3))
    rgb[0, 0] = (0.25, 0.5, 0.75)        # known per-channel values
    rgb[0, 1] = (0.0, 0.0, 0.0)          # black
    rgb[0, 2] = (1.0, 1.0, 1.0)          # white level
    return rgb


# --------------------------------------------------------------------------------- write + decode
@pytest.mark.parametrize("black", [512, BLACK4])
def test_rawpy_decodes_the_mosaic_bit_exactly(tmp_path, black):
    rgb = rendering()
    path = tmp_path / "f.dng"
    mosaic = write_dng(path, rgb, exposure_s=0.02, black_level=black)
    assert mosaic.shape == (24, 28) and mosaic.dtype == np.uint16
    with rawpy.imread(os.fspath(path)) as rp:
        assert np.array_equal(rp.raw_image_visible, mosaic)
        assert rp.white_level == WHITE
        want = [black] * 4 if isinstance(black, int) else [black[0], black[1], black[3], black[2]]
        assert list(rp.black_level_per_channel) == want          # rawpy order: R, G, B, G2
        assert rp.color_desc == b"RGBG"
        assert rp.raw_colors_visible[:2, :2].tolist() == [[0, 1], [3, 2]]


def test_mosaic_layout_is_rggb_with_black_level_added():
    rgb = np.zeros((1, 1, 3))
    rgb[0, 0] = (0.25, 0.5, 1.0)
    m = mosaic_rggb(rgb, black_level=BLACK4, white_level=WHITE)
    assert m.tolist() == [[round(500 + 0.25 * (WHITE - 500)), round(510 + 0.5 * (WHITE - 510))],
                          [round(520 + 0.5 * (WHITE - 520)), WHITE]]


@pytest.mark.parametrize("black", [512, BLACK4])
def test_load_linear_recovers_rendering_up_to_quantization(tmp_path, black):
    rgb = rendering()
    path = tmp_path / "f.dng"
    write_dng(path, rgb, exposure_s=0.02, black_level=black)
    out, meta = load_linear(path)
    assert out.dtype == np.float32 and out.shape == rgb.shape
    b = np.broadcast_to(np.asarray(black, dtype=float), (4,))
    quant = 0.5 / (WHITE - np.array([b[0], min(b[1], b[2]), b[3]]))     # half a DN, per channel
    err = np.abs(out.astype(np.float64) - rgb)
    assert np.all(err <= quant + 1e-7), err.max(axis=(0, 1))
    assert np.all(out[0, 1] == 0.0)                  # black level subtracted exactly
    assert np.all(out[0, 2] == 1.0)                  # white level -> 1.0
    np.testing.assert_allclose(out[0, 0], (0.25, 0.5, 0.75), atol=quant.max() + 1e-7)
    assert meta["cfa_pattern"] == "RGGB"
    assert meta["black_levels"] == tuple(float(x) for x in b)
    assert meta["white_level"] == WHITE
    assert meta["exposure_s"] == 0.02
    assert (meta["make"], meta["model"]) == ("sssrig", "SimCam")
    assert meta["path"] == os.fspath(path) and meta["raw_shape"] == (24, 28)


def test_load_linear_is_linear_without_gamma_or_auto_brightness(tmp_path):
    ramp = np.zeros((11, 11, 3))
    ramp[..., :] = np.linspace(0.0, 0.1, 11)[None, :, None]     # a dim ramp: auto-brightness would lift it
    write_dng(tmp_path / "r.dng", ramp, exposure_s=1.0, bits=12)
    out, meta = load_linear(tmp_path / "r.dng")
    assert meta["white_level"] == 4095
    slope = np.polyfit(ramp[0, :, 0], out[0, :, 0], 1)
    np.testing.assert_allclose(slope, (1.0, 0.0), atol=2e-3)
    assert out.max() <= 0.1 + 0.5 / (4095 - 512)


def test_saturation_and_below_black_noise(tmp_path):
    rgb = np.full((11, 11, 3), 0.5)
    rgb[0, 0] = (1.7, 1.0, 2.0)               # over-exposed: clipped at the white level
    rgb[0, 1] = (-0.01, -0.01, -0.01)         # read noise below black: kept (DN below black)
    mosaic = write_dng(tmp_path / "s.dng", rgb, exposure_s=0.01)
    assert mosaic.max() == WHITE
    out, _ = load_linear(tmp_path / "s.dng")
    assert np.all(out[0, 0] == 1.0)
    np.testing.assert_allclose(out[0, 1], -0.01, atol=0.5 / (WHITE - 512))


def test_exposure_metadata_is_exact_for_awkward_values(tmp_path):
    write_dng(tmp_path / "e.dng", np.zeros((11, 11, 3)), exposure_s=1 / 3)
    _, meta = load_linear(tmp_path / "e.dng")
    assert meta["exposure_s"] == pytest.approx(1 / 3, rel=1e-9)


@settings(max_examples=40, deadline=None)
@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 5), st.integers(1, 5), st.just(3)),
                  elements=st.floats(0.0, 1.0)),
       st.lists(st.integers(0, 600), min_size=4, max_size=4), st.integers(10, 16))
def test_superpixel_inverts_mosaic_up_to_quantization(rgb, black, bits):
    white = (1 << bits) - 1
    m = mosaic_rggb(rgb, black_level=black, white_level=white)
    cell = ((0, 0), (0, 1), (1, 0), (1, 1))
    out = superpixel_rgb(m, cell, np.reshape(black, (2, 2)), np.full((2, 2), white))
    tol = 0.5 / (white - max(black)) + 1e-6
    assert np.all(np.abs(out - rgb) <= tol)


# --------------------------------------------------------------------------------- CFA handling
def test_other_bayer_layouts_and_odd_edges():
    colors = np.tile(np.array([[2, 1], [3, 0]]), (3, 4))[:5, :7]    # BGGR, odd size
    r, g1, g2, b, name = cfa_cell_indices(colors, "RGBG")
    assert name == "BGGR" and (r, b) == ((1, 1), (0, 0)) and {g1, g2} == {(0, 1), (1, 0)}
    raw = np.arange(35, dtype=np.uint16).reshape(5, 7) + 100
    out = superpixel_rgb(raw, (r, g1, g2, b), np.full((2, 2), 100.0), np.full((2, 2), 200.0))
    assert out.shape == (2, 3, 3)                                   # last row and column dropped
    assert out[0, 0].tolist() == pytest.approx([8 / 100, (1 + 7) / 2 / 100, 0.0])


@pytest.mark.parametrize("colors, desc, match", [
    (np.tile(np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1]]), (2, 2)), "RGBG", "2x2"),   # not 2x2-periodic
    (np.tile(np.array([[0, 1], [2, 3]]), (2, 2)), "CMYG", "one R, two G"),
    (np.tile(np.array([[0, 0], [0, 0]]), (2, 2)), "RGBG", "one R, two G"),
])
def test_unsupported_cfas_are_refused(colors, desc, match):
    with pytest.raises(RawFileError, match=match):
        cfa_cell_indices(colors, desc, "x.raw")


def test_unreadable_and_missing_files_name_the_file(tmp_path):
    bad = tmp_path / "junk.dng"
    bad.write_bytes(b"II*\x00 this is not a raw file" * 10)
    with pytest.raises(RawFileError, match="junk.dng") as info:
        load_linear(bad)
    assert info.value.path == os.fspath(bad)
    with pytest.raises(FileNotFoundError, match="missing.dng"):
        load_linear(tmp_path / "missing.dng")


@pytest.mark.parametrize("rgb, kw, match", [
    (np.zeros((10, 20, 3)), {}, "too small"),
    (np.full((11, 11, 3), np.nan), {}, "NaN"),
    (np.zeros((11, 11)), {}, r"\(H, W, 3\)"),
    (np.zeros((11, 11, 3)), {"bits": 17}, "bits"),
    (np.zeros((11, 11, 3)), {"black_level": 20000}, "black level"),
])
def test_write_dng_refuses_bad_input(tmp_path, rgb, kw, match):
    with pytest.raises(ValueError, match=match):
        write_dng(tmp_path / "x.dng", rgb, exposure_s=0.01, **kw)
    assert list(tmp_path.iterdir()) == []


def test_write_is_atomic_and_cleans_up_on_failure(tmp_path, monkeypatch):
    write_dng(tmp_path / "ok.dng", np.zeros((11, 11, 3)), exposure_s=0.01)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.dng"]          # no temporary left over
    assert (tmp_path / "ok.dng").stat().st_mode & 0o777 == 0o644
    import tifffile

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(tifffile, "imwrite", boom)
    with pytest.raises(OSError, match="disk full"):
        write_dng(tmp_path / "fail.dng", np.zeros((11, 11, 3)), exposure_s=0.01)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.dng"]


# --------------------------------------------------------------------------------- FolderCamera
def _write_later(path, rgb, delay_s, exposure_s=0.02) -> threading.Thread:
    def run() -> None:
        time.sleep(delay_s)
        write_dng(path, rgb, exposure_s=exposure_s)
    th = threading.Thread(target=run)
    th.start()
    return th


def test_folder_camera_picks_up_a_new_dng(tmp_path):
    write_dng(tmp_path / "old.dng", np.zeros((11, 11, 3)), exposure_s=0.5)    # present before arm
    cam = FolderCamera(tmp_path, settle_s=0.02)
    assert isinstance(cam, Camera)
    cam.arm()
    rgb = rendering(11, 13, seed=3)
    th = _write_later(tmp_path / "IMG_0001.DNG", rgb, 0.1)
    frame = cam.fetch(timeout_s=3.0)
    th.join()
    assert isinstance(frame, RawFrame)
    assert frame.path == os.fspath(tmp_path / "IMG_0001.DNG")
    assert frame.exposure_s == 0.02
    assert np.all(np.abs(frame.rgb - rgb) <= 0.5 / (WHITE - 512) + 1e-7)
    with pytest.raises(DeviceTimeout):          # the same file is not returned twice
        cam.fetch(timeout_s=0.1)


def test_folder_camera_times_out_when_nothing_arrives(tmp_path):
    write_dng(tmp_path / "old.dng", np.zeros((11, 11, 3)), exposure_s=0.5)
    (tmp_path / "notes.txt").write_text("not a frame")
    cam = FolderCamera(tmp_path)
    cam.arm()
    (tmp_path / "other.txt").write_text("still not a frame")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"\*\.dng"):
        cam.fetch(timeout_s=0.25)
    assert 0.25 <= time.monotonic() - t0 < 1.0


def test_folder_camera_returns_several_new_files_oldest_first(tmp_path):
    cam = FolderCamera(tmp_path, settle_s=0.0)
    cam.arm()
    write_dng(tmp_path / "b.dng", np.full((11, 11, 3), 0.2), exposure_s=0.01)
    time.sleep(0.02)
    write_dng(tmp_path / "a.dng", np.full((11, 11, 3), 0.4), exposure_s=0.02)
    first, second = cam.fetch(1.0), cam.fetch(1.0)
    assert [os.path.basename(first.path), os.path.basename(second.path)] == ["b.dng", "a.dng"]
    assert (first.exposure_s, second.exposure_s) == (0.01, 0.02)


def test_folder_camera_waits_for_a_file_still_being_written(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    rgb = rendering(11, 11, seed=5)
    write_dng(src / "full.dng", rgb, exposure_s=0.03)
    data = (src / "full.dng").read_bytes()
    drop = tmp_path / "drop"
    drop.mkdir()
    cam = FolderCamera(drop, settle_s=0.1)
    cam.arm()

    def slow_writer() -> None:               # a non-atomic writer: the file grows in chunks
        with open(drop / "slow.dng", "wb") as fh:
            for i in range(0, len(data), 128):
                fh.write(data[i:i + 128])
                fh.flush()
                time.sleep(0.02)

    th = threading.Thread(target=slow_writer)
    th.start()
    frame = cam.fetch(timeout_s=5.0)
    th.join()
    assert os.path.getsize(frame.path) == len(data)
    assert np.all(np.abs(frame.rgb - rgb) <= 0.5 / (WHITE - 512) + 1e-7)


def test_folder_camera_replaced_file_counts_as_new(tmp_path):
    write_dng(tmp_path / "shot.dng", np.zeros((11, 11, 3)), exposure_s=0.1)
    cam = FolderCamera(tmp_path, settle_s=0.0)
    cam.arm()
    write_dng(tmp_path / "shot.dng", np.full((11, 11, 3), 0.5), exposure_s=0.2)   # same name, new file
    frame = cam.fetch(1.0)
    assert frame.exposure_s == 0.2 and abs(float(frame.rgb.mean()) - 0.5) < 1e-3


def test_folder_camera_corrupt_frame_and_misuse(tmp_path):
    cam = FolderCamera(tmp_path, settle_s=0.0)
    with pytest.raises(RuntimeError, match="before arm"):
        cam.fetch(0.1)
    cam.arm()
    (tmp_path / "bad.dng").write_bytes(b"\x00" * 4096)
    with pytest.raises(RawFileError, match="bad.dng"):
        cam.fetch(1.0)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        FolderCamera(tmp_path / "nowhere").arm()
    assert cam.identify().extra["folder"] == os.fspath(tmp_path)
    cam.close()
    with pytest.raises(RuntimeError, match="closed"):
        cam.fetch(0.1)
    assert math.isfinite(cam.settle_s)
