"""The project's Monte Carlo renderer against Mitsuba 3's volumetric path tracer on the same scenes (issue 19,
build item 1: the measurement).

Scenes (materials from ``rig.config.MATERIALS``: reduced sigma_s', sigma_a per mm, isotropic phase so
sigma_s = sigma_s'; lengths in mm; radiance in the lights' units):

1. ``cube_point``: a 20 mm marble-R cube, eta 1.3, seen from above by an orthographic camera, under one point
   light of intensity I. Mitsuba's ``volpath`` cannot render a point light behind a smooth dielectric (a delta
   light through a delta interface: its shadow rays stop at the surface and a path never hits a point), so the
   script shows that image (0) and renders Mitsuba with a small spherical ``area`` emitter of radius r at the same
   centre and radiance I / (pi r^2): a uniform sphere gives every point that sees all of it the irradiance of a
   point of intensity I (exact), the angular spread of the light (half-angle r/D) changes the image by
   O((r/D)^2) ~ 0.4 % here. Ours: the point light, refracted next-event estimation (docs/monte-carlo.md sec. 1).
2. ``sphere_env``: a 10 mm-radius skin1 sphere (RGB), eta 1.3, orthographic view from the side, under a smooth
   asymmetric lat-long environment map (sky gradient + a coloured soft lobe); specular reflection included on both
   sides (ours: ``include_specular``, deterministic for a convex shape; Mitsuba: the dielectric's reflection).
   Both renderers are plain path tracers here (ours: environment NEE is off through a refracting analytic sphere).
3. ``relief_x``: a skin1-G slab (Mitsuba grey) with the seeded random relief of the gradient tests, a closed
   non-convex mesh of 3680 triangles, eta 1.3, under the "x" gradient pattern (ours: analytic; Mitsuba: its
   lat-long map), seen from above; specular reflection included on both sides.

Also ``cube_point_eta1`` (scene 1 index-matched: both sides sample the point light) and ``sphere_env_R`` (scene 2's
red channel alone; Mitsuba grey, without the RGB mode's chromatic-extinction fireflies).

Conventions matched (and checked by the agreement of the images): pixel = box filter over its area on both
sides (Mitsuba: ``box`` rfilter, one uniformly placed ray per sample; ours: one uniformly jittered ray per
pixel per pass, ``passes`` passes, so each pass is an unbiased estimate of the box-filtered pixel); the
lat-long map's orientation (ours: row 0 = +z, azimuth from +x to +y, :class:`estimation.single_image.EnvironmentMap`;
Mitsuba's ``envmap``: u = atan2(x, -z) / 2 pi, v = acos(y) / pi, docs/scene-file.md) — the map is mirrored in
azimuth and turned by a proper rotation (``to_world``); Mitsuba interpolates the map bilinearly, ours looks it up
per pixel, so Mitsuba gets the map replicated 4 x 4 per pixel (the two agree except within 1/8 pixel of the
map's pixel edges). Compared pixels: the object mask eroded by one pixel (pixels wholly on the object: no
background). Mitsuba: ``scalar_rgb`` (``--variant``), ``volpath`` with ``max_depth`` -1, ``rr_depth`` 5.

Per-pixel standard errors come from ``passes`` independent renders with different seeds on each side
(N/passes spp each): se = std over passes / sqrt(passes). Efficiency = 1 / (rel. variance x seconds) with the
median relative variance over compared pixels; agreement: z = (ours - mitsuba) / sqrt(se_o^2 + se_m^2) per
pixel (mean z, fraction |z| > 3 beside its expectation under agreement with se estimated from ``passes``
passes, simulated), and the ratio of the image means over compared pixels with its standard error.

Run: ``python benchmarks/mc_vs_mitsuba.py [--quick] [--json [PATH]]`` (needs the ``bench`` extra:
``pip install -e '.[bench]'``). References: Jakob et al., Mitsuba 3 (2022), plugin docs of ``volpath``,
``dielectric``, ``homogeneous``, ``envmap``, ``orthographic``, ``hdrfilm``; Pharr, Jakob, Humphreys PBR 3rd ed.
sec. 14.5, 15.3 (volumetric path tracing; why delta lights cannot be reached through specular interfaces);
Mitchell & Hanrahan 1992 (the refracted connection ours uses).
"""
from __future__ import annotations

import argparse
import atexit
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.ndimage import binary_erosion

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimation.camera import OrthographicCamera  # noqa: E402
from estimation.single_image import EnvironmentMap, PointLights  # noqa: E402
from rig.config import MATERIALS  # noqa: E402
from simulators.mc import Box, Medium, Sphere, render  # noqa: E402

ETA = 1.3


@dataclass(frozen=True)
class JitteredOrtho:
    """An :class:`OrthographicCamera` whose every ray starts at a uniformly random point of its pixel (one draw
    per pixel per pass): the box filter of Mitsuba's film, sampled once per pass."""

    cam: OrthographicCamera
    rng: np.random.Generator

    @property
    def width_px(self) -> int:
        return self.cam.width_px

    @property
    def height_px(self) -> int:
        return self.cam.height_px

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        o, d = self.cam.pixel_rays()
        R = self.cam.R
        j = self.rng.uniform(-0.5, 0.5, size=o.shape[:2] + (2,)) * self.cam.pixel_size_mm
        return o + j[..., :1] * R[0] + j[..., 1:] * R[1], d


@dataclass
class Scene:
    name: str
    shape: Any
    media: list[Medium]
    cam: OrthographicCamera
    lights: Any
    include_specular: bool
    mitsuba: Callable[[Any, int], dict]        # (mi, spp) -> scene dict
    note: str
    channel_names: str = "R"


def _medium_dict(media: list[Medium]) -> dict:
    st = [m.sigma_t_per_mm for m in media]
    al = [m.albedo for m in media]
    if len(media) == 1:
        st, al = st * 3, al * 3
    # Mitsuba reads an "rgb" sigma_t as a reflectance in [0, 1]: pass sigma_t / max with scale = max
    top = max(st)
    return {"type": "homogeneous", "sigma_t": {"type": "rgb", "value": [v / top for v in st]},
            "albedo": {"type": "rgb", "value": al}, "phase": {"type": "isotropic"}, "scale": top}


def _sensor(mi: Any, cam: OrthographicCamera, spp: int) -> dict:
    """Mitsuba's orthographic sensor with our camera's view: our rows of R are right, down, forward; Mitsuba's
    look_at puts image +u along cross(dir, up) and +v along -up, so up = -down gives the same image axes."""
    T = mi.ScalarTransform4f
    R = cam.R
    t = np.asarray(cam.target_mm)
    half = 0.5 * cam.width_px * cam.pixel_size_mm
    origin = t - 500.0 * R[2]
    return {"type": "orthographic",
            "to_world": T().look_at(origin=origin.tolist(), target=t.tolist(), up=(-R[1]).tolist())
            @ T().scale([half, half, 1.0]),
            "near_clip": 1.0, "far_clip": 2000.0,
            "film": {"type": "hdrfilm", "width": cam.width_px, "height": cam.height_px,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb", "sample_border": False},
            "sampler": {"type": "independent", "sample_count": int(spp)}}


def _base(mi: Any, sc: "Scene", spp: int) -> dict:
    return {"type": "scene",
            "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": 5},
            "sensor": _sensor(mi, sc.cam, spp)}


def _dielectric() -> dict:
    return {"type": "dielectric", "int_ior": ETA, "ext_ior": 1.0}


# ---------------------------------------------------------------- scene 1: marble-R cube, point light
CUBE_HALF_MM = 10.0
LIGHT_POS_MM = np.array([-30.0, 15.0, 55.0])
LIGHT_INTENSITY = 1.0e4       # radiant intensity [radiance unit x mm^2]
LIGHT_RADIUS_MM = 3.5         # Mitsuba's stand-in: a uniform sphere of this radius


def cube_point(size_px: int, eta: float = ETA) -> Scene:
    """Scene 1; with ``eta`` = 1 (``cube_point_eta1``) the boundary is index-matched (Mitsuba: ``null`` BSDF) and
    both renderers can sample the point light itself (Mitsuba: next-event estimation through the null interface)."""
    ssp, sa = MATERIALS["marble"][0][0], MATERIALS["marble"][1][0]
    media = [Medium.from_reduced(ssp, sa, eta=eta)]
    matched = abs(eta - 1.0) < 1e-12
    cam = OrthographicCamera.looking_at(width_px=size_px, height_px=size_px, pixel_size_mm=22.0 / size_px,
                                        direction=(0.0, 0.0, -1.0), target_mm=(0.0, 0.0, CUBE_HALF_MM),
                                        up=(0.0, 1.0, 0.0))
    shape = Box((-CUBE_HALF_MM,) * 3, (CUBE_HALF_MM,) * 3)
    lights = PointLights(LIGHT_POS_MM[None, :], np.array([LIGHT_INTENSITY]))

    def mitsuba(mi: Any, spp: int, *, point: bool = False) -> dict:
        """``point``: Mitsuba's own point emitter (at eta != 1 volpath renders 0 with it)."""
        T = mi.ScalarTransform4f
        d = _base(mi, sc, spp)
        d["cube"] = {"type": "cube", "to_world": T().scale(CUBE_HALF_MM),
                     "bsdf": {"type": "null"} if matched else _dielectric(), "interior": _medium_dict(media)}
        if point or matched:
            d["light"] = {"type": "point", "position": LIGHT_POS_MM.tolist(),
                          "intensity": {"type": "rgb", "value": [LIGHT_INTENSITY] * 3}}
        else:
            rad = LIGHT_INTENSITY / (math.pi * LIGHT_RADIUS_MM ** 2)
            d["light"] = {"type": "sphere", "center": LIGHT_POS_MM.tolist(), "radius": LIGHT_RADIUS_MM,
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [rad] * 3}}}
        return d

    dist = float(np.linalg.norm(LIGHT_POS_MM - np.array([0, 0, CUBE_HALF_MM])))
    if matched:
        note = (f"marble-R cube 20 mm, eta 1 (index-matched); point light I = {LIGHT_INTENSITY:g} at "
                f"{LIGHT_POS_MM.tolist()} mm on both sides")
    else:
        note = (f"marble-R cube 20 mm, eta {eta}; ours: point light I = {LIGHT_INTENSITY:g} at "
                f"{LIGHT_POS_MM.tolist()} mm; Mitsuba: sphere emitter r = {LIGHT_RADIUS_MM} mm there "
                f"(r/D = {LIGHT_RADIUS_MM / dist:.3f})")
    sc = Scene("cube_point_eta1" if matched else "cube_point", shape, media, cam, lights, False, mitsuba, note)
    return sc


# ---------------------------------------------------------------- scene 2: skin1 sphere, environment map
SPHERE_RADIUS_MM = 10.0
ENV_ROWS = 32
ENV_UPSAMPLE = 4


def env_map_rgb(rows: int = ENV_ROWS) -> np.ndarray:
    """A smooth asymmetric lat-long map (rows, 2 rows, 3) in our convention: sky gradient + a warm lobe."""
    h, w = rows, 2 * rows
    th = np.pi * (np.arange(h) + 0.5) / h
    ph = 2 * np.pi * (np.arange(w) + 0.5) / w
    th, ph = np.meshgrid(th, ph, indexing="ij")
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)
    lobe_dir = np.array([0.5, -0.6, 0.62])
    lobe_dir /= np.linalg.norm(lobe_dir)
    lobe = np.exp((dirs @ lobe_dir - 1.0) / 0.15)
    sky = 0.3 + 0.7 * np.clip(dirs[..., 2], 0, None)
    col_sky = np.array([0.6, 0.8, 1.0])
    col_lobe = np.array([4.0, 2.5, 1.0])
    return sky[..., None] * col_sky + lobe[..., None] * col_lobe


def sphere_env(size_px: int, channel: int | None = None) -> Scene:
    """Scene 2; ``channel`` (``sphere_env_R``: 0) renders that skin1 channel alone, on Mitsuba's side as a grey
    medium (its RGB mode samples distances with one channel's sigma_t and weights the others, which gives the
    channel with the smallest sigma_t -- red -- rare large weights)."""
    ssp, sa = MATERIALS["skin1"]
    media = [Medium.from_reduced(s, a, eta=ETA) for s, a in zip(ssp, sa)]
    if channel is not None:
        media = media[channel:channel + 1]
    cam = OrthographicCamera.looking_at(width_px=size_px, height_px=size_px, pixel_size_mm=22.0 / size_px,
                                        direction=(0.0, 1.0, -0.3), target_mm=(0.0, 0.0, 0.0),
                                        up=(0.0, 0.0, 1.0))
    shape = Sphere((0.0, 0.0, 0.0), SPHERE_RADIUS_MM)
    env = env_map_rgb()
    if channel is not None:
        env = np.repeat(env[..., channel:channel + 1], 3, axis=2)
    lights = EnvironmentMap(env if channel is None else env[..., :1])

    def mitsuba(mi: Any, spp: int) -> dict:
        T = mi.ScalarTransform4f
        d = _base(mi, sc, spp)
        d["sphere"] = {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": SPHERE_RADIUS_MM,
                       "bsdf": _dielectric(), "interior": _medium_dict(media)}
        # ours -> Mitsuba: mirror the azimuth (column j -> W-1-j), then a proper rotation with
        # world x = -local z, world y = -local x, world z = local y (module docstring)
        img = np.repeat(np.repeat(env[:, ::-1, :], ENV_UPSAMPLE, axis=0), ENV_UPSAMPLE, axis=1)
        m = np.array([[0, 0, -1, 0], [-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
        d["env"] = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)),
                    "to_world": T(m.tolist()), "scale": 1.0}
        return d

    what = "RGB" if channel is None else f"channel {'RGB'[channel]} alone, Mitsuba grey"
    sc = Scene("sphere_env" if channel is None else f"sphere_env_{'RGB'[channel]}", shape, media, cam, lights, True,
               mitsuba, f"skin1 sphere r {SPHERE_RADIUS_MM} mm ({what}), eta {ETA}, {ENV_ROWS}x{2 * ENV_ROWS} env "
               "map, specular reflection included", "RGB" if channel is None else "RGB"[channel])
    return sc


# ---------------------------------------------------------------- scene 3: skin1 relief slab, gradient pattern
RELIEF_STEP_MM = 0.5
RELIEF_EXTENT_MM = 20.0
RELIEF_THICKNESS_MM = 5.0
PATTERN_ROWS = 64


def pattern_map(pattern: str, rows: int = PATTERN_ROWS) -> np.ndarray:
    """The gradient pattern's radiance a + b.w (:data:`simulators.mc.lights.PATTERN_COEFFS`) at the pixel centres of
    a (rows, 2 rows) lat-long map in our convention (Mitsuba's stand-in for the analytic pattern: a linear function
    of w, so a pixel's centre value differs from its mean by O(pixel^2) ~ 1e-4)."""
    from simulators.mc.lights import PATTERN_COEFFS
    a, b = PATTERN_COEFFS[pattern]
    th = np.pi * (np.arange(rows) + 0.5) / rows
    ph = 2 * np.pi * (np.arange(2 * rows) + 0.5) / (2 * rows)
    th, ph = np.meshgrid(th, ph, indexing="ij")
    w = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)
    return np.clip(a + w @ np.asarray(b), 0.0, None)


def relief_pattern(size_px: int, channel: int = 1, pattern: str = "x") -> Scene:
    """Scene 3: a skin1 slab (one channel, Mitsuba grey) with the seeded random relief of
    :class:`simulators.scene.BumpySlabObject` (rms slope 0.1, wavelengths 1.5-6 mm) triangulated every
    ``RELIEF_STEP_MM`` (:func:`simulators.mc_capture.relief_mesh`, a closed non-convex mesh: ours path-traces it,
    re-entry included), under the gradient pattern ``pattern`` (ours: the analytic pattern; Mitsuba: its lat-long
    map), seen from above over the central 12 mm; specular reflection included on both sides."""
    import tempfile

    from simulators.mc import GradientPattern, Mesh
    from simulators.mc_capture import relief_mesh
    from simulators.scene import BumpySlabObject

    ssp, sa = MATERIALS["skin1"]
    obj = BumpySlabObject((0.0, 0.0, 0.0), tuple(ssp), tuple(sa), ETA, normal=(0.0, 0.0, 1.0),
                          extent_mm=RELIEF_EXTENT_MM, patch_mm=RELIEF_STEP_MM)
    tm = relief_mesh(obj, RELIEF_STEP_MM, RELIEF_THICKNESS_MM)
    media = [Medium.from_reduced(ssp[channel], sa[channel], eta=ETA)]
    cam = OrthographicCamera.looking_at(width_px=size_px, height_px=size_px, pixel_size_mm=12.0 / size_px,
                                        direction=(0.0, 0.0, -1.0), target_mm=(0.0, 0.0, 0.0),
                                        up=(0.0, 1.0, 0.0))
    ply = Path(tempfile.gettempdir()) / f"sssrig_relief_{os.getpid()}.ply"
    tm.export(str(ply))
    atexit.register(ply.unlink, missing_ok=True)
    env = np.repeat(pattern_map(pattern)[..., None], 3, axis=2)

    def mitsuba(mi: Any, spp: int) -> dict:
        T = mi.ScalarTransform4f
        d = _base(mi, sc, spp)
        d["slab"] = {"type": "ply", "filename": str(ply), "face_normals": True, "bsdf": _dielectric(),
                     "interior": _medium_dict(media)}
        m = np.array([[0, 0, -1, 0], [-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
        d["env"] = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(env[:, ::-1, :], dtype=np.float32)),
                    "to_world": T(m.tolist()), "scale": 1.0}
        return d

    sc = Scene(f"relief_{pattern}", Mesh(tm), media, cam, GradientPattern(pattern), True, mitsuba,
               f"skin1-{'RGB'[channel]} relief slab {RELIEF_EXTENT_MM:g} mm ({len(tm.faces)} triangles, step "
               f"{RELIEF_STEP_MM} mm, {RELIEF_THICKNESS_MM} mm thick), eta {ETA}, gradient pattern '{pattern}', "
               "Mitsuba grey, specular included", "RGB"[channel])
    return sc


# ---------------------------------------------------------------- rendering
def render_ours(sc: Scene, spp: int, passes: int, seed: int) -> tuple[np.ndarray, float]:
    """(passes, H, W, C) images, wall seconds; pass k: jittered pixel rays, seed + k."""
    rng = np.random.default_rng(seed)
    out = []
    t0 = time.perf_counter()
    for k in range(passes):
        img = render(sc.shape, sc.media, JitteredOrtho(sc.cam, rng), sc.lights, spp=spp // passes,
                     seed=seed + k, include_specular=sc.include_specular)
        out.append(img.radiance)
    return np.stack(out), time.perf_counter() - t0


def render_mitsuba(mi: Any, sc: Scene, spp: int, passes: int, seed: int, **kw: Any) -> tuple[np.ndarray, float]:
    """(passes, H, W, C) images (C = the scene's channels), wall seconds of the renders (scene load excluded)."""
    scene = mi.load_dict(sc.mitsuba(mi, spp // passes, **kw))
    out = []
    t0 = time.perf_counter()
    for k in range(passes):
        out.append(np.array(mi.render(scene, seed=seed + k, spp=spp // passes)))
    sec = time.perf_counter() - t0
    imgs = np.stack(out)[..., :3]
    return (imgs[..., :1] if len(sc.media) == 1 else imgs), sec


def null_fraction_gt3(passes: int, n: int = 200_000, seed: int = 7) -> float:
    """P(|z| > 3) when both images agree and each se is estimated from ``passes`` passes (simulated)."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n, passes))
    b = rng.standard_normal((n, passes))
    se2 = (a.var(axis=1, ddof=1) + b.var(axis=1, ddof=1)) / passes
    z = (a.mean(axis=1) - b.mean(axis=1)) / np.sqrt(se2)
    return float(np.mean(np.abs(z) > 3))


BLOCK_PX = 4


def block_z(passes_o: np.ndarray, passes_m: np.ndarray, cmp_px: np.ndarray, c: int) -> np.ndarray:
    """z of BLOCK_PX x BLOCK_PX pixel blocks wholly inside the compared pixels (pass images summed per block):
    sums over 16 pixels are closer to normal than single pixels when an estimator is skewed (rare bright paths)."""
    h, w = cmp_px.shape
    hb, wb = h // BLOCK_PX, w // BLOCK_PX

    def blocks(a: np.ndarray) -> np.ndarray:
        return a[..., :hb * BLOCK_PX, :wb * BLOCK_PX].reshape(a.shape[:-2] + (hb, BLOCK_PX, wb, BLOCK_PX)).sum(
            axis=(-3, -1))

    full = blocks(cmp_px.astype(float)) == BLOCK_PX ** 2
    bo, bm = blocks(passes_o[..., c])[:, full], blocks(passes_m[..., c])[:, full]
    se2 = bo.var(0, ddof=1) / len(bo) + bm.var(0, ddof=1) / len(bm)
    return (bo.mean(0) - bm.mean(0)) / np.sqrt(se2)


def stats(passes_o: np.ndarray, sec_o: float, passes_m: np.ndarray, sec_m: float, cmp_px: np.ndarray) -> dict:
    k_o, k_m = len(passes_o), len(passes_m)
    mo, mm = passes_o.mean(0), passes_m.mean(0)
    so = passes_o.std(0, ddof=1) / math.sqrt(k_o)
    sm = passes_m.std(0, ddof=1) / math.sqrt(k_m)
    out: dict = {"compared_pixels": int(cmp_px.sum()), "channels": []}
    for c in range(mo.shape[-1]):
        o, m, eo, em = mo[cmp_px, c], mm[cmp_px, c], so[cmp_px, c], sm[cmp_px, c]
        ref = 0.5 * (o + m)   # one denominator for both (a pixel's own mean would favour a skewed estimator)
        rel_o = float(np.median(eo / ref))
        rel_m = float(np.median(em / ref))
        eff_o = 1.0 / (rel_o ** 2 * sec_o)
        eff_m = 1.0 / (rel_m ** 2 * sec_m) if rel_m > 0 else float("inf")
        z = (o - m) / np.sqrt(eo ** 2 + em ** 2)
        zb = block_z(passes_o, passes_m, cmp_px, c)
        ratio = float(o.sum() / m.sum()) if m.sum() > 0 else float("inf")
        ratio_se = ratio * math.sqrt(float((eo ** 2).sum()) / o.sum() ** 2 + float((em ** 2).sum()) / m.sum() ** 2) \
            if m.sum() > 0 else float("nan")
        out["channels"].append({
            "rel_stderr_ours": rel_o, "rel_stderr_mitsuba": rel_m, "efficiency_ours": eff_o,
            "efficiency_mitsuba": eff_m, "efficiency_ratio": eff_o / eff_m,
            "mean_z": float(z.mean()), "frac_abs_z_gt3": float(np.mean(np.abs(z) > 3)),
            "block_mean_z": float(zb.mean()) if len(zb) else float("nan"),
            "block_frac_abs_z_gt3": float(np.mean(np.abs(zb) > 3)) if len(zb) else float("nan"),
            "blocks": int(len(zb)),
            "max_over_median_stderr_ours": float(eo.max() / np.median(eo)),
            "max_over_median_stderr_mitsuba": float(em.max() / np.median(em)),
            "mean_ratio": ratio, "mean_ratio_se": ratio_se})
    return out


def run_scene(mi: Any, sc: Scene, spp_o: int, spp_m: int, passes: int, seed: int) -> dict:
    ours, sec_o = render_ours(sc, spp_o, passes, seed)
    mits, sec_m = render_mitsuba(mi, sc, spp_m, passes, seed + 1000)
    mask = render(sc.shape, sc.media, sc.cam, sc.lights, spp=1, seed=0).mask
    cmp_px = binary_erosion(mask, iterations=1)
    res = {"scene": sc.name, "note": sc.note, "channel_names": sc.channel_names, "spp_ours": spp_o, "spp_mitsuba": spp_m, "passes": passes,
           "seconds_ours": sec_o, "seconds_mitsuba": sec_m, "load_average": list(os.getloadavg())}
    res.update(stats(ours, sec_o, mits, sec_m, cmp_px))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small images and sample counts (~1 min)")
    ap.add_argument("--json", nargs="?", const="-", metavar="PATH",
                    help="write JSON to PATH (alone: print JSON instead of the table)")
    ap.add_argument("--variant", default="scalar_rgb", help="Mitsuba variant (scalar_rgb, llvm_ad_rgb)")
    ap.add_argument("--scenes", default="cube_point,cube_point_eta1,sphere_env,sphere_env_R,relief_x")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    try:
        import mitsuba as mi
    except ImportError:
        print("mitsuba is not installed: pip install -e '.[bench]'", file=sys.stderr)
        return 2
    mi.set_variant(args.variant)
    passes = 16
    # (size px, spp ours, spp Mitsuba) per scene; Mitsuba's cube needs far more paths (its light is found only by
    # escaping paths that hit the small sphere)
    plan = {"cube_point": (12, 64, 2048) if args.quick else (20, 128, 8192),
            "cube_point_eta1": (12, 64, 64) if args.quick else (20, 128, 256),
            "sphere_env": (12, 64, 128) if args.quick else (32, 512, 2048),
            "sphere_env_R": (12, 64, 128) if args.quick else (32, 512, 2048),
            "relief_x": (12, 32, 64) if args.quick else (24, 256, 1024)}
    builders = {"cube_point": cube_point, "cube_point_eta1": lambda n: cube_point(n, eta=1.0),
                "sphere_env": sphere_env, "sphere_env_R": lambda n: sphere_env(n, channel=0),
                "relief_x": relief_pattern}
    out: dict = {"mitsuba": mi.__version__, "variant": args.variant, "quick": bool(args.quick),
                 "cpu_count": os.cpu_count(), "null_frac_abs_z_gt3": null_fraction_gt3(passes), "scenes": []}
    t = time.perf_counter()
    for name in args.scenes.split(","):          # warm-up: numba compile/cache load, Mitsuba plugin load
        sc = builders[name](4)
        render_ours(sc, 4, 2, 0)
        render_mitsuba(mi, sc, 4, 2, 0)
    out["warmup_s"] = time.perf_counter() - t
    if "cube_point" in args.scenes.split(","):
        sc = cube_point(8)
        img, _ = render_mitsuba(mi, sc, 16, 2, 0, point=True)
        out["mitsuba_point_light_image_max"] = float(img.max())
    for name in args.scenes.split(","):
        size, spp_o, spp_m = plan[name]
        out["scenes"].append(run_scene(mi, builders[name](size), spp_o, spp_m, passes, args.seed))
    if args.json:
        text = json.dumps(out, indent=1)
        if args.json == "-":
            print(text)
            return 0
        Path(args.json).write_text(text)
    print(f"Mitsuba {out['mitsuba']} ({out['variant']}), {passes} passes per side, warm-up {out['warmup_s']:.1f} s; "
          f"expected fraction |z| > 3 if the images agree: {out['null_frac_abs_z_gt3']:.4f}")
    if "mitsuba_point_light_image_max" in out:
        print(f"cube_point with Mitsuba's point emitter (volpath, dielectric): image max = "
              f"{out['mitsuba_point_light_image_max']:g}")
    print("| scene | ch | spp o/m | s ours | s Mitsuba | rel se o | rel se m | eff o | eff m | ratio o/m "
          "| mean z | frac |z|>3 | 4x4-block mean z, frac |z|>3 (n) | mean o/m | max/median se o, m | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in out["scenes"]:
        for c, ch in enumerate(r["channels"]):
            print(f"| {r['scene']} | {r['channel_names'][c]} | {r['spp_ours']}/{r['spp_mitsuba']} "
                  f"| {r['seconds_ours']:.1f} | {r['seconds_mitsuba']:.1f} | {ch['rel_stderr_ours']:.4f} "
                  f"| {ch['rel_stderr_mitsuba']:.4f} | {ch['efficiency_ours']:.3g} | {ch['efficiency_mitsuba']:.3g} "
                  f"| {ch['efficiency_ratio']:.3g} | {ch['mean_z']:+.2f} | {ch['frac_abs_z_gt3']:.3f} "
                  f"| {ch['block_mean_z']:+.2f}, {ch['block_frac_abs_z_gt3']:.3f} ({ch['blocks']}) "
                  f"| {ch['mean_ratio']:.4f} +- {ch['mean_ratio_se']:.4f} "
                  f"| {ch['max_over_median_stderr_ours']:.1f}, {ch['max_over_median_stderr_mitsuba']:.1f} "
                  f"| {' '.join(f'{v:.1f}' for v in r['load_average'])} |")
    for r in out["scenes"]:
        print(f"{r['scene']}: {r['note']}; {r['compared_pixels']} compared pixels")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
