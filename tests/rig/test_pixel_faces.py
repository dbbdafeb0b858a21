"""rig.estimate.pixel_map.pixel_faces: exact pixel-to-face maps by one ray per pixel centre (estimation.rays.RayEngine).

The scenes are non-convex: a painter's order by face-centroid depth (the rasterizer this replaced, kept below as
``_painters_order`` to show that each scene does tell the two apart) draws a far face over a near one when the
far face's centroid is nearer than the near face's. The ray-cast map is checked against trimesh's own pure-python
intersector (float64, no Embree) and against what the geometry says analytically."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from estimation.camera import PinholeCamera
from estimation.single_image import patches_from_mesh
from rig.estimate.pixel_map import pixel_faces


def _painters_order(mesh: trimesh.Trimesh, camera: PinholeCamera) -> np.ndarray:
    """The replaced rasterizer: front faces filled back to front by centroid depth (cv2.fillConvexPoly)."""
    import cv2

    verts, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    uv, depth = camera.project(verts)
    centers = verts[faces].mean(axis=1)
    facing = np.sum(np.asarray(mesh.face_normals) * (camera.C - centers), axis=1) > 0
    idx = np.flatnonzero(facing & np.all(depth[faces] > 0, axis=1))
    order = idx[np.argsort(-camera.project(centers[idx])[1])]
    buf = np.full((camera.height_px, camera.width_px), -1, np.int32)
    for f, tri in zip(order, np.round(uv[faces[order]] * 256).astype(np.int32)):
        cv2.fillConvexPoly(buf, tri, int(f), lineType=cv2.LINE_8, shift=8)
    return buf


def _trimesh_map(mesh: trimesh.Trimesh, camera: PinholeCamera) -> np.ndarray:
    """Nearest face per pixel ray by trimesh's pure-python intersector (all hits, nearest kept)."""
    o, d = camera.pixel_rays()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    loc, iray, itri = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_location(o, d)
    dist = np.einsum("ij,ij->i", loc - o[iray], d[iray])
    best = np.full(len(o), np.inf)
    out = np.full(len(o), -1)
    for r, f, s in zip(iray, itri, dist):
        if 0 < s < best[r]:
            best[r], out[r] = s, f
    return out.reshape(camera.height_px, camera.width_px)


def _tilted_wall_and_cube() -> tuple[trimesh.Trimesh, int]:
    """A wall receding from the camera (the plane y = 50 + 2x, x in [-20, 20]: 10 to 90 mm deep, its big faces'
    centroids 37-63 mm deep) and a small cube *behind* the wall's near end (x = -15, 30 mm deep, where the wall is
    20 mm deep): a painter's order draws the cube last, over the wall. Returns (mesh, number of wall faces)."""
    wall = trimesh.creation.box(extents=(float(np.hypot(40.0, 80.0)), 1.0, 30.0))
    wall.apply_transform(trimesh.transformations.rotation_matrix(np.arctan2(80.0, 40.0), [0, 0, 1]))
    wall.apply_translation((0, 50.0, 0))
    cube = trimesh.creation.box(extents=(4.0, 4.0, 4.0))
    cube.apply_translation((-15.0, 30.0, 0.0))
    return trimesh.util.concatenate([wall, cube]), len(wall.faces)


def _camera(w: int = 96, h: int = 72) -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=w, height_px=h, fx_px=70.0, position_mm=(0, 0, 0),
                                    target_mm=(0, 100.0, 0))


def test_ray_cast_map_is_exact_where_painters_order_is_wrong() -> None:
    mesh, n_wall = _tilted_wall_and_cube()
    cam = _camera()
    got = pixel_faces(mesh, cam)
    ref = _trimesh_map(mesh, cam)
    assert got.shape == (cam.height_px, cam.width_px) and got.dtype == np.int32
    # the cube is entirely hidden behind the wall (a ray to each of its corners crosses the wall first) ...
    corners = mesh.vertices[np.asarray(mesh.faces[n_wall:]).ravel()]
    f, _ = _first(mesh, cam, corners)
    assert np.all((f >= 0) & (f < n_wall))
    assert not np.any(got >= n_wall) and not np.any(ref >= n_wall)
    # ... so no pixel may show it; the painter's order does show it (this scene tells the two apart)
    old = _painters_order(mesh, cam)
    assert np.sum(old >= n_wall) > 20
    # and the map is trimesh's own answer pixel for pixel (up to rays through an edge shared by two faces)
    assert np.array_equal(got >= 0, ref >= 0)
    assert np.mean(got[ref >= 0] == ref[ref >= 0]) > 0.995


def _first(mesh: trimesh.Trimesh, cam: PinholeCamera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from estimation.rays import RayEngine

    return RayEngine(mesh.vertices, mesh.faces).first_hit(np.broadcast_to(cam.C, points.shape), points - cam.C)


def test_torus_map_matches_trimesh_and_patch_visibility() -> None:
    torus = trimesh.creation.torus(20.0, 7.0, major_sections=40, minor_sections=20)
    cam = PinholeCamera.looking_at(width_px=80, height_px=60, fx_px=100.0, position_mm=(0, -70.0, 45.0),
                                   target_mm=(0, 0, 0))
    got = pixel_faces(torus, cam)
    ref = _trimesh_map(torus, cam)
    assert 0.2 < np.mean(ref >= 0) < 0.8
    assert np.array_equal(got >= 0, ref >= 0)
    assert np.mean(got[ref >= 0] == ref[ref >= 0]) > 0.995
    # every face the map shows is one that patch visibility (occlusion on) lets through, bar grazing ones
    p = patches_from_mesh(torus, cam, occlusion=True, cos_min=0.0)
    shown = np.unique(got[got >= 0])
    assert np.mean(p.visible[shown]) > 0.97
    # patch visibility = facing and no face on the segment to the camera, as trimesh's intersector says
    p = patches_from_mesh(torus, cam.C, occlusion=True, cos_min=0.0)    # a position: no image-frame test
    o = p.centers_mm
    d = cam.C - o
    loc, iray, _ = trimesh.ray.ray_triangle.RayMeshIntersector(torus).intersects_location(o + 1e-6 * d, d)
    s = np.einsum("ij,ij->i", loc - o[iray], d[iray]) / np.einsum("ij,ij->i", d[iray], d[iray])
    blocked = np.zeros(len(o), bool)
    blocked[iray[(s > 1e-6) & (s < 1 - 1e-6)]] = True
    facing = p.cos_out >= 0.0
    assert np.any(blocked & facing)                              # the torus does hide some of its front faces
    assert np.array_equal(p.visible, facing & ~blocked)


def test_open_mesh_seen_from_behind_is_background() -> None:
    plane = trimesh.Trimesh([[-99, 0, -99], [99, 0, -99], [99, 0, 99], [-99, 0, 99]], [[0, 1, 2], [0, 2, 3]])
    assert plane.face_normals[0][1] < 0                           # faces -y, i.e. away from a camera at +y
    front = PinholeCamera.looking_at(width_px=20, height_px=20, fx_px=30.0, position_mm=(0, -40.0, 0),
                                     target_mm=(0, 0, 0))
    back = PinholeCamera.looking_at(width_px=20, height_px=20, fx_px=30.0, position_mm=(0, 40.0, 0),
                                    target_mm=(0, 0, 0))
    assert np.all(pixel_faces(plane, front) >= 0)
    assert np.all(pixel_faces(plane, back) == -1)


@pytest.mark.parametrize("w,h", [(1, 1), (7, 3)])
def test_shapes(w: int, h: int) -> None:
    box = trimesh.creation.box(extents=(1000.0, 1000.0, 1.0))
    cam = PinholeCamera.looking_at(width_px=w, height_px=h, fx_px=10.0, position_mm=(0, 0, 50.0),
                                   target_mm=(0, 0, 0), up=(0, 1, 0))
    got = pixel_faces(box, cam)
    assert got.shape == (h, w) and np.all(got >= 0)


def test_candidate_pixels_give_the_map_of_every_pixel() -> None:
    """With a pinhole camera only pixels inside the projected faces' boxes cast rays: the map (and the surface
    points) equal one ray through every pixel centre, here with the torus partly out of frame."""
    from estimation.rays import RayEngine

    torus = trimesh.creation.torus(30.0, 10.0, major_sections=40, minor_sections=20)
    cam = PinholeCamera.looking_at(width_px=90, height_px=60, fx_px=70.0, position_mm=(25.0, -90.0, 40.0),
                                   target_mm=(-30.0, 0.0, 0.0))
    eng = RayEngine(torus.vertices, torus.faces)
    pts = np.empty((60, 90, 3))
    got = pixel_faces(torus, cam, engine=eng, points=pts)
    o, d = cam.pixel_rays()
    face, t = eng.first_hit(o, d)
    front = (face >= 0) & (np.einsum("hwc,hwc->hw", eng.face_normals[np.maximum(face, 0)], d) < 0)
    want = np.where(front, face, -1)
    assert 0.2 < np.mean(want >= 0) < 0.9 and np.any(want[:, -1] >= 0)    # partly out of frame, background too
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(pts[front], (o + t[..., None] * d)[front], atol=1e-9)
    assert np.all(np.isnan(pts[~front]))
