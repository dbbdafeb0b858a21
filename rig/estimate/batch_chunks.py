"""Render chunks of ``rig estimate batch`` (rig/estimate/batch.py, docs/scale-out.md section 2): a scene reference's
Monte Carlo render split into interleaved row chunks, each a task on the Dask cluster the item runs on, put back in
place bit-identically (every pixel keeps its random stream: :func:`simulators.mc.render`'s ``rows``); the automatic
chunks of an item (:class:`RenderChunks`: only renders expected to take long, independent renders as one wave)."""
from __future__ import annotations

import threading
from typing import Any, Sequence

import numpy as np

__all__ = ["CHUNK_PRIORITY", "AUTO_CHUNKS_PER_SLOT", "AUTO_MAX_CHUNKS", "AUTO_MIN_CHUNK_ROWS",
           "AUTO_MIN_CHUNKED_RENDER_S", "AUTO_FIRST_S_PER_SAMPLE", "chunk_row_sets", "chunked_render", "RenderChunks"]

#: Dask priority of render-chunk tasks: above the items' (1..N, longest expected first), so the chunks of a started
#: item run before further items start (an item waiting on its chunks has left its worker slot)
CHUNK_PRIORITY = 1 << 30
#: automatic render chunks (``render_chunk_rows=None``): chunks per render per item slot of the cluster, at most
#: AUTO_MAX_CHUNKS (on a big cluster every running item's renders would otherwise be split into thousands of tasks:
#: each chunk task carries the scene and pays Dask's ~4-30 ms), each of at least AUTO_MIN_CHUNK_ROWS rows
AUTO_CHUNKS_PER_SLOT, AUTO_MAX_CHUNKS, AUTO_MIN_CHUNK_ROWS = 1, 8, 8
#: automatic chunks: a render expected to take less than AUTO_MIN_CHUNKED_RENDER_S runs whole in its item's task
#: (:class:`RenderChunks`), expected = its pixel-samples x the item's last render's seconds per pixel-sample (before the
#: first: AUTO_FIRST_S_PER_SAMPLE, a fast walk's, so only a big first render is split). Measured on the batch
#: benchmark's zoo scenes: the short items' renders take 0.05-0.13 s (2 us per pixel-sample), their chunks then cost
#: more in round trips and in waiting for a chunk behind another item's fit than they save; the long item's 64-spp
#: renders take 2.3-3.0 s (6 us per pixel-sample)
AUTO_MIN_CHUNKED_RENDER_S, AUTO_FIRST_S_PER_SAMPLE = 0.5, 1e-6


def _stack_chunks(parts: Sequence[Any]) -> Any:
    """One :class:`simulators.mc.MCImage` from the images of interleaved row chunks: part k holds the frame's rows
    k, k + n, k + 2n, ... (n = len(parts); :func:`chunk_row_sets`)."""
    from simulators.mc.render import MCImage

    n = len(parts)
    n_paths = [max(1, int(p.mask.sum())) for p in parts]
    w = sum(n_paths)
    h = sum(p.mask.shape[0] for p in parts)

    def put(name: str) -> Any:
        if getattr(parts[0], name) is None:
            return None
        first = getattr(parts[0], name)
        out = np.empty((h,) + first.shape[1:], dtype=first.dtype)
        for k, p in enumerate(parts):
            out[k::n] = getattr(p, name)
        return out

    return MCImage(put("radiance"), put("stderr"), put("mask"), parts[0].spp, parts[0].seed,
                   float(sum(p.seconds for p in parts)),
                   float(sum(p.mean_collisions * n_p for p, n_p in zip(parts, n_paths)) / w),
                   float(sum(p.truncated_fraction * n_p for p, n_p in zip(parts, n_paths)) / w),
                   put("d_log_sigma"), put("d_log_sigma_stderr"))


def chunk_row_sets(height_px: int, chunk_rows: int = 0, chunks: int = 0) -> list[tuple[int, int, int]]:
    """The row sets of a render split into chunks, as :func:`simulators.mc.render` ``rows`` = (k, height_px, n):
    chunk k takes the rows k, k + n, ... (interleaved, so every chunk gets an equal share of the object: measured on
    the zoo's z19 at 64 spp, contiguous quarters of the frame cost 0.2 / 2.1 / 2.2 / 0.2 CPU s, the two middle
    ones carrying the cube). n = ceil(height_px / chunk_rows) for ``chunk_rows`` > 0, else ``chunks`` capped so a
    chunk keeps at least :data:`AUTO_MIN_CHUNK_ROWS` rows."""
    h = int(height_px)
    if chunk_rows > 0:
        n = -(-h // int(chunk_rows))
    elif chunks >= 1:
        n = max(1, min(int(chunks), h // AUTO_MIN_CHUNK_ROWS))
    else:
        raise ValueError(f"chunk_rows or chunks must be >= 1; got {chunk_rows}, {chunks}")
    n = max(1, min(n, h))
    return [(k, h, n) for k in range(n)]


def chunked_render(shape: Any, media: Any, camera: Any, lights: Any, *, chunk_rows: int = 0, chunks: int = 0,
                   **kw: Any) -> Any:
    """:func:`simulators.mc.render` split into interleaved row chunks (:func:`chunk_row_sets`: ``chunk_rows`` rows
    each, or ``chunks`` chunks), each a task on the Dask cluster this task runs on (the calling task leaves its worker
    slot, :func:`_leave_worker_slot`), put back in place. Every pixel keeps its random stream
    (render's ``rows``), so the image is bit-identical to the whole render for any chunking and any number of
    workers. Outside a Dask worker: the chunks one after another."""
    return _renders_in_chunks([(shape, media, camera, lights, kw)], chunk_rows, chunks)[0]


def _renders_in_chunks(calls: Sequence[tuple[Any, Any, Any, Any, dict[str, Any]]], chunk_rows: int = 0,
                       chunks: int = 0) -> list[Any]:
    """The images of several renders ``(shape, media, camera, lights, kw)``, each in row chunks
    (:func:`chunked_render`), every chunk of every render submitted at once (on a Dask worker), then gathered."""
    from simulators.mc import render

    bounds = [chunk_row_sets(int(c[2].height_px), chunk_rows, chunks) for c in calls]
    if all(len(b) == 1 for b in bounds):
        return [render(*c[:4], **c[4]) for c in calls]
    try:
        from distributed import get_client, get_worker
        get_worker()
    except (ImportError, ValueError):
        return [_stack_chunks([render(*c[:4], rows=r, **c[4]) for r in b]) for c, b in zip(calls, bounds)]
    client = get_client()
    _leave_worker_slot()
    # above every item's priority (run_batch gives items 1..N): a started item's chunks run before new items start
    futures = [[client.submit(render, *c[:4], rows=r, pure=False, priority=CHUNK_PRIORITY, **c[4]) for r in b]
               for c, b in zip(calls, bounds)]
    return [_stack_chunks(parts) for parts in client.gather(futures)]


class RenderChunks:
    """The render chunks of one item (:func:`run_item`'s render function): with ``chunk_rows`` > 0 every render in
    chunks of that many rows; else (automatic) each render as ``chunks`` chunks (:func:`chunked_render`) when it is
    expected to take at least :data:`AUTO_MIN_CHUNKED_RENDER_S`, else whole in the item's own task; expected from the
    item's last render (its seconds per pixel-sample x this render's pixel-samples: height x width x spp x media).
    :meth:`many` renders independent renders as one wave. Which renders are split changes when they run, never their
    numbers (a render is bit-identical whole or in chunks)."""

    def __init__(self, chunks: int = 0, chunk_rows: int = 0) -> None:
        self.chunks, self.chunk_rows = int(chunks), int(chunk_rows)
        self.s_per_sample = AUTO_FIRST_S_PER_SAMPLE

    @staticmethod
    def _samples(media: Any, camera: Any, kw: dict[str, Any]) -> float:
        n_media = len(media) if isinstance(media, (list, tuple)) else 1
        return float(camera.height_px) * float(camera.width_px) * float(kw.get("spp", 1)) * n_media

    def _splits(self) -> bool:
        return self.chunk_rows > 0 or self.chunks >= 2

    def __call__(self, shape: Any, media: Any, camera: Any, lights: Any, **kw: Any) -> Any:
        long = self.chunk_rows > 0 or self.s_per_sample * self._samples(media, camera, kw) >= AUTO_MIN_CHUNKED_RENDER_S
        return self.many([(shape, media, camera, lights, kw)], split=long)[0]

    def many(self, calls: Sequence[tuple[Any, Any, Any, Any, dict[str, Any]]], split: bool = True) -> list[Any]:
        """The images of renders ``(shape, media, camera, lights, kw)`` that do not depend on one another (a
        reference's ``prefetch``): with ``split``, every chunk of every one submitted at once (one wave: the workers
        stay busy to the wave's end, not to each render's end); the same images as one by one."""
        from simulators.mc import render

        if split and self._splits():
            imgs = _renders_in_chunks(calls, self.chunk_rows, self.chunks)
        else:
            imgs = [render(*c[:4], **c[4]) for c in calls]
        self.s_per_sample = float(imgs[-1].seconds) / max(1.0, self._samples(*(calls[-1][i] for i in (1, 2, 4))))
        return imgs


_SECEDED = threading.local()


def _leave_worker_slot() -> None:
    """Leave the worker's thread pool for the rest of this task, once (``distributed.secede``, never ``rejoin``):
    the slot runs render chunks from then on, and the item's own work between its renders (its fits) runs beside
    them on this thread. ``worker_client`` instead rejoins after every gather, which waits until the slot is free:
    behind a chunk of another item (up to a chunk's duration, ~0.5-1 s at the zoo's 64 spp) after every render.
    The item keeps its :data:`ITEM_RESOURCE` until it ends (no second item starts on the worker). A seceded thread
    ends with its task, so the flag is per task."""
    from distributed import secede

    if not getattr(_SECEDED, "done", False):
        secede()
        _SECEDED.done = True
