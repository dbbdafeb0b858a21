"""The LED response LUT's numba sum (estimation.gradients.response._led_response_kernel, issue 19) against a
straightforward numpy one: per (normal, LED) pair the vector from the surface point to the LED, its cosine, the
Fresnel-Lambertian kernel and the 1/d^2 falloff, no culling, no shared weight columns. The fast build skips LEDs
behind whole stencil caps and sums identical weight columns once; neither may change the table beyond rounding."""
from __future__ import annotations

import numpy as np
import pytest

from estimation.gradients import GRADIENT_PATTERNS, LedRig, build_response_lut
from estimation.gradients import response as resp


def _reference_response(normals, leds, weights, kt, center, radius, **_ignored):
    """E (M, W) = sum_j K(cos_j) (d_j^2 / |p_j - x|^2) w_j, x = center + radius n, K by np.interp of the table."""
    table, _ = kt
    n = np.asarray(normals, dtype=np.float64)
    if leds.distances_mm is None:
        cos = n @ leds.directions.T
        falloff = np.ones_like(cos)
    else:
        p = leds.distances_mm[:, None] * leds.directions
        v = p[None, :, :] - (np.asarray(center)[None, None, :] + radius * n[:, None, :])  # (M, N, 3)
        dist2 = np.einsum("mjk,mjk->mj", v, v)
        cos = np.einsum("mjk,mk->mj", v, n) / np.sqrt(dist2)
        falloff = leds.distances_mm[None, :] ** 2 / dist2
    k = np.interp(np.clip(cos, 0.0, 1.0), np.linspace(0.0, 1.0, table.size), table)
    return (k * falloff) @ weights


def _rig(near: bool, grey: bool) -> LedRig:
    rng = np.random.default_rng(3)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    gains = np.ones((40, 3)) if grey else rng.uniform(0.5, 1.5, (40, 3))
    # close LEDs (40-60 mm from a 2 mm sphere 17 mm off centre): LEDs beyond a normal's horizon seen from the origin
    # light the surface point, so the near-field term of the culling bound matters
    dist = rng.uniform(40.0, 60.0, 40) if near else None
    pats = {"x": np.round(rng.uniform(0, 1, (40, 3)), 1)} if not grey else None
    return LedRig(d, gains, dist, pats)


@pytest.mark.parametrize("near,grey", [(True, False), (True, True), (False, False)])
def test_fast_lut_build_equals_a_straightforward_sum(near: bool, grey: bool, monkeypatch) -> None:
    leds = _rig(near, grey)
    kw = dict(eta=1.4, size=9, smoothing_rad=0.3, surface_center_mm=(9.0, -12.0, 8.0), surface_radius_mm=2.0)
    fast = build_response_lut(leds, **kw)
    monkeypatch.setattr(resp, "_led_response", _reference_response)
    slow = build_response_lut(leds, **kw)
    scale = np.abs(slow.coeffs).max()
    assert scale > 0 and np.isfinite(fast.coeffs).all()
    np.testing.assert_allclose(fast.coeffs, slow.coeffs, rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(fast.fit_residual, slow.fit_residual, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fast.reference_full, slow.reference_full, rtol=1e-13)


def test_culled_response_equals_the_full_sum_on_grazing_normals() -> None:
    """Groups of 16 normals within 0.4 rad of random axes, close LEDs: culling by the group bound (LEDs near every
    group's horizon are kept, those beyond it dropped) gives the full sum to rounding."""
    leds = _rig(True, False)
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(30, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    spread = 0.4
    offs = rng.normal(size=(30, 16, 3)) * 0.25
    normals = axes[:, None, :] + offs - np.einsum("gqk,gk->gq", offs, axes)[..., None] * axes[:, None, :]
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    ang = np.arccos(np.clip(np.einsum("gqk,gk->gq", normals, axes), -1, 1))
    normals[ang > spread] = axes[np.nonzero(ang > spread)[0]]
    normals = normals.reshape(-1, 3)
    w = np.concatenate([leds.gains * leds.pattern_values(p) for p in GRADIENT_PATTERNS], axis=1)
    kt = resp._kernel_table(1.4)
    center = np.array([9.0, -12.0, 8.0])
    fast = resp._led_response(normals, leds, w, kt, center, 2.0, group=16, axes=axes, spread_rad=spread)
    plain = resp._led_response(normals, leds, w, kt, center, 2.0)
    ref = _reference_response(normals, leds, w, kt, center, 2.0)
    assert (ref > 0).any()
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-14 * ref.max())
    np.testing.assert_allclose(fast, plain, rtol=1e-13, atol=1e-15 * ref.max())
    with pytest.raises(ValueError, match="axes"):
        resp._led_response(normals, leds, w, kt, center, 2.0, group=16, axes=axes[:3], spread_rad=spread)
