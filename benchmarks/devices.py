"""Benchmark of the device path: is the controller ever the bottleneck of a capture?

Against the bundled simulators (no hardware), for the LED sphere on three transports — the binary serial
protocol on a pty, the same protocol on a loopback TCP socket (``socket://``), and Modbus TCP:

1. pattern-switch round trip: ``select_slot`` latency (median, p99, max) and switches per second;
2. upload of one full pattern (343 LEDs, ``led_layout(6, 1000.0, -60.0)``): median time per upload;
3. a whole gradient sequence (the 7 spherical-gradient patterns, Ma et al. 2007): for each pattern,
   select its slot, then fire the ESPER trigger simulator (on its own pty) with the minimum exposure
   (1 ms), then the next. Reported as sequences/s and frames/s. The camera (rendering, readout, file
   transfer) is left out on purpose: this measures the controller path only;
4. the controller's frames/s against a typical camera burst of 5 frames/s, as a ratio.

Run: ``python benchmarks/devices.py [--quick] [--json [out.json]]`` (default: 500 switches, 30 uploads,
100 sequences per transport, ~4 s; ``--quick`` ~1 s). ``--json`` alone prints JSON instead of the table.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.led_sphere import open_led_sphere_serial  # noqa: E402
from drivers.led_sphere_modbus import open_led_sphere_modbus  # noqa: E402
from drivers.trigger.esper import open_esper_trigger  # noqa: E402
from rig.acquire.geometry import led_layout  # noqa: E402
from rig.acquire.patterns import GRADIENT_PATTERNS, pattern_rgb16  # noqa: E402
from simulators.led_sphere import LedSphereModel  # noqa: E402
from simulators.led_sphere_modbus import LedSphereModbusSim  # noqa: E402
from simulators.serve import serve  # noqa: E402
from simulators.trigger import EsperTriggerModel  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

CAMERA_BURST_FPS = 5.0          # a typical DSLR/mirrorless burst rate
# Generous limits: this measures timing, not the safety checks (a full-on pattern of 343 LEDs draws
# 343 * 3 * 0.02 A = 20.6 A in the current model).
LIMITS = dict(max_total_current_a=50.0, max_mean_duty=1.0)
TRANSPORTS = ("serial/pty", "serial/TCP", "Modbus TCP")


def stats_ms(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s) * 1e3
    return {"n": int(a.size), "median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "mean_ms": float(a.mean())}


def time_calls(fn: Callable[[int], None], n: int, warmup: int = 3) -> list[float]:
    for i in range(warmup):
        fn(i)
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(time.perf_counter() - t0)
    return out


def bench_sphere(name: str, light: Any, trigger: Any, patterns: list[np.ndarray], *, n_switch: int,
                 n_upload: int, n_seq: int, exposure_s: float) -> dict[str, Any]:
    slots = list(range(len(patterns)))
    light.identify()
    for slot, p in zip(slots, patterns):
        light.upload_pattern(slot, p)

    # (1) pattern switch: cycle through the stored slots, one SELECT per call
    switch = time_calls(lambda i: light.select_slot(slots[i % len(slots)]), n_switch)
    # (2) a full-pattern upload into a spare slot (not the lit one)
    spare = len(slots)
    upload = time_calls(lambda i: light.upload_pattern(spare, patterns[i % len(patterns)]), n_upload, warmup=1)
    # (3) whole gradient sequence: select -> fire (minimum exposure) -> next
    def sequence(_: int) -> None:
        for slot in slots:
            light.select_slot(slot)
            trigger.fire(exposure_s)
    seq = time_calls(sequence, n_seq, warmup=1)
    light.all_off()

    s, u, q = stats_ms(switch), stats_ms(upload), stats_ms(seq)
    total = float(sum(seq))
    return {"transport": name, "switch": s, "switches_per_s": len(switch) / float(sum(switch)),
            "upload": u, "sequence": q, "sequences_per_s": len(seq) / total,
            "frames_per_s": len(seq) * len(slots) / total, "frames_per_sequence": len(slots)}


def render(results: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    lines = [
        f"Device path benchmark: {meta['leds']} LEDs, {meta['frames_per_sequence']}-pattern gradient sequence, "
        f"exposure {meta['exposure_s'] * 1e3:g} ms (ESPER trigger simulator on a pty). "
        f"Iterations: {meta['n_switch']} switches, {meta['n_upload']} uploads, {meta['n_seq']} sequences "
        "per transport.",
        "",
        "| transport | switch median ms | switch p99 ms | switch max ms | switches/s | upload median ms "
        "| sequences/s | frames/s | x camera 5 fps |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        s = r["switch"]
        lines.append(f"| {r['transport']} | {s['median_ms']:.3f} | {s['p99_ms']:.3f} | {s['max_ms']:.3f} "
                     f"| {r['switches_per_s']:.0f} | {r['upload']['median_ms']:.2f} "
                     f"| {r['sequences_per_s']:.1f} | {r['frames_per_s']:.1f} "
                     f"| {r['frames_per_s'] / CAMERA_BURST_FPS:.1f} |")
    lines += [
        "",
        "This measures the controller path only (driver + simulated device over the transport + trigger "
        f"with the minimum {meta['exposure_s'] * 1e3:g} ms exposure); camera rendering, readout and file "
        "transfer are left out.",
    ]
    slowest = min(results, key=lambda r: r["frames_per_s"])
    ratio = slowest["frames_per_s"] / CAMERA_BURST_FPS
    verdict = "the controller is not the bottleneck" if ratio > 1 else "the controller IS the bottleneck"
    lines.append(f"Controller vs camera: slowest transport ({slowest['transport']}) reaches "
                 f"{slowest['frames_per_s']:.1f} frames/s = {ratio:.1f}x a typical camera's "
                 f"{CAMERA_BURST_FPS:g} fps burst; {verdict}.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few iterations (< 15 s)")
    ap.add_argument("--json", nargs="?", const="-", metavar="PATH",
                    help="write results as JSON to PATH, or print them (instead of the table) if no PATH")
    args = ap.parse_args(argv)
    n_switch, n_upload, n_seq = (60, 5, 10) if args.quick else (500, 30, 100)

    _, dirs = led_layout(6, 1000.0, -60.0)
    patterns = [pattern_rgb16(p, dirs) for p in GRADIENT_PATTERNS]
    exposure_s = 0.001
    kw = dict(n_switch=n_switch, n_upload=n_upload, n_seq=n_seq, exposure_s=exposure_s)
    results: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    with ExitStack() as stack:     # closes every driver, server and port, also on error
        esper_model = EsperTriggerModel(on_fire=lambda exposure: None)
        esper_server = serve(esper_model, "pty")
        stack.callback(esper_server.close)
        trigger = open_esper_trigger(esper_server.url, min_exposure_s=exposure_s)
        stack.callback(trigger.close)
        min_exposure_s = trigger.min_exposure_s

        for name, url in (("serial/pty", "pty"), ("serial/TCP", "tcp://127.0.0.1:0")):
            model = LedSphereModel(len(dirs), max_current_a=LIMITS["max_total_current_a"])
            server = serve(model, url)
            stack.callback(server.close)
            light = open_led_sphere_serial(server.url, **LIMITS)
            stack.callback(light.close)
            results.append(bench_sphere(name, light, trigger, patterns, **kw))
            light.close()
            server.close()

        sim = LedSphereModbusSim(len(dirs), tcp="127.0.0.1:0").start()
        stack.callback(sim.stop)
        light = open_led_sphere_modbus(sim.url, **LIMITS)
        stack.callback(light.close)
        results.append(bench_sphere("Modbus TCP", light, trigger, patterns, **kw))
        light.close()
        sim.stop()
        shots = esper_model.shots

    meta = {"leds": len(dirs), "frames_per_sequence": len(patterns), "exposure_s": min_exposure_s,
            "n_switch": n_switch, "n_upload": n_upload, "n_seq": n_seq, "trigger_shots": shots,
            "camera_burst_fps": CAMERA_BURST_FPS, "controller_path_only": True,
            "wall_s": time.perf_counter() - t_start}
    payload = {"meta": meta, "results": results}
    if args.json == "-":
        print(json.dumps(payload, indent=1))
    else:
        print(render(results, meta))
        print(f"\n({meta['wall_s']:.1f} s, {shots} trigger shots)")
        if args.json:
            write_json(args.json, payload, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
