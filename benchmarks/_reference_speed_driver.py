"""One timed reference-corrected estimate in this process, for benchmarks/reference_speed.py (issue 19).

Run as ``python _reference_speed_driver.py KIND FOLDER OPTIONS_JSON`` with ``PYTHONPATH`` pointing at the source
tree to time: the current checkout, or a ``git worktree`` of the anchor commit (the start of issue 19, before rig/
was split into rooms: hence both module layouts are tried). Standalone on purpose: it imports nothing of the
benchmark, so the anchor's code runs unchanged.

KIND ``scene``: FOLDER/scene.toml through ``estimate_scene`` (``rig estimate single-image``'s library entry) with
``model`` / ``reference_spp`` / ``reference_iterations`` / ``reference_seed`` from OPTIONS_JSON. KIND ``sphere``: the
capture folder through ``estimate_capture(..., reference=OPTIONS_JSON["reference"])`` (``rig estimate gradients
--reference``). Before the clock starts, the same estimate runs once at 2 spp and one render (``warm``: numba compiles
or loads every kernel the timed run uses, so neither tree pays compilation in its timing; with OPTIONS_JSON
``"lut": "cold"`` the LED response LUTs it built are then forgotten, see :func:`_forget_luts`). Prints one JSON line:
wall and CPU seconds of the timed estimate (``time.perf_counter``, ``time.process_time``: this process, one numba thread),
the CPU seconds inside the reference loop (``estimate_with_reference`` / ``reference_corrected_sphere``, wrapped
wherever a module holds them) and the result (scene) or summary (sphere).
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _scene(folder: Path, opts: dict[str, Any], spp: int, iterations: int) -> dict[str, Any]:
    try:
        from rig.estimate.scenes import estimate_scene
        from rig.files.scene_file import load_scene
    except ImportError:          # the anchor's layout (before rig/ in rooms)
        from rig.scene_estimate import estimate_scene  # type: ignore[no-redef]
        from rig.scene_file import load_scene  # type: ignore[no-redef]
    import inspect

    kw = {}
    if opts.get("reference_mode") and "reference_mode" in inspect.signature(estimate_scene).parameters:
        kw["reference_mode"] = opts["reference_mode"]      # the current tree only (the anchor has one mode)
    return estimate_scene(load_scene(folder / "scene.toml"), model=opts["model"], reference_spp=spp,
                          reference_iterations=iterations, reference_seed=opts.get("reference_seed"), **kw)


def _sphere(folder: Path, opts: dict[str, Any], spp: int, iterations: int) -> dict[str, Any]:
    try:
        from rig.estimate.capture_folder import estimate_capture, load_capture
    except ImportError:
        from rig.capture_folder import estimate_capture, load_capture  # type: ignore[no-redef]
    ref = {**opts.get("reference", {}), "spp": spp, "iterations": iterations}
    with tempfile.TemporaryDirectory(prefix="reference-speed-") as tmp:
        return estimate_capture(load_capture(folder), tmp, reference=ref)


#: the reference loops (both trees' names): their own CPU seconds are measured by wrapping them
_LOOPS = ("estimate_with_reference", "reference_corrected_sphere")
_LOOP_CPU: list[float] = []


def _wrap_loops() -> None:
    """Replace each reference loop, wherever a loaded module holds it, by a wrapper adding its CPU seconds to
    :data:`_LOOP_CPU` (after the warm-up run, which has imported every module the timed run uses)."""
    import functools

    for name in _LOOPS:
        originals = {id(getattr(m, name)): getattr(m, name) for m in list(sys.modules.values())
                     if m is not None and callable(getattr(m, name, None)) and not getattr(getattr(m, name), "_timed",
                                                                                               False)}
        for fn in originals.values():
            @functools.wraps(fn)
            def timed(*a: Any, __fn: Any = fn, **k: Any) -> Any:
                c0 = time.process_time()
                try:
                    return __fn(*a, **k)
                finally:
                    _LOOP_CPU.append(time.process_time() - c0)
            timed._timed = True  # type: ignore[attr-defined]
            for m in list(sys.modules.values()):
                if m is not None and getattr(m, name, None) is fn:
                    setattr(m, name, timed)


def _forget_luts() -> None:
    """``lut: "cold"``: drop the LED response LUTs the warm-up run built (the current tree keeps them in the process,
    :mod:`rig.estimate.response_cache`; run with ``SSSRIG_LUT_CACHE=off`` so that none comes from disk either): the
    timed run then builds its LUT and solve tables like the first capture on a rig. A no-op for trees without the
    cache (the anchor builds its table in every estimate)."""
    try:
        from rig.estimate.response_cache import clear_memory_cache
    except ImportError:
        return
    clear_memory_cache()


def main() -> int:
    kind, folder, opts = sys.argv[1], Path(sys.argv[2]), json.loads(sys.argv[3])
    run = {"scene": _scene, "sphere": _sphere}[kind]
    spp, iterations = int(opts["spp"]), int(opts["iterations"])
    tw = time.perf_counter()
    if opts.get("warm", True):
        run(folder, opts, 2, 1)
    warm_s = time.perf_counter() - tw
    if opts.get("lut") == "cold":
        _forget_luts()
    _wrap_loops()
    t0, c0 = time.perf_counter(), time.process_time()
    res = run(folder, opts, spp, iterations)
    sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    import numba

    print(json.dumps({"seconds": sec, "cpu_seconds": cpu, "loop_cpu_seconds": sum(_LOOP_CPU),
                      "loop_calls": len(_LOOP_CPU), "warm_seconds": warm_s, "pid": os.getpid(),
                      "numba_threads": int(numba.get_num_threads()), "result": res}, default=_default))
    return 0


def _default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    return str(o)


if __name__ == "__main__":
    sys.exit(main())
