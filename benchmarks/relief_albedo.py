"""Where the relief slabs' R_d map exceeds the half-space's R_d (issue 16): the map's convention on Monte Carlo light.

Two measurements with the project's renderer (simulators.mc), printed as R_map / R_d(table) - 1 per channel, where
R_d(table) is the Monte Carlo table's total diffuse reflectance (estimation.mc_table, normal incidence, per unit
power entering) and R_map the albedo map's convention (estimation.gradients: the value divided by F_t(eta, n.v)/pi
and by the transmitted irradiance E_t):

1. ``halfspace``: photons on a half-space (simulators.mc.pencil_beam_profile), cosine-weighted (uniform radiance)
   incidence, exit cosines >= 0.9: R_map = pi L_o / (F_t E_t). By reciprocity a half-space under uniform light reads
   R_d / c(eta) (estimation.relief.exit_normalization; 1/c = 1.065 at eta 1.3). Also printed: R_d under normal and
   under cosine-weighted incidence, and the map value for normal incidence.
2. ``box``: flat boxes of the acceptance relief cases' size (benchmarks/gradients_cases.py: extent view + 2 margin,
   thickness margin = 2.75 x the material's largest l_d, scaled by ``--scale``) under the cases' 362 LEDs as a distant
   map, head-on orthographic camera, ``--px`` x ``--px`` centre pixels of 0.25 mm: all LEDs, or (``--front``) only
   the LEDs in front of the slab (a black backing hides the rear hemisphere).

Run: ``python benchmarks/relief_albedo.py halfspace --materials marble,skin1 --photons 200000`` or
``python benchmarks/relief_albedo.py box --materials skin1 [--front] [--scale 3] --px 4 --spp 512``.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from benchmarks.gradients_cases import ETA, MARGIN_L_D, _leds, materials, truth  # noqa: E402


def _table_rd(ssp: np.ndarray, sa: np.ndarray) -> np.ndarray:
    from estimation.mc_table import default_table
    tab = default_table()
    return np.array([float(tab.total_reflectance(s / (s + a), ETA)) for s, a in zip(ssp, sa)])


def halfspace(material: str, photons: int, seed: int = 1) -> None:
    from estimation.fresnel import fresnel_transmittance
    from simulators.mc import Medium
    from simulators.mc.profile import DirectionSet, pencil_beam_profile

    ssp, sa = (np.asarray(x, float) for x in materials()[material])
    rt = _table_rd(ssp, sa)
    ft = float(fresnel_transmittance(ETA, np.linspace(0.9, 1.0, 101)).mean())   # exit bin cos 0.9-1
    for c in range(3):
        med = Medium.from_reduced(ssp[c], sa[c], eta=ETA)
        out = []
        for inc in (None, DirectionSet(0.0, 1.0, 0.0, 2 * np.pi)):
            p = pencil_beam_profile(med, [0.0, 1e9], photons, seed=seed, incidence=inc, cos_edges=[0.0, 0.9, 1.0])
            ent = 1.0 - p.specular_reflectance
            out.append((p.total_diffuse_reflectance / ent, np.pi * p.brdf_per_sr[1] / (ft * ent),
                        np.pi * p.brdf_stderr_per_sr[1] / (ft * ent)))
        (rn, mn, _), (rdf, mdf, sdf) = out
        print(f"{material} {'RGB'[c]}: R_d table {rt[c]:.4f}; normal incidence R_d {rn / rt[c] - 1:+.1%}, map "
              f"{mn / rt[c] - 1:+.1%}; cosine-weighted incidence R_d {rdf / rt[c] - 1:+.1%}, map "
              f"{mdf / rt[c] - 1:+.1%} +- {sdf / rt[c]:.1%}", flush=True)


def box(material: str, front: bool, scale: float, px: int, spp: int, seed: int = 7) -> None:
    from estimation.camera import OrthographicCamera
    from estimation.fresnel import fresnel_transmittance
    from rig.estimate.reference.folder_reference import renderable_camera
    from simulators import mc
    from simulators.mc_capture import led_environment, mc_media
    from simulators.scene import BumpySlabObject

    ssp, sa = materials()[material]
    rt = _table_rd(np.asarray(ssp), np.asarray(sa))
    pos, inten, _ = _leds()
    nref = np.array([0.0, -1.0, 0.0])                 # the slab faces the camera on -y
    dirs = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    cos = np.clip(dirs @ nref, 0.0, 1.0)
    et = (fresnel_transmittance(ETA, cos) * cos) @ (inten / np.sum(pos ** 2, axis=1, keepdims=True))
    ft0 = float(fresnel_transmittance(ETA, 1.0))
    cam = renderable_camera(OrthographicCamera.looking_at(width_px=px, height_px=px, pixel_size_mm=0.25,
                                                          direction=(0.0, 1.0, 0.0)))
    margin = scale * MARGIN_L_D * max(truth(material)["l_d_mm"])
    half = 0.5 * px * 0.25 + margin
    em = inten * ((dirs @ nref) > 0)[:, None] if front else inten
    lit = np.any(em > 0, axis=1)
    env = led_environment(pos[lit], em[lit], rows=90)
    shape = mc.Box((-half, 0.0, -half), (half, margin, half))
    t0 = time.perf_counter()
    img = mc.render(shape, mc_media(BumpySlabObject((0.0, 0.0, 0.0), ssp, sa, ETA, rms_slope=0.0)), cam, env,
                    spp=spp, seed=seed)
    norm = ft0 / np.pi * et
    r = img.radiance.reshape(-1, 3).mean(0) / norm
    se = np.sqrt((img.stderr.reshape(-1, 3) ** 2).mean(0) / (px * px)) / norm
    print(f"{material} box {2 * half:.0f} x {margin:.1f} mm, {'front LEDs only' if front else 'all LEDs'}: R_map / "
          f"R_d(table) - 1 = " + " / ".join(f"{x / t - 1:+.1%} +- {s / t:.1%}" for x, s, t in zip(r, se, rt))
          + f" ({time.perf_counter() - t0:.0f} s)", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("halfspace", "box"))
    ap.add_argument("--materials", default="marble,skin1,apple,skimmilk")
    ap.add_argument("--photons", type=int, default=200_000, help="halfspace: photons per channel and incidence")
    ap.add_argument("--front", action="store_true", help="box: only the LEDs in front of the slab")
    ap.add_argument("--scale", type=float, default=1.0, help="box: margin and thickness x this")
    ap.add_argument("--px", type=int, default=4)
    ap.add_argument("--spp", type=int, default=512)
    a = ap.parse_args(argv)
    for m in a.materials.split(","):
        if a.what == "halfspace":
            halfspace(m, a.photons)
        else:
            box(m, a.front, a.scale, a.px, a.spp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
