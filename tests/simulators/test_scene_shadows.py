"""Cast shadows in the simulated camera's fast renderer (simulators/scene.py, MeshObject) and the single-image
estimate from its frames: a non-convex L-shaped block (a wall on a slab) lit from beyond the wall."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera
from estimation.single_image import PointLights, estimate_single_image, patches_from_mesh, sample_image_at_patches
from simulators.scene import MeshObject, render_object, wall_on_slab_mesh

SSP, SA, ETA = 2.0, 0.05, 1.3           # skin-like: l_d = 1.8 mm
LIGHT_MM = np.array([[-40.0, 0.0, 100.0]])   # the wall's shadow covers the slab's top for x < 17 mm
INTENSITY = np.full((1, 3), 2e4)


def _camera() -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=80, height_px=60, fx_px=100.0, position_mm=(70.0, -40.0, 80.0),
                                    target_mm=(18.0, 0.0, 6.0))


@pytest.fixture(scope="module")
def frames() -> dict:
    """Cross-polarized fast renders of the block (renderer's tessellation 2 mm, flat shading) with and without
    shadows, and the pixels' surface points."""
    cam = _camera()
    mesh = wall_on_slab_mesh(max_edge_mm=2.0, flat_shading=True)
    out = {}
    for shadows in (True, False):
        obj = MeshObject(mesh, (SSP,) * 3, (SA,) * 3, ETA, shadows=shadows)
        out[shadows] = render_object(obj, cam, LIGHT_MM, INTENSITY, Polarization.CROSS, include_specular=False)
    out["points"], _ = MeshObject(mesh, (SSP,) * 3, (SA,) * 3, ETA).intersect(cam)
    return out


def test_renderer_darkens_the_shadow_and_nothing_else_far_from_it(frames: dict) -> None:
    on, off = frames[True], frames[False]
    assert np.array_equal(on.mask, off.mask)
    pts = frames["points"]
    top = on.mask & (np.abs(pts[..., 2] - 5.0) < 1e-6)
    deep = top & (pts[..., 0] < 12.0)            # > 5 mm (~3 l_d) inside the shadow
    far = top & (pts[..., 0] > 24.0)             # > 7 mm outside it
    assert deep.sum() > 20 and far.sum() > 20
    # deep in the shadow only light scattered in from the lit part arrives: < 5 % of the unshadowed radiance
    assert np.all(on.radiance[deep, 0] < 0.05 * off.radiance[deep, 0])
    # far from it the shadow removes only the light those shadowed patches would have scattered there (< 2 %)
    ratio = on.radiance[far, 0] / off.radiance[far, 0]
    assert np.all(ratio <= 1.0 + 1e-12) and np.all(ratio > 0.98)


def test_renderer_shadows_the_specular_lobe_and_leaves_convex_meshes_alone() -> None:
    cam = _camera()
    mesh = wall_on_slab_mesh(max_edge_mm=4.0, flat_shading=True)
    # a wide GGX lobe (roughness 0.5): every lit pixel of the slab shows some specular light
    obj = MeshObject(mesh, (SSP,) * 3, (SA,) * 3, ETA, specular_roughness=0.5)
    obj_off = MeshObject(mesh, (SSP,) * 3, (SA,) * 3, ETA, specular_roughness=0.5, shadows=False)
    par = render_object(obj, cam, LIGHT_MM, INTENSITY, Polarization.PARALLEL)
    crs = render_object(obj, cam, LIGHT_MM, INTENSITY, Polarization.CROSS)
    par_off = render_object(obj_off, cam, LIGHT_MM, INTENSITY, Polarization.PARALLEL)
    crs_off = render_object(obj_off, cam, LIGHT_MM, INTENSITY, Polarization.CROSS)
    pts, _ = obj.intersect(cam)
    top = par.mask & (np.abs(pts[..., 2] - 5.0) < 1e-6)
    shadow = top & (pts[..., 0] < 15.0)
    lit = top & (pts[..., 0] > 19.0)
    spec, spec_off = (par.radiance - crs.radiance)[..., 0], (par_off.radiance - crs_off.radiance)[..., 0]
    assert shadow.sum() > 10 and lit.sum() > 10
    assert np.all(spec_off[shadow] > 0) and np.all(spec[shadow] == 0.0)
    np.testing.assert_allclose(spec[lit], spec_off[lit], rtol=1e-12)
    # a convex mesh (auto): no shadow rays, the same image as with shadows off
    box = trimesh.creation.box(extents=(20.0, 20.0, 10.0))
    a = render_object(MeshObject(box, (SSP,) * 3, (SA,) * 3, ETA, 1), cam, LIGHT_MM, INTENSITY,
                      Polarization.PARALLEL)
    b = render_object(MeshObject(box, (SSP,) * 3, (SA,) * 3, ETA, 1, shadows=False), cam, LIGHT_MM, INTENSITY,
                      Polarization.PARALLEL)
    assert MeshObject(box, (SSP,) * 3, (SA,) * 3, ETA).shadow_engine() is None
    np.testing.assert_array_equal(a.radiance, b.radiance)
    with pytest.raises(ValueError, match="shadows"):
        MeshObject(mesh, (SSP,) * 3, (SA,) * 3, ETA, shadows="yes").shadow_engine()


def test_single_image_estimate_needs_the_shadows(frames: dict) -> None:
    """Frames of the non-convex block rendered with shadows: the estimate with shadows recovers sigma_s' (same
    dipole model, estimator tessellation 3 mm vs the renderer's 2 mm); without them the shadowed slab is read as
    light that scattered far, and sigma_s' comes out far off."""
    cam = _camera()
    img = frames[True]
    patches = patches_from_mesh(wall_on_slab_mesh(), cam, max_edge_mm=3.0)
    assert patches.shadows
    obs = 2.0 * sample_image_at_patches(img.radiance, cam, patches, mask=img.mask)[:, :1]   # cross-polarized
    lights = PointLights(LIGHT_MM, INTENSITY[:, :1])
    assert np.isfinite(obs).sum() > 300
    errors = {}
    for shadows in (True, False):
        p = patches if shadows else patches.with_shadows(None)
        res = estimate_single_image(obs, p, lights, ETA, model="dipole-jensen")
        assert res, res.message
        errors[shadows] = res.sigma_s_prime_per_mm[0] / SSP - 1.0
    print(f"sigma_s' error: shadows on {errors[True]:+.1%}, off {errors[False]:+.1%}")
    assert abs(errors[True]) < 0.05
    assert abs(errors[False]) > 0.15 and abs(errors[False]) > 5 * abs(errors[True])
