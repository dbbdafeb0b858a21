"""``rig estimate batch ITEMS...``: many estimates at once, on dask.distributed (docs/scale-out.md).

An item is what the single estimate commands take today:

- a **session folder** (``manifest.json``; ``rig estimate session``: :func:`rig.estimate.sessions.estimate_session`),
- a **scene file** (a ``.toml`` scene; ``rig estimate single-image``: :func:`rig.estimate.scenes.estimate_scene`),
- a **capture folder** (``capture.toml``; ``rig estimate gradients``: :func:`rig.estimate.capture_folder.estimate_capture`).

Each item is one Dask task (:func:`run_item`), run on a :class:`distributed.LocalCluster` of ``workers`` processes
with one thread each (:func:`local_cluster`), or on any scheduler given by address, or in this process
(``workers=0``: the serial run). Every random number of a Monte Carlo render is keyed by (seed, channel, pixel,
sample) (:mod:`simulators.mc.rng`), the seeds come from the item's options, never from the worker or the schedule,
and workers run with one numba/BLAS thread: a batch gives the same numbers on 1, 2 or 200 workers as the serial
run (:func:`result_digest` compares them without the timings).

Outputs: ``OUT/<key>/`` per item (``key`` = a readable name + 8 hex of the item's absolute path), holding
``result.json`` (the estimate's JSON; capture folders also their ``maps/``), every file written by the project's
atomic writer (:mod:`drivers.atomic`), and last ``done.json``, the marker that commits the item: the item's content
SHA-256 (:func:`content_sha256`: the scene file and the files it names; every input file of a folder), its options,
the result's digest, seconds and worker. An item folder without a matching marker is incomplete: it is cleared and
redone. A re-run skips every item whose marker matches its content and options. ``OUT/batch.json`` lists the
run's items and their status.

A worker that dies mid-batch (killed, out of memory, a lost node) takes its running task with it; the scheduler
re-runs the task elsewhere (Dask's ``distributed.scheduler.allowed-failures``, default 3) and, since the item
folder is only committed by its marker, nothing half-written survives.

Order: the items are submitted longest-expected-first (:func:`expected_cost`: the CPU seconds an earlier run of the
item recorded in its marker, else pixels x channels x spp x renders of a scene reference, else the input's bytes),
each with Dask ``priority`` by that rank, so an item known to be long does not start last and run alone (list
scheduling's longest-processing-time rule, Graham 1969: makespan within 4/3 - 1/(3W) of the optimum with the true
costs; :func:`list_schedule_makespan`). On a first run the static estimate cannot see what the estimate will do (a
scene whose reference loop ends in the ridge line search costs ~15x one that converges, at the same pixels and spp);
render chunks then spread a late long item over the idle workers. The order changes when items run, never their
numbers.

Render chunks (``render_chunk_rows``, CLI ``--render-chunk-rows``): inside an item, each Monte Carlo reference
render of a scene file is split into chunks of rows, each a task on the cluster (:func:`rig.estimate.batch_chunks.chunked_render`); every pixel
keeps its random stream, so the numbers do not change. By default (None) on a cluster whose workers advertise the
item resource (:func:`item_restrictions`) with two or more item slots: :data:`AUTO_CHUNKS_PER_SLOT` chunks per
item slot, at most :data:`AUTO_MAX_CHUNKS`, at least :data:`AUTO_MIN_CHUNK_ROWS` rows each (so the long item that
runs last spreads its renders over the workers the others left idle), only for renders expected to take at least
:data:`AUTO_MIN_CHUNKED_RENDER_S` (:class:`RenderChunks`); independent renders a reference announces (the ridge line
search's, :meth:`rig.estimate.reference.mc_reference.MonteCarloReference.prefetch`) go out as one wave of chunks;
else whole renders. 0: whole renders; > 0: every render in chunks of that many rows. The gradient reference of
capture folders and the session estimates are not chunked (one task per item).
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import shutil
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Literal, Sequence

from drivers.atomic import fsync_dir
from drivers.errors import ConfigError
from rig.estimate.batch_chunks import AUTO_CHUNKS_PER_SLOT, AUTO_MAX_CHUNKS, AUTO_MIN_CHUNK_ROWS, RenderChunks
from rig.files.provenance import json_default, write_json

__all__ = ["BatchItem", "BatchOptions", "BatchReport", "classify_item", "content_sha256", "result_digest",
           "expected_cost", "submission_order", "list_schedule_makespan", "run_item", "run_batch", "local_cluster",
           "item_slots", "item_restrictions", "as_completed_in_slots", "WORKER_ENV", "ITEM_RESOURCE", "DONE_FILE",
           "RESULT_FILE"]

ItemKind = Literal["session", "scene", "capture"]
DONE_FILE = "done.json"
RESULT_FILE = "result.json"
BATCH_FILE = "batch.json"
MARKER_FORMAT = "sssrig-batch-item"
#: environment of each local worker process: one thread for numba's prange and for BLAS (a worker is one core)
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}
#: Dask settings of the local workers: no MALLOC_TRIM_THRESHOLD_ (the nanny's default 65536 returns freed memory to
#: the system at once: measured on a zoo scene's reference estimate in a worker, 25x the page faults and 10x the
#: system time of the same estimate in a plain process), no statistical profiler (it samples every thread's stack
#: every 10 ms), and WORKER_ENV in the pre-spawn environment: the nanny's ``env`` is applied only after the worker
#: process has imported numpy, whose OpenBLAS then keeps a second thread spinning (measured in a 1-worker cluster:
#: 4.9 CPU s of a blas_thread_server thread beside 11.2 s of the task's, found with gdb; after: 11.1 CPU s in 10.9 s)
NANNY_CONFIG = {"distributed.nanny.pre-spawn-environ": dict(WORKER_ENV), "distributed.worker.profile.enabled": False}
#: result keys that differ between two runs of the same inputs (timings, timestamps, where outputs were written)
_VOLATILE = re.compile(r"seconds|^created$|^paths_per_s$|^out_dir$|^files$|^elapsed")
#: output files whose bytes are part of an item's digest (the maps; sidecars and previews hold paths and times)
_DIGEST_SUFFIXES = (".exr", ".tif", ".tiff", ".npy")
#: folders inside an input folder that earlier estimates wrote (not inputs: left out of the content hash)
_OUTPUT_DIRS = {"session": ("estimates", "report"), "capture": ("maps",)}
_HASH_CHUNK = 1 << 20
#: Dask worker resource held by each running item (:func:`local_cluster` gives every worker one per thread): an item
#: waiting on its render chunks secedes from its thread slot (``batch_chunks._leave_worker_slot``) but keeps its
#: resources until
#: it ends (distributed's worker state machine releases them only when the task finishes, the scheduler alike), so the
#: freed slot runs chunks, never a second item: a one-thread worker stays one core. Render chunks carry none.
ITEM_RESOURCE = "item"
#: threads hashing the items' inputs on the calling machine (SHA-256 ran at ~450 MB/s per core here)
HASH_THREADS = 8


class BatchItemError(ConfigError):
    """A batch item that is not a session folder, a capture folder or a scene file (names the item)."""


@dataclass(frozen=True)
class BatchItem:
    """One input of a batch: its absolute ``path``, ``kind`` and output folder name ``key``."""

    path: Path
    kind: ItemKind
    key: str


@dataclass(frozen=True)
class BatchOptions:
    """Options of every item, as the single commands take them (None: the item's own or the command's default).

    Scene files: ``model``, ``method``, ``reference_spp``, ``reference_iterations``, ``reference_seed``
    (``rig estimate single-image``). Capture folders: ``reference`` (the Monte Carlo corrected sphere summary) with
    the same ``reference_*`` values, ``maps_format`` (``rig estimate gradients``). Sessions: ``calibration``."""

    model: str | None = None
    method: str | None = None
    reference_spp: int | None = None
    reference_iterations: int | None = None
    reference_seed: int | None = None
    reference: bool = False
    maps_format: str = "exr"
    calibration: str | None = None
    #: > 0: each Monte Carlo reference render of a scene split into chunks of this many rows across the workers; 0:
    #: whole renders; None: chosen from the cluster (module docstring). Bit-identical to whole renders, so not part
    #: of :meth:`for_kind` nor of the done-marker's options
    render_chunk_rows: int | None = None

    def for_kind(self, kind: ItemKind) -> dict[str, Any]:
        """The options that reach an item of this kind (what the done-marker records and compares)."""
        ref = {"spp": self.reference_spp, "iterations": self.reference_iterations, "seed": self.reference_seed}
        if kind == "scene":
            return {"model": self.model, "method": self.method, **{f"reference_{k}": v for k, v in ref.items()}}
        if kind == "capture":
            return {"format": self.maps_format, "reference": ref if self.reference else None}
        return {"calibration": None if self.calibration is None else str(Path(self.calibration).resolve())}


@dataclass
class BatchReport:
    """What :func:`run_batch` did: one record per item (status "done", "skipped" or "failed"), seconds."""

    out_dir: Path
    records: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    workers: int | str = 0

    @property
    def ok(self) -> bool:
        return all(r["status"] != "failed" for r in self.records)

    def count(self, status: str) -> int:
        return sum(1 for r in self.records if r["status"] == status)

    def to_dict(self) -> dict[str, Any]:
        return {"out_dir": str(self.out_dir), "workers": self.workers, "seconds": self.seconds, "ok": self.ok,
                "done": self.count("done"), "skipped": self.count("skipped"), "failed": self.count("failed"),
                "items": self.records}


# ------------------------------------------------------------------------------------------------ items
def classify_item(path: str | os.PathLike[str]) -> BatchItem:
    """The kind of an item path; :class:`BatchItemError` naming the item if it is none of the three."""
    p = Path(path).expanduser()
    expected = ("a session folder (manifest.json), a capture folder (capture.toml) or a scene file (.toml); "
                "docs/scale-out.md")
    if not p.exists():
        raise BatchItemError(str(p), "ITEMS", expected, "no such file or folder")
    p = p.resolve()
    if p.is_dir():
        if (p / "manifest.json").is_file():
            kind: ItemKind = "session"
        elif (p / "capture.toml").is_file():
            kind = "capture"
        else:
            raise BatchItemError(str(p), "ITEMS", expected, "a folder without manifest.json or capture.toml")
        name = p.name
    elif p.suffix.lower() == ".toml":
        if p.name == "capture.toml":
            raise BatchItemError(str(p), "ITEMS", expected + " (give the capture folder, not its capture.toml)",
                                 p.name)
        kind = "scene"
        name = f"{p.parent.name}_{p.stem}"
    else:
        raise BatchItemError(str(p), "ITEMS", expected, f"a {p.suffix or 'suffix-less'} file")
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "item"
    return BatchItem(p, kind, f"{safe[:60]}-{hashlib.sha256(str(p).encode()).hexdigest()[:8]}")


def _hash_file(h: Any, path: Path, label: str) -> None:
    h.update(f"{label}\0{path.stat().st_size}\0".encode())
    with open(path, "rb") as fh:
        while chunk := fh.read(_HASH_CHUNK):
            h.update(chunk)


def _scene_paths(doc: Any, where: str = "") -> Iterable[tuple[str, str]]:
    """(TOML key, path string) of every ``path`` / ``*_path`` key of a scene document."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            key = f"{where}.{k}" if where else k
            if isinstance(v, str) and (k == "path" or k.endswith("_path")):
                yield key, v
            else:
                yield from _scene_paths(v, key)
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _scene_paths(v, f"{where}[{i}]")


def content_sha256(item: BatchItem) -> str:
    """SHA-256 of everything an item's estimate reads: a scene file's bytes and every file its ``path`` keys name
    (relative to the scene file, as :mod:`rig.files.scene_file` resolves them); every file of a folder except hidden
    ones and the outputs earlier estimates wrote there (``estimates/``, ``report/``; ``maps/``). Raises
    :class:`BatchItemError` naming the key of a scene's missing file."""
    h = hashlib.sha256(f"{item.kind}\0".encode())
    if item.kind == "scene":
        _hash_file(h, item.path, item.path.name)
        try:
            doc = tomllib.loads(item.path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise BatchItemError(str(item.path), "ITEMS", "a scene file in TOML", f"unreadable ({exc})") from None
        for key, text in sorted(_scene_paths(doc)):
            f = Path(text).expanduser()
            f = f if f.is_absolute() else item.path.parent / f
            if not f.is_file():
                raise BatchItemError(str(item.path), key, "an existing file", text)
            _hash_file(h, f, key)
        return h.hexdigest()
    skip = _OUTPUT_DIRS[item.kind]
    files = sorted(f for f in item.path.rglob("*") if f.is_file()
                   and not any(part.startswith(".") for part in f.relative_to(item.path).parts)
                   and f.relative_to(item.path).parts[0] not in skip)
    for f in files:
        _hash_file(h, f, f.relative_to(item.path).as_posix())
    return h.hexdigest()


def _options_sha256(options: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(options, sort_keys=True).encode()).hexdigest()


def _strip_volatile(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _strip_volatile(v) for k, v in o.items() if not _VOLATILE.search(str(k))}
    if isinstance(o, list):
        return [_strip_volatile(v) for v in o]
    return o


def result_digest(result: dict[str, Any], files: Sequence[Path] = ()) -> str:
    """SHA-256 of a result without its volatile keys (timings, timestamps, output paths: ``_VOLATILE``) and of the
    bytes of ``files``: equal digests are bit-identical estimates (every float printed with repr precision)."""
    h = hashlib.sha256(json.dumps(_strip_volatile(result), sort_keys=True, default=json_default).encode())
    for f in sorted(files, key=lambda p: p.name):
        _hash_file(h, f, f.name)
    return h.hexdigest()


def _read_marker(folder: Path) -> dict[str, Any] | None:
    try:
        m = json.loads((folder / DONE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) and m.get("format") == MARKER_FORMAT else None


def _finished(folder: Path, sha: str, options: dict[str, Any]) -> dict[str, Any] | None:
    """The item's marker if it records this content and these options (and its result file is there)."""
    m = _read_marker(folder)
    if m and m.get("content_sha256") == sha and m.get("options_sha256") == _options_sha256(options) \
            and (folder / RESULT_FILE).is_file():
        return m
    return None


# ------------------------------------------------------------------------------------------------ order
#: the scene references' defaults when neither the options nor the scene file set them (rig.files.scene_file)
_SCENE_DEFAULT_SPP, _SCENE_DEFAULT_ITERATIONS = 128, 4


def exr_channel_count(path: Path) -> int | None:
    """The number of channels an OpenEXR file's header lists (its ``channels`` attribute, a ``chlist``; OpenEXR
    file layout: magic, version, then attributes name\\0 type\\0 int32 size, data); None when it is not a readable
    EXR. Reads the header only."""
    import struct

    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return None
    if head[:4] != b"\x76\x2f\x31\x01":
        return None
    i = 8
    while i < len(head) and head[i] != 0:
        j = head.index(b"\0", i)
        name = head[i:j]
        k = head.index(b"\0", j + 1)
        kind = head[j + 1:k]
        (size,) = struct.unpack_from("<i", head, k + 1)
        data = head[k + 5:k + 5 + size]
        if name == b"channels" and kind == b"chlist":
            n, pos = 0, 0
            while pos < len(data) and data[pos] != 0:
                pos = data.index(b"\0", pos) + 1 + 16     # name, then pixel type, pLinear + 3 reserved, x/y sampling
                n += 1
            return n
        i = k + 5 + size
    return None


def image_channel_count(path: Path) -> int | None:
    """Colour channels of an image from its header alone: OpenEXR (:func:`exr_channel_count`) or PNG (the IHDR
    colour type: grey 1, RGB 3, palette 3, grey + alpha 1, RGBA 3; alpha is not a colour channel); None otherwise."""
    n = exr_channel_count(path)
    if n is not None:
        return n
    try:
        with open(path, "rb") as fh:
            head = fh.read(32)
    except OSError:
        return None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 26:
        return {0: 1, 2: 3, 3: 3, 4: 1, 6: 3}.get(head[25])
    return None


def _scene_work(path: Path, options: dict[str, Any]) -> float | None:
    """pixels x channels x spp x renders of a scene file's Monte Carlo reference (None: unreadable). Channels from
    the image's header (EXR, PNG; 3 otherwise); without a reference model pixels x channels."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
        cam = doc.get("camera", {})
        pixels = int(cam["width_px"]) * int(cam["height_px"])
    except (OSError, ValueError, KeyError, TypeError, tomllib.TOMLDecodeError):
        return None
    img = doc.get("image", {}) if isinstance(doc.get("image"), dict) else {}
    channels = 3
    if isinstance(img.get("path"), str):
        f = Path(img["path"]).expanduser()
        channels = image_channel_count(f if f.is_absolute() else path.parent / f) or 3
    pixels *= channels
    est = doc.get("estimation", {}) if isinstance(doc.get("estimation"), dict) else {}
    mat = doc.get("material", {}) if isinstance(doc.get("material"), dict) else {}
    model = options.get("model") or mat.get("model") or ""
    if "reference" not in str(model):
        return float(pixels)
    spp = options.get("reference_spp") or est.get("reference_spp") or _SCENE_DEFAULT_SPP
    renders = options.get("reference_iterations") or est.get("reference_iterations") or _SCENE_DEFAULT_ITERATIONS
    return float(pixels) * float(spp) * float(renders)


def expected_cost(item: BatchItem, options: dict[str, Any], previous: dict[str, Any] | None = None) -> tuple[int, float]:
    """The expected cost of an item, for the submission order only (never for its numbers): ``(tier, value)``,
    compared as a tuple, larger first. Tier 2: ``previous`` (an earlier run's done-marker of the item, whatever its
    content or options) recorded its CPU seconds. Tier 1: a scene file's pixels x channels x reference spp x
    reference renders (options, else the scene's ``[estimation]``, else the defaults; the renderer traces every
    channel's paths). Tier 0: the bytes of the item's inputs (capture
    and session folders; a scene without a readable camera). Units differ between tiers: an item measured before
    goes first, then the scenes by their render work, then the rest by size."""
    if previous is not None:
        cpu = previous.get("cpu_seconds", previous.get("seconds"))
        if isinstance(cpu, (int, float)) and cpu > 0:
            return 2, float(cpu)
    if item.kind == "scene":
        work = _scene_work(item.path, options)
        if work is not None:
            return 1, work
        return 0, float(item.path.stat().st_size)
    size = sum(f.stat().st_size for f in item.path.rglob("*") if f.is_file())
    return 0, float(size)


def submission_order(costs: Sequence[tuple[int, float]]) -> list[int]:
    """Indices of ``costs`` largest first; ties keep the given order (stable)."""
    return sorted(range(len(costs)), key=lambda i: (-costs[i][0], -costs[i][1], i))


def list_schedule_makespan(seconds: Sequence[float], workers: int) -> float:
    """The makespan of items of these durations taken in this order by ``workers`` identical workers, each item
    going to the first worker free (greedy list scheduling; Graham 1966/1969). With ``seconds`` sorted longest
    first it is the LPT schedule. Scheduling overhead is not modelled."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1; got {workers}")
    free = [0.0] * int(workers)
    for s in seconds:
        i = min(range(len(free)), key=free.__getitem__)
        free[i] += float(s)
    return max(free)


# ------------------------------------------------------------------------------------------------ one item
def _estimate(item: BatchItem, options: dict[str, Any], folder: Path) -> tuple[dict[str, Any], list[Path]]:
    """Run the item's estimator with outputs in ``folder``; (JSON result, output files that enter the digest)."""
    if item.kind == "scene":
        from rig.estimate.scenes import estimate_scene
        from rig.files.scene_file import load_scene
        o = options
        return estimate_scene(load_scene(item.path), model=o["model"], method=o["method"],
                              reference_spp=o["reference_spp"], reference_iterations=o["reference_iterations"],
                              reference_seed=o["reference_seed"]), []
    if item.kind == "capture":
        from rig.estimate.capture_folder import estimate_capture, load_capture
        ref = options["reference"]
        ref = None if ref is None else {k: v for k, v in ref.items() if v is not None}
        maps = folder / "maps"
        summary = estimate_capture(load_capture(item.path), maps, options["format"],
                                   reference=ref)
        return summary, [f for f in maps.iterdir() if f.suffix.lower() in _DIGEST_SUFFIXES]
    from rig.estimate.sessions import estimate_session
    return estimate_session(item.path, calibration=options["calibration"]), []


def run_item(item: BatchItem, options: dict[str, Any], out_dir: str | os.PathLike[str], sha: str,
             chunk_rows: int = 0, chunks: int = 0) -> dict[str, Any]:
    """The task of one item (runs on a worker, or in this process for the serial run): clear ``OUT/<key>``, run
    the estimate, write ``result.json`` and then ``done.json`` atomically; return the marker's record.
    ``chunk_rows`` > 0: the scene references' Monte Carlo renders in chunks of that many rows across the cluster,
    else with ``chunks`` > 0 in that many chunks where a render is long (:class:`RenderChunks`; the same numbers).
    Exceptions of the estimate propagate (the batch reports the item failed; Dask does not retry them)."""
    from rig.estimate.reference.mc_reference import render_with
    from rig.files.session import software_version

    t0, c0, started = time.perf_counter(), time.process_time(), time.time()
    folder = Path(out_dir) / item.key
    if folder.exists():     # a killed earlier attempt or an item whose inputs changed: start clean
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    with render_with(RenderChunks(chunks, chunk_rows) if chunk_rows > 0 or chunks > 0 else None):
        result, files = _estimate(item, options, folder)
    write_json(folder / RESULT_FILE, result)
    record = {"format": MARKER_FORMAT, "format_version": 1, "key": item.key, "kind": item.kind,
              "item": str(item.path), "content_sha256": sha, "options": options,
              "options_sha256": _options_sha256(options), "digest": result_digest(result, files),
              "success": bool(result.get("success", True)) if isinstance(result, dict) else True,
              "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
              "worker_pid": os.getpid(), "host": os.uname().nodename, "software_version": software_version(),
              "started_unix_s": started, "finished_unix_s": time.time(),
              "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    write_json(folder / DONE_FILE, record)
    fsync_dir(folder.parent)
    return record


# ------------------------------------------------------------------------------------------------ the batch
_SPAWN = {"running": 0, "saved": {}}


@functools.lru_cache(maxsize=1)
def _environ_keeping_nanny() -> type:
    """A :class:`distributed.Nanny` that puts the calling process's environment back after spawning its worker:
    distributed's nanny sets ``distributed.nanny.pre-spawn-environ`` (:data:`NANNY_CONFIG`: :data:`WORKER_ENV`, and
    PYTHONHASHSEED) in ``os.environ`` of the process that runs it -- the caller's, for a LocalCluster -- and leaves it
    there, so after a batch the caller's numba and BLAS started with one thread (found by the test suite: a later
    test of that process could not set NUMBA_NUM_THREADS to 2). Nannies start concurrently on one event loop: the
    environment is saved when the first spawn begins and restored when the last one ends."""
    from distributed import Nanny

    class EnvironKeepingNanny(Nanny):
        async def instantiate(self) -> Any:
            if _SPAWN["running"] == 0:
                _SPAWN["saved"] = {k: os.environ.get(k) for k in self.pre_spawn_env}
            _SPAWN["running"] += 1
            try:
                return await super().instantiate()
            finally:
                _SPAWN["running"] -= 1
                if _SPAWN["running"] == 0:
                    for k, v in _SPAWN["saved"].items():
                        if v is None:
                            os.environ.pop(k, None)
                        else:
                            os.environ[k] = v

    return EnvironKeepingNanny


def local_cluster(workers: int, **kw: Any) -> Any:
    """A :class:`distributed.LocalCluster` of ``workers`` processes, one thread each, :data:`WORKER_ENV` set in
    every worker (restarted workers too: the nanny spawns them with it) and not left in this process
    (:func:`_environ_keeping_nanny`), one :data:`ITEM_RESOURCE` per worker (one
    item at a time, its render chunks beside it), the scheduler's HTTP server (dashboard) on a free port unless
    ``dashboard_address`` is given: distributed starts it even for ``dashboard_address=None``, on the default port
    8787, and a second cluster on the machine (a batch beside another) then warned "Port 8787 is already in use"."""
    from distributed import LocalCluster

    if workers < 1:
        raise ValueError(f"workers must be >= 1 for a LocalCluster; got {workers}")
    import dask

    kw.setdefault("dashboard_address", ":0")
    with dask.config.set(NANNY_CONFIG):  # read by each Nanny when it is made (here), kept for its restarts
        return LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                            worker_class=kw.pop("worker_class", _environ_keeping_nanny()),
                            env={**WORKER_ENV, **kw.pop("env", {})}, silence_logs=kw.pop("silence_logs", 40),
                            resources=kw.pop("resources", {ITEM_RESOURCE: 1}), **kw)


def item_slots(client: Any) -> int:
    """How many items the cluster's workers run at once: the sum of the :data:`ITEM_RESOURCE` they advertise."""
    try:        # n_workers=-1: every worker, asked explicitly
        info = client.scheduler_info(n_workers=-1)
    except TypeError:   # a distributed without the argument (it lists them all)
        info = client.scheduler_info()
    workers = info.get("workers", {}).values()
    return int(sum(float((w.get("resources") or {}).get(ITEM_RESOURCE, 0)) for w in workers))


def item_restrictions(client: Any) -> dict[str, Any]:
    """The ``client.submit`` keywords of an item task: ``resources={ITEM_RESOURCE: 1}`` when a worker of the
    cluster advertises :data:`ITEM_RESOURCE` (:func:`local_cluster`'s do; on a cluster of one's own: ``dask worker
    ... --resources item=THREADS``), so a worker runs as many items at once as it has of it; else none (any
    scheduler without the resource still runs the batch: then an item waiting on its render chunks frees its
    thread for the next item too, and a worker can run more items than it has threads)."""
    return {"resources": {ITEM_RESOURCE: 1}} if item_slots(client) >= 1 else {}


def as_completed_in_slots(client: Any, submit: Callable[[int], Any], n: int, limited: bool
                          ) -> Iterable[tuple[int, Any]]:
    """``submit(0)``, ..., ``submit(n - 1)`` in that order, yielding (i, future) as each completes. ``limited``
    (items restricted to :data:`ITEM_RESOURCE`): at most :func:`item_slots` (re-read as items end: workers come and
    go; at least 1) submitted and not yet completed. Why: the scheduler hands resource-restricted tasks to a worker
    at once (they are not queued), and it queues unrestricted tasks, such as render chunks, while a worker has
    ``worker-saturation`` x threads tasks processing that have not seceded; items waiting for the item resource
    count there, so with every item submitted at once the chunks of the running item stayed queued for good
    (measured: a 1-worker batch of 8 items hung with 7 items constrained on the worker, 2 chunks queued)."""
    from distributed import as_completed

    done = as_completed()
    nxt = in_flight = 0

    def fill() -> None:
        nonlocal nxt, in_flight
        cap = max(1, item_slots(client)) if limited else n
        while nxt < n and in_flight < cap:
            fut = submit(nxt)
            index[fut.key] = nxt
            done.add(fut)
            nxt += 1
            in_flight += 1

    index: dict[Any, int] = {}
    fill()
    for fut in done:
        in_flight -= 1
        yield index[fut.key], fut
        fill()


def _progress_bar(total: int, enabled: bool) -> Any:
    if not enabled or total == 0:
        return None
    from tqdm import tqdm
    return tqdm(total=total, file=sys.stderr, unit="item", desc="rig estimate batch", leave=False,
                disable=not sys.stderr.isatty())


def run_batch(items: Sequence[str | os.PathLike[str]], out_dir: str | os.PathLike[str], *,
              options: BatchOptions | None = None, workers: int = 2, scheduler: str | None = None,
              client: Any = None, say: Callable[[str], None] | None = None, progress: bool = True) -> BatchReport:
    """Estimate every item into ``out_dir`` (module docstring); return the :class:`BatchReport`.

    Where: ``client`` (a connected :class:`distributed.Client`), else ``scheduler`` (an address), else a
    :func:`local_cluster` of ``workers`` (``workers=0``: this process, one item after another). Items are checked
    (kind, content hash) before anything runs: a bad item raises :class:`BatchItemError` naming it. Items whose
    done-marker matches their content and options are skipped. ``say`` gets one line per item as it finishes."""
    say = say or (lambda m: None)
    opts = options or BatchOptions()
    out = Path(out_dir).expanduser().resolve()
    t0 = time.perf_counter()
    resolved = [classify_item(p) for p in items]
    seen: dict[str, BatchItem] = {}
    for it in resolved:
        if it.key in seen:
            raise BatchItemError(str(it.path), "ITEMS", "each item once", "given twice")
        seen[it.key] = it
    # hashing reads every input byte on this machine; hashlib releases the GIL, so threads overlap reads and hashing
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(max_workers=min(HASH_THREADS, max(1, len(resolved)))) as pool:
        shas = dict(zip((it.key for it in resolved), pool.map(content_sha256, resolved)))
    report = BatchReport(out, workers=scheduler or (getattr(client, "scheduler", None) and "client") or workers)
    todo: list[BatchItem] = []
    for it in resolved:
        m = _finished(out / it.key, shas[it.key], opts.for_kind(it.kind))
        if m is None:
            todo.append(it)
        else:
            report.records.append({**m, "status": "skipped"})
            say(f"{it.key}: skipped (done, same content {shas[it.key][:12]} and options)")
    out.mkdir(parents=True, exist_ok=True)
    bar = _progress_bar(len(todo), progress)

    def finished(it: BatchItem, rec: dict[str, Any] | None, exc: BaseException | None) -> None:
        if exc is None and rec is not None:
            report.records.append({**rec, "status": "done"})
            say(f"{it.key}: done in {rec['seconds']:.1f} s (digest {rec['digest'][:12]})")
        else:
            msg = f"{type(exc).__name__}: {exc}"
            report.records.append({"key": it.key, "kind": it.kind, "item": str(it.path), "status": "failed",
                                   "content_sha256": shas[it.key], "error": msg})
            say(f"{it.key}: FAILED: {msg}")
        if bar is not None:
            bar.update(1)

    try:
        if todo and client is None and scheduler is None and workers == 0:
            from threadpoolctl import threadpool_limits

            # one BLAS thread, as in the workers (WORKER_ENV): a reduction's order, hence its last bits, depends on it
            with threadpool_limits(limits=1):
                for it in todo:
                    try:
                        rec = run_item(it, opts.for_kind(it.kind), out, shas[it.key], opts.render_chunk_rows or 0)
                    except Exception as exc:  # noqa: BLE001 - one failed item does not stop the batch
                        finished(it, None, exc)
                    else:
                        finished(it, rec, None)
        elif todo:
            _run_distributed(todo, opts, out, shas, client, scheduler, workers, finished, say)
    finally:
        if bar is not None:
            bar.close()
    order = {it.key: i for i, it in enumerate(resolved)}
    report.records.sort(key=lambda r: order[r["key"]])
    report.seconds = time.perf_counter() - t0
    write_json(out / BATCH_FILE, report.to_dict())
    return report


def _run_distributed(todo: list[BatchItem], opts: BatchOptions, out: Path, shas: dict[str, str], client: Any,
                     scheduler: str | None, workers: int, finished: Callable[..., None],
                     say: Callable[[str], None]) -> None:
    from distributed import Client

    own_cluster = own_client = None
    try:
        if client is None:
            if scheduler is not None:
                own_client = client = Client(scheduler)
            else:
                say(f"starting a local Dask cluster: {workers} worker processes, 1 thread each")
                own_cluster = local_cluster(workers)
                own_client = client = Client(own_cluster)
        # longest expected first (module docstring): submitted in that order and with Dask priorities by rank
        costs = [expected_cost(it, opts.for_kind(it.kind), _read_marker(out / it.key)) for it in todo]
        order = submission_order(costs)
        slots, restrict = item_slots(client), item_restrictions(client)
        rows = opts.render_chunk_rows
        chunks = min(AUTO_MAX_CHUNKS, AUTO_CHUNKS_PER_SLOT * slots) if rows is None and slots >= 2 else 0
        if rows is None:
            say(f"render chunks: {f'{chunks} per render (of >= {AUTO_MIN_CHUNK_ROWS} rows)' if chunks else 'none'} "
                f"({slots} item slots)")

        def submit(rank: int) -> Any:
            it = todo[order[rank]]
            return client.submit(run_item, it, opts.for_kind(it.kind), str(out), shas[it.key], rows or 0, chunks,
                                 key=f"rig-batch-{it.key}-{shas[it.key][:12]}", pure=False,
                                 priority=len(order) - rank, **restrict)

        for rank, fut in as_completed_in_slots(client, submit, len(order), bool(restrict)):
            it = todo[order[rank]]
            try:
                rec = fut.result()
            except Exception as exc:  # noqa: BLE001 - the task's own error (or too many worker deaths)
                finished(it, None, exc)
            else:
                finished(it, rec, None)
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()


def format_report(report: BatchReport) -> str:
    """One line per item and the totals."""
    lines = [f"{'item':<48} {'kind':<8} {'status':<8} {'seconds':>8}  digest"]
    for r in report.records:
        secs = f"{r['seconds']:.1f}" if "seconds" in r else "-"
        tail = r.get("digest", "")[:16] if r["status"] != "failed" else r.get("error", "")
        lines.append(f"{r['key']:<48} {r['kind']:<8} {r['status']:<8} {secs:>8}  {tail}")
    lines.append(f"{report.count('done')} done, {report.count('skipped')} skipped, {report.count('failed')} failed "
                 f"in {report.seconds:.1f} s ({report.workers} workers) -> {report.out_dir}")
    return "\n".join(lines)


def run_cli(args: Any) -> int:
    """``rig estimate batch ITEMS... [--workers N | --scheduler ADDRESS] [--out DIR] [options]``: exit 0 when
    every item is done or skipped, 1 when an item failed (its reason is in the table and ``batch.json``)."""
    opts = BatchOptions(model=args.model, method=args.method, reference_spp=args.reference_spp,
                        reference_iterations=args.reference_iterations, reference_seed=args.reference_seed,
                        reference=bool(args.reference), maps_format=args.format,
                        calibration=None if args.calibration is None else str(args.calibration),
                        render_chunk_rows=args.render_chunk_rows)
    import logging

    if not getattr(args, "verbose", 0) and getattr(args, "log_level", None) is None:
        logging.getLogger("distributed").setLevel(logging.ERROR)   # the cluster's INFO/WARNING chatter (-v shows it)
    fb = getattr(args, "feedback", None)
    say = fb if fb is not None else (lambda m: print(m, file=sys.stderr, flush=True))
    progress = not (args.no_progress or getattr(args, "quiet", False))
    if fb is not None and progress and sys.stderr.isatty():
        fb.suspend()                     # the items' bar owns the status line
    report = run_batch(args.items, args.out, options=opts, workers=args.workers, scheduler=args.scheduler,
                       say=say, progress=progress)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(format_report(report))
    return 0 if report.ok else 1

