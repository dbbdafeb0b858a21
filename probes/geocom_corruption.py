"""Probe (issue 18): surveys through a GeoCOM link that flips bits in the instrument's replies.

Serves the simulated total station on loopback TCP with ``simulators.serve.Faults(corrupt_probability=P)``,
measures targets through ``open_total_station`` as the runner would (a ProtocolError or timeout is retried, up
to 10 attempts) and counts coordinates that were *returned as good* but lie more than ``--tol-mm`` from the
truth ("silently wrong"). Run with the CRC on (the default config) and off to compare:

    python probes/geocom_corruption.py --surveys 300 --corrupt 0.003            # CRC + plausibility (defaults)
    python probes/geocom_corruption.py --surveys 300 --corrupt 0.003 --no-crc --no-plausibility
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.errors import DeviceRejected, DeviceTimeout, ProtocolError  # noqa: E402
from drivers.total_station import open_total_station  # noqa: E402
from simulators.serve import Faults, serve  # noqa: E402
from simulators.total_station import GeoComModel  # noqa: E402

TARGETS = {"R1": (600.0, 0.0, 0.0), "R2": (-600.0, 0.0, 0.0), "R3": (0.0, 600.0, 300.0), "R4": (0.0, -600.0, -300.0)}
STATION = (0.0, -3000.0, 200.0)


def run(surveys: int, corrupt: float, *, crc: bool = True, max_error_mm: float | None = 50.0, tol_mm: float = 0.5,
        seed: int = 1) -> dict:
    model = GeoComModel(TARGETS, STATION, noise_mm=0.0, angle_noise_rad=0.0, seed=seed, checksum=crc)
    faults = Faults(seed=seed)
    server = serve(model, "tcp://127.0.0.1:0", faults)
    wrong, worst, retries, failed = 0, 0.0, 0, 0
    try:
        feed = open_total_station(server.url, station_xyz_mm=STATION, targets=TARGETS, checksum=crc, timeout_s=0.3,
                                  edm_wait_s=0.0, max_error_mm=max_error_mm)
        faults.corrupt_probability = corrupt         # after the connect handshake
        names = sorted(TARGETS)
        try:
            for i in range(surveys):
                name = names[i % len(names)]
                for _attempt in range(10):
                    try:
                        p = feed.measure(name)
                    except (ProtocolError, DeviceTimeout, DeviceRejected):
                        retries += 1
                        continue
                    err = math.dist(p.xyz_mm, TARGETS[name])
                    worst = max(worst, err)
                    wrong += err > tol_mm
                    break
                else:
                    failed += 1
        finally:
            feed.close()
    finally:
        server.close()
    return {"surveys": surveys, "corrupt_probability": corrupt, "crc": crc, "max_survey_error_mm": max_error_mm,
            "silently_wrong": wrong, "worst_error_mm": round(worst, 3), "retries": retries, "failed": failed}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surveys", type=int, default=300)
    ap.add_argument("--corrupt", type=float, default=0.003)
    ap.add_argument("--no-crc", action="store_true")
    ap.add_argument("--no-plausibility", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    out = run(args.surveys, args.corrupt, crc=not args.no_crc,
              max_error_mm=None if args.no_plausibility else 50.0, seed=args.seed)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
