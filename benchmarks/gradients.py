"""Benchmark of the gradient-map pipeline at camera resolution: throughput beside a streaming-read floor, and memory.

A synthetic frame set (default 6000 x 4000 px = 24 MP, 3 channels float32: ambient, full, x, y, z cross-polarized,
``--parallel`` adds the parallel-polarized full, x, y, z and ambient) of a marble sphere that overfills the frame
(~95 % object pixels, grazing ring in the corners), with spatially varying albedo, the blur-shortened diffuse
normals of the sphere model and 14-bit Poisson-Gaussian noise, is written as ``.npy`` memory maps
(``np.lib.format.open_memmap``) into a temporary folder together with the known normals (float32). Then, each in
a fresh subprocess, in this order:

1. **read floor**: every input tile (frames and normals, the same ``tile_rows`` tiles, from the same memory maps)
   is read once and summed — nothing else;
2. **pipeline**: what ``rig estimate gradients`` computes for a sphere: the LED response LUT (362 LEDs, the default
   rig), :func:`estimation.gradients.compute_maps` in LED mode (the per-pixel least-squares solve, twice; without
   the diagnostic ``consistency`` map, which that command does not write) and
   :func:`estimation.diffusion.estimate_sphere` (per-pixel (albedo, shortening) -> alpha', l', then the region
   summary), the stored maps written tile by tile into memory maps (``out_dir``): albedo, diffuse vectors, masks,
   shortening, alpha', l', unknown, censored (~113 bytes per pixel); diffuse normals, sigma_s', sigma_a, D, R_d, ...
   are derived element-wise on access (``DerivedMap``), not stored. Row tiles run in ``--workers`` threads
   (default min(2, CPUs));
3. **read floor** again (both floors run on a warm page cache: the frames were just written or read);
4. **write floor**: writing the same number of bytes the pipeline wrote, into fresh memory maps, tile by tile;
5. the pipeline again under ``tracemalloc`` (numpy registers its allocations with it) for the exact peak of
   allocated memory (``--quick``: the timed run itself is traced).

Throughput = megapixels / wall time. Memory: the *bounded* quantity is the process's own (anonymous) memory —
heap and numpy arrays — reported as the tracemalloc peak and as the peak RssAnon (sampled every 2 ms) above the
process's baseline after imports, each divided by the size of one frame set in memory (frames x H x W x 3 x 4
bytes). Pages of the memory-mapped inputs and outputs are file pages the kernel can write back and evict; they
appear in the peak resident set VmHWM (printed for reference) but are not process memory. Targets (issue 5, item 4): pipeline
throughput >= 1/3 of the read floor's; peak memory <= 2 frame sets.

Run: ``python benchmarks/gradients.py [--quick] [--json out.json]`` (24 MP: several minutes and ~8 GB of
temporary files, removed afterwards unless ``--keep``; ``--quick``: 1.2 MP, ~25 s). ``--megapixels``,
``--tile-rows``, ``--parallel``, ``--tmp`` (folder for the temporary files) adjust the run; ``--ram`` adds a
diagnostic run with the maps in RAM (the compute without map I/O). ``--relief`` adds the relief branch of
``rig estimate gradients`` (no sphere: the per-window relief fit and its maps, issue 16), ``--relief-only`` runs only
the read floor and that branch. The synthetic frames are cached under ``benchmarks/out/gradients_frames/`` (keyed by
size, options and the source of :func:`synthesize`; 24 MP: ~1.8 GB, made once in ~5 min); ``--no-cache`` makes them
in the temporary folder, ``--synthesize-only`` fills the cache and stops.
"""
from __future__ import annotations

import argparse
import json
import os

# The pipeline is single-threaded numpy; only its fixed-cost table builds call BLAS. On a small shared machine
# OpenBLAS's thread pool can cost more than it gives (measured here: the LUT build 2.6 s with one thread, 12 s
# with two under load), so one BLAS thread unless the caller says otherwise (inherited by the worker processes).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimation.diffusion import estimate_sphere, sphere_albedo, sphere_shortening  # noqa: E402
from estimation.fresnel import fresnel_transmittance  # noqa: E402
from estimation.gradients import LedRig, build_response_lut, compute_maps  # noqa: E402
from rig.acquire.geometry import led_layout  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

ETA = 1.3
RADIUS_MM = 10.0
MARBLE = (np.array([2.19, 2.62, 3.00]), np.array([0.0021, 0.0041, 0.0071]))  # Jensen 2001, 1/mm
CROSS = ("ambient", "full", "x", "y", "z")
LED_R_MM = 1000.0
VALUE_SCALE = 0.4  # frame value of the full-on pattern for R_d = 1 facing the camera (headroom below white)


def leds() -> LedRig:
    """The default rig: 362-LED class-I geodesic (f = 6) at 1 m, LEDs below -60 deg absent."""
    pos, _ = led_layout(6, LED_R_MM, -60.0)
    return LedRig.from_positions(pos, np.full((len(pos), 3), LED_R_MM ** 2 * 4 * np.pi / len(pos)))


def frame_names(parallel: bool) -> list[str]:
    return list(CROSS) + ([f"{p}_parallel" for p in CROSS] if parallel else [])


def frame_key(name: str) -> Any:
    return (name[:-9], "parallel") if name.endswith("_parallel") else name


# ------------------------------------------------------------------------------------------------- synthesis
def synthesize(folder: Path, H: int, W: int, parallel: bool, tile_rows: int, lut: Any, seed: int = 1) -> None:
    """Frames of a marble sphere (radius 0.55 frame widths) seen orthographically from -y, as float32 memory maps.

    Cross-polarized: I_P = (R/albedo_scale) F_t(n.v) (a_P(n) + b_P(n).(S n)) per channel, the LED rig's local
    affine response (``lut``) to the blur-shortened normal S n of a translucent sphere (science.md sec. 4; S of
    marble on a 10 mm sphere from the sphere model), R the sphere's apparent albedo modulated by a smooth +-10 %
    texture; plus an ambient 0.002 and the noise of a 14-bit sensor (2 e-/DN, 2 DN read noise; Gaussian
    approximation of Poisson). Parallel frames add a narrow specular highlight where n faces the camera, with
    the gradient values of the mirror direction. Normals are stored (NaN off the sphere) as float32
    ``normals.npy``.
    """
    rng = np.random.default_rng(seed)
    names = frame_names(parallel)
    out = {n: np.lib.format.open_memmap(folder / f"{n}.npy", "w+", np.float32, (H, W, 3)) for n in names}
    normals = np.lib.format.open_memmap(folder / "normals.npy", "w+", np.float32, (H, W, 3))
    S = sphere_shortening(RADIUS_MM, *MARBLE, ETA)
    R = sphere_albedo(RADIUS_MM, *MARBLE, ETA)
    r_px = 0.55 * W
    e_per_unit, read = 16383 * 2.0, 2.0 / 16383
    xs = (np.arange(W) - W / 2 + 0.5) / r_px
    pats = {p: lut.patterns.index(p) for p in ("full", "x", "y", "z")}
    for r0 in range(0, H, tile_rows):
        r1 = min(H, r0 + tile_rows)
        zs = -(np.arange(r0, r1) - H / 2 + 0.5) / r_px
        u, w = np.meshgrid(xs, zs)
        r2 = u * u + w * w
        hit = r2 < 1.0
        n = np.stack([u, -np.sqrt(np.clip(1.0 - r2, 0.0, None)), w], -1)
        normals[r0:r1] = np.where(hit[..., None], n, np.nan)
        nn = n.reshape(-1, 3)
        # the rig's response per pattern, in chunks of normals: lut.affine of a whole 256-row tile of a 24 MP
        # frame is a (1.5 M, P, 3, 4) float64 array (~0.6 GB per bilinear corner)
        resp = {p: np.empty((nn.shape[0], 3)) for p in pats}
        for s0 in range(0, nn.shape[0], 65536):
            coef = lut.affine(nn[s0:s0 + 65536])  # (m, P, 3, 4)
            for p, ip in pats.items():
                c = coef[:, ip]
                resp[p][s0:s0 + 65536] = c[..., 0] + S * np.einsum("mck,mk->mc", c[..., 1:], nn[s0:s0 + 65536])
        tex = 1.0 + 0.1 * np.sin(40 * u)[..., None] * np.cos(30 * w)[..., None] * np.array([1.0, 0.8, 0.6])
        base = (VALUE_SCALE * R * tex * fresnel_transmittance(ETA, np.clip(-n[..., 1], 0, 1))[..., None]
                * hit[..., None])
        refl = 2 * (-n[..., 1:2]) * n - np.array([0.0, -1.0, 0.0])  # mirror direction of the view vector
        spec = 0.02 * np.exp((np.clip(-n[..., 1:2], 0, 1) - 1) / 0.002) * hit[..., None]  # highlight at n = v
        for name in names:
            pat = name.split("_")[0]
            if pat == "ambient":
                clean = np.zeros_like(base)
            else:
                clean = base * resp[pat].reshape(base.shape)
            if name.endswith("_parallel") and pat != "ambient":
                val = 1.0 if pat == "full" else 0.5 * (1 + refl[..., "xyz".index(pat):"xyz".index(pat) + 1])
                clean = clean + spec * val
            clean = clean + 0.002
            noisy = clean + rng.standard_normal(clean.shape) * np.sqrt(clean / e_per_unit + read * read)
            out[name][r0:r1] = np.clip(np.round(noisy * 16383) / 16383, 0, 1)
    for a in out.values():
        a.flush()
    normals.flush()


FRAME_CACHE = ROOT / "benchmarks" / "out" / "gradients_frames"


def frame_cache_key(H: int, W: int, parallel: bool, tile_rows: int, seed: int = 1) -> str:
    """Content key of a synthetic frame set: its size, options and the source of :func:`synthesize` and of the
    constants it uses (a change to any of them makes a new key)."""
    import hashlib
    import inspect
    text = json.dumps([H, W, parallel, tile_rows, seed, ETA, RADIUS_MM, VALUE_SCALE, LED_R_MM,
                       [m.tolist() for m in MARBLE]])
    text += inspect.getsource(synthesize) + inspect.getsource(leds)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def cached_frames(H: int, W: int, parallel: bool, tile_rows: int) -> tuple[Path, float | None]:
    """The folder of the synthetic frames under ``benchmarks/out/gradients_frames/<key>/`` (git-ignored),
    synthesized on the first call (then renamed into place, so an interrupted synthesis is never reused).
    Returns (folder, synthesis seconds or None when it was cached)."""
    folder = FRAME_CACHE / f"{W}x{H}{'-parallel' if parallel else ''}-{frame_cache_key(H, W, parallel, tile_rows)}"
    if (folder / "normals.npy").exists():
        return folder, None
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    t0 = time.perf_counter()
    synthesize(tmp, H, W, parallel, tile_rows, build_response_lut(leds(), eta=ETA, surface_radius_mm=RADIUS_MM))
    dt = time.perf_counter() - t0
    tmp.rename(folder)
    return folder, dt


# ------------------------------------------------------------------------------------------------ workers
class AnonSampler:
    """Peak RssAnon of this process (from /proc/self/status), sampled every ``period_s`` in a thread."""

    def __init__(self, period_s: float = 0.002) -> None:
        self.period_s = period_s
        self.peak = self.baseline = self._read()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _read(field: str = "RssAnon:") -> int:
        try:
            with open("/proc/self/status") as f:
                for line in f:
                    if line.startswith(field):
                        return int(line.split()[1]) * 1024
        except OSError:
            pass
        return 0

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._read())
            time.sleep(self.period_s)

    def __enter__(self) -> "AnonSampler":
        self._t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._read())


def load_inputs(folder: Path, parallel: bool) -> tuple[dict[Any, np.ndarray], np.ndarray]:
    frames = {frame_key(n): np.load(folder / f"{n}.npy", mmap_mode="r") for n in frame_names(parallel)}
    return frames, np.load(folder / "normals.npy", mmap_mode="r")


def run_floor(folder: Path, parallel: bool, tile_rows: int) -> dict[str, Any]:
    frames, normals = load_inputs(folder, parallel)
    H = normals.shape[0]
    arrays = list(frames.values()) + [normals]
    total = 0.0
    t0 = time.perf_counter()
    for r0 in range(0, H, tile_rows):
        for a in arrays:
            total += float(np.add.reduce(a[r0:r0 + tile_rows], axis=None))
    return {"seconds": time.perf_counter() - t0, "checksum": total}


def run_write(folder: Path, nbytes: int, shape: tuple[int, int], tile_rows: int) -> dict[str, Any]:
    """Write ``nbytes`` into fresh float32 memory maps of shape (H, W, 3), tile by tile (a constant)."""
    H, W = shape
    per_map = H * W * 3 * 4
    n_maps = max(1, int(round(nbytes / per_map)))
    out = folder / "write_floor"
    out.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    maps = [np.lib.format.open_memmap(out / f"w{i}.npy", "w+", np.float32, (H, W, 3)) for i in range(n_maps)]
    tile = np.full((tile_rows, W, 3), 0.5, np.float32)
    for r0 in range(0, H, tile_rows):
        r1 = min(H, r0 + tile_rows)
        for m in maps:
            m[r0:r1] = tile[: r1 - r0]
    del maps
    dt = time.perf_counter() - t0
    shutil.rmtree(out)
    return {"seconds": dt, "maps": n_maps, "bytes": n_maps * per_map}


def run_pipeline(folder: Path, parallel: bool, tile_rows: int, trace: bool, ram: bool = False,
                 workers: int | None = None) -> dict[str, Any]:
    frames, normals = load_inputs(folder, parallel)
    out = None if ram else folder / "maps"
    if out is not None and out.exists():
        shutil.rmtree(out)
    if trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    rig = leds()
    lut = build_response_lut(rig, eta=ETA, surface_radius_mm=RADIUS_MM)
    t_lut = time.perf_counter()
    maps = compute_maps(frames, albedo_scale=1.0 / VALUE_SCALE, lut=lut, eta=ETA, geometry_normals=normals,
                        tile_rows=tile_rows, out_dir=out, workers=workers,
                        consistency=False)  # as rig estimate gradients: the diagnostic map is not an output
    t_maps = time.perf_counter()
    est = estimate_sphere(maps, radius_mm=RADIUS_MM, true_normals=normals, tile_rows=tile_rows, out_dir=out,
                          workers=workers)
    t_end = time.perf_counter()
    peak = tracemalloc.get_traced_memory()[1] if trace else None
    if trace:
        tracemalloc.stop()
    s = est.summary
    written = sum(p.stat().st_size for p in out.glob("*.npy")) if out is not None else 0
    truth_D = 1.0 / (3.0 * (MARBLE[0] + MARBLE[1]))
    return {"seconds": t_end - t0, "seconds_lut": t_lut - t0, "seconds_maps": t_maps - t_lut,
            "seconds_diffusion": t_end - t_maps, "tracemalloc_peak_bytes": peak, "bytes_written": written,
            "known_fraction": float((~maps.unknown[..., 0]).mean()), "workers": maps.provenance["workers"],
            "stored": sorted(p.stem for p in out.glob("*.npy")) if out is not None else [],
            "D_mm": s.value("D_mm").tolist(), "D_rel_err": (s.value("D_mm") / truth_D - 1).tolist(),
            "status": list(s.status)}


def run_relief(folder: Path, parallel: bool, tile_rows: int, workers: int | None = None, trace: bool = True
               ) -> dict[str, Any]:
    """The relief branch of ``rig estimate gradients`` (a capture folder without a sphere: issue 16) on the same
    frames, traced: compute_maps (memory-mapped maps), the per-window relief fit of the diffuse normals against
    the known normals with its full-resolution window maps written as EXR
    (:func:`rig.estimate.folder_diffusion.relief_estimate`, 64-px windows as the CLI's default), and the apparent albedo
    map (:func:`rig.estimate.folder_diffusion.albedo_apparent`) written as EXR. Returns seconds and the tracemalloc peak."""
    from estimation.camera import OrthographicCamera
    from rig.estimate.folder_diffusion import RELIEF_WINDOW_PX, albedo_apparent, relief_estimate
    from rig.files.imageio import write_exr

    frames, normals = load_inputs(folder, parallel)
    H, W = normals.shape[:2]
    out = folder / "relief"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir()
    cam = OrthographicCamera.looking_at(width_px=W, height_px=H, pixel_size_mm=RADIUS_MM / (0.55 * W),
                                        direction=(0.0, 1.0, 0.0))
    if trace:
        tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    rig = leds()
    lut = build_response_lut(rig, eta=ETA, surface_radius_mm=RADIUS_MM)
    maps = compute_maps(frames, albedo_scale=1.0 / VALUE_SCALE, lut=lut, eta=ETA, geometry_normals=normals,
                        tile_rows=tile_rows, out_dir=out / "maps", workers=workers, consistency=False)
    t_maps, c_maps = time.perf_counter(), time.process_time()
    summary, files, fit = relief_estimate(maps, normals, "benchmark normals", cam, None, out, "exr",
                                          RELIEF_WINDOW_PX)
    t_relief, c_relief = time.perf_counter(), time.process_time()
    alb = albedo_apparent(maps, normals, ETA, rig, np.array([0.0, -1.0, 0.0]), rows=tile_rows)
    alb[np.asarray(maps.unknown)] = np.nan
    write_exr(out / "albedo_apparent.exr", alb)
    del alb
    t_end, c_end = time.perf_counter(), time.process_time()
    peak = tracemalloc.get_traced_memory()[1] if trace else None
    if trace:
        tracemalloc.stop()
    return {"seconds": t_end - t0, "seconds_maps": t_maps - t0, "seconds_relief": t_relief - t_maps,
            "seconds_albedo_apparent": t_end - t_relief, "cpu_seconds": c_end - c0,
            "cpu_seconds_maps": c_maps - c0, "cpu_seconds_relief": c_relief - c_maps,
            "cpu_seconds_albedo_apparent": c_end - c_relief, "tracemalloc_peak_bytes": peak,
            "fitted_window_channels": fit.provenance.get("fitted_window_channels") if fit is not None else 0,
            "seconds_fit": fit.provenance.get("seconds") if fit is not None else 0.0,
            "cpu_seconds_fit": fit.provenance.get("cpu_seconds") if fit is not None else 0.0,
            "loadavg_end": list(os.getloadavg()),
            "windows": summary["windows"], "window_status": summary["window_status"], "files": len(files) + 1}


def worker(args: argparse.Namespace) -> int:
    folder = Path(args.dir)
    with AnonSampler() as mem:
        if args.worker == "floor":
            res = run_floor(folder, args.parallel, args.tile_rows)
        elif args.worker == "write":
            res = run_write(folder, args.write_bytes, (args.height, args.width), args.tile_rows)
        elif args.worker == "relief":
            res = run_relief(folder, args.parallel, args.tile_rows, workers=args.workers)
        elif args.worker == "ram":
            res = run_pipeline(folder, args.parallel, args.tile_rows, trace=False, ram=True, workers=args.workers)
        else:  # --quick: one pipeline run, traced (tracemalloc adds a little time to it)
            res = run_pipeline(folder, args.parallel, args.tile_rows, trace=args.worker == "trace" or args.quick,
                               workers=args.workers)
    res.update(anon_baseline_bytes=mem.baseline, anon_peak_bytes=mem.peak, vmhwm_bytes=mem._read("VmHWM:"))
    print(json.dumps(res))
    return 0


def spawn(kind: str, folder: Path, args: argparse.Namespace, **extra: Any) -> dict[str, Any]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", kind, "--dir", str(folder),
           "--tile-rows", str(args.tile_rows), "--height", str(args.height), "--width", str(args.width)]
    if args.parallel:
        cmd.append("--parallel")
    if args.quick:
        cmd.append("--quick")
    if args.workers is not None:
        cmd += ["--workers", str(args.workers)]
    for k, v in extra.items():
        cmd += [f"--{k.replace('_', '-')}", str(v)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), *sys.path]))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"worker {kind} failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def print_relief(relief: dict[str, Any], mpx: float, floor_ref: float, frame_set: int) -> bool:
    """Print the relief branch's lines (time, CPU, throughput beside the read floor, memory); True when its peak
    process memory is within 2 frame sets."""
    r_tm, r_anon = relief["tracemalloc_peak_bytes"], relief["anon_peak_bytes"] - relief["anon_baseline_bytes"]
    relief_ok = max(r_tm, r_anon) <= 2 * frame_set
    print(f"\nrelief branch (no sphere; {relief['windows'][0]} x {relief['windows'][1]} windows of "
          f"64 px, status per channel {relief['window_status']}; {relief['files']} EXR maps): "
          f"{relief['seconds']:.1f} s (maps {relief['seconds_maps']:.1f}, relief fit + window maps "
          f"{relief['seconds_relief']:.1f} of which the fit {relief.get('seconds_fit', float('nan')):.1f}, "
          f"apparent albedo {relief['seconds_albedo_apparent']:.1f}); CPU {relief['cpu_seconds']:.1f} s (relief "
          f"fit + window maps {relief['cpu_seconds_relief']:.1f} s, the fit "
          f"{relief.get('cpu_seconds_fit', float('nan')):.1f} s for {relief['fitted_window_channels']} fitted "
          f"window-channels: {relief.get('cpu_seconds_fit', float('nan')) / max(relief['fitted_window_channels'], 1):.4f}"
          f" s each); load average at its end {relief['loadavg_end']}")
    r_mps = mpx / relief["seconds"]
    print(f"relief branch throughput {r_mps:.3f} MP/s = {r_mps / floor_ref:.4f} x the read floor "
          f"(the 1/3 line is the sphere pipeline's; for reference)")
    print("| memory (relief branch) | GiB | / frame set |\n|---|---|---|")
    print(f"| tracemalloc peak | {r_tm / 2**30:.3f} | {r_tm / frame_set:.3f} |")
    print(f"| peak RssAnon above baseline (sampled) | {r_anon / 2**30:.3f} | {r_anon / frame_set:.3f} |")
    print(f"relief branch peak process memory / frame set = {max(r_tm, r_anon) / frame_set:.3f} (target <= 2: "
          f"{'met' if relief_ok else 'NOT met'})")
    return relief_ok


# ------------------------------------------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1.2 MP instead of 24 MP")
    ap.add_argument("--megapixels", type=float, default=None, help="frame size (3:2 aspect); default 24")
    ap.add_argument("--tile-rows", type=int, default=256, help="rows per tile (reading and processing)")
    ap.add_argument("--parallel", action="store_true", help="add the parallel-polarized frames (specular maps)")
    ap.add_argument("--workers", type=int, default=None,
                    help="threads over row tiles in compute_maps / estimate_diffusion (default min(2, CPUs))")
    ap.add_argument("--tmp", type=Path, default=None, help="folder for the temporary files")
    ap.add_argument("--keep", action="store_true", help="keep the temporary files")
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    ap.add_argument("--ram", action="store_true",
                    help="diagnostic: also run the pipeline with its maps in RAM (compute without map I/O; memory "
                         "then grows with the frame: ~4 frame sets)")
    ap.add_argument("--relief", action="store_true",
                    help="also run the relief branch of rig estimate gradients (no sphere: per-window relief fit, "
                         "its window maps and the apparent albedo written as EXR) and report its memory (issue 16)")
    ap.add_argument("--relief-only", action="store_true",
                    help="only the read floor and the relief branch (skips the sphere pipeline's four workers)")
    ap.add_argument("--no-cache", action="store_true",
                    help="synthesize the frames into the temporary folder instead of reusing (or filling) the cache "
                         "benchmarks/out/gradients_frames/ (24 MP: ~1.8 GB, keyed by size, options and source)")
    ap.add_argument("--synthesize-only", action="store_true", help="fill the frame cache and stop")
    ap.add_argument("--worker", choices=["floor", "pipeline", "trace", "write", "ram", "relief"],
                    help=argparse.SUPPRESS)
    ap.add_argument("--dir", help=argparse.SUPPRESS)
    ap.add_argument("--height", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--width", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--write-bytes", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args)
    mp = args.megapixels or (1.2 if args.quick else 24.0)
    W = int(round(np.sqrt(mp * 1e6 * 1.5)))
    H = int(round(mp * 1e6 / W))
    args.height, args.width = H, W
    folder = Path(tempfile.mkdtemp(prefix="sssrig-gradbench-", dir=args.tmp))
    try:
        t0 = time.perf_counter()
        if args.no_cache:
            synthesize(folder, H, W, args.parallel, args.tile_rows,
                       build_response_lut(leds(), eta=ETA, surface_radius_mm=RADIUS_MM))
            synth = f"synthesis {time.perf_counter() - t0:.0f} s"
        else:   # the frames from the cache, linked into the work folder (the workers write their maps there)
            src, dt = cached_frames(H, W, args.parallel, args.tile_rows)
            for n in frame_names(args.parallel) + ["normals"]:
                (folder / f"{n}.npy").symlink_to(src / f"{n}.npy")
            synth = (f"synthesis {dt:.0f} s" if dt is not None else "frames cached") + f" in {src}"
        if args.synthesize_only:
            print(synth)
            return 0
        n_frames = len(frame_names(args.parallel))
        frame_set = n_frames * H * W * 3 * 4
        print(f"# gradient-map pipeline benchmark: {W} x {H} px ({H * W / 1e6:.1f} MP), {n_frames} frames "
              f"(frame set {frame_set / 2**30:.2f} GiB float32), tile_rows {args.tile_rows}; {synth}; "
              f"work files in {folder}\n")
        floor1 = spawn("floor", folder, args)
        if args.relief_only:
            relief = spawn("relief", folder, args)
            floor2 = spawn("floor", folder, args)
            mpx = H * W / 1e6
            floor_mps = [mpx / floor1["seconds"], mpx / floor2["seconds"]]
            print(f"read floor {floor1['seconds']:.2f} / {floor2['seconds']:.2f} s ({max(floor_mps):.2f} MP/s, the "
                  "faster as the reference; the sphere pipeline's workers skipped: --relief-only)")
            ok = print_relief(relief, mpx, max(floor_mps), frame_set)
            if args.json:
                write_json(args.json, {"width_px": W, "height_px": H, "megapixels": mpx, "frames": n_frames,
                                       "frame_set_bytes": frame_set, "floor_read_mps": floor_mps,
                                       "targets_met": {"relief_memory": ok},
                                       "runs": {"floor1": floor1, "floor2": floor2, "relief": relief}}, indent=1)
            return 0
        pipe = spawn("pipeline", folder, args)
        floor2 = spawn("floor", folder, args)
        write = spawn("write", folder, args, write_bytes=pipe["bytes_written"])
        trace = spawn("trace", folder, args) if not args.quick else pipe
        ram = spawn("ram", folder, args) if args.ram else None
        relief = spawn("relief", folder, args) if args.relief else None
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    mpx = H * W / 1e6
    floor_mps = [mpx / floor1["seconds"], mpx / floor2["seconds"]]
    floor_ref = max(floor_mps)
    pipe_mps = mpx / pipe["seconds"]
    per_px = pipe["seconds"] - pipe["seconds_lut"]
    rows = [
        ("read floor (1st)", floor1["seconds"], floor_mps[0], ""),
        ("read floor (2nd)", floor2["seconds"], floor_mps[1], ""),
        ("write floor (same bytes as the maps)", write["seconds"], mpx / write["seconds"],
         f"{write['bytes'] / 2**30:.2f} GiB"),
        ("pipeline: LUT + maps + diffusion", pipe["seconds"], pipe_mps, ""),
        ("  LUT build (fixed cost)", pipe["seconds_lut"], float("nan"), ""),
        ("  compute_maps", pipe["seconds_maps"], mpx / pipe["seconds_maps"], ""),
        ("  estimate_sphere (maps + summary)", pipe["seconds_diffusion"], mpx / pipe["seconds_diffusion"], ""),
        ("  per-pixel part (maps + diffusion)", per_px, mpx / per_px, ""),
    ]
    if ram is not None:
        ram_px = ram["seconds"] - ram["seconds_lut"]
        rows += [("pipeline, maps in RAM (diagnostic)", ram["seconds"], mpx / ram["seconds"],
                  f"peak RssAnon {(ram['anon_peak_bytes'] - ram['anon_baseline_bytes']) / frame_set:.2f} frame sets"),
                 ("  per-pixel part, maps in RAM", ram_px, mpx / ram_px, "")]
    print("read floor = only reading the same inputs the same way: every input .npy memory map (the frames and the "
          "known normals), the same tile_rows row tiles, np.add.reduce over each tile, nothing else; fresh process, "
          "warm page cache (the inputs were just written / read); the faster of two runs is the reference.")
    print(f"pipeline: {pipe['workers']} worker thread(s); maps stored: {', '.join(pipe['stored'])} "
          f"({pipe['bytes_written'] / 2**30:.2f} GiB); every other map is derived on access.\n")
    print("| stage | s | MP/s | note |\n|---|---|---|---|")
    for name, s, r, note in rows:
        print(f"| {name} | {s:.2f} | {r:.2f} | {note} |")
    ratio = pipe_mps / floor_ref
    io_mps = mpx / (mpx / floor_ref + write["seconds"])
    print(f"\npipeline / read floor (faster of the two) = {ratio:.3f} (target >= 0.333: "
          f"{'met' if ratio >= 1 / 3 else 'NOT met'}); pipeline / (read + write floor) = {pipe_mps / io_mps:.3f}")
    tm = trace["tracemalloc_peak_bytes"]
    anon = pipe["anon_peak_bytes"] - pipe["anon_baseline_bytes"]
    print("\n| memory (pipeline) | GiB | / frame set |\n|---|---|---|")
    print(f"| tracemalloc peak (numpy + Python allocations) | {tm / 2**30:.3f} | {tm / frame_set:.3f} |")
    print(f"| peak RssAnon above baseline (sampled) | {anon / 2**30:.3f} | {anon / frame_set:.3f} |")
    print(f"| VmHWM: peak RSS incl. mapped file pages (reference) | {pipe['vmhwm_bytes'] / 2**30:.3f} | "
          f"{pipe['vmhwm_bytes'] / frame_set:.3f} |")
    mem_ok = max(tm, anon) <= 2 * frame_set
    print(f"\npeak process memory / frame set = {max(tm, anon) / frame_set:.3f} (target <= 2: "
          f"{'met' if mem_ok else 'NOT met'})")
    relief_ok = print_relief(relief, mpx, floor_ref, frame_set) if relief is not None else None
    print(f"\nresult check: known pixels (red) {pipe['known_fraction']:.3f}, D_mm {np.round(pipe['D_mm'], 5).tolist()}"
          f" (rel. err. vs marble {np.round(pipe['D_rel_err'], 4).tolist()}, status {pipe['status']})")
    result = {"width_px": W, "height_px": H, "megapixels": mpx, "frames": n_frames, "frame_set_bytes": frame_set,
              "tile_rows": args.tile_rows, "floor_read_mps": floor_mps, "write_floor_mps": mpx / write["seconds"],
              "pipeline_mps": pipe_mps, "io_floor_mps": io_mps, "per_pixel_mps": mpx / per_px, "ratio_pipeline_over_floor": ratio,
              "tracemalloc_peak_over_frame_set": tm / frame_set, "anon_peak_over_frame_set": anon / frame_set,
              "targets_met": {"throughput": ratio >= 1 / 3, "memory": mem_ok, "relief_memory": relief_ok},
              "runs": {"floor1": floor1, "pipeline": pipe, "floor2": floor2, "write": write, "trace": trace,
                       "ram": ram, "relief": relief}}
    if args.json:
        write_json(args.json, result, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
