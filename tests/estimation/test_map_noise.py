"""The frames' noise through the gradient maps into the relief fit (issue 16 item 2: intervals from the noise).

Monte Carlo frames of tests/data/relief_skin1 (skin1 relief slab, 64 x 64 px of 0.2 mm, 128 spp) with
Poisson-Gaussian camera noise added here (seeded); the maps are computed by compute_maps with one LED response
table for the module. Measured (docs/gradients.md sec. 9, "Noise"): the propagated standard errors of albedo and
diffuse normals match the scatter over 32 noise realizations to 0-8 % (2000 e-/value), the specular normals' to
1 % where their noise is small (0.07 rad); the relief fit's window intervals widen with the stated noise.
"""
from __future__ import annotations


import numpy as np
import pytest

from estimation.gradients import build_response_lut, compute_maps
from estimation.gradients.uncertainty import propagate_frame_noise, shot_read_stderr
from estimation.relief import fit_relief_windows, parameters_from_l_prime

from _relief_skin1 import ETA, SA, SSP, load_relief_skin1  # tests/estimation/_relief_skin1.py

TRUTH = parameters_from_l_prime(SSP / (SSP + SA), 1 / (SSP + SA))
GAIN = 5000.0           # electrons per frame value: full-on signal ~0.1-0.36 -> 450-1800 e-


@pytest.fixture(scope="module")
def rig_maps():
    cap = load_relief_skin1()
    frames, rig, scale, tn, view = cap["frames"], cap["rig"], cap["scale"], cap["true_normals"], cap["view"]
    lut = build_response_lut(rig, eta=ETA)

    def maps_fn(fb, rows):
        return compute_maps(fb, albedo_scale=scale, leds=rig, eta=ETA, lut=lut, view_dirs=view[rows])
    return frames, maps_fn, tn


def _noisy(frames, gain, seed):
    rng = np.random.default_rng(seed)
    se = {k: shot_read_stderr(a, gain, 2e-4) for k, a in frames.items()}
    return {k: a + rng.standard_normal(a.shape).astype(np.float32) * se[k] for k, a in frames.items()}, se


def test_propagated_stderr_matches_the_scatter_of_noise_realizations(rig_maps) -> None:
    frames, maps_fn, _ = rig_maps
    se = {k: shot_read_stderr(a, 20000.0, 2e-4) for k, a in frames.items()}
    nz = propagate_frame_noise(maps_fn, frames, se, rows_per_band=40)     # two bands: banding is exact
    assert nz.provenance["map_calls"] == 2 * (1 + 3 * len(frames))
    rng = np.random.default_rng(3)
    A, N, S = [], [], []
    for _ in range(16):
        m = maps_fn({k: a + rng.standard_normal(a.shape).astype(np.float32) * se[k] for k, a in frames.items()},
                    slice(None))
        A.append(np.asarray(m.albedo, float))
        N.append(np.asarray(m.diffuse_normals, float))
        S.append(np.asarray(m.specular_normals, float))

    def tangential_sd(V):
        V = np.array(V)
        n0 = np.nanmean(V, axis=0)
        n0 /= np.linalg.norm(n0, axis=-1, keepdims=True)
        d = V - n0
        d -= np.sum(d * n0, -1, keepdims=True) * n0
        return np.sqrt(np.nanmean(np.sum(d * d, -1), axis=0) / 2)

    ra = np.nanmedian(nz.albedo / np.nanstd(np.array(A), axis=0), axis=(0, 1))
    rn = np.nanmedian(nz.diffuse_normal_rad / tangential_sd(N), axis=(0, 1))
    rs = np.nanmedian(nz.specular_normal_rad / tangential_sd(S))
    assert np.all((ra > 0.85) & (ra < 1.15)), ra
    assert np.all((rn > 0.85) & (rn < 1.15)), rn
    assert 0.8 < rs < 1.25, rs                  # channels perturbed one at a time: the specular sum mixes them


def test_relief_intervals_widen_with_the_stated_noise_and_cover(rig_maps) -> None:
    """The same noisy maps fitted with the frames' noise stated at 1x and 4x its level: every fitted window's l'
    interval is at least as wide at 4x, wider overall, and every l_d / D interval covers the truth."""
    frames, maps_fn, tn = rig_maps
    noisy, se = _noisy(frames, GAIN, 0)
    m = maps_fn(noisy, slice(None))
    dn, alb = np.asarray(m.diffuse_normals, float), np.asarray(m.albedo, float)
    fits = []
    for k in (1.0, 4.0):
        nz = propagate_frame_noise(maps_fn, noisy, {key: k * s for key, s in se.items()})
        fits.append(fit_relief_windows(dn, tn, alb, 0.2, ETA, window_px=32, valid=~m.unknown,
                                       residual_stderr_rad=nz.diffuse_normal_rad))
    fitted = (fits[0].status != "unknown") & (fits[1].status != "unknown")
    assert fitted[..., 1:].all()                                      # G, B: every window fitted
    w = [np.log(f.intervals["l_prime_mm"][..., 1] / f.intervals["l_prime_mm"][..., 0])[fitted] for f in fits]
    assert np.all(w[1] >= w[0] - 1e-9), (w[0], w[1])
    assert w[1].sum() > 1.2 * w[0].sum(), (w[0].sum(), w[1].sum())
    for f in fits:
        assert f.provenance["residual_weights"].startswith("Hann x 1/sigma^2")
        for name in ("l_d_mm", "D_mm"):
            iv = f.intervals[name][..., 1:, :][fitted[..., 1:]]
            t = np.broadcast_to(TRUTH[name][1:], fitted[..., 1:].shape)[fitted[..., 1:]]
            assert np.all((iv[:, 0] <= t) & (t <= iv[:, 1])), (name, iv, t)


def test_bad_stderr_input_is_refused_naming_it(rig_maps) -> None:
    frames, maps_fn, _ = rig_maps
    with pytest.raises(ValueError, match="stderr"):
        propagate_frame_noise(maps_fn, frames, {("full", "cross"): np.ones((3, 3))})
    with pytest.raises(ValueError, match="electrons_per_value"):
        shot_read_stderr(np.ones(3), 0.0)
