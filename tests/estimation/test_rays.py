"""estimation.rays.RayEngine against trimesh's pure-python intersector (trimesh.ray.ray_triangle, float64, no
Embree), against analytic answers, and both backends (Embree, numba BVH) against each other."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from estimation.rays import RayEngine, embree_available

BACKENDS = ["bvh"] + (["embree"] if embree_available() else [])


def _random_rays(n: int, seed: int, spread: float = 25.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3)) * spread
    aim = rng.normal(size=(n, 3)) * 6.0              # aim near the mesh so that about half the rays hit
    return o, aim - o


def _two_meshes() -> list[trimesh.Trimesh]:
    torus = trimesh.creation.torus(10.0, 4.0, major_sections=48, minor_sections=24)
    a = trimesh.creation.box(extents=(8, 8, 8))
    b = trimesh.creation.box(extents=(4, 4, 4))
    b.apply_translation((3, 3, 6))                   # overlapping boxes: intersecting, non-convex union
    return [torus, trimesh.util.concatenate([a, b])]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("which", [0, 1])
def test_first_hit_matches_trimesh_pure_python(backend: str, which: int) -> None:
    mesh = _two_meshes()[which]
    o, d = _random_rays(4000, seed=which)
    face, t = RayEngine(mesh.vertices, mesh.faces, backend=backend).first_hit(o, d)
    ref = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    loc, iray, itri = ref.intersects_location(o, d, multiple_hits=True)
    t_ref = np.full(len(o), np.inf)
    f_ref = np.full(len(o), -1)
    dist = np.einsum("ij,ij->i", loc - o[iray], d[iray] / np.linalg.norm(d[iray], axis=1, keepdims=True))
    for r, f, s in zip(iray, itri, dist):     # nearest of all hits (intersects_first does not sort them)
        if 0 < s < t_ref[r]:
            t_ref[r], f_ref[r] = s, f
    hit = f_ref >= 0
    assert 0.2 < hit.mean() < 0.9                                     # the rays do test something
    assert np.array_equal(face >= 0, hit)
    size = float(np.linalg.norm(mesh.extents))
    # float64 BVH: to rounding; Embree: float32 arithmetic in a box scaled to 100 units
    np.testing.assert_allclose(t[hit], t_ref[hit], rtol=0, atol=(1e-10 if backend == "bvh" else 2e-6) * size)
    same = face[hit] == f_ref[hit]
    # a different face only where two faces meet at the same distance (a ray through a shared edge)
    assert same.mean() > 0.995
    assert np.all(np.isinf(t[~hit]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_backends_agree_and_known_answers(backend: str) -> None:
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    eng = RayEngine(box.vertices, box.faces, backend=backend)
    o = np.array([[0.1, 0.2, 5.0], [0.1, 0.2, 5.0], [3.0, 3.0, 5.0], [0.0, 0.0, 0.0]])
    d = np.array([[0, 0, -2.0], [0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]])
    face, t = eng.first_hit(o, d)
    np.testing.assert_allclose(t, [4.0, np.inf, np.inf, 1.0], atol=1e-6)  # from inside: the wall at x = 1
    assert face[0] >= 0 and eng.face_normals[face[0]][2] > 0.99 and face[1] == face[2] == -1
    # occlusion: the box blocks the segment through it, not one that stops short of it or starts beyond it
    occ = eng.occluded([[0, 0, 5.0], [0, 0, 5.0], [0, 0, -1.0]], [[0, 0, -1.0]] * 3, [10.0, 3.9, 10.0])
    assert occ.tolist() == [True, False, False]
    # a point on the surface does not occlude itself (default min_dist), but the far wall behind it does
    occ = eng.occluded([[0.2, 0.3, 1.0], [0.2, 0.3, 1.0]], [[0, 0, 1.0], [0, 0, -1.0]], [10.0, 10.0])
    assert occ.tolist() == [False, True]
    # own_face: a ray's own face is passed through wherever it is met; what lies beyond it still counts
    o2, d2 = np.array([[0.1, 0.2, -5.0]] * 3), np.array([[0, 0, 1.0]] * 3)
    bottom, _ = eng.first_hit(o2, d2)                                 # the face at z = -1 (t = 4)
    occ = eng.occluded(o2, d2, [10.0, 5.5, 3.0], own_face=bottom)     # the top face is at t = 6
    assert occ.tolist() == [True, False, False]
    assert eng.occluded(o2, d2, [5.5, 5.5, 5.5]).tolist() == [True] * 3   # without own_face the bottom counts
    # shapes broadcast and come back as given
    f2, t2 = eng.first_hit(np.zeros((2, 3, 3)) + [0, 0, 5.0], [0, 0, -1.0])
    assert f2.shape == t2.shape == (2, 3)


def test_embree_and_bvh_agree_on_a_large_nonconvex_mesh() -> None:
    if not embree_available():
        pytest.skip("embreex not installed")
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    v = sphere.vertices * (1 + 0.15 * np.sin(3 * sphere.vertices[:, :1]) * np.cos(2 * sphere.vertices[:, 1:2]))
    o, d = _random_rays(20000, seed=5)
    o += rng.normal(size=o.shape) * 0.01
    fe, te = RayEngine(v, sphere.faces, backend="embree").first_hit(o, d)
    fb, tb = RayEngine(v, sphere.faces, backend="bvh").first_hit(o, d)
    assert np.mean(fe == fb) > 0.999
    both = (fe >= 0) & (fb >= 0)
    # float32 vs float64: ~1e-6 of the size, up to ~1e-5 for rays grazing a face
    np.testing.assert_allclose(te[both], tb[both], rtol=0, atol=1e-5 * np.ptp(v, axis=0).max())


def test_clear_errors() -> None:
    box = trimesh.creation.box()
    with pytest.raises(ValueError, match="backend must be"):
        RayEngine(box.vertices, box.faces, backend="optix")
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        RayEngine(box.vertices[:, :2], box.faces)
    with pytest.raises(ValueError, match="face indices"):
        RayEngine(box.vertices, box.faces + 100)
    with pytest.raises(ValueError, match="no faces"):
        RayEngine(box.vertices, np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="non-zero"):
        RayEngine(box.vertices, box.faces).first_hit([[0, 0, 5.0]], [[0, 0, 0.0]])


def test_auto_falls_back_to_the_numba_bvh_without_embreex() -> None:
    """A fresh interpreter in which ``import embreex`` fails: "auto" picks the BVH, "embree" says what to install,
    and the pixel map still comes out (the fallback is the same engine, not a mock)."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['embreex'] = None\n"
            "import trimesh\n"
            "from estimation.rays import RayEngine, embree_available\n"
            "from estimation.camera import PinholeCamera\n"
            "from rig.estimate.pixel_map import pixel_faces\n"
            "b = trimesh.creation.box()\n"
            "assert not embree_available() and RayEngine(b.vertices, b.faces).backend == 'bvh'\n"
            "try:\n"
            "    RayEngine(b.vertices, b.faces, backend='embree')\n"
            "except ImportError as e:\n"
            "    assert 'pip install embreex' in str(e)\n"
            "else:\n"
            "    raise AssertionError('no ImportError')\n"
            "cam = PinholeCamera.looking_at(width_px=8, height_px=6, fx_px=60.0, position_mm=(0, -5.0, 0),\n"
            "                               target_mm=(0, 0, 0))\n"
            "m = pixel_faces(b, cam)\n"
            "assert m.shape == (6, 8) and (m >= 0).all()\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          cwd=str(__import__("pathlib").Path(__file__).resolve().parents[2]))
    assert proc.returncode == 0, proc.stderr


def test_direct_embree_binding_equals_embreex_classes() -> None:
    """The ctypes binding (estimation._embree4: shared buffers, 16-ray packets) is the default where it loads and
    answers as embreex's EmbreeScene does on the same float32 scene: same faces, distances to float32 rounding;
    ray counts that are not a multiple of the packet size (padding lanes) included."""
    if not embree_available():
        pytest.skip("embreex not installed")
    mesh = _two_meshes()[0]
    direct = RayEngine(mesh.vertices, mesh.faces)
    assert direct.embree_binding == "direct"
    classes = RayEngine(mesh.vertices, mesh.faces, embree_binding="embreex")
    assert classes.embree_binding == "embreex"
    for n in (1, 15, 16, 17, 5001):
        o, d = _random_rays(n, seed=n)
        fa, ta = direct.first_hit(o, d)
        fb, tb = classes.first_hit(o, d)
        assert np.mean(fa == fb) > 0.999 and (n < 100 or 0.2 < np.mean(fa >= 0) < 0.8)
        both = (fa >= 0) & (fa == fb)
        np.testing.assert_allclose(ta[both], tb[both], rtol=0, atol=2e-6 * 28.0)
        assert np.all(np.isinf(ta[fa < 0]))
    with pytest.raises(ValueError, match="embree_binding"):
        RayEngine(mesh.vertices, mesh.faces, embree_binding="optix")
