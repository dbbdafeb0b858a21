"""The zoo's scenes, drawn with ``numpy.random.default_rng(15)`` and forced to cover every failure class of issue 15.

A scene is a :class:`SceneSpec` (plain numbers, JSON-able, hashed for the cache) in a z-up world (mm):

- shape: ``cube`` (edge = size), ``pyramid`` (square base = size, height 0.7 size), ``sphere`` (icosphere with
  320 faces, diameter = size), ``box`` (5 x 20 x 40 mm in a random axis order); size 5-40 mm, at most 14 l_d
  of the material's shortest channel (so that patches of ~l_d/3 fit the patch budget); turned by ``yaw_deg`` about
  the vertical, centred at ``position_mm``. All convex; the non-convex family (``lblock``, ``ushape``: issue 17,
  self-shadowing) is designed in benchmarks/zoo/nonconvex.py, indices 24 on, outside :func:`draw_zoo`.
- camera: looks at the object centre from ``camera_distance_mm`` at ``camera_elevation_deg`` above the horizon
  and ``camera_azimuth_deg``; the object spans ~70 % of the frame. Five scenes are drawn at 22-30 deg elevation,
  where a face is seen 60-68 deg from its normal (grazing, still inside the estimator's 70 deg limit).
- lights: ``point1`` one point light placed (rejection-sampled) so that at least one *observed* face (front-facing,
  < 70 deg from the view) has the light behind its plane — unlit, checked geometrically
  (:func:`face_light_counts`) — while another observed face is lit; ``point2`` two point lights; ``sun`` a
  lat-long map with a small bright sun lobe (Gaussian, 3.5 deg) over a dim sky; ``sky`` a smooth sky (no sun).
  Maps are written in the scene file's convention with drawn ``up`` / ``phi0`` / ``azimuth`` / ``rotation_deg``.
- the file's world frame: ``z-up`` (as drawn), ``y-up`` (x, z, -y: Blender/glTF exports) or ``tilted`` (a random
  rotation: ``up`` becomes a vector): the mesh, camera, lights and map are written in it.
- material-channel from science.md sec. 2 (reduced sigma_s', sigma_a per mm), one channel or RGB; eta in
  {1.0, 1.3, 1.5}, at least three eta = 1 cubes (index-matched boundary).
- noise (``zeros`` only with point lights: an evenly lit object under a map has no dark pixels to clip):
  ``mc`` the Monte Carlo frame at low spp (heavy-tailed pixels, fireflies), EXR (frames of the other classes
  at 256 spp, sun-lit ones at 1024); ``zeros`` camera shot +
  read noise clipped at 0 after black-level subtraction (dark pixels exactly 0); ``camera`` Poisson-Gaussian
  (electrons per value, read noise) as float EXR (unclipped) or 16-bit PNG. ``noise_section``: the scene file
  carries the true gain and read noise in ``[noise]``, or nothing.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import trimesh

MATERIALS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    # science.md sec. 2 (Jensen et al. 2001 Table 2, pbrt's reduced sigma_s'), per mm, R G B
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
}
# every material at least once, three RGB scenes; the remaining slots draw from this list again
MATERIAL_CHANNELS = ("marble-R", "marble-RGB", "skin1-R", "skin1-G", "apple-G", "apple-RGB", "apple-B", "skimmilk-R",
                     "skimmilk-B", "skimmilk-RGB", "ketchup-R", "potato-B", "marble-B", "skimmilk-G", "apple-R")
SHAPES = ("cube", "pyramid", "sphere", "box")
LIGHTS = ("point1", "point2", "sun", "sky")
NOISES = ("mc", "zeros", "camera")
ETAS = (1.0, 1.3, 1.5)
BOX_MM = (5.0, 20.0, 40.0)
MAX_VIEW_DEG = 70.0      # the estimator's default grazing limit: faces beyond it are not observed
GRAZING_DEG = 60.0       # a scene is "graze" when an observed face is seen farther than this from its normal
SUN_SIGMA_DEG = 3.5
# the renderer finds a map's sun only when an escaping walk happens to leave towards it (no light sampling of maps):
# at 256 spp a sun-lit frame is 25-45 % noisy per pixel; the zeros/camera classes render sun scenes at 4x the spp
# so that the camera noise is not swamped (the mc class keeps its 32 spp)
SUN_SPP_FACTOR = 4
QUICK_CLASSES = ("unlit", "eta1", "sun", "mc", "zeros", "camera")   # what the --quick subset must cover


@dataclass(frozen=True)
class SceneSpec:
    index: int
    shape: str
    size_mm: float
    dims_mm: tuple[float, float, float]       # box extents along x, y, z before the yaw
    yaw_deg: float
    position_mm: tuple[float, float, float]
    camera_distance_mm: float
    camera_elevation_deg: float
    camera_azimuth_deg: float
    size_px: int
    light: str
    point_lights: tuple[tuple[float, float, float, float], ...]   # x, y, z (mm), intensity (W/sr)
    sun_direction: tuple[float, float, float]
    sky_tint: tuple[float, float, float]        # the soft sky's brighter horizontal direction
    env_rows: int
    env_keys: tuple[tuple[str, Any], ...]      # up, phi0, azimuth, rotation_deg as written in the file frame
    world: str
    world_rotation: tuple[tuple[float, ...], ...]   # z-up world -> file world
    material: str
    channels: tuple[str, ...]
    eta: float
    noise: str
    noise_section: bool
    gain_e_per_value: float
    read_noise_e: float
    image_format: str
    frame_spp: int
    frame_seed: int
    noise_seed: int
    patch_budget: int
    frame_rule: bool = True      # camera / zeros: render until the Monte Carlo noise is below the camera's (frames.py)

    @property
    def sigma_s_prime_per_mm(self) -> np.ndarray:
        return np.array([MATERIALS[self.material][0]["RGB".index(c)] for c in self.channels])

    @property
    def sigma_a_per_mm(self) -> np.ndarray:
        return np.array([MATERIALS[self.material][1]["RGB".index(c)] for c in self.channels])

    @property
    def name(self) -> str:
        flags = [self.shape, f"{self.size_mm:.0f}mm" if self.shape != "box" else "5x20x40", self.light]
        flags += ["unlit"] if self.light.startswith("point") and self.unlit_faces > 0 else []
        flags += ["graze"] if self.grazing else []
        flags += [f"eta{self.eta:g}", f"{self.material}-{''.join(self.channels)}", self.noise,
                  "noise-section" if self.noise_section else "no-noise-section"]
        return f"z{self.index:02d} " + " ".join(flags)

    @property
    def classes(self) -> set[str]:
        out = {self.shape, self.light, self.noise, f"eta{self.eta:g}"}
        out |= {"unlit"} if self.light.startswith("point") and self.unlit_faces > 0 else set()
        out |= {"eta1"} if self.eta == 1.0 else set()
        out |= {"graze"} if self.grazing else set()
        out |= {"rgb"} if len(self.channels) == 3 else set()
        return out

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    # geometry -------------------------------------------------------------------------------------------
    def mesh(self) -> trimesh.Trimesh:
        """The object in the z-up world (mm), outward winding."""
        s = self.size_mm
        if self.shape in ("lblock", "ushape"):   # the non-convex family (benchmarks/zoo/nonconvex.py)
            from .nonconvex import nonconvex_mesh

            m = nonconvex_mesh(self.shape, self.dims_mm)
        elif self.shape == "cube":
            m = trimesh.creation.box(extents=(s, s, s))
        elif self.shape == "box":
            m = trimesh.creation.box(extents=self.dims_mm)
        elif self.shape == "sphere":
            m = trimesh.creation.icosphere(subdivisions=2, radius=s / 2)
        else:
            a, h = s / 2, 0.7 * s
            z0 = -h / 3
            v = np.array([[-a, -a, z0], [a, -a, z0], [a, a, z0], [-a, a, z0], [0, 0, z0 + h]])
            f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
            m = trimesh.Trimesh(v, f, process=False)
        t = np.eye(4)
        t[:3, :3] = _rz(self.yaw_deg)
        t[:3, 3] = self.position_mm
        m.apply_transform(t)
        return m

    def camera_position_mm(self) -> np.ndarray:
        return np.asarray(self.position_mm) + self.camera_distance_mm * _unit(self.camera_azimuth_deg,
                                                                               self.camera_elevation_deg)

    def bounding_radius_mm(self) -> float:
        m = self.mesh()
        return float(np.linalg.norm(m.vertices - np.asarray(self.position_mm), axis=1).max())

    def fx_px(self) -> float:
        return 0.37 * self.size_px * self.camera_distance_mm / self.bounding_radius_mm()

    @property
    def view_angles_deg(self) -> np.ndarray:
        """Angle between each front-facing face's normal and its view direction (degrees; NaN if back-facing)."""
        m = self.mesh()
        v = self.camera_position_mm()[None, :] - m.triangles_center
        cos = np.einsum("ij,ij->i", m.face_normals, v) / np.linalg.norm(v, axis=1)
        return np.where(cos > 0, np.degrees(np.arccos(np.clip(cos, -1, 1))), np.nan)

    @property
    def grazing(self) -> bool:
        a = self.view_angles_deg
        return bool(np.any((a > GRAZING_DEG) & (a < MAX_VIEW_DEG)))

    @property
    def unlit_faces(self) -> int:
        return face_light_counts(self.mesh(), self.view_angles_deg, np.array(self.point_lights)[:, :3])[0] \
            if self.point_lights else 0


def face_light_counts(mesh: trimesh.Trimesh, view_deg: np.ndarray, lights_mm: np.ndarray) -> tuple[int, int]:
    """(observed faces no light reaches, observed faces lit): a face of a convex body is unlit by a point light
    exactly when the light lies behind its plane (n . (L - x) <= 0 at any point x of the face)."""
    observed = np.nan_to_num(view_deg, nan=180.0) < MAX_VIEW_DEG
    lit = np.zeros(len(mesh.faces), bool)
    for p in np.atleast_2d(lights_mm):
        lit |= np.einsum("ij,ij->i", mesh.face_normals, p[None, :] - mesh.triangles_center) > 0
    return int(np.sum(observed & ~lit)), int(np.sum(observed & lit))


def _rz(deg: float) -> np.ndarray:
    t = math.radians(deg)
    return np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])


def _unit(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def l_d_min_mm(material: str, channels: tuple[str, ...]) -> float:
    s, a = MATERIALS[material]
    return min(1.0 / math.sqrt(3 * a[i] * (a[i] + s[i])) for i in ("RGB".index(c) for c in channels))


def _split(mc: str) -> tuple[str, tuple[str, ...]]:
    name, ch = mc.split("-")
    return name, tuple(ch)


def _balanced(rng: np.random.Generator, values: tuple[Any, ...], n: int) -> list[Any]:
    out = [values[i % len(values)] for i in range(n)]
    return [out[i] for i in rng.permutation(n)]


def _world(rng: np.random.Generator) -> tuple[str, np.ndarray]:
    kind = ("z-up", "y-up", "tilted")[int(rng.integers(3))]
    if kind == "z-up":
        return kind, np.eye(3)
    if kind == "y-up":
        return kind, np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z -> +y, y -> -z
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return kind, q * np.sign(np.linalg.det(q))


def _axis_name(v: np.ndarray) -> str | list[float]:
    for name, ax in (("+x", (1, 0, 0)), ("-x", (-1, 0, 0)), ("+y", (0, 1, 0)), ("-y", (0, -1, 0)),
                     ("+z", (0, 0, 1)), ("-z", (0, 0, -1))):
        if np.allclose(v, ax, atol=1e-12):
            return name
    return [round(float(x), 9) for x in v]


def _env_keys(rng: np.random.Generator, up_file: np.ndarray) -> tuple[tuple[str, Any], ...]:
    """Orientation keys in the file's frame: up is the true up; phi0 a drawn axis or vector not along it."""
    while True:
        cand = np.eye(3)[int(rng.integers(3))] * (1 if rng.random() < 0.5 else -1) if rng.random() < 0.6 \
            else rng.normal(size=3)
        if np.linalg.norm(np.cross(cand / np.linalg.norm(cand), up_file)) > 0.3:
            break
    phi0 = _axis_name(cand) if rng.random() < 0.6 else [round(float(x), 6) for x in cand]
    rot = 0.0 if rng.random() < 0.3 else round(float(rng.uniform(-180, 180)), 2)
    return (("up", _axis_name(up_file)), ("phi0", phi0),
            ("azimuth", ("counterclockwise", "clockwise")[int(rng.integers(2))]), ("rotation_deg", rot))


def _point_lights(rng: np.random.Generator, spec: SceneSpec) -> tuple[tuple[float, float, float, float], ...]:
    mesh, view = spec.mesh(), spec.view_angles_deg
    centre = np.asarray(spec.position_mm)
    n = 1 if spec.light == "point1" else 2
    for _ in range(2000):
        lights = []
        for _k in range(n):
            d = float(np.exp(rng.uniform(math.log(300), math.log(900))))
            u = _unit(rng.uniform(0, 360), rng.uniform(-10 if n == 1 else 10, 75))
            lights.append((*(centre + d * u), d * d * float(rng.uniform(0.5, 2.0))))
        unlit, lit = face_light_counts(mesh, view, np.array(lights)[:, :3])
        n_obs = unlit + lit
        if spec.light == "point2" and lit >= 0.5 * n_obs:
            return tuple(tuple(float(x) for x in light) for light in lights)
        if spec.light == "point1" and unlit >= max(1, 0.1 * n_obs) and lit >= max(1, 0.3 * n_obs):
            return tuple(tuple(float(x) for x in light) for light in lights)
    return ()  # this view shows too few faces: the caller turns the camera


def draw_zoo(n: int = 24, *, size_px: int = 64, spp: dict[str, int] | None = None, patch_budget: int = 6000,
             seed: int = 15) -> list[SceneSpec]:
    """``n`` scenes (>= 24 for full coverage) drawn with ``default_rng(seed)``; ``spp``: frame spp per noise
    class (default mc 32, zeros/camera 256)."""
    spp = {"mc": 32, "zeros": 256, "camera": 256, **(spp or {})}
    rng = np.random.default_rng(seed)
    shapes, lights, noises = _balanced(rng, SHAPES, n), _balanced(rng, LIGHTS, n), _balanced(rng, NOISES, n)
    etas = _balanced(rng, ETAS, n)
    for i in range(n):   # exact zeros need dark object pixels: the zeros class goes with point lights
        if noises[i] == "zeros" and not lights[i].startswith("point"):
            j = next((k for k in range(n) if lights[k].startswith("point") and noises[k] != "zeros"), None)
            if j is not None:
                noises[i], noises[j] = noises[j], noises[i]
    mats = list(MATERIAL_CHANNELS) + [MATERIAL_CHANNELS[int(i)] for i in rng.integers(len(MATERIAL_CHANNELS),
                                                                                       size=max(0, n - 15))]
    for _ in range(10000):   # boxes (40 mm) only with materials whose shortest l_d is >= 3 mm
        mats = [mats[i] for i in rng.permutation(len(mats))]
        if all(s != "box" or l_d_min_mm(*_split(m)) >= 3.0 for s, m in zip(shapes, mats[:n])):
            break
    cubes = [i for i, s in enumerate(shapes) if s == "cube"]
    for i in cubes[:3]:                          # at least three index-matched cubes
        if etas[i] != 1.0:
            j = next(k for k, e in enumerate(etas) if e == 1.0 and k not in cubes[:3])
            etas[i], etas[j] = etas[j], etas[i]
    for i in range(n):   # a point-lit sphere at eta != 1: the renderer's refracted point-light connection scans
        # the mesh face by face (~50x slower per collision on 320 faces than on a cube): give it eta = 1
        if shapes[i] == "sphere" and lights[i].startswith("point") and etas[i] != 1.0:
            j = next((k for k, e in enumerate(etas) if e == 1.0 and k not in cubes[:3]
                      and not (shapes[k] == "sphere" and lights[k].startswith("point"))), None)
            if j is None:
                j = next(k for k in range(n) if shapes[k] != "sphere" and not lights[k].startswith("point"))
                lights[i], lights[j] = lights[j], lights[i]
            else:
                etas[i], etas[j] = etas[j], etas[i]
    grazing = set(int(i) for i in rng.choice(n, size=5, replace=False))
    sections = _balanced(rng, (True, False), n)
    out = []
    for i in range(n):
        material, channels = _split(mats[i])
        size_max = min(40.0, 14 * l_d_min_mm(material, channels))
        size = float(np.exp(rng.uniform(math.log(5.0), math.log(max(5.0, size_max)))))
        dims = tuple(float(x) for x in rng.permutation(BOX_MM)) if shapes[i] == "box" else (size,) * 3
        world, rot = _world(rng)
        noise = noises[i]
        gain = float(np.exp(rng.uniform(math.log(500), math.log(5000)) if noise == "zeros"
                            else rng.uniform(math.log(1000), math.log(50000))))
        read_e = float(rng.uniform(5, 30) if noise == "zeros" else rng.uniform(2, 10))
        fmt = "exr" if noise == "mc" or rng.random() < 0.5 else "png16"
        spec = SceneSpec(
            index=i, shape=shapes[i], size_mm=round(size if shapes[i] != "box" else 40.0, 3), dims_mm=dims,
            yaw_deg=round(float(rng.uniform(0, 360)), 3),
            position_mm=tuple(round(float(x), 3) for x in rng.uniform([-15, -15, -5], [15, 15, 5])),
            camera_distance_mm=round(float(np.exp(rng.uniform(math.log(200), math.log(600)))), 2),
            camera_elevation_deg=round(float(rng.uniform(22, 30) if i in grazing else rng.uniform(8, 70)), 3),
            camera_azimuth_deg=round(float(rng.uniform(0, 360)), 3), size_px=size_px, light=lights[i],
            point_lights=(), sun_direction=tuple(_unit(rng.uniform(0, 360), rng.uniform(15, 75))),
            sky_tint=tuple(_unit(rng.uniform(0, 360), 0.0)), env_rows=int(rng.choice([32, 64, 64, 128])),
            env_keys=_env_keys(rng, rot @ np.array([0.0, 0.0, 1.0])), world=world,
            world_rotation=tuple(tuple(float(x) for x in row) for row in rot), material=material,
            channels=channels, eta=etas[i], noise=noise, noise_section=bool(sections[i]) and noise != "mc",
            gain_e_per_value=round(gain, 2), read_noise_e=round(read_e, 3), image_format=fmt,
            frame_spp=spp[noise] * (SUN_SPP_FACTOR if lights[i] == "sun" and noise != "mc" else 1),
            frame_seed=1000 + i, noise_seed=2000 + i, patch_budget=patch_budget)
        while spec.light.startswith("point") and not spec.point_lights:
            spec = replace(spec, point_lights=_point_lights(rng, spec))
            if not spec.point_lights:
                spec = replace(spec, camera_azimuth_deg=round(float(rng.uniform(0, 360)), 3))
        out.append(spec)
    return out


def quick_subset(specs: list[SceneSpec], n: int = 6) -> list[SceneSpec]:
    """At least ``n`` scenes covering :data:`QUICK_CLASSES` (greedy: most uncovered classes first, then the
    smallest objects), then the other lights, shapes and etas while room is left."""
    want = list(QUICK_CLASSES) + ["point2", "sky", "sphere", "pyramid", "box", "eta1.5", "graze", "rgb"]
    chosen: list[SceneSpec] = []
    covered: set[str] = set()
    for goal in (set(QUICK_CLASSES), set(want)):
        while (goal - covered) and len(chosen) < (n if goal != set(QUICK_CLASSES) else 99):
            best = max((s for s in specs if s not in chosen),
                       key=lambda s: (len((s.classes & goal) - covered), -s.size_mm * (1 + (s.shape == "sphere"))))
            if not (best.classes & goal) - covered:
                break
            chosen.append(best)
            covered |= best.classes
    rest = sorted((s for s in specs if s not in chosen), key=lambda s: s.size_mm * (1 + (s.shape == "sphere")))
    chosen += rest[:max(0, n - len(chosen))]
    return sorted(chosen, key=lambda s: s.index)


def quick_variant(spec: SceneSpec, *, size_px: int = 48, spp: int = 64, patch_budget: int = 2500) -> SceneSpec:
    """The same scene at the CI subset's cost: small frame, 64-spp frame, fewer patches. The frame rule
    (benchmarks/zoo/frames.py) is off here: at 64 spp the camera classes' Monte Carlo sd is 1.2-6x the camera's,
    and meeting the rule would need 29-329x the spp (measured: z02 80x, z16 329x; ~1-6 min of CI per frame), so
    the CI subset's camera / zeros frames carry Monte Carlo noise their ``[noise]`` section does not state."""
    return replace(spec, size_px=size_px, frame_spp=spp, patch_budget=patch_budget, frame_rule=False)
