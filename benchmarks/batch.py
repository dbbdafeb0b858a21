"""Benchmark of ``rig estimate batch`` on Dask (rig/estimate/batch.py, issue 19 item 3; docs/scale-out.md).

Eight scene files of the scene zoo (benchmarks/zoo: the CI subset's 48 x 48 px Monte Carlo frames, ``quick_subset(
draw_zoo(), 8)``), each estimated with ``mc-table+reference`` (a Monte Carlo reference render per iteration), as
one batch on a LocalCluster of 1 worker process and then of 2 (one thread each, rig.estimate.batch.WORKER_ENV). Printed, all
from one run:

- per worker count: cluster start + warm-up (every worker imports the estimators and loads numba's cached kernels
  before the clock of the batch starts), the batch's wall time, the sum of the items' seconds on the workers, the
  worker processes' own CPU seconds and CPU / wall (the 1-worker run should be one core: <= 1.05), the most items at
  once on one worker, and each worker's runnable fraction with a rough idle-core estimate (:class:`RunnableSampler`);
- the speed-up = wall(1 worker) / wall(2 workers) (anchor: the 1-worker batch of the same run; target >= 1.7),
  the CPU seconds the items got per wall second ("cores got": on a machine shared with other jobs, what the
  workers were given; its 2-vs-1 ratio says how much more CPU two workers got than one), and
  whether the two batches' result digests (rig.estimate.batch.result_digest: every number of every result, without
  timings) are bit-identical; with ``--serial`` also the in-process serial run's digests;
- the per-task costs behind docs/scale-out.md's predictions: median item seconds, Dask's overhead per task (200
  no-op tasks on the 2-worker cluster), the content hash of an item, and the load average before and after.

Run: ``python benchmarks/batch.py [--spp N] [--iterations K] [--pairs P] [--serial] [--json]`` (defaults 8 spp, 2
iterations, 1 pair: ~3-6 min per pair on 2 idle cores; the 8 scenes and the 3 warm-up scenes are rendered once into
benchmarks/out/zoo, ~10 s each after numba's cache).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from rig.estimate.batch import (BatchOptions, classify_item, content_sha256, expected_cost,  # noqa: E402
                                list_schedule_makespan, local_cluster, run_batch, submission_order)


def _warm(scene_paths: list[str]) -> int:
    """Imports of the single-image reference path and numba's cached kernels, run on every worker before the batch's
    clock starts: a 4 x 4 px, 2-spp render of a sphere under a point light, then a 2-spp, one-render reference
    estimate of each of ``scene_paths`` (zoo scenes outside the batch: a point-, a sky- and a sun-lit one; the
    renders under an environment, the fits' kernels and the model tables). Without the estimates a worker's first
    item paid ~2.5 s more (a sky-lit zoo scene, measured in one process: 6.5 s first, 3.9 s second), once per
    worker: twice in the 2-worker run, once in the 1-worker run."""
    import numpy as np

    import rig.estimate.scenes  # noqa: F401
    import rig.estimate.reference.scene_reference  # noqa: F401
    from estimation.camera import PinholeCamera
    from estimation.single_image import PointLights
    from rig.files.scene_file import load_scene
    from simulators.mc import Medium, Sphere, render

    cam = PinholeCamera(4, 4, 8.0, 8.0, 2.0, 2.0, ((1, 0, 0), (0, 0, -1), (0, 1, 0)), (0.0, -100.0, 0.0))
    render(Sphere((0.0, 0.0, 0.0), 10.0), Medium.from_reduced(1.0, 0.01, eta=1.3), cam,
           PointLights(np.array([[0.0, -200.0, 100.0]]), np.array([1.0])), spp=2, derivatives=True,
           fd_log_sigma_s=0.1)
    for path in scene_paths:
        rig.estimate.scenes.estimate_scene(load_scene(path), model="mc-table+reference", reference_spp=2,
                                           reference_iterations=1, reference_seed=1)
    return os.getpid()


def warm_scenes(batch: list[Path]) -> list[Path]:
    """The first point-, sky- and sun-lit zoo scenes not in ``batch`` (their quick variants: :func:`_warm`)."""
    from zoo.frames import build_scene
    from zoo.scenes import draw_zoo, quick_variant

    names = {p.parent.name for p in batch}
    out: dict[str, Path] = {}
    for spec in draw_zoo():
        light = "point" if spec.light.startswith("point") else spec.light
        if light in out:
            continue
        path = build_scene(quick_variant(spec), HERE / "out" / "zoo")[0] / "scene.toml"
        if path.parent.name not in names:
            out[light] = path
    return list(out.values())


def _noop(i: int) -> int:
    return i


def _process_cpu_s() -> float:
    """CPU seconds (user + system, every thread) of this worker process so far."""
    import psutil

    t = psutil.Process().cpu_times()
    return float(t.user + t.system)


def scenes(n: int) -> list[Path]:
    from zoo.frames import build_scene
    from zoo.scenes import draw_zoo, quick_subset, quick_variant

    specs = quick_subset(draw_zoo(), n)[:n]
    return [build_scene(quick_variant(s), HERE / "out" / "zoo")[0] / "scene.toml" for s in specs]


class RunnableSampler:
    """Samples, every ``period_s``, whether each worker process has a thread in state R (running or waiting for a
    CPU: ``/proc/PID/task/*/stat``; Linux). A worker waiting on its chunks or with no task has none. Runnable seconds
    per worker ~ the wall time it wanted a core; on a loaded machine its CPU seconds are less (the other jobs took
    the rest). If the load slows every worker alike, the batch on idle cores would take ~ wall x sum(CPU s) /
    sum(runnable s): an estimate, not a measurement (the load is not uniform in time)."""

    def __init__(self, pids: list[int], period_s: float = 0.05) -> None:
        import threading

        self.pids, self.period_s = pids, period_s
        self.samples = 0
        self.runnable = {p: 0 for p in pids}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _has_runnable_thread(self, pid: int) -> bool:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                stat = (task / "stat").read_text()
            except OSError:
                continue
            if stat[stat.rindex(")") + 2] == "R":
                return True
        return False

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                hits = {p: self._has_runnable_thread(p) for p in self.pids}
            except OSError:         # a worker gone (restarted): skip the sample
                continue
            self.samples += 1
            for p, hit in hits.items():
                self.runnable[p] += hit

    def __enter__(self) -> "RunnableSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()

    def runnable_fraction(self) -> dict[int, float]:
        return {p: n / max(1, self.samples) for p, n in self.runnable.items()}


def run_workers(items: list[Path], opts: BatchOptions, workers: int, out: Path, warm: list[Path]
                ) -> dict[str, Any]:
    from distributed import Client

    t0 = time.perf_counter()
    with local_cluster(workers) as cluster, Client(cluster) as client:
        client.wait_for_workers(workers, timeout=300)
        client.run(_warm, [str(p) for p in warm])
        t_start = time.perf_counter() - t0
        load0 = os.getloadavg()
        pids = client.run(os.getpid)
        cpu0 = client.run(_process_cpu_s)
        t1 = time.perf_counter()
        with RunnableSampler(sorted(pids.values())) as sampler:
            rep = run_batch(items, out, options=opts, client=client)
        wall = time.perf_counter() - t1
        cpu1 = client.run(_process_cpu_s)
        load1 = os.getloadavg()
        overhead = None
        if workers > 1:
            t2 = time.perf_counter()
            client.gather(client.map(_noop, range(200), pure=False))
            overhead = (time.perf_counter() - t2) / 200
    assert rep.ok, [r for r in rep.records if r["status"] == "failed"]
    render_s = {}
    for r in rep.records:       # the reference renders' own seconds (the part render chunks could spread)
        res = json.loads((out / r["key"] / "result.json").read_text())
        ref = res.get("reference") or {}
        render_s[r["key"]] = float(sum(float(x.get("seconds") or 0.0) for x in
                                       list(ref.get("renders") or []) + list(ref.get("scan_renders") or [])
                                       + list(ref.get("line_search_renders") or [])))
    # the worker processes' own CPU seconds over the batch (items, their render chunks, Dask's threads): what the
    # run really used; the items' process_time sums double-count items that overlap in one process
    worker_cpu = sum(cpu1[a] - cpu0[a] for a in cpu1 if a in cpu0)
    runnable_s = sum(sampler.runnable_fraction().values()) * wall
    return {"item_render_seconds": render_s, "workers": workers, "start_and_warm_s": t_start, "wall_s": wall,
            "worker_cpu_s": worker_cpu, "worker_cores_used": worker_cpu / wall,
            "worker_runnable_fraction": {str(p): f for p, f in sampler.runnable_fraction().items()},
            "worker_runnable_s": runnable_s, "runnable_samples": sampler.samples,
            "idle_cores_wall_estimate_s": wall * worker_cpu / runnable_s if runnable_s > 0 else None,
            "chunked": bool(opts.render_chunk_rows) or (opts.render_chunk_rows is None and workers > 1),
            "item_windows_unix_s": {r["key"]: [r["started_unix_s"], r["finished_unix_s"], r["worker_pid"]]
                                    for r in rep.records},
            "item_seconds": {r["key"]: r["seconds"] for r in rep.records},
            "item_cpu_seconds": {r["key"]: r["cpu_seconds"] for r in rep.records},
            "digests": {r["key"]: r["digest"] for r in rep.records},
            "worker_pids": sorted({r["worker_pid"] for r in rep.records}),
            "load_before": load0, "load_after": load1, "dask_overhead_per_task_s": overhead}


def _max_overlap(windows: dict[str, list[float]]) -> int:
    """The most items that ran at once on one worker process (from the markers' start and end times)."""
    best = 0
    for key, (s0, _e0, pid) in windows.items():
        best = max(best, sum(1 for s, e, p in windows.values() if p == pid and s <= s0 < e))
    return best


def makespans(items: list[Path], opts: BatchOptions, one: dict[str, Any], two: dict[str, Any]) -> dict[str, Any]:
    """Expected 2-worker makespans (rig.estimate.batch.list_schedule_makespan) from the per-item CPU seconds (the
    smaller of the 1- and the 2-worker run's: a worker's first item also pays the numba kernels the warm-up did not
    load, measured up to ~19 s; each worker given one core): in the given order (the submission order before the longest-first rule),
    in the batch's order now (rig.estimate.batch.expected_cost without a previous run: the static estimate), and
    longest-first by the recorded costs (what a re-run with earlier markers submits); with render chunks, idealised:
    greedy in the batch's order; the time the last item runs alone has its renders (in that item's proportion of
    render seconds) shared by both workers (chunking's transfers and the chunks' own overhead not modelled)."""
    resolved = [classify_item(p) for p in items]
    # with render chunks on 2 workers an item's process_time misses its chunks run on the other worker: then the
    # 1-worker run's (one item at a time per process, its chunks in it)
    best = [one if two["chunked"] or one["item_cpu_seconds"][it.key] <= two["item_cpu_seconds"][it.key] else two
            for it in resolved]
    cost = [float(r["item_cpu_seconds"][it.key]) for r, it in zip(best, resolved)]
    wall = [float(r["item_seconds"][it.key]) for r, it in zip(best, resolved)]
    rend = [min(c, float(r["item_render_seconds"][it.key]) * (c / w if w > 0 else 1.0))
            for r, it, c, w in zip(best, resolved, cost, wall)]   # render wall seconds scaled to CPU seconds
    static = [expected_cost(it, opts.for_kind(it.kind)) for it in resolved]
    order = submission_order(static)
    lpt = sorted(range(len(cost)), key=lambda i: -cost[i])
    # chunks, idealised: the batch's order; after the first worker runs out of items (t_idle) only the last item
    # runs; its remaining time R holds renders in the item's own proportion, which chunks share over both workers
    free = [0.0, 0.0]
    last = order[0]
    for i in order:
        k = min(range(2), key=free.__getitem__)
        free[k] += cost[i]
        if free[k] >= max(free):
            last = i
    t_idle, remaining = min(free), max(free) - min(free)
    share = rend[last] / cost[last] if cost[last] > 0 else 0.0
    chunked = t_idle + remaining * (1.0 - share) + remaining * share / 2
    return {"sum_s": sum(cost), "longest_s": max(cost), "given_order_s": list_schedule_makespan(cost, 2),
            "batch_order_s": list_schedule_makespan([cost[i] for i in order], 2),
            "lpt_recorded_s": list_schedule_makespan([cost[i] for i in lpt], 2),
            "lower_bound_s": max(sum(cost) / 2, max(cost)), "chunked_ideal_s": chunked,
            "render_share": sum(rend) / sum(cost), "static_ties": len(static) - len(set(static)),
            "item_cpu_s_given_order": cost, "item_render_cpu_s_given_order": rend}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--items", type=int, default=8)
    ap.add_argument("--spp", type=int, default=8, help="reference spp (default 8)")
    ap.add_argument("--iterations", type=int, default=2, help="reference iterations (default 2)")
    ap.add_argument("--serial", action="store_true", help="also the in-process serial run (workers=0)")
    ap.add_argument("--render-chunk-rows", type=int, default=None,
                    help="split each reference render into chunks of this many rows across the workers (as "
                         "`rig estimate batch --render-chunk-rows`; 0: whole renders; default: the batch's automatic "
                         "chunks, none on 1 worker)")
    ap.add_argument("--pairs", type=int, default=1,
                    help="run 1 worker then 2 workers this many times, one pair after another (the machine's speed "
                         "drifts over minutes: each ratio is taken within its pair); the speed-up printed is the "
                         "median of the pairs' ratios, the other lines are the last pair's")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.pairs < 1:
        ap.error(f"--pairs must be >= 1; got {args.pairs}")
    items = scenes(args.items)
    warm = warm_scenes(items)
    opts = BatchOptions(model="mc-table+reference", reference_spp=args.spp, reference_iterations=args.iterations,
                        reference_seed=19, render_chunk_rows=args.render_chunk_rows)
    t = time.perf_counter()
    for p in items:
        content_sha256(classify_item(p))
    hash_s = (time.perf_counter() - t) / len(items)
    runs: dict[int, dict[str, Any]] = {}
    serial: dict[str, Any] | None = None
    pairs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="batch-bench-") as tmp:
        for k in range(args.pairs):
            for w in (1, 2):
                print(f"# pair {k + 1} of {args.pairs}: {w} worker(s) ...", file=sys.stderr, flush=True)
                runs[w] = run_workers(items, opts, w, Path(tmp) / f"p{k}w{w}", warm)
            pairs.append({"wall_1_s": runs[1]["wall_s"], "wall_2_s": runs[2]["wall_s"],
                          "speedup": runs[1]["wall_s"] / runs[2]["wall_s"],
                          "bit_identical": runs[1]["digests"] == runs[2]["digests"],
                          "one_worker_cores_used": runs[1]["worker_cores_used"]})
        if args.serial:
            print("# serial (in process) ...", file=sys.stderr, flush=True)
            t = time.perf_counter()
            rep = run_batch(items, Path(tmp) / "serial", options=opts, workers=0)
            serial = {"wall_s": time.perf_counter() - t, "digests": {r["key"]: r["digest"] for r in rep.records}}
    one, two = runs[1], runs[2]
    doc_makespan = makespans(items, opts, one, two)
    speedup = statistics.median(p["speedup"] for p in pairs)
    identical = all(p["bit_identical"] for p in pairs)
    item_s = list(one["item_seconds"].values())
    doc = {"items": len(items), "reference_spp": args.spp, "reference_iterations": args.iterations,
           "runs": {str(k): {kk: vv for kk, vv in v.items() if kk != "digests"} for k, v in runs.items()},
           "speedup_2_vs_1": speedup, "pairs": pairs, "target": 1.7, "bit_identical_1_vs_2": identical,
           "bit_identical_serial": None if serial is None else serial["digests"] == one["digests"],
           "serial_wall_s": None if serial is None else serial["wall_s"],
           "median_item_s_1_worker": statistics.median(item_s), "content_hash_s_per_item": hash_s,
           "dask_overhead_per_task_s": two["dask_overhead_per_task_s"], "cpu_count": os.cpu_count(),
           "expected_makespan_2_workers": doc_makespan,
           "cpu_rate_ratio_2_vs_1": (sum(two["item_cpu_seconds"].values()) / two["wall_s"])
           / (sum(one["item_cpu_seconds"].values()) / one["wall_s"]),
           "render_chunk_rows": args.render_chunk_rows,
           "one_worker_cores_used": one["worker_cores_used"],
           "speedup_2_vs_1_idle_cores_estimate": (one["idle_cores_wall_estimate_s"] / two["idle_cores_wall_estimate_s"]
                                                  if one["idle_cores_wall_estimate_s"]
                                                  and two["idle_cores_wall_estimate_s"] else None),
           "one_worker_is_one_core": all(p["one_worker_cores_used"] <= 1.05 for p in pairs),
           "max_items_at_once_per_worker": max(_max_overlap(r["item_windows_unix_s"]) for r in runs.values())}
    if args.json:
        print(json.dumps(doc, indent=2))
        return 0
    print(f"# rig estimate batch: {len(items)} zoo scene files, mc-table+reference, {args.spp} spp, "
          f"{args.iterations} iteration(s); {os.cpu_count()} cores")
    print(f"{'workers':>7} {'start+warm s':>12} {'batch wall s':>12} {'sum item s':>10} {'sum item CPU s':>14} "
          f"{'cores got':>9} {'worker CPU s':>12} {'CPU/wall':>8} {'load before':>16} {'load after':>16}")
    for w, r in runs.items():
        lb = "/".join(f"{x:.1f}" for x in r["load_before"])
        la = "/".join(f"{x:.1f}" for x in r["load_after"])
        cpu = sum(r["item_cpu_seconds"].values())
        print(f"{w:>7} {r['start_and_warm_s']:>12.1f} {r['wall_s']:>12.1f} {sum(r['item_seconds'].values()):>10.1f} "
              f"{cpu:>14.1f} {cpu / r['wall_s']:>9.2f} {r['worker_cpu_s']:>12.1f} {r['worker_cores_used']:>8.2f} "
              f"{lb:>16} {la:>16}")
    if len(pairs) > 1:
        print("pairs (1 worker s / 2 workers s = ratio, bit-identical): " + "; ".join(
            f"{p['wall_1_s']:.1f} / {p['wall_2_s']:.1f} = {p['speedup']:.2f}x {p['bit_identical']}" for p in pairs))
    print(f"speed-up 2 vs 1 workers{f' (median of {len(pairs)} pairs)' if len(pairs) > 1 else ''}: {speedup:.2f}x "
          f"(target >= 1.7: {'met' if speedup >= 1.7 else 'NOT met'}); "
          f"CPU-time speed-up (item CPU s per wall s, 2 vs 1): {doc['cpu_rate_ratio_2_vs_1']:.2f}x")
    chunking = "automatic" if args.render_chunk_rows is None else (f"{args.render_chunk_rows} rows"
                                                                   if args.render_chunk_rows > 0 else "none")
    one_core = ", ".join(f"{p['one_worker_cores_used']:.2f}" for p in pairs)
    print(f"render chunks: {chunking}; 1-worker runs on one core (worker CPU s / wall {one_core} <= 1.05): "
          f"{doc['one_worker_is_one_core']}; most items running at once on "
          f"one worker: {doc['max_items_at_once_per_worker']}")
    est = doc["speedup_2_vs_1_idle_cores_estimate"]
    print("runnable fraction of each worker process (sampled every 50 ms): " + "; ".join(
        f"{w} worker(s) " + ", ".join(f"{f:.2f}" for f in r["worker_runnable_fraction"].values())
        + f" -> wall on idle cores ~ {r['idle_cores_wall_estimate_s']:.1f} s" for w, r in runs.items())
        + (f"; estimated speed-up on idle cores {est:.2f}x (an estimate: wall x CPU s / runnable s)" if est else ""))
    print(f"bit-identical 1 vs 2 workers: {identical}")
    if serial is not None:
        print(f"bit-identical serial (in process, {serial['wall_s']:.1f} s) vs workers: {doc['bit_identical_serial']}")
    m = doc_makespan
    print(f"expected makespan of 2 workers from the items' CPU seconds (sum {m['sum_s']:.1f} s, longest "
          f"{m['longest_s']:.1f} s; greedy list schedule, no overhead): given order {m['given_order_s']:.1f} s "
          f"({m['sum_s'] / m['given_order_s']:.2f}x of 1 worker), batch's order (static cost estimate; "
          f"{m['static_ties']} ties) {m['batch_order_s']:.1f} s ({m['sum_s'] / m['batch_order_s']:.2f}x), "
          f"longest-first by the recorded costs (a re-run) {m['lpt_recorded_s']:.1f} s "
          f"({m['sum_s'] / m['lpt_recorded_s']:.2f}x), bound max(sum/2, longest) {m['lower_bound_s']:.1f} s "
          f"({m['sum_s'] / m['lower_bound_s']:.2f}x); with render chunks (renders {m['render_share']:.0%} of the "
          f"CPU, idealised: the last item's renders split over both workers) {m['chunked_ideal_s']:.1f} s "
          f"({m['sum_s'] / m['chunked_ideal_s']:.2f}x)")
    print(f"per task: median item {doc['median_item_s_1_worker']:.2f} s (1 worker), Dask overhead "
          f"{1e3 * doc['dask_overhead_per_task_s']:.1f} ms, content hash {1e3 * hash_s:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
