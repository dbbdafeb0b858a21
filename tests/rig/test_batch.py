"""``rig estimate batch`` on Dask (rig/estimate/batch.py, docs/scale-out.md): the same numbers serially and on two worker
processes, a worker killed mid-batch changes nothing, a re-run skips finished items, a bad item is named.

Items: two scene files of the scene zoo's CI subset (benchmarks/zoo, 48 x 48 px Monte Carlo frames; a sphere under
a point light and a pyramid under a sky), estimated with ``mc-table+reference`` at 4 spp and one reference render:
a Monte Carlo render inside every item, so the bit-identity covers the renderer's seeding. ~40-60 s on 2 cores
(one serial run, one two-worker LocalCluster shared by the two distributed tests).
"""
from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from rig.estimate.batch import (DONE_FILE, RESULT_FILE, BatchItemError, BatchOptions, classify_item,  # noqa: E402
                                item_restrictions, local_cluster, run_batch)
from rig.estimate.batch_chunks import chunk_row_sets  # noqa: E402

pytestmark = pytest.mark.timeout(600)

OPTIONS = BatchOptions(model="mc-table+reference", reference_spp=4, reference_iterations=1, reference_seed=7)
#: the zoo's CI subset: the sphere under one point light and the pyramid under a sky (the two fastest to render)
QUICK_INDICES = (3, 4)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    from zoo.frames import build_scene
    from zoo.scenes import draw_zoo, quick_subset, quick_variant

    root = tmp_path_factory.mktemp("batch_scenes")
    specs = quick_subset(draw_zoo())
    return [build_scene(quick_variant(specs[i]), root)[0] / "scene.toml" for i in QUICK_INDICES]


@pytest.fixture(scope="module")
def serial(scenes: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Any:
    out = tmp_path_factory.mktemp("batch_serial")
    return run_batch(scenes, out, options=OPTIONS, workers=0)


@pytest.fixture(scope="module")
def client() -> Any:
    from distributed import Client

    with local_cluster(2) as cluster, Client(cluster) as c:
        c.wait_for_workers(2, timeout=120)
        yield c


def test_workers_get_one_thread_and_the_caller_keeps_its_environment(client: Any) -> None:
    """WORKER_ENV (one numba / BLAS thread) in every worker, set before it imported numpy (distributed's pre-spawn
    environment), and this process's environment as it was: distributed's nanny sets that environment in the process
    that runs it, the caller's, and leaves it (a test after a batch in the same process could not set
    NUMBA_NUM_THREADS to 2 any more)."""
    from rig.estimate.batch import WORKER_ENV

    for env in client.run(lambda: {k: os.environ.get(k) for k in WORKER_ENV}).values():
        assert env == WORKER_ENV
    before = {k: os.environ.get(k) for k in (*WORKER_ENV, "PYTHONHASHSEED")}
    with local_cluster(1) as cluster:
        assert len(cluster.workers) == 1
        assert {k: os.environ.get(k) for k in before} == before
    assert {k: os.environ.get(k) for k in before} == before


def _digests(report: Any) -> dict[str, str]:
    return {r["key"]: r["digest"] for r in report.records}


def test_serial_run_writes_each_item_and_its_marker(serial: Any) -> None:
    assert serial.ok and serial.count("done") == 2, serial.records
    for r in serial.records:
        folder = serial.out_dir / r["key"]
        result = json.loads((folder / RESULT_FILE).read_text())
        marker = json.loads((folder / DONE_FILE).read_text())
        assert result["model"] == "mc-table+reference" and result["reference"]["renders"], r["key"]
        assert marker["digest"] == r["digest"] and len(marker["content_sha256"]) == 64
    listing = json.loads((serial.out_dir / "batch.json").read_text())
    assert [i["status"] for i in listing["items"]] == ["done", "done"]


def _small_scene(height_px: int = 16) -> tuple[tuple[Any, ...], dict[str, Any]]:
    """A 12 px wide sphere under a point light and its render keywords (16 rows: two automatic chunks of >=
    AUTO_MIN_CHUNK_ROWS)."""
    import numpy as np

    from estimation.camera import PinholeCamera
    from estimation.single_image import PointLights
    from simulators.mc import Medium, Sphere

    cam = PinholeCamera(12, height_px, 20.0, 20.0, 6.0, height_px / 2, ((1, 0, 0), (0, 0, -1), (0, 1, 0)), (0.0, -100.0, 0.0))
    scene = (Sphere((0.0, 0.0, 0.0), 10.0), [Medium.from_reduced(1.0, 0.01, eta=1.3)] * 2, cam,
             PointLights(np.array([[0.0, -200.0, 100.0]]), np.array([1.0])))
    return scene, dict(spp=4, seed=3, derivatives=True, fd_log_sigma_s=0.1)


def test_chunked_render_is_bit_identical_to_whole_render() -> None:
    import numpy as np

    from rig.estimate.batch_chunks import chunked_render
    from simulators.mc import render

    scene, kw = _small_scene(10)
    cam = scene[2]
    whole = render(*scene, **kw)
    for rows in (3, 4):                          # 10 rows: uneven last chunks
        part = chunked_render(*scene, chunk_rows=rows, **kw)
        for name in ("radiance", "stderr", "mask", "d_log_sigma", "d_log_sigma_stderr"):
            assert np.array_equal(getattr(part, name), getattr(whole, name)), (rows, name)
    assert whole.mask.any() and not whole.mask.all()
    # interleaved chunks share the object: every chunk's hit count within one row's pixels of the others'
    hits = [int(render(*scene, rows=b, **kw).mask.sum()) for b in chunk_row_sets(10, chunk_rows=1)]
    assert len(hits) == 10 and sum(hits) == int(whole.mask.sum())
    halves = [int(render(*scene, rows=b, **kw).mask.sum()) for b in chunk_row_sets(10, chunk_rows=5)]
    assert abs(halves[0] - halves[1]) <= cam.width_px
    for bad in ((5, 11), (0, 10, 0), (0, 10, 1, 1)):
        with pytest.raises(ValueError, match="rows"):
            render(*scene, rows=bad, **kw)


def _render_chunks_on_a_worker(s_per_sample: float, wave: bool) -> list[Any]:
    """One render, or a wave of two (``many``), through RenderChunks(2) starting from ``s_per_sample``, as a task on a
    worker."""
    from rig.estimate.batch_chunks import RenderChunks

    scene, kw = _small_scene()
    auto = RenderChunks(2)
    auto.s_per_sample = s_per_sample
    return auto.many([(*scene, kw), (*scene, {**kw, "seed": 4})]) if wave else [auto(*scene, **kw)]


def test_automatic_chunks_split_only_long_renders_and_a_wave_at_once(client: Any) -> None:
    """RenderChunks (the batch's automatic chunks): a render expected below AUTO_MIN_CHUNKED_RENDER_S runs whole in
    the item's task (no chunk task), a longer one in 2 chunks; a wave (``many``, a reference's prefetch) in 2
    chunks per render whatever its expected time; every image bit-identical to the whole render."""
    import numpy as np
    from distributed import get_task_stream

    from simulators.mc import render

    scene, kw = _small_scene()
    want = {False: [render(*scene, **kw)], True: [render(*scene, **kw), render(*scene, **{**kw, "seed": 4})]}
    for s_per_sample, wave, n_chunks in ((1e-9, False, 0), (1.0, False, 2), (1e-9, True, 4)):
        with get_task_stream(client) as ts:
            imgs = client.submit(_render_chunks_on_a_worker, s_per_sample, wave, pure=False).result()
        assert sum(str(t["key"]).startswith("render-") for t in ts.data) == n_chunks, (s_per_sample, wave)
        for img, w in zip(imgs, want[wave], strict=True):
            for name in ("radiance", "stderr", "mask", "d_log_sigma", "d_log_sigma_stderr"):
                assert np.array_equal(getattr(img, name), getattr(w, name)), (s_per_sample, wave, name)


def test_two_workers_bit_identical_to_serial(scenes: list[Path], serial: Any, client: Any,
                                             tmp_path: Path) -> None:
    """Each item a task, and each of its reference renders split into 16-row chunks across the two workers."""
    from dataclasses import replace

    from distributed import get_task_stream

    with get_task_stream(client) as ts:
        report = run_batch(scenes, tmp_path, options=replace(OPTIONS, render_chunk_rows=16), client=client)
    assert report.ok and report.count("done") == 2
    chunks = [t for t in ts.data if str(t["key"]).startswith("render-")]
    assert len(chunks) >= 2 * 3                   # 48-row frames: 3 chunks per render, >= 1 render per item
    assert _digests(report) == _digests(serial)
    pids = {r["worker_pid"] for r in report.records}
    assert os.getpid() not in pids      # ran on the workers, not here
    assert item_restrictions(client) == {"resources": {"item": 1}}     # local_cluster's workers advertise it
    for r in report.records:            # one item at a time per worker, while its chunks ran on both
        for o in report.records:
            if o is not r and o["worker_pid"] == r["worker_pid"]:
                assert o["finished_unix_s"] <= r["started_unix_s"] or r["finished_unix_s"] <= o["started_unix_s"]
    for r in report.records:            # the estimates themselves, not only their digests
        a = json.loads((tmp_path / r["key"] / RESULT_FILE).read_text())["parameters"]
        b = json.loads((serial.out_dir / r["key"] / RESULT_FILE).read_text())["parameters"]
        assert a == b


def _item_like(seconds: float) -> tuple[float, float]:
    """An item's shape: two renders of four chunk tasks each (seceding from its thread slot while it waits, as
    chunked_render does), then it computes on; (start, end) wall times."""
    from distributed import worker_client

    from rig.estimate.batch_chunks import CHUNK_PRIORITY

    t0 = time.time()
    for _ in range(2):
        with worker_client() as c:
            c.gather([c.submit(time.sleep, seconds / 4, pure=False, priority=CHUNK_PRIORITY) for _ in range(4)])
    time.sleep(seconds)
    return t0, time.time()


@pytest.mark.parametrize("resources", [{"item": 1}, None])
def test_item_resource_keeps_one_item_per_worker_thread(resources: dict[str, int] | None) -> None:
    """With the item resource a seceded item (waiting on its chunks) keeps its worker's only item slot: each item
    starts after the one before ends (and the chunks still run: the items are submitted as slots free,
    as_completed_in_slots). Without it (a scheduler whose workers do not advertise it), the next item starts while
    the one before waits: the overlap this rules out. One in-process worker, one thread, three items."""
    from distributed import Client, LocalCluster

    from rig.estimate.batch import as_completed_in_slots

    # the HTTP server on a free port: the module's 2-worker cluster holds the default one (8787)
    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0",
                           resources=resources)
    with cluster, Client(cluster) as c:
        restrict = item_restrictions(c)
        assert restrict == ({"resources": {"item": 1}} if resources else {})
        got = {i: f.result(timeout=60) for i, f in as_completed_in_slots(
            c, lambda i: c.submit(_item_like, 0.2, pure=False, priority=3 - i, **restrict), 3, bool(restrict))}
    windows = sorted(got.values())
    overlaps = [min(a1, b1) - max(a0, b0) for (a0, a1), (b0, b1) in zip(windows, windows[1:])]
    if resources:
        assert max(overlaps) <= 0, windows
    else:
        assert min(overlaps) > 0.1, windows


def test_killed_worker_task_reruns_and_batch_matches_serial(scenes: list[Path], serial: Any, client: Any,
                                                            tmp_path: Path) -> None:
    killed: dict[str, Any] = {}

    def killer() -> None:
        deadline = time.monotonic() + 120
        def busy() -> dict[str, list[Any]]:
            return {w: ks for w, ks in client.processing().items() if any("rig-batch-" in str(k) for k in ks)}

        while time.monotonic() < deadline and not killed:
            if busy():
                time.sleep(0.3)         # mid-task: the item is being estimated (~1-3 s each)
                now = busy()            # still at it (a short item may have ended meanwhile: then the next one)
                if now:
                    addr = sorted(now)[0]
                    pid = client.run(os.getpid, workers=[addr])[addr]
                    os.kill(pid, signal.SIGKILL)
                    killed.update(addr=addr, pid=pid, keys=[str(k) for k in now[addr]])
                    return
            time.sleep(0.05)

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    report = run_batch(scenes, tmp_path, options=OPTIONS, client=client)
    t.join(timeout=5)
    assert killed, "no worker was busy with a batch task to kill"
    with pytest.raises(ProcessLookupError):
        os.kill(killed["pid"], 0)                       # the worker is really gone
    assert report.ok and report.count("done") == 2, report.records
    assert _digests(report) == _digests(serial)
    assert killed["pid"] not in {r["worker_pid"] for r in report.records}   # its task was re-run elsewhere
    assert not list(tmp_path.glob("*/.*"))              # no temporary file left behind


def test_rerun_skips_finished_items_and_redoes_uncommitted(scenes: list[Path], serial: Any) -> None:
    out = serial.out_dir
    result = out / serial.records[0]["key"] / RESULT_FILE
    before = result.stat().st_mtime_ns
    again = run_batch(scenes, out, options=OPTIONS, workers=0)
    assert [r["status"] for r in again.records] == ["skipped", "skipped"]
    assert result.stat().st_mtime_ns == before                  # not rewritten
    # other options are other results: nothing is skipped for them (checked without running: the marker test)
    from rig.estimate.batch import _finished, content_sha256
    item = classify_item(scenes[0])
    sha = content_sha256(item)
    assert _finished(out / item.key, sha, OPTIONS.for_kind("scene")) is not None
    assert _finished(out / item.key, sha, BatchOptions(model="mc-table").for_kind("scene")) is None
    assert _finished(out / item.key, "0" * 64, OPTIONS.for_kind("scene")) is None
    # an item folder without its marker (killed before committing) is redone, with the same digest
    (out / serial.records[1]["key"] / DONE_FILE).unlink()
    third = run_batch(scenes, out, options=OPTIONS, workers=0)
    assert [r["status"] for r in third.records] == ["skipped", "done"]
    assert _digests(third) == _digests(serial)


def test_bad_items_are_named(tmp_path: Path, scenes: list[Path]) -> None:
    with pytest.raises(BatchItemError, match="no such file") as e:
        classify_item(tmp_path / "missing")
    assert e.value.field == "ITEMS" and "missing" in str(e.value)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(BatchItemError, match="notes.txt"):
        run_batch([scenes[0], tmp_path / "notes.txt"], tmp_path / "out", workers=0)
    assert not (tmp_path / "out").exists()             # refused before anything ran
    with pytest.raises(BatchItemError, match="without manifest.json or capture.toml"):
        classify_item(tmp_path)
    bad = tmp_path / "scene.toml"
    bad.write_text('[mesh]\npath = "nope.ply"\n')
    from rig.estimate.batch import content_sha256
    with pytest.raises(BatchItemError, match="mesh.path"):
        content_sha256(classify_item(bad))
    from rig.cli import main
    assert main(["estimate", "batch", str(tmp_path / "missing"), "--workers", "0", "--out", str(tmp_path)]) == 2


def test_kinds(tmp_path: Path) -> None:
    data = Path(__file__).resolve().parents[1] / "data"
    assert classify_item(data / "relief_skin1").kind == "capture"
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "manifest.json").write_text("{}")
    assert classify_item(tmp_path / "s").kind == "session"
    with pytest.raises(BatchItemError, match="capture folder, not its capture.toml"):
        classify_item(data / "relief_skin1" / "capture.toml")


def test_longest_expected_first_order_and_its_makespan(tmp_path: Path) -> None:
    """Items go longest-expected-first (rig.estimate.batch.expected_cost): an earlier run's recorded CPU seconds
    beat any static estimate, then a scene's pixels x spp x renders, then input bytes; ties keep the given order.
    The greedy list schedule of 2 workers is what the docs' makespans are computed with (Graham's LPT example)."""
    from rig.estimate.batch import BatchItem, expected_cost, list_schedule_makespan, submission_order

    def scene(name: str, w: int, h: int, extra: str = "") -> BatchItem:
        f = tmp_path / f"{name}.toml"
        f.write_text(f"version = 1\n[camera]\nwidth_px = {w}\nheight_px = {h}\n{extra}")
        return BatchItem(f, "scene", name)

    opts = {"model": "mc-table+reference", "method": None, "reference_spp": None, "reference_iterations": None,
            "reference_seed": None}
    import struct
    for name, colour_type in (("grey.png", 0), ("rgb.png", 2)):    # a PNG header: signature, IHDR, colour type
        (tmp_path / name).write_bytes(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR"
                                      + struct.pack(">IIBB", 48, 48, 8, colour_type) + b"\0\0\0")
    grey = '[image]\npath = "grey.png"\n'
    small, big = scene("small", 48, 48, grey), scene("big", 64, 64, grey)
    own = scene("own", 48, 48, grey + "[estimation]\nreference_spp = 512\nreference_iterations = 2\n")
    rgb = scene("rgb", 48, 48, '[image]\npath = "rgb.png"\n')
    assert expected_cost(big, opts) == (1, 64 * 64 * 128 * 4)          # the scene-file defaults: 128 spp, 4 renders
    assert expected_cost(own, opts) == (1, 48 * 48 * 512 * 2)          # the scene's own [estimation]
    assert expected_cost(own, {**opts, "reference_spp": 8, "reference_iterations": 1}) == (1, 48 * 48 * 8)
    assert expected_cost(rgb, opts) == (1, 3 * 48 * 48 * 128 * 4)      # three channels: three times the paths
    assert expected_cost(scene("noimage", 48, 48), opts) == expected_cost(rgb, opts)   # unknown: 3 channels
    assert expected_cost(small, {**opts, "model": "mc-table"}) == (1, 48 * 48)   # no reference: pixels
    assert expected_cost(small, opts, {"cpu_seconds": 3.5}) == (2, 3.5)        # measured before: first
    folder = tmp_path / "cap"
    folder.mkdir()
    (folder / "capture.toml").write_bytes(b"x" * 100)
    assert expected_cost(BatchItem(folder, "capture", "cap"), opts) == (0, 100.0)
    costs = [expected_cost(i, opts) for i in (small, big, own)] + [(1, 48 * 48 * 128 * 4)]
    assert submission_order(costs) == [2, 1, 0, 3]                     # own > big > small == the 4th (stable)
    assert list_schedule_makespan([3, 3, 2, 2, 2], 2) == 7 and list_schedule_makespan([2, 2, 2, 3, 3], 2) == 7
    assert list_schedule_makespan([1, 1, 1, 1, 4], 2) == 6 and list_schedule_makespan([4, 1, 1, 1, 1], 2) == 4
    with pytest.raises(ValueError, match="workers"):
        list_schedule_makespan([1.0], 0)
