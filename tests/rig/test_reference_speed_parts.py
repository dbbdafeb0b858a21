"""Issue 19's speed-only parts of the capture folder's --reference estimate: the LED response LUT cached per LED
layout (rig.estimate.response_cache) and the Monte Carlo reference rendering only the summary's pixels
(rig.estimate.reference.mc_reference.PixelSubsetCamera). Both must change nothing but the time."""
from __future__ import annotations

import numpy as np
import pytest

from estimation.camera import PinholeCamera
from estimation.gradients import LedRig, build_response_lut
from rig.acquire.geometry import led_layout


def _rig(n_rings: int = 3) -> LedRig:
    pos, _ = led_layout(n_rings, 1000.0, -60.0)
    return LedRig.from_positions(pos, np.full((len(pos), 3), 1000.0))


LUT_KW = dict(eta=1.3, size=9, reference_normal=(0.0, -1.0, 0.0), surface_center_mm=(0.0, 0.0, 0.0),
              surface_radius_mm=5.0)


def test_response_lut_cache_is_bit_identical_and_keyed_by_content(tmp_path, monkeypatch) -> None:
    """A cached table (in the process, then from disk in a 'new process') equals a fresh build bit for bit; a
    different eta or LED gain is a different table; a corrupt cache file is rebuilt, not trusted; 'off' writes
    nothing."""
    from rig.estimate import response_cache as rc

    monkeypatch.setenv("SSSRIG_LUT_CACHE", str(tmp_path / "lut"))
    rc.clear_memory_cache()
    leds = _rig()
    fresh = build_response_lut(leds, **LUT_KW)
    first = rc.response_lut(leds, **LUT_KW)
    files = list((tmp_path / "lut").glob("*.npz"))
    assert len(files) == 1
    assert rc.response_lut(leds, **LUT_KW) is first             # the same object within the process
    rc.clear_memory_cache()
    loaded = rc.response_lut(leds, **LUT_KW)                   # from disk
    assert loaded is not first
    for a in (first, loaded):
        assert np.array_equal(a.coeffs, fresh.coeffs) and np.array_equal(a.reference_full, fresh.reference_full)
        assert np.array_equal(a.fit_residual, fresh.fit_residual)
        assert (a.size, a.patterns, a.smoothing_rad, a.eta, a.provenance) == (
            fresh.size, fresh.patterns, fresh.smoothing_rad, fresh.eta, fresh.provenance)
    other = rc.response_lut(leds, **{**LUT_KW, "eta": 1.4})
    assert not np.array_equal(other.coeffs, fresh.coeffs)
    brighter = LedRig(leds.directions, leds.gains * np.array([1.0, 1.0, 2.0]), leds.distances_mm)
    assert rc.lut_key(brighter, **{k: v for k, v in LUT_KW.items()}, smoothing_rad=None) != rc.lut_key(
        leds, **LUT_KW, smoothing_rad=None)
    assert len(list((tmp_path / "lut").glob("*.npz"))) == 2
    files[0].write_bytes(b"not a table")
    rc.clear_memory_cache()
    rebuilt = rc.response_lut(leds, **LUT_KW)
    assert np.array_equal(rebuilt.coeffs, fresh.coeffs)
    monkeypatch.setenv("SSSRIG_LUT_CACHE", "off")
    assert rc.lut_cache_dir() is None
    rc.clear_memory_cache()
    assert np.array_equal(rc.response_lut(leds, **{**LUT_KW, "eta": 1.5}).coeffs,
                          build_response_lut(leds, **{**LUT_KW, "eta": 1.5}).coeffs)
    assert len(list((tmp_path / "lut").glob("*.npz"))) == 2
    rc.clear_memory_cache()


def test_pixel_subset_camera_renders_its_pixels_bit_identically_and_skips_the_rest() -> None:
    """A Monte Carlo render through PixelSubsetCamera: every pixel of the mask equals the whole-frame render bit for
    bit (each pixel's random stream is keyed by its index), every other pixel is empty (no hit, zero radiance)."""
    from simulators.mc import Medium, Sphere, render, uniform_environment

    from rig.estimate.reference.mc_reference import PixelSubsetCamera

    cam = PinholeCamera.looking_at(width_px=10, height_px=10, fx_px=200.0, position_mm=(0.0, -100.0, 0.0),
                                   target_mm=(0.0, 0.0, 0.0))
    media = [Medium(1.0, 0.05, 0.0, 1.3)] * 3
    lights = uniform_environment(1.0)
    whole = render(Sphere((0.0, 0.0, 0.0), 3.0), media, cam, lights, spp=4, seed=5)
    mask = np.zeros((10, 10), bool)
    mask[3:7, 2:6] = True
    assert whole.mask[mask].all() and whole.mask[~mask].any()
    sub = render(Sphere((0.0, 0.0, 0.0), 3.0), media, PixelSubsetCamera(cam, mask), lights, spp=4, seed=5)
    assert np.array_equal(sub.radiance[mask], whole.radiance[mask])
    assert np.array_equal(sub.stderr[mask], whole.stderr[mask])
    assert not sub.mask[~mask].any() and np.all(sub.radiance[~mask] == 0.0)
    assert PixelSubsetCamera(cam, mask).fx_px == cam.fx_px          # the rest is the wrapped camera's
    with pytest.raises(ValueError, match="mask must be"):
        PixelSubsetCamera(cam, np.ones((9, 10), bool))


def test_reference_prefetch_renders_ahead_once_and_changes_no_number() -> None:
    """MonteCarloReference.prefetch (the ridge line search's independent renders, rig.estimate.batch's waves): with a
    render function that has ``many``, the announced calls are rendered there at once and each later call with the
    same arguments takes its image (no second render), returning exactly what the call alone returns; a call it did
    not announce (another seed) renders as usual; without ``many`` prefetch renders nothing."""
    from estimation.single_image import Patches
    from simulators.mc import Sphere, render, uniform_environment

    from rig.estimate.reference.mc_reference import MonteCarloReference, render_with

    cam = PinholeCamera.looking_at(width_px=10, height_px=10, fx_px=200.0, position_mm=(0.0, -100.0, 0.0),
                                   target_mm=(0.0, 0.0, 0.0))
    centers = np.array([[0.0, -3.0, 0.0], [1.0, -2.8, 0.0]])
    normals = centers / np.linalg.norm(centers, axis=1, keepdims=True)
    patches = Patches(centers, normals, np.ones(2), np.ones(2), np.ones(2, bool))
    ref = MonteCarloReference(Sphere((0.0, 0.0, 0.0), 3.0), cam, uniform_environment(1.0), patches, spp=4)
    calls = [(np.array([1.0, 2.0]), np.array([0.05, 0.05]), 1.3, 5), (np.array([1.5, 2.0]), np.array([0.05, 0.1]),
                                                                       1.3, 5)]
    plain = [ref(*c) for c in calls]
    log: list[str] = []

    class Counting:
        def __call__(self, *a: object, **kw: object) -> object:
            log.append("one")
            return render(*a, **kw)

        def many(self, batch: list[tuple[object, ...]]) -> list[object]:
            log.append(f"many {len(batch)}")
            return [render(*b[:4], **b[4]) for b in batch]

    with render_with(Counting()):
        ref.prefetch(calls)
        ahead = [ref(*c) for c in calls]
        other = ref(calls[0][0], calls[0][1], 1.3, 6)
    assert log == ["many 2", "one"]
    for a, p in zip(ahead, plain, strict=True):
        for x, y in zip(a, p, strict=True):
            assert np.array_equal(x, y, equal_nan=True)
    assert not np.array_equal(other[0], ahead[0][0], equal_nan=True)
    with render_with(render):
        ref.prefetch(calls)
    assert ref._ahead == {}
