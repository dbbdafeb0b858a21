"""Verification of the Monte Carlo reference renderer (simulators/mc) against known answers (issue 8, item 2).

Every comparison is |MC - reference| < 4 sigma_MC + model term, sigma_MC the estimator's own standard error
(per-photon or per-pixel, see simulators/mc/profile.py and render.py); the model term is 0 for exact oracles and
is stated where the reference is itself an approximation (diffusion). Seeds are fixed, so each test is
deterministic; 4 sigma keeps a correct implementation passing after any change of the random-number consumption
(false-failure probability ~6e-5 per comparison).

(a) total reflectance of an index-matched half-space (isotropic scattering) vs Chandrasekhar's closed form
    R(mu0 = 1) = 1 - H(1) sqrt(1 - albedo), with H solved here by two independent methods; and the matched slab of
    van de Hulst's tables quoted as the MCML benchmark.
(b) energy conservation: albedo 1 -- every photon entering a closed object comes back out (zero variance), the
    white furnace (uniform radiance 1 around a non-absorbing object) renders as exactly 1.
(c) reciprocity: exchange between two direction sets on a half-space; swapping point light and camera.
(d) the dipole's agreement in its regime of validity; (e) its known disagreement near the source, at low albedo and
    (index-matched boundary) at intermediate distances, in the documented direction.
(f) determinism: same seed -> identical results, independent of the thread count.
(g) the image estimators (exit look-up, next-event estimation) agree with the photon tallies.
"""
import math
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import trimesh
from scipy import integrate

from estimation import dipole
from estimation.camera import PinholeCamera
from estimation.fresnel import fresnel_transmittance
from estimation.single_image import PointLights
from simulators.mc.shapes import STACK_SIZE, nearest_hit
from simulators.mc import (Box, DirectionSet, HalfSpace, Medium, Mesh, OrthographicCamera, Sphere,
                           energy_balance, exchange_fraction, optical_medium, pencil_beam_profile, render,
                           uniform_environment)

ROOT = Path(__file__).resolve().parents[2]


def within(mc, se, ref, model=0.0, k=4.0):
    return abs(mc - ref) <= k * se + model


# ------------------------------------------------------------------------------------------------------------ (a)
def h_function_iterative(albedo, mu, n=200):
    """Chandrasekhar's H for isotropic scattering from 1/H(mu) = sqrt(1 - a) + (a/2) int_0^1 mu' H(mu')/(mu + mu')
    dmu' (Chandrasekhar 1950, "Radiative Transfer", ch. V), iterated on a Gauss-Legendre grid."""
    x, w = np.polynomial.legendre.leggauss(n)
    m, w = 0.5 * (x + 1), 0.5 * w
    h = np.ones(n)
    for _ in range(20000):
        hn = 1.0 / (np.sqrt(1 - albedo) + 0.5 * albedo * np.sum(w * m * h / (m[:, None] + m), axis=1))
        if np.max(np.abs(hn - h)) < 1e-15:
            break
        h = hn
    return float(1.0 / (np.sqrt(1 - albedo) + 0.5 * albedo * np.sum(w * m * h / (mu + m))))


def h_function_integral(albedo, mu):
    """The same H from its integral representation
    ln H(mu) = -(mu/pi) int_0^{pi/2} ln(1 - a t cot t) / (cos^2 t + mu^2 sin^2 t) dt (Chandrasekhar eq. V.(48))."""
    def f(t):
        tc = 1.0 if t == 0 else t / math.tan(t)
        return math.log(1 - albedo * tc) / (math.cos(t) ** 2 + mu * mu * math.sin(t) ** 2)

    v, _ = integrate.quad(f, 0, math.pi / 2, limit=200, epsabs=1e-13)
    return math.exp(-mu / math.pi * v)


def test_h_function_oracle_is_self_consistent():
    """Both solvers agree to 1e-9, and the conservative H(1) = 2.9078 (Chandrasekhar's table)."""
    for a in (0.5, 0.9, 0.99):
        assert h_function_iterative(a, 1.0) == pytest.approx(h_function_integral(a, 1.0), abs=1e-9)
    assert h_function_integral(1.0, 1.0) == pytest.approx(2.9078, abs=1e-4)


@pytest.mark.parametrize("albedo,n_photons", [(0.5, 100_000), (0.9, 100_000), (0.99, 100_000)])
def test_index_matched_half_space_total_reflectance_matches_h_function(albedo, n_photons):
    """Normally incident beam, eta = 1, isotropic: R = 1 - H(1) sqrt(1 - albedo) (van de Hulst 1980, "Multiple
    Light Scattering" vol. 1; Chandrasekhar 1950): 0.11523, 0.41495, 0.75272. Tolerance 4 sigma (exact oracle)."""
    ref = 1 - h_function_integral(albedo, 1.0) * math.sqrt(1 - albedo)
    p = pencil_beam_profile(optical_medium(albedo), [0.0, 1.0], n_photons, seed=11)
    assert p.specular_reflectance == 0.0 and p.truncated_fraction == 0.0
    assert within(p.total_diffuse_reflectance, p.total_diffuse_reflectance_stderr, ref), \
        (p.total_diffuse_reflectance, p.total_diffuse_reflectance_stderr, ref)
    assert p.total_diffuse_reflectance_stderr < 0.002


def test_matched_slab_matches_van_de_hulst_tables():
    """Slab of optical thickness 2 (mu_s = 9, mu_a = 1 /mm, g = 0.75, d = 0.2 mm, n = 1): R_d = 0.09739,
    T_t = 0.66096 (van de Hulst 1980, the benchmark of Wang, Jacques & Zheng 1995 MCML, Table 3); T_t includes
    the unscattered e^-2. Tolerance 4 sigma; a 2e7-photon run of this code gave 0.097344(52), 0.661064(74)."""
    p = pencil_beam_profile(Medium(9.0, 1.0, 0.75, 1.0), [0.0, 1.0], 400_000, seed=5, thickness_mm=0.2)
    assert within(p.total_diffuse_reflectance, p.total_diffuse_reflectance_stderr, 0.09739)
    assert within(p.transmittance, p.transmittance_stderr, 0.66096)
    assert p.transmittance_stderr < 1e-3


# ------------------------------------------------------------------------------------------------------------ (b)
CLOSED = [
    (Sphere((0.0, 0.0, 0.0), 3.0), (0.0, 0.0, 3.0)),
    (Box((-2.0, -1.0, -3.0), (2.0, 1.0, 3.0)), (0.5, 0.2, 3.0)),
    (Mesh(trimesh.creation.icosphere(subdivisions=2, radius=3.0)), (0.0, 0.0, 3.0)),
]


@pytest.mark.parametrize("eta", [1.0, 1.4])
@pytest.mark.parametrize("shape,entry", CLOSED, ids=["sphere", "box", "mesh"])
def test_closed_objects_without_absorption_return_all_light(shape, entry, eta):
    """Albedo 1: each photon keeps its weight F_t until it leaves (no roulette fires), so the exited power plus the
    specular reflection is 1 to rounding -- a zero-variance check of the boundary logic (TIR, nudging, BVH)."""
    b = energy_balance(shape, Medium(2.0, 0.0, 0.6, eta), 4000, entry_mm=entry, seed=3,
                       incidence=DirectionSet(0.2, 1.0, 0.0, 2 * math.pi))
    assert b.truncated_fraction == 0.0 and b.not_entered_fraction == 0.0
    assert abs(b.exited + b.specular - 1.0) < 1e-12 and abs(b.absorbed) < 1e-12


def test_slab_without_absorption_reflects_or_transmits_everything():
    p = pencil_beam_profile(Medium(5.0, 0.0, 0.0, 1.5), [0.0, 1.0], 20_000, seed=2, thickness_mm=0.7,
                            incidence=DirectionSet(0.3, 1.0, 0.0, 2 * math.pi))
    assert abs(p.specular_reflectance + p.total_diffuse_reflectance + p.transmittance - 1) < 1e-12
    assert p.truncated_fraction == 0.0


def _first_hit_cosines(shape, camera):
    """cos between the outward normal and the reversed camera ray at each pixel's first hit (NaN: miss)."""
    g = shape.geometry()
    st = np.empty(STACK_SIZE, np.int64)
    o, d = camera.pixel_rays()
    out = np.full(o.shape[:2], np.nan)
    for idx in np.ndindex(out.shape):
        t, nx, ny, nz = nearest_hit(g.kind, g.params, g.nodes_box, g.nodes_idx, g.triangles, *o[idx], *d[idx],
                                    g.eps_t, st)
        if t < math.inf:
            out[idx] = -(nx * d[idx][0] + ny * d[idx][1] + nz * d[idx][2])
    return out


@pytest.mark.parametrize("eta", [1.0, 1.4])
def test_white_furnace_images(eta):
    """Uniform radiance 1 around a non-absorbing object (the white furnace): every path leaves again, so the
    subsurface radiance is exactly F_t(eta, cos_o) at the first hit (estimation.fresnel) with zero variance, and
    with the specular reflection added the image is exactly 1 -- for a sphere, a box, a convex mesh and a non-convex
    mesh (annulus: exit rays re-enter the object, mirrored rays see the object). Tolerance 1e-9 (rounding)."""
    cam = PinholeCamera.looking_at(width_px=12, height_px=12, fx_px=25, position_mm=(0, -40, 8), target_mm=(0, 0, 0))
    m = Medium(1.5, 0.0, 0.5, eta)
    shapes = [Sphere((0, 0, 0), 6.0), Box((-4, -4, -4), (4, 4, 4)),
              Mesh(trimesh.creation.icosphere(subdivisions=2, radius=6.0)),
              Mesh(trimesh.creation.annulus(r_min=2.5, r_max=6.0, height=5.0))]
    for shape in shapes:
        sub = render(shape, m, cam, uniform_environment(1.0), spp=3, seed=1)
        tot = render(shape, m, cam, uniform_environment(1.0), spp=3, seed=1, include_specular=True)
        cos_o = _first_hit_cosines(shape, cam)
        assert sub.mask.sum() > 20 and sub.truncated_fraction == 0
        np.testing.assert_array_equal(sub.mask, np.isfinite(cos_o))
        np.testing.assert_allclose(sub.radiance[sub.mask, 0], fresnel_transmittance(eta, cos_o[sub.mask]),
                                   atol=1e-9)
        np.testing.assert_allclose(sub.stderr[sub.mask], 0.0, atol=1e-9)
        np.testing.assert_allclose(tot.radiance[tot.mask], 1.0, atol=1e-9)


# ------------------------------------------------------------------------------------------------------------ (c)
def test_reciprocity_of_direction_exchange_on_a_half_space():
    """Pi_A P(A -> B) = Pi_B P(B -> A) (Helmholtz reciprocity of the half-space's reflectance, Fresnel boundary
    eta = 1.4 and strongly forward HG g = 0.8 so that nothing is symmetric by construction); tolerance 4 sigma of
    the difference."""
    m = Medium(4.0, 0.2, 0.8, 1.4)
    A = DirectionSet(0.9, 1.0, 0.0, 2 * math.pi)
    B = DirectionSet(0.25, 0.6, 0.3, 2.0)
    ab, ab_se = exchange_fraction(m, A, B, 150_000, seed=1)
    ba, ba_se = exchange_fraction(m, B, A, 150_000, seed=2)
    lhs, rhs = A.projected_solid_angle_sr * ab, B.projected_solid_angle_sr * ba
    se = math.hypot(A.projected_solid_angle_sr * ab_se, B.projected_solid_angle_sr * ba_se)
    assert within(lhs, se, rhs) and se < 0.03 * rhs, (lhs, rhs, se)


def _far_light_render(shape, m, theta_i_deg, theta_o_deg, spp, seed, size=8):
    """Orthographic view from theta_o, a point light 1e5 mm away at theta_i (irradiance 1 at normal incidence),
    light and camera on opposite sides of the plane of incidence; pixel-averaged radiance and its standard error."""
    ti, to = np.deg2rad(theta_i_deg), np.deg2rad(theta_o_deg)
    wi = np.array([np.sin(ti), 0, np.cos(ti)])
    wo = np.array([-np.sin(to), 0, np.cos(to)])
    cam = OrthographicCamera.looking_at(width_px=size, height_px=size, pixel_size_mm=5.0, direction=-wo,
                                        up=(0, 1, 0), ray_start_mm=1e3)
    D = 1e5
    img = render(shape, m, cam, PointLights(wi[None] * D, [D * D]), spp=spp, seed=seed)
    v = img.radiance[..., 0]
    return float(v.mean()), float(np.sqrt(np.sum(img.stderr[..., 0] ** 2)) / v.size)


def test_reciprocity_swapping_point_light_and_camera():
    """L(i -> o) / cos_i = L(o -> i) / cos_o on a half-space, eta = 1.3, g = 0.5: exercises the refracted
    next-event connection (its Jacobian is asymmetric in i and o) against the camera-side refraction."""
    m = Medium(2.0, 0.02, 0.5, 1.3)
    a, a_se = _far_light_render(HalfSpace(0.0), m, 60, 15, 400, 1)
    b, b_se = _far_light_render(HalfSpace(0.0), m, 15, 60, 400, 2)
    lhs, rhs = a / math.cos(math.radians(60)), b / math.cos(math.radians(15))
    se = math.hypot(a_se / math.cos(math.radians(60)), b_se / math.cos(math.radians(15)))
    assert within(lhs, se, rhs) and se < 0.02 * rhs, (lhs, rhs, se)


def test_large_sphere_and_box_look_like_the_half_space_under_a_point_light():
    """The sphere's refracted connections (root finding + finite-difference Jacobian) and the box's bounded faces
    reproduce the half-space locally: radius 1e4 mm seen over 20 mm. Same seed: the paths are nearly identical, so
    the comparison is much tighter than 4 sigma; it is asserted at 4 sigma + 0.2% (curvature ~ 1e-3)."""
    m = Medium(2.0, 0.02, 0.0, 1.3)
    R = 1e4
    h, h_se = _far_light_render(HalfSpace(0.0), m, 50, 10, 300, 3, size=4)
    s, s_se = _far_light_render(Sphere((0, 0, -R), R), m, 50, 10, 300, 3, size=4)
    b, b_se = _far_light_render(Box((-1e3, -1e3, -1e3), (1e3, 1e3, 0.0)), m, 50, 10, 300, 3, size=4)
    assert within(s, s_se, h, model=0.002 * h) and within(b, b_se, h, model=1e-6 * h)


# ------------------------------------------------------------------------------------------------------ (d), (e)
EDGES = np.array([0.0, 0.2, 0.5, 1.0, 2.0, 4.0, 7.0, 12.0])


@pytest.fixture(scope="module")
def marble_like_profile():
    """Isotropic, sigma_t' = 1 (lengths in transport mean free paths), albedo' 0.999, eta 1.3."""
    return pencil_beam_profile(Medium(0.999, 0.001, 0.0, 1.3), EDGES, 150_000, seed=17)


def test_dipole_agrees_far_from_the_source_at_high_albedo(marble_like_profile):
    """Jensen et al. 2001 dipole (estimation.dipole, exact bin integrals by cumulative_disk) vs MC for r = 2-12
    transport mean free paths: |MC/dipole - 1| <= 7% + 4 sigma. The 7% is the dipole's own modelling error in this
    regime, not Monte Carlo noise: a 2e5-photon run in finer bins measured ratios 0.95-1.02 over 2-12 mfp (0.94 at
    15-20). Total R_d: |MC - dipole| <= 1.5% + 4 sigma (measured 0.857 vs 0.864)."""
    p = marble_like_profile
    bins = np.diff(dipole.cumulative_disk(EDGES, 0.999, 0.001, 1.3, fdr="exact"))
    ratio = p.annulus_fraction / bins
    ratio_se = p.annulus_fraction_stderr / bins
    far = EDGES[:-1] >= 2.0
    assert far.sum() == 3
    for r, s in zip(ratio[far], ratio_se[far]):
        assert abs(r - 1) <= 0.07 + 4 * s, (ratio[far], ratio_se[far])
        assert s < 0.02
    rd = float(dipole.total_diffuse_reflectance(0.999, 0.001, 1.3, fdr="exact"))
    assert within(p.total_diffuse_reflectance, p.total_diffuse_reflectance_stderr, rd, model=0.015 * rd)


def test_dipole_underestimates_near_the_source(marble_like_profile):
    """Within 0.2 transport mfp of the beam, single and low-order scattering (absent from diffusion theory; the MC
    profile grows like 1/r towards the entry point) dominate: MC exceeds the dipole by more than a factor 2 (measured
    ~5x), beyond 4 sigma. Documented direction: dipole too low near the source."""
    p = marble_like_profile
    bins = np.diff(dipole.cumulative_disk(EDGES, 0.999, 0.001, 1.3, fdr="exact"))
    assert p.annulus_fraction[0] - 2 * bins[0] > 4 * p.annulus_fraction_stderr[0]


def test_dipole_underestimates_total_reflectance_at_low_albedo():
    """Albedo 0.5, eta = 1, isotropic: exact R = 1 - H(1) sqrt(0.5) = 0.1152 (checked in (a)); the Jensen dipole
    gives 0.0878 and d'Eon's better dipole 0.046 (science.md sec. 5). Documented direction: both too low, by more
    than 4 sigma + 0.02."""
    p = pencil_beam_profile(optical_medium(0.5), [0.0, 1.0], 100_000, seed=9)
    for model in ("dipole-jensen", "dipole-better"):
        rd = float(dipole.total_diffuse_reflectance(0.5, 0.5, 1.0, model=model, fdr="exact"))
        assert p.total_diffuse_reflectance - rd > 4 * p.total_diffuse_reflectance_stderr + 0.02, (model, rd)


def test_index_matched_dipole_overestimates_at_intermediate_distances():
    """With an index-matched boundary (eta = 1, A = 1) the classical dipole is too high at 1-4 transport mfp even at
    albedo 0.99 (measured MC/dipole 0.76-0.81, cross-checked with an independent numpy analog Monte Carlo), while
    its total R_d is within 1% (0.7467 vs exact 0.7527). Documented direction: dipole too high there; asserted
    MC/dipole < 0.9 beyond 4 sigma in [1, 4] mfp."""
    edges = np.array([0.0, 1.0, 4.0])
    p = pencil_beam_profile(optical_medium(0.99), edges, 60_000, seed=13)
    bins = np.diff(dipole.cumulative_disk(edges, 0.99, 0.01, 1.0, fdr="exact"))
    assert 0.9 * bins[1] - p.annulus_fraction[1] > 4 * p.annulus_fraction_stderr[1]


# ------------------------------------------------------------------------------------------------------------ (f)
def _small_scene(seed):
    cam = PinholeCamera.looking_at(width_px=10, height_px=8, fx_px=20, position_mm=(0, -30, 10), target_mm=(0, 0, 0))
    m = Medium.from_reduced(1.5, 0.05, g=0.4, eta=1.3)
    return render(Sphere((0, 0, 0), 5.0), m, cam, [PointLights([[10.0, -20.0, 15.0]], [50.0]),
                                                   uniform_environment(0.2)], spp=16, seed=seed)


def test_same_seed_same_result_and_different_seed_different_result():
    a, b, c = _small_scene(1), _small_scene(1), _small_scene(2)
    assert np.array_equal(a.radiance, b.radiance) and np.array_equal(a.stderr, b.stderr)
    assert not np.array_equal(a.radiance, c.radiance)
    p1 = pencil_beam_profile(optical_medium(0.9, eta=1.3), [0, 1, 2], 5000, seed=4, chunk=1000)
    p2 = pencil_beam_profile(optical_medium(0.9, eta=1.3), [0, 1, 2], 5000, seed=4, chunk=4096)
    # the chunk size changes only the order of the final sums: equal to rounding
    np.testing.assert_allclose(p1.annulus_fraction, p2.annulus_fraction, rtol=1e-12)


_CHILD = """
import sys, numpy as np, numba
sys.path.insert(0, {root!r}); sys.path.insert(0, {tests!r})
from test_mc_verification import _small_scene
from simulators.mc import pencil_beam_profile, optical_medium
assert numba.get_num_threads() == 2
img = _small_scene(1)
p = pencil_beam_profile(optical_medium(0.9, eta=1.3), [0, 1, 2], 5000, seed=4)
np.savez({out!r}, radiance=img.radiance, stderr=img.stderr, prof=p.annulus_fraction)
"""


def test_results_do_not_depend_on_the_thread_count(tmp_path):
    """One thread here, two in a child process (NUMBA_NUM_THREADS=2): bit-identical images and profiles, because
    every path owns a random stream keyed by (seed, channel, pixel, sample) / (seed, photon)."""
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        img = _small_scene(1)
        p = pencil_beam_profile(optical_medium(0.9, eta=1.3), [0, 1, 2], 5000, seed=4)
    finally:
        numba.set_num_threads(prev)
    out = tmp_path / "child.npz"
    env = dict(os.environ, NUMBA_NUM_THREADS="2", PYTHONPATH=os.pathsep.join(sys.path))
    code = _CHILD.format(root=str(ROOT), tests=str(Path(__file__).parent), out=str(out))
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    child = np.load(out)
    assert np.array_equal(child["radiance"], img.radiance) and np.array_equal(child["stderr"], img.stderr)
    assert np.array_equal(child["prof"], p.annulus_fraction)


# ------------------------------------------------------------------------------------------------------------ (g)
def test_environment_exit_lookup_matches_photon_tally():
    """Uniform radiance 1 over a half-space: by reciprocity the subsurface radiance seen from theta_o equals the
    total diffuse reflectance for a beam incident from theta_o (specular excluded on both sides), eta 1.3, g 0.6.
    Tolerance 4 sigma of the difference (both are exact estimators of the same number)."""
    m = Medium(3.0, 0.15, 0.6, 1.3)
    to = math.radians(40)
    wo = np.array([math.sin(to), 0, math.cos(to)])
    cam = OrthographicCamera.looking_at(width_px=6, height_px=6, pixel_size_mm=3.0, direction=-wo, up=(0, 1, 0),
                                        ray_start_mm=1e3)
    img = render(HalfSpace(0.0), m, cam, uniform_environment(1.0), spp=1200, seed=5)
    v, v_se = float(img.radiance.mean()), float(np.sqrt(np.sum(img.stderr ** 2)) / img.radiance.size)
    p = pencil_beam_profile(m, [0.0, 1.0], 100_000, seed=6, incidence=DirectionSet.at_angle(to))
    se = math.hypot(v_se, p.total_diffuse_reflectance_stderr)
    assert within(v, se, p.total_diffuse_reflectance) and se < 0.01 * v, (v, p.total_diffuse_reflectance, se)


def test_point_light_next_event_estimate_matches_photon_tally():
    """Far point light at normal incidence (irradiance 1) on a half-space, eta 1.3, albedo 0.99: the radiance seen
    from 30 deg equals the angular photon tally dR/(cos dOmega) in a narrow cos bin around 30 deg (the bin average
    differs from the point value by < 0.1% for this smooth distribution). Tolerance 4 sigma + 0.2%."""
    m = Medium(0.99, 0.01, 0.0, 1.3)
    v, v_se = _far_light_render(HalfSpace(0.0), m, 0, 30, 400, 7)
    c = math.cos(math.radians(30))
    p = pencil_beam_profile(m, [0.0, 1.0], 300_000, seed=8, cos_edges=[0.0, c - 0.02, c + 0.02, 1.0])
    f, f_se = p.brdf_per_sr[1], p.brdf_stderr_per_sr[1]
    assert within(v, math.hypot(v_se, f_se), f, model=0.002 * f), (v, v_se, f, f_se)
