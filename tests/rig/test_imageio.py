"""Round trips of the linear image reader/writers, and the errors a user sees for bad files."""
from __future__ import annotations

import numpy as np
import pytest

from rig.files.imageio import (ImageFileError, read_image, write_exr, write_float_tiff, write_png16, write_png8)
from simulators.dng import write_dng


@pytest.fixture
def rgb() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.uniform(0.0, 1.0, (7, 9, 3)).astype(np.float32)


def test_exr_round_trip_keeps_float_and_channel_order(tmp_path, rgb):
    rgb[0, 0] = [1.0, 0.0, 0.0]  # pure red stays in the first channel
    write_exr(tmp_path / "a.exr", rgb * 100.0)
    out, meta = read_image(tmp_path / "a.exr")
    assert meta["format"] == "exr"
    np.testing.assert_array_equal(out, rgb * 100.0)
    assert out[0, 0].tolist() == [100.0, 0.0, 0.0]


def test_exr_half_and_single_channel(tmp_path, rgb):
    write_exr(tmp_path / "h.exr", rgb, half=True)
    out, _ = read_image(tmp_path / "h.exr")
    np.testing.assert_allclose(out, rgb, rtol=1e-3, atol=1e-4)  # half precision: 11-bit mantissa
    write_exr(tmp_path / "y.exr", rgb[..., 1])
    out, _ = read_image(tmp_path / "y.exr")
    assert out.shape == (7, 9)


def test_float_tiff_round_trip(tmp_path, rgb):
    write_float_tiff(tmp_path / "a.tif", rgb * 3.5, description="test")
    out, meta = read_image(tmp_path / "a.tif")
    assert meta["source_dtype"] == "float32"
    np.testing.assert_array_equal(out, rgb * 3.5)


def test_png16_round_trip_is_linear_with_rgb_order(tmp_path, rgb):
    rgb[1, 2] = [0.0, 0.0, 1.0]
    write_png16(tmp_path / "a.png", rgb)
    out, meta = read_image(tmp_path / "a.png")
    assert meta["format"] == "png16"
    np.testing.assert_allclose(out, rgb, atol=0.5 / 65535 + 1e-7)
    assert out[1, 2].tolist() == [0.0, 0.0, 1.0]


def test_8bit_png_is_refused_with_the_reason(tmp_path, rgb):
    write_png8(tmp_path / "a.png", rgb)
    with pytest.raises(ImageFileError, match=r"a\.png: PNG with uint8 samples: expected a 16-bit linear PNG"):
        read_image(tmp_path / "a.png")


def test_dng_goes_through_the_raw_loader(tmp_path):
    rgb = np.zeros((12, 14, 3))
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 0.25, 0.5, 0.125
    write_dng(tmp_path / "a.dng", rgb, exposure_s=0.01, black_level=512, bits=14)
    out, meta = read_image(tmp_path / "a.dng")
    assert meta["format"] == "raw" and out.shape == (12, 14, 3)
    np.testing.assert_allclose(out[0, 0], [0.25, 0.5, 0.125], atol=1.0 / (16383 - 512))  # 14-bit quantization


@pytest.mark.parametrize("name, content, message", [
    ("missing.exr", None, "no such file"),
    ("a.jpg", b"x", "unknown image suffix '.jpg'"),
    ("bad.exr", b"not an exr", "not a readable OpenEXR file"),
    ("bad.tif", b"not a tiff", "not a readable TIFF file"),
    ("bad.png", b"not a png", "not a readable PNG file"),
])
def test_bad_files_name_the_file_and_the_expectation(tmp_path, name, content, message):
    p = tmp_path / name
    if content is not None:
        p.write_bytes(content)
    with pytest.raises(ImageFileError) as ei:
        read_image(p)
    assert name in str(ei.value) and message in str(ei.value)


def test_nan_pixels_are_refused(tmp_path, rgb):
    rgb[2, 3, 1] = np.nan
    write_float_tiff(tmp_path / "n.tif", rgb)
    with pytest.raises(ImageFileError, match="1 pixel values are NaN or infinite"):
        read_image(tmp_path / "n.tif")


def test_writers_leave_no_temporary_files(tmp_path, rgb):
    write_exr(tmp_path / "a.exr", rgb)
    write_float_tiff(tmp_path / "a.tif", rgb)
    write_png16(tmp_path / "a.png", rgb)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png", "a.tif"]
