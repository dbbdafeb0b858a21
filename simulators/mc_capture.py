"""Monte Carlo ("exact") frames of the simulated scene: the bridge from the scene objects to ``simulators.mc``.

The simulated camera renders a capture either **fast** (the Jensen dipole over surface patches,
:mod:`simulators.scene`) or **mc** (a seeded Monte Carlo random walk in the object, :func:`simulators.mc.render`).
This module converts what a scene holds into what the Monte Carlo renderer needs:

- geometry (:func:`mc_shape`): :class:`~simulators.scene.SphereObject` -> analytic ``Sphere``;
  :class:`~simulators.scene.MeshObject` -> ``Mesh`` (its own BVH; flat faces; refracted point-light connections
  for convex meshes), except an axis-aligned box mesh, which becomes the analytic ``Box``; :class:`~simulators.scene.
  BumpySlabObject` -> a closed ``Mesh``: the relief h(u, v) sampled every ``MCSettings.relief_step_mm`` on the
  top, flat sides and bottom ``slab_thickness_mm`` below (default half the extent: deep enough to act as a
  half-space for every material of science.md sec. 2 except the thinnest-absorbing channels);
- media (:func:`mc_media`): one :class:`~simulators.mc.Medium` per colour channel, built from the object's reduced
  sigma_s' and sigma_a with isotropic scattering (g = 0, so sigma_s = sigma_s': the parametrization the
  estimators use) and the object's eta;
- lights (:func:`led_lights`): the LED sphere's current emission (N, 3) as
  - ``"points"``: isotropic point lights at the LED positions, exactly what the fast renderer uses. The renderer
    connects every collision to one LED (next-event estimation through the refracting boundary) -- exact, but
    noisy (a 10 mm marble sphere under all 362 LEDs: ~35 % per-pixel standard error at 8 samples per pixel)
    and unavailable for non-convex meshes with eta != 1 (convex meshes, e.g. pyramids, are supported);
  - ``"distant"``: the LEDs as a distant lat-long radiance map in which every map pixel takes the radiance of its
    nearest LED, I_l / d_l^2 spread over that LED's (Voronoi) cell (pixels farther than 0.75 x the largest
    nearest-neighbour LED spacing from any LED stay dark, e.g. below the lowest ring). It has the LEDs'
    irradiance (same total per LED, same direction to within the cell size) without the near field (1/d^2 and
    direction change across the object, relative order 2 |x| / R_sphere: 2 % for a 10 mm object at 1 m) and
    with piecewise-constant cells instead of points. Walks then read the map in their exit direction: low
    variance (the same sphere: ~2 % at 8 spp), any shape;
  - ``"auto"`` (default): "distant" for gradient captures (many LEDs lit), "points" when at most
    ``MCSettings.max_point_lights`` LEDs are lit and the renderer supports them (analytic shape, convex mesh or
    eta = 1), else "distant".

Every frame carries the Monte Carlo standard error of its diffuse radiance. Frames of one capture share the
seed, i.e. the same random walks (common random numbers): under distant light a walk does not depend on the
pattern, so ratios of frames (gradient normals) see far less Monte Carlo noise than each frame alone.

Surface reflection is not simulated by the walk: parallel-polarized frames add the same analytic GGX lobe as
the fast renderer (:func:`simulators.scene.specular_radiance`), so only the subsurface transport differs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .objects import BumpySlabObject, MeshObject, SphereObject

FloatArray = npt.NDArray[np.float64]

__all__ = ["RENDER_MODES", "LED_MODES", "MCSettings", "mc_shape", "mc_media", "led_environment", "led_lights",
           "render_mc", "relief_mesh", "check_render_mode"]

RENDER_MODES: tuple[str, ...] = ("fast", "mc")
LED_MODES: tuple[str, ...] = ("auto", "points", "distant")


def check_render_mode(mode: str) -> str:
    if mode not in RENDER_MODES:
        raise ValueError(f"unknown render_mode {mode!r}; valid: {', '.join(RENDER_MODES)}")
    return mode


@dataclass(frozen=True)
class MCSettings:
    """Options of the Monte Carlo render mode.

    ``spp``: paths per pixel (>= 2: the standard error needs two); ``seed``: the random streams (same seed, same
    image on any thread count); ``leds``: "auto" | "points" | "distant" (module docstring); ``env_rows``: rows of
    the distant LED map (columns = 2 x rows; 90 = 2 deg pixels, the LEDs of the default rig are 10.7 deg apart);
    ``max_point_lights``: "auto" uses point lights up to this many lit LEDs; ``relief_step_mm``: triangle grid
    of a bumpy slab's relief (None: the object's ``patch_mm``); ``slab_thickness_mm``: depth of the bumpy slab's
    mesh (None: half its extent); ``max_sampled_lights``: passed to :func:`simulators.mc.render`.
    """

    spp: int = 64
    seed: int = 0
    leds: str = "auto"
    env_rows: int = 90
    max_point_lights: int = 8
    relief_step_mm: float | None = None
    slab_thickness_mm: float | None = None
    max_sampled_lights: int = 8

    def __post_init__(self) -> None:
        if self.spp < 2:
            raise ValueError("spp must be >= 2 (the standard error needs two samples per pixel)")
        if self.leds not in LED_MODES:
            raise ValueError(f"unknown leds mode {self.leds!r}; valid: {', '.join(LED_MODES)}")
        if self.env_rows < 4:
            raise ValueError("env_rows must be >= 4")


# ------------------------------------------------------------------------------------------------ geometry
def relief_mesh(obj: Any, step_mm: float | None = None, thickness_mm: float | None = None) -> Any:
    """A closed trimesh of a :class:`~simulators.scene.BumpySlabObject`: the relief sampled on a square grid of
    ``step_mm`` (default ``obj.patch_mm``) over the extent, vertical sides, a flat bottom ``thickness_mm`` below
    the mean plane (default extent / 2). Outward winding, watertight."""
    import trimesh

    step = float(step_mm if step_mm is not None else obj.patch_mm)
    depth = float(thickness_mm if thickness_mm is not None else 0.5 * obj.extent_mm)
    half = 0.5 * obj.extent_mm
    m = max(2, int(np.ceil(obj.extent_mm / step)))
    g = np.linspace(-half, half, m + 1)
    c, n, e1, e2 = obj._frame()
    uu, vv = np.meshgrid(g, g, indexing="ij")
    h, _, _ = obj.height(uu, vv)
    top = (c + uu[..., None] * e1 + vv[..., None] * e2 + h[..., None] * n).reshape(-1, 3)
    idx = np.arange((m + 1) ** 2).reshape(m + 1, m + 1)
    a, b, cc, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    # (u, v, n) is right-handed, so (a, b, c) counter-clockwise seen from +n is outward for the top
    faces = [np.stack([a, b, cc], -1).reshape(-1, 3), np.stack([a, cc, d], -1).reshape(-1, 3)]
    # boundary loop of the top grid, counter-clockwise seen from +n: v = -half (u up), u = +half, v = +half, u = -half
    loop = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    lu = np.concatenate([g, np.full(m, half), g[-2::-1], np.full(m - 1, -half)])
    lv = np.concatenate([np.full(m + 1, -half), g[1:], np.full(m, half), g[-2:0:-1]])
    nb = len(loop)
    base = len(top)
    bottom = c + lu[:, None] * e1 + lv[:, None] * e2 - depth * n
    center = (c - depth * n)[None, :]
    verts = np.concatenate([top, bottom, center])
    i = np.arange(nb)
    j = (i + 1) % nb
    t0, t1, b0, b1 = loop[i], loop[j], base + i, base + j
    faces.append(np.stack([t0, b0, b1], -1))          # sides: outward for a counter-clockwise loop
    faces.append(np.stack([t0, b1, t1], -1))
    faces.append(np.stack([np.full(nb, base + nb), b1, b0], -1))   # bottom fan, facing -n
    mesh = trimesh.Trimesh(verts, np.concatenate(faces), process=False)
    if float(mesh.volume) < 0:
        mesh.invert()
    return mesh


def _is_box_mesh(mesh: Any) -> bool:
    v = np.asarray(mesh.vertices, float)
    if len(v) != 8:
        return False
    lo, hi = v.min(0), v.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    tol = 1e-9 * max(1.0, float(np.abs(v).max()))
    return bool(np.all(np.min(np.linalg.norm(v[:, None] - corners[None], axis=-1), axis=1) <= tol)
                and np.all(np.min(np.linalg.norm(corners[:, None] - v[None], axis=-1), axis=1) <= tol))


def mc_shape(obj: Any, settings: MCSettings | None = None) -> Any:
    """The Monte Carlo shape of a scene object (module docstring); meshes are cached on the object."""
    from simulators import mc

    s = settings or MCSettings()
    if isinstance(obj, SphereObject):
        return mc.Sphere(tuple(float(x) for x in obj.center_mm), float(obj.radius_mm))
    if isinstance(obj, MeshObject):
        if _is_box_mesh(obj.mesh):
            v = np.asarray(obj.mesh.vertices, float)
            return mc.Box(tuple(v.min(0)), tuple(v.max(0)))
        return mc.Mesh(obj.mesh)
    if isinstance(obj, BumpySlabObject):
        key = ("mc_mesh", s.relief_step_mm, s.slab_thickness_mm)
        cache = obj.__dict__.setdefault("_mc_cache", {})
        if key not in cache:
            cache[key] = mc.Mesh(relief_mesh(obj, s.relief_step_mm, s.slab_thickness_mm))
        return cache[key]
    raise TypeError(f"no Monte Carlo shape for {type(obj).__name__}")


def mc_media(obj: Any) -> list[Any]:
    """One isotropic :class:`simulators.mc.Medium` per channel from the object's sigma_s', sigma_a and eta."""
    from simulators.mc import Medium

    ssp = np.broadcast_to(np.asarray(obj.sigma_s_prime_per_mm, float), (3,))
    sa = np.broadcast_to(np.asarray(obj.sigma_a_per_mm, float), (3,))
    return [Medium.from_reduced(float(s), float(a), eta=float(obj.eta)) for s, a in zip(ssp, sa)]


# ------------------------------------------------------------------------------------------------ lights
def led_environment(led_positions_mm: npt.ArrayLike, emission: npt.ArrayLike, *, center_mm: npt.ArrayLike = (0, 0, 0),
                    rows: int = 90) -> Any:
    """The LEDs' emission (N, 3) (radiant intensity) as a distant :class:`estimation.single_image.EnvironmentMap`
    seen from ``center_mm``: each map pixel gets the radiance of its nearest LED, I_l / d_l^2 / Omega_l with
    Omega_l the solid angle of that LED's cell, so every LED delivers its irradiance at ``center_mm``; pixels
    farther than 0.75 x the largest nearest-neighbour LED spacing from every LED are dark."""
    from scipy.spatial import cKDTree

    from estimation.single_image import EnvironmentMap

    p = np.asarray(led_positions_mm, float).reshape(-1, 3) - np.asarray(center_mm, float).reshape(1, 3)
    em = np.asarray(emission, float)
    em = np.repeat(em.reshape(-1, 1), 3, axis=1) if em.ndim == 1 else em.reshape(len(p), -1)
    dist = np.linalg.norm(p, axis=1)
    dirs = p / dist[:, None]
    h, w = int(rows), 2 * int(rows)
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * (np.arange(w) + 0.5) / w
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    pix = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    d_omega = (np.sin(th) * (np.pi / h) * (2 * np.pi / w)).reshape(-1)
    tree = cKDTree(dirs)
    if len(dirs) > 1:
        nn, _ = tree.query(dirs, k=2)
        reach = 0.75 * float(nn[:, 1].max())
    else:
        reach = 2.0  # one LED: half the sphere of directions around it
    chord, owner = tree.query(pix, k=1)
    own = chord <= reach
    cell = np.bincount(owner[own], weights=d_omega[own], minlength=len(dirs))
    gain = np.where(cell > 0, 1.0 / np.where(cell > 0, cell, 1.0), 0.0) / (dist * dist)
    rad = np.zeros((h * w, em.shape[1]))
    rad[own] = em[owner[own]] * gain[owner[own], None]
    return EnvironmentMap(rad.reshape(h, w, -1), max_size=h)


def _point_lights_supported(obj: Any, shape: Any) -> bool:
    """Point lights work for every shape at eta = 1 and, at eta != 1, for analytic shapes, convex meshes and
    non-convex meshes of any size (refracted connections with shadow rays, :mod:`simulators.mc.nee`)."""
    from simulators.mc import Mesh
    from simulators.mc.shapes import refracted_point_lights_supported

    return (not isinstance(shape, Mesh) or abs(float(obj.eta) - 1.0) < 1e-12
            or refracted_point_lights_supported(shape.geometry()))


def led_lights(obj: Any, shape: Any, led_positions_mm: npt.ArrayLike, emission: npt.ArrayLike,
               settings: MCSettings) -> tuple[Any, str]:
    """The renderer's lights for the LEDs' emission (N, 3) and the mode used ("points" | "distant")."""
    from estimation.single_image import PointLights

    pos = np.asarray(led_positions_mm, float).reshape(-1, 3)
    em = np.asarray(emission, float).reshape(len(pos), -1)
    lit = np.any(em > 0, axis=1)
    mode = settings.leds
    if mode == "auto":
        few = int(lit.sum()) <= settings.max_point_lights
        mode = "points" if few and _point_lights_supported(obj, shape) else "distant"
    if mode == "points":
        if not _point_lights_supported(obj, shape):
            raise ValueError("point LEDs through a refractive (eta != 1) non-convex mesh boundary of this many "
                             "face planes are not supported by the Monte Carlo renderer: use leds=\"distant\", a "
                             "convex mesh, a mesh of fewer planes or eta = 1")
        return PointLights(pos[lit], em[lit]), mode
    center = getattr(obj, "center_mm", None)
    if center is None:
        center = np.asarray(obj.mesh.bounds, float).mean(0)
    return led_environment(pos[lit], em[lit], center_mm=center, rows=settings.env_rows), mode


# ------------------------------------------------------------------------------------------------ rendering
def render_mc(obj: Any, camera: Any, lights: Any, settings: MCSettings | None = None) -> Any:
    """Monte Carlo image (:class:`simulators.mc.MCImage`: radiance, stderr (H, W, 3), mask) of the subsurface
    light of a scene object under any lights the renderer understands (``PointLights``, ``EnvironmentMap``,
    ``GradientPattern``). Surface reflection is not included."""
    from simulators.mc import render

    s = settings or MCSettings()
    shape = mc_shape(obj, s)
    return render(shape, mc_media(obj), camera, lights, spp=int(s.spp), seed=int(s.seed),
                  max_sampled_lights=int(s.max_sampled_lights))


def render_mc_leds(obj: Any, camera: Any, led_positions_mm: npt.ArrayLike, emission: npt.ArrayLike,
                   settings: MCSettings | None = None) -> tuple[Any, str]:
    """:func:`render_mc` under the LEDs' emission (N, 3) (lights by :func:`led_lights`); returns the image and
    the LED mode used."""
    s = settings or MCSettings()
    shape = mc_shape(obj, s)
    lights, mode = led_lights(obj, shape, led_positions_mm, emission, s)
    return render_mc(obj, camera, lights, s), mode
