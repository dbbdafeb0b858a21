"""Tests of estimation.forward: exact flat-plane limit, convergence under refinement, both summation paths."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from estimation import dipole as dp
from estimation.forward import (diffuse_exitance, irradiance_directional, irradiance_point_lights,
                                radiance_from_exitance)
from estimation.fresnel import fresnel_moment, fresnel_transmittance

MARBLE = (np.array([2.19, 2.62, 3.00]), np.array([0.0021, 0.0041, 0.0071]))
SKIN1 = (np.array([0.74, 0.88, 1.01]), np.array([0.032, 0.17, 0.48]))


def _plane(half_mm: float, h_mm: float) -> tuple[np.ndarray, np.ndarray]:
    g = np.arange(-half_mm, half_mm + 1e-9, h_mm)
    x, y = np.meshgrid(g, g)
    centers = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    return centers, np.full(x.size, h_mm * h_mm)


@pytest.mark.parametrize("model", dp.MODELS)
@pytest.mark.parametrize("coeffs,half,h", [(MARBLE, 50.0, 0.5), (SKIN1, 30.0, 0.25)])
def test_flat_plane_uniform_irradiance_gives_total_reflectance(model, coeffs, half, h):
    """Infinite flat plane, uniform E: B = R_d E (science.md sec. 4) — within 0.5 % (truncation tol 1e-4)."""
    centers, areas = _plane(half, h)
    e = np.array([1.0, 2.0, 0.5])
    irr = np.broadcast_to(e, (len(centers), 3))
    pts = np.array([[0.0, 0.0, 0.0], [h / 2, h / 3, 0.0], [0.37, -0.81, 0.0]])  # on and off patch centres
    b = diffuse_exitance(pts, centers, areas, irr, *coeffs, 1.3, model=model, tolerance=1e-4)
    rd = dp.total_diffuse_reflectance(*coeffs, 1.3, model=model)
    np.testing.assert_allclose(b / (rd * e), 1.0, atol=5e-3)


def test_flat_plane_error_falls_under_refinement():
    """Against the exact truncated truth cumulative_disk(r_cut): < 0.5 % at every spacing, smaller when fine."""
    r_cut = dp.cutoff_radius_mm(1e-3, *MARBLE, 1.3)
    truth = dp.cumulative_disk(r_cut, *MARBLE, 1.3)  # plane half-width 36 mm > r_cut = 32 mm
    errs = []
    for h in (1.0, 0.5, 0.25, 0.125):
        centers, areas = _plane(36.0, h)
        b = diffuse_exitance([[0.3, 0.1, 0.0], [0.0, 0.0, 0.0]], centers, areas, np.ones((len(centers), 3)),
                             *MARBLE, 1.3, tolerance=1e-3)
        errs.append(np.abs(b / truth - 1).max())
    assert max(errs) < 5e-3
    assert errs[-1] < 0.5 * errs[0]


def _sphere(sub: int, radius: float = 10.0):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    return m.triangles_center, m.face_normals, m.area_faces


LIGHT = np.array([[0.0, -1000.0, 300.0]])
INTENSITY = np.array([[1e6, 1e6, 1e6]])
PROBES = np.array([[0, -10.0, 0], [0, 0, 10.0], [0, 10.0, 0], [0, 0, -10.0], [-7.0710678, -7.0710678, 0]])


def test_sphere_point_light_converges_under_refinement():
    results = []
    for sub in (2, 3, 4, 5):
        c, n, a = _sphere(sub)
        e = irradiance_point_lights(c, n, LIGHT, INTENSITY, 1.3)
        results.append(diffuse_exitance(PROBES, c, a, e, *MARBLE, 1.3))
    ref = results[-1]
    errs = [np.abs(r / ref - 1).max() for r in results[:-1]]
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 0.01  # 5120 patches (spacing 0.35 mm) agree with 20480 to 1 %
    assert np.all(np.isfinite(ref)) and np.all(ref > 0)


def _brute_force(pts, centers, areas, irr, ssp, sa, eta, rho, r_cut):
    """The documented algorithm written out point by point (reference for both summation paths)."""
    out = np.zeros((len(pts), len(ssp)))
    for p_i, p in enumerate(pts):
        d = np.linalg.norm(centers - p, axis=1)
        s_area = 0.0
        for k in np.argsort(d, kind="stable"):
            if d[k] > rho:
                break
            r_in = np.sqrt(s_area / np.pi)
            s_area += areas[k]
            ring = dp.cumulative_disk(np.sqrt(s_area / np.pi), ssp, sa, eta) - dp.cumulative_disk(r_in, ssp, sa, eta)
            out[p_i] += ring * irr[k]
        far = (d > rho) & (d <= r_cut)
        out[p_i] += (dp.profile(d[far, None], ssp, sa, eta) * irr[far] * areas[far, None]).sum(0)
    return out


def test_dense_and_sparse_paths_match_brute_force():
    rng = np.random.default_rng(3)
    centers, areas = _plane(25.0, 1.0)
    irr = rng.uniform(0.2, 1.0, (len(centers), 3))
    pts = np.c_[rng.uniform(-20, 20, (9, 2)), np.zeros(9)]
    for tol in (1e-2, 1e-9):  # 1e-2: cutoff 18 mm < plane diagonal -> KD-tree path; 1e-9: dense path
        r_cut = dp.cutoff_radius_mm(tol, *MARBLE, 1.3)
        want = _brute_force(pts, centers, areas, irr, *MARBLE, 1.3, 2.0, r_cut)
        for chunk in (4, 2048):
            got = diffuse_exitance(pts, centers, areas, irr, *MARBLE, 1.3, tolerance=tol, chunk=chunk)
            np.testing.assert_allclose(got, want, rtol=1e-10)


def test_near_radius_choice_and_linearity():
    c, n, a = _sphere(4)
    e = irradiance_point_lights(c, n, LIGHT, INTENSITY, 1.3)
    b2 = diffuse_exitance(PROBES, c, a, e, *MARBLE, 1.3)
    b3 = diffuse_exitance(PROBES, c, a, e, *MARBLE, 1.3, near_radius_mm=3 * np.sqrt(np.median(a)))
    np.testing.assert_allclose(b3, b2, rtol=2e-2)
    np.testing.assert_allclose(diffuse_exitance(PROBES, c, a, 2 * e, *MARBLE, 1.3), 2 * b2, rtol=1e-12)
    one = diffuse_exitance(PROBES, c, a, e[:, 1], MARBLE[0][1], MARBLE[1][1], 1.3)
    assert one.shape == (5, 1)
    np.testing.assert_allclose(one[:, 0], b2[:, 1], rtol=1e-12)


@pytest.mark.parametrize("sigma_a,eta", [(1e-9, 1.3), (0.0, 1.0), (1.45, 2.0)])
def test_extremes_are_finite(sigma_a, eta):
    c, n, a = _sphere(3)
    e = irradiance_point_lights(c, n, LIGHT, INTENSITY[:, :1], eta)
    b = diffuse_exitance(c[:50], c, a, e, 1.0, sigma_a, eta, model="dipole-better")
    assert np.all(np.isfinite(b)) and np.all(b >= 0)


def test_shape_errors():
    c, _, a = _sphere(1)
    with pytest.raises(ValueError, match="channel"):
        diffuse_exitance(c, c, a, np.ones((len(c), 2)), *MARBLE, 1.3)
    with pytest.raises(ValueError, match="valid models"):
        diffuse_exitance(c, c, a, np.ones((len(c), 3)), *MARBLE, 1.3, model="pbrt")
    assert diffuse_exitance(np.zeros((0, 3)), c, a, np.ones((len(c), 3)), *MARBLE, 1.3).shape == (0, 3)


# ---------------------------------------------------------------- irradiance and radiance helpers
def test_radiance_from_exitance():
    b = np.array([[1.0, 2.0, 3.0], [1.0, 1.0, 1.0], [5.0, 5.0, 5.0]])
    cos = np.array([1.0, 0.3, -0.2])
    got = radiance_from_exitance(b, cos, 1.3)
    np.testing.assert_allclose(got[:2], fresnel_transmittance(1.3, cos[:2])[:, None] / np.pi * b[:2])
    np.testing.assert_array_equal(got[2], 0.0)


def test_point_light_irradiance():
    centers = np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0]])
    normals = np.array([[0.0, 0, 1], [0, 0, -1], [1, 0, 1]])  # facing, facing away, 45 degrees (unnormalized)
    e = irradiance_point_lights(centers, normals, [[0, 0, 100.0]], [[1e4, 2e4, 3e4]], 1.5)
    np.testing.assert_allclose(e[0], fresnel_transmittance(1.5, 1.0) * np.array([1, 2, 3.0]))
    np.testing.assert_array_equal(e[1], 0.0)
    c45 = np.sqrt(0.5)
    np.testing.assert_allclose(e[2], fresnel_transmittance(1.5, c45) * c45 * np.array([1, 2, 3.0]))
    two = irradiance_point_lights(centers[:1], normals[:1], [[0, 0, 100.0], [0, 0, 200.0]], [[1e4], [4e4]], 1.0)
    np.testing.assert_allclose(two, [[2.0]])  # inverse square, eta = 1: no Fresnel loss


@pytest.mark.parametrize("eta", [1.0, 1.3, 1.5])
def test_uniform_environment_gives_tau0(eta):
    """Uniform radiance L over the sphere of directions: E_t = L tau0, tau0 = pi (1 - 2 FM1_external)."""
    k = 400
    mu = (np.arange(k) + 0.5) / k * 2 - 1  # uniform in cos(theta) on [-1, 1]
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    m, p = np.meshgrid(mu, phi)
    s = np.sqrt(1 - m**2)
    dirs = np.c_[(s * np.cos(p)).ravel(), (s * np.sin(p)).ravel(), m.ravel()]
    weights = np.full((len(dirs), 1), 4 * np.pi / len(dirs))  # L = 1 times the solid angle per sample
    e = irradiance_directional([[0, 0, 1.0]], dirs, weights, eta)
    tau0 = np.pi * (1 - 2 * fresnel_moment(eta, 1, side="external"))
    assert e[0, 0] == pytest.approx(tau0, rel=1e-4)
