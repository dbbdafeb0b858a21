"""Measurements of the Monte Carlo renderer's point lights through a refracting non-convex mesh of any size
(issue 17 part 3; simulators.mc.nee ``bvh_mesh_connections``: candidate triangles within the connection radius,
found by the mesh's BVH, instead of every face plane).

1. **Against the existing paths** (eta 1.3, one point light, pinhole camera): the L-block and the U-channel of
   the scene zoo (plane tables, 8 and 10 planes: ``nonconvex_mesh_connections``) and the scene zoo's pyramid
   (convex face table: ``mesh_connections``), each rendered by its own path and by the BVH path forced onto the
   same mesh (different seeds): image-mean ratio with its standard error, per-pixel z-scores (rms, fraction
   |z| > 3), render times.
2. **A finely tessellated analytic case**: a sphere (analytic refracted connections, ``sphere_connections``)
   beside an icosphere of 5,120 faces (convex, so by default the face table; here forced onto the BVH path),
   sigma_s = 8 / mm.
   The tessellation itself changes the image (faceted normals, ~1.5 deg steps): the ratio is printed.
3. **Energy conservation** on a scanned-like non-convex mesh (an icosphere displaced by smooth noise with a crater,
   5,120 faces, radius 5 mm; more than 512 planes, so the BVH path by default) at eta 1.3, albedo 1
   (sigma_s = 10/mm, sigma_a = 0): the flux leaving the object, 4 pi x the mean over view directions of the power
   an orthographic camera receives (sum of radiance x pixel area; two randomly rotated Fibonacci sets of 12
   directions, their difference the error estimate; pixels 0.4 mm, the grid shifted by a random sub-pixel offset
   per view), against the
   flux that enters it, I x the integral over the light's directions that hit the mesh of the Fresnel
   transmittance (estimated by rays from the light, estimation.rays.RayEngine). Not counted by either: light
   reflected at the first surface and entering elsewhere (the renderer's point-light connections need a direct
   path), light that leaves and re-enters before its first scattering (module docstring of simulators.mc.nee).

Run: ``python benchmarks/mc_bvh_connections.py [--quick] [--json out.json]`` (minutes; not run in CI).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from estimation.camera import OrthographicCamera, PinholeCamera  # noqa: E402
from estimation.rays import RayEngine  # noqa: E402
from estimation.single_image import PointLights  # noqa: E402
from simulators.mc import Medium, Mesh, Sphere, render  # noqa: E402
from simulators.mc.optics import fresnel_r  # noqa: E402
from simulators.mc.shapes import BVH_CONNECTIONS  # noqa: E402
from simulators.scene import wall_on_slab_mesh  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402
from zoo.nonconvex import u_channel_mesh  # noqa: E402


def forced_bvh(mesh: trimesh.Trimesh) -> Mesh:
    """The mesh with its refracted connections searched by the BVH whatever its plane count."""
    shape = Mesh(mesh)
    geo = shape.geometry()
    shape._cache["g"] = geo._replace(params=np.array([0.0, BVH_CONNECTIONS] + [0.0] * 6), convex=False)
    return shape


def pyramid() -> trimesh.Trimesh:
    v = np.array([[-6.0, -6.0, 0.0], [6.0, -6.0, 0.0], [6.0, 6.0, 0.0], [-6.0, 6.0, 0.0], [0.0, 0.0, 8.0]])
    f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return trimesh.Trimesh(v, f, process=True)


def scanned_blob(subdivisions: int = 4, radius_mm: float = 5.0, seed: int = 7) -> trimesh.Trimesh:
    """benchmarks/meshes.py's scanned-like body (smooth noise + crater) without the handle (the renderer needs
    one closed, non-self-intersecting surface)."""
    rng = np.random.default_rng(seed)
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    u = np.asarray(s.vertices)
    k = rng.normal(size=(12, 3)) * 2.5
    ph = rng.uniform(0, 2 * np.pi, 12)
    amp = rng.normal(size=12) * 0.06 / np.sqrt(12)
    r = 1.0 + np.sin(u @ k.T + ph) @ amp
    axis = np.array([0.3, -0.8, 0.52]) / np.linalg.norm([0.3, -0.8, 0.52])
    r -= 0.45 * np.exp(-(np.arccos(np.clip(u @ axis, -1, 1)) / 0.35) ** 2)
    return trimesh.Trimesh(u * r[:, None] * radius_mm, s.faces, process=False)


def compare(name: str, ref_shape: Any, new_shape: Any, med: Medium, cam: Any, light: PointLights, spp: int
            ) -> dict[str, Any]:
    a = render(ref_shape, med, cam, light, spp=spp, seed=1)
    b = render(new_shape, med, cam, light, spp=spp, seed=2)
    m = a.mask & b.mask & (a.radiance[..., 0] > 0)
    ra, rb = a.radiance[m, 0], b.radiance[m, 0]
    sa, sb = a.stderr[m, 0], b.stderr[m, 0]
    z = (rb - ra) / np.maximum(np.hypot(sa, sb), 1e-300)
    mean_a, mean_b = ra.mean(), rb.mean()
    se = math.hypot(np.sqrt(np.sum(sa ** 2)) / len(ra) / mean_a, np.sqrt(np.sum(sb ** 2)) / len(rb) / mean_b)
    out = {"name": name, "pixels": int(m.sum()), "mean_ref": float(mean_a), "mean_new": float(mean_b),
           "ratio": float(mean_b / mean_a), "ratio_se": float(se * mean_b / mean_a),
           "z_rms": float(np.sqrt(np.mean(z ** 2))), "z_gt3": float(np.mean(np.abs(z) > 3)),
           "seconds_ref": a.seconds, "seconds_new": b.seconds}
    print(f"{name}: {out['pixels']} px, mean new/ref {out['ratio']:.4f} +- {out['ratio_se']:.4f}, per-pixel z rms "
          f"{out['z_rms']:.2f}, |z|>3 {out['z_gt3']:.1%}; render {a.seconds:.1f} s (ref path) vs {b.seconds:.1f} s "
          f"(BVH path)", flush=True)
    return out


def fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def flux_in(mesh: trimesh.Trimesh, light_mm: np.ndarray, intensity: float, eta: float, n_rays: int) -> tuple[float,
                                                                                                           float]:
    """I x integral of F_t over the light's directions that hit the mesh first (uniform over the cone that
    bounds the mesh's bounding sphere): (value, standard error)."""
    c = mesh.bounding_sphere.primitive.center
    rad = mesh.bounding_sphere.primitive.radius
    axis = (c - light_mm) / np.linalg.norm(c - light_mm)
    cos_max = math.sqrt(max(0.0, 1 - (rad / np.linalg.norm(c - light_mm)) ** 2))
    rng = np.random.default_rng(11)
    cz = rng.uniform(cos_max, 1.0, n_rays)
    ph = rng.uniform(0, 2 * math.pi, n_rays)
    sz = np.sqrt(1 - cz * cz)
    t1 = np.cross(axis, [0.3, 0.5, 0.8])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(axis, t1)
    d = (cz[:, None] * axis + (sz * np.cos(ph))[:, None] * t1 + (sz * np.sin(ph))[:, None] * t2)
    eng = RayEngine(mesh.vertices, mesh.faces)
    face, _ = eng.first_hit(light_mm, d)
    hit = face >= 0
    cos1 = np.zeros(n_rays)
    cos1[hit] = -np.einsum("ij,ij->i", eng.face_normals[face[hit]], d[hit])
    ft = np.zeros(n_rays)
    ft[hit] = [1.0 - fresnel_r(eta, float(cc)) for cc in np.clip(cos1[hit], 0.0, 1.0)]
    omega = 2 * math.pi * (1 - cos_max)
    return intensity * omega * float(ft.mean()), intensity * omega * float(ft.std() / math.sqrt(n_rays))


def energy(mesh: trimesh.Trimesh, med: Medium, light_mm: np.ndarray, intensity: float, n_views: int, spp: int,
           pixel_mm: float) -> dict[str, Any]:
    shape = Mesh(mesh)
    assert shape.geometry().params[1] == BVH_CONNECTIONS
    c = mesh.bounding_sphere.primitive.center
    rad = mesh.bounding_sphere.primitive.radius
    n_px = int(math.ceil(2.2 * rad / pixel_mm))
    light = PointLights(light_mm[None, :], [intensity])
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    secs = 0.0
    sets = []
    for rot_seed in (1, 2):      # two randomly rotated Fibonacci sets: two unbiased estimates of the integral
        powers, ses = [], []
        dirs = Rotation.random(random_state=rot_seed).apply(fibonacci_directions(n_views))
        for k, w in enumerate(dirs):
            up = (0.0, 0.0, 1.0) if abs(w[2]) < 0.9 else (1.0, 0.0, 0.0)
            # rays through pixel centres: a random sub-pixel shift of the grid per view makes the sum an unbiased
            # estimate of the area integral (no silhouette bias of the midpoint rule)
            shift = np.linalg.svd(w[None, :])[2][1:].T @ rng.uniform(-0.5, 0.5, 2) * pixel_mm
            cam = OrthographicCamera.looking_at(width_px=n_px, height_px=n_px, pixel_size_mm=pixel_mm,
                                                direction=-w, target_mm=c + shift, up=up)
            img = render(shape, med, cam, light, spp=spp, seed=100 * rot_seed + k)
            secs += img.seconds
            powers.append(float(img.radiance[..., 0].sum()) * pixel_mm ** 2)
            ses.append(float(np.sqrt(np.sum(img.stderr[..., 0] ** 2))) * pixel_mm ** 2)
        sets.append((4 * math.pi * float(np.mean(powers)),
                     4 * math.pi * float(np.sqrt(np.sum(np.square(ses)))) / len(powers)))
    (fa, sa), (fb, sb) = sets
    out_flux = 0.5 * (fa + fb)
    # error: the renders' noise and the direction quadrature, estimated by the two sets' difference (which holds
    # the render noise as well: the larger of the two is taken)
    out_se = max(0.5 * math.hypot(sa, sb), 0.5 * abs(fa - fb))
    in_flux, in_se = flux_in(mesh, light_mm, intensity, med.eta, 400_000)
    res = {"faces": len(mesh.faces), "views": 2 * n_views, "flux_out_sets": [fa, fb], "spp": spp,
           "pixel_mm": pixel_mm, "flux_out": out_flux,
           "flux_out_se": out_se, "flux_in": in_flux, "flux_in_se": in_se, "ratio": out_flux / in_flux,
           "ratio_se": out_flux / in_flux * math.hypot(out_se / out_flux, in_se / in_flux), "seconds": secs}
    print(f"energy, scanned-like blob ({len(mesh.faces)} faces, radius 5 mm, eta {med.eta}, sigma_s "
          f"{med.sigma_s_per_mm}/mm, sigma_a 0, pixels {pixel_mm} mm): flux out {out_flux:.5g} +- {out_se:.2g} "
          f"(2 x {n_views} orthographic views: {fa:.5g}, {fb:.5g}; {spp} spp) vs in {in_flux:.5g} +- "
          f"{in_se:.2g}: out/in "
          f"{res['ratio']:.4f} +- {res['ratio_se']:.4f}; "
          f"renders {secs:.0f} s", flush=True)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--only", default="compare,sphere,energy")
    a = ap.parse_args(argv)
    q = a.quick
    only = set(a.only.split(","))
    print(f"# load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; NUMBA_NUM_THREADS="
          f"{os.environ.get('NUMBA_NUM_THREADS', 'default')}", flush=True)
    t0 = time.perf_counter()
    out: dict[str, Any] = {"load_average": os.getloadavg(), "compare": []}
    n_px, spp = (12, 32) if q else (24, 128)
    med = Medium(1.5, 0.02, 0.0, 1.3)
    if "compare" in only:
        cases = [("L-block (plane table, 8 planes)", wall_on_slab_mesh(), (40.0, -20.0, 60.0), (15.0, -60.0, 45.0)),
                 ("U-channel (plane table)", u_channel_mesh(), (-20.0, -30.0, 50.0), (20.0, -60.0, 40.0)),
                 ("pyramid (convex face table)", pyramid(), (20.0, -25.0, 30.0), (10.0, -40.0, 30.0))]
        for name, mesh, light_pos, cam_pos in cases:
            c = mesh.bounds.mean(axis=0)
            cam = PinholeCamera.looking_at(width_px=n_px, height_px=n_px, fx_px=1.5 * n_px, position_mm=cam_pos,
                                           target_mm=c)
            light = PointLights([light_pos], [1e4])
            out["compare"].append(compare(name, Mesh(mesh), forced_bvh(mesh), med, cam, light, spp))
    if "sphere" in only:
        ico = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
        cam = PinholeCamera.looking_at(width_px=n_px, height_px=n_px, fx_px=1.2 * n_px, position_mm=(0, -18.0, 8.0),
                                       target_mm=(0, 0, 0))
        # sigma_t 8 / mm: a connection radius of 1.7 mm (at 1.5 / mm the ball would hold the whole 5 mm sphere)
        out["sphere"] = compare("sphere (analytic) vs icosphere 5120 faces (BVH path), sigma_s 8 / mm",
                                Sphere((0.0, 0.0, 0.0), 5.0), forced_bvh(ico), Medium(8.0, 0.05, 0.0, 1.3), cam,
                                PointLights([(8.0, -12.0, 12.0)], [1e4]), spp // 2)
    if "energy" in only:
        out["energy"] = energy(scanned_blob(), Medium(10.0, 0.0, 0.0, 1.3), np.array([9.0, -14.0, 11.0]), 1e4,
                               4 if q else 12, 8, 0.5 if q else 0.4)
    print(f"# run {time.perf_counter() - t0:.0f} s; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if a.json:
        write_json(a.json, out, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
