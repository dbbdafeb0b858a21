"""How noisy is the ridge line search's objective? Its points re-rendered with more seeds (issue 15, the gate).

Runs ``benchmarks/scene_zoo.py`` (its arguments, unchanged) with :func:`estimation.ridge_scan.ridge_line_search`
wrapped: after the search (seed ``s``, its own renders and decision as in any run), every grid point it visited is
rendered again with seeds ``s + o`` for ``o`` in ``--extra-seeds`` (each seed's renders share it: common random
numbers as in the search) and read by :func:`estimation.ridge_scan.profile_objective` with that seed's k = 0 metric,
as the search reads its own (``--metric search``: with the search's, as the gate reads its check seeds). Printed and written (``--noise-json``) per scene and channel: the objective and its
delta-method standard deviation per point and seed, the seed-to-seed spread of each point's objective and of each
gain J(0) - J(k) against the predicted sqrt(sd_0^2 + sd_k^2) (the bound for independent renders), and the
correlation of the two points' first-order noise under one seed, sum_i g0_i e0_i gk_i ek_i over pixels and seeds
(g = psi(z) / m the objective's derivative, e the render's deviation from the seeds' mean), normalised.

The search's own renders are its seed's (not rendered again). The extra renders are not added to the estimator's record (the result and its intervals are those of a plain run).

Run: ``NUMBA_NUM_THREADS=1 python benchmarks/zoo/line_noise.py --noise-json n.json -- --models mc-table+reference
--scenes 19 --root benchmarks/out/zoo --json z19.json``
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import estimation.model_correction as mc  # noqa: E402
from estimation.ridge_scan import objective_gradient, profile_objective, ridge_line_search  # noqa: E402
from rig.files.provenance import write_json  # noqa: E402

_SEED_OFFSET = [0]
_RECORDS: list[dict[str, Any]] = []


def _render(reference: Any, theta: Any, eta: float, seed: int, patches: Any, n_ch: int) -> Any:
    return _ORIG_RENDER(reference, theta, eta, int(seed) + _SEED_OFFSET[0], patches, n_ch)


def _noise_of(q: np.ndarray, se: np.ndarray, dq: Any, obs: np.ndarray, m: np.ndarray, c: int) -> np.ndarray:
    """(m,) the objective's derivative g = -psi(z) / m per row (0 where unusable), z after the sigma_a refit."""
    g = objective_gradient(q, dq, obs, m, c)
    return np.zeros(q.shape[0]) if g is None else np.where(np.isfinite(g), g, 0.0)


def _line_with_seeds(render: Any, obs: np.ndarray, metric: Any, theta: np.ndarray, channels: np.ndarray,
                     **kw: Any) -> Any:
    seen: list[tuple[np.ndarray, Any]] = []

    def logged(th: np.ndarray) -> Any:
        out_r = render(th)
        seen.append((th.copy(), out_r))
        return out_r

    out, info = ridge_line_search(logged, obs, metric, theta, channels, **kw)
    cells = [c.cell_contents for c in (render.__closure__ or ())]
    cells = [x for x in cells if isinstance(x, list)] + [x.renders for x in cells
                                                          if isinstance(getattr(x, "renders", None), list)]
    lengths = [len(x) for x in cells]
    step = info["step_log"]
    n_ch = theta.shape[0]
    grids = [[g["k"] for g in info["grid"][c]] for c in range(n_ch)]
    ks = sorted({k for g in grids for k in g}, key=lambda k: (k != 0, k))
    per_seed: dict[int, dict[int, list[Any]]] = {}
    pix: dict[int, dict[int, list[Any]]] = {}

    def read(off: int, th: np.ndarray, r: Any, m0: np.ndarray) -> None:
        q, se, dq, _ = r
        for c in range(n_ch):
            k = int(round((th[c, 0] - theta[c, 0]) / step))
            if k in grids[c] and k not in per_seed[off].setdefault(c, {}):
                per_seed[off][c][k] = profile_objective(q, se, dq, obs, m0, c)
                pix[off].setdefault(c, {})[k] = (q[:, c].copy(), _noise_of(q, se, dq, obs, m0, c))

    per_seed[0], pix[0] = {}, {}
    m_0 = metric(seen[0][1][1], seen[0][1][0])  # the search's own: its first render's
    for th, r in seen:
        read(0, th, r, m_0)
    for off in EXTRA:
        _SEED_OFFSET[0] = off
        per_seed[off], pix[off] = {}, {}
        m0 = None
        for k in ks:
            th = theta.copy()
            for c in range(n_ch):
                if k in grids[c]:
                    th[c] = theta[c] + k * step
            r = render(th)
            if m0 is None:
                m0 = metric(r[1], r[0]) if OWN_METRIC else m_0
            read(off, th, r, m0)
        _SEED_OFFSET[0] = 0
    for x, n in zip(cells, lengths):  # the extra renders leave the estimator's record as it was
        del x[n:]
    rec: dict[str, Any] = {"seeds_offsets": [0] + EXTRA, "search": {k: info[k] for k in (
        "gain", "gain_sd", "gain_threshold_sd", "moved", "vertex_k")}, "channels": []}
    for c in range(n_ch):
        if not grids[c]:
            rec["channels"].append(None)
            continue
        objs = {k: [per_seed[o][c][k][0] for o in per_seed] for k in grids[c]}
        sds = {k: [per_seed[o][c][k][2] for o in per_seed] for k in grids[c]}
        qs = {k: np.stack([pix[o][c][k][0] for o in pix]) for k in grids[c]}  # (seeds, m)
        gs = {k: np.stack([pix[o][c][k][1] for o in pix]) for k in grids[c]}
        rows = []
        for k in grids[c]:
            gain = [objs[0][i] - objs[k][i] for i in range(len(per_seed))]
            pred = [float(np.hypot(sds[0][i], sds[k][i])) for i in range(len(per_seed))]
            e0, ek = qs[0] - qs[0].mean(axis=0), qs[k] - qs[k].mean(axis=0)
            a, b = np.nan_to_num(gs[0] * e0), np.nan_to_num(gs[k] * ek)
            den = np.sqrt(np.sum(a * a) * np.sum(b * b))
            rows.append({"k": k, "sigma_s_prime_per_mm": float(np.exp(theta[c, 0] + k * step)),
                         "objective": objs[k], "objective_sd_pred": sds[k],
                         "objective_sd_seeds": float(np.std(objs[k], ddof=1)),
                         "gain": gain, "gain_sd_pred_independent": pred,
                         "gain_sd_seeds": float(np.std(gain, ddof=1)) if k != 0 else 0.0,
                         "crn_correlation": float(np.sum(a * b) / den) if den > 0 and k != 0 else None})
        rec["channels"].append(rows)
        print(f"  line noise, channel {c}: k, sigma_s' /mm, objective per seed, sd pred (seed 0) / seeds; gain per "
              f"seed, its sd pred (independent) / seeds, CRN correlation", flush=True)
        for r in rows:
            cr = r["crn_correlation"]
            print(f"    {r['k']:+d} {r['sigma_s_prime_per_mm']:.4g}  "
                  f"{' '.join(f'{x:.1f}' for x in r['objective'])}  {r['objective_sd_pred'][0]:.1f} / "
                  f"{r['objective_sd_seeds']:.1f};  {' '.join(f'{x:.1f}' for x in r['gain'])}  "
                  f"{r['gain_sd_pred_independent'][0]:.1f} / {r['gain_sd_seeds']:.1f}  "
                  f"{'' if cr is None else f'{cr:.2f}'}", flush=True)
    _RECORDS.append(rec)
    if NOISE_JSON is not None:
        write_json(NOISE_JSON, {"records": _RECORDS}, indent=1)
    return out, info


_ORIG_RENDER = mc._render
EXTRA: list[int] = []
NOISE_JSON: Path | None = None
OWN_METRIC = True


def main(argv: list[str] | None = None) -> int:
    global EXTRA, NOISE_JSON, OWN_METRIC
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--extra-seeds", default="1009,2017", help="seed offsets of the re-renders (default 1009,2017)")
    ap.add_argument("--noise-json", type=Path, help="write the records here (after every line search)")
    ap.add_argument("--metric", choices=["own", "search"], default="own",
                    help="each extra seed's objective in its own k = 0 render's metric (as the search reads its "
                         "seed; default) or in the search's (as the gate's check seeds are read)")
    ap.add_argument("zoo", nargs=argparse.REMAINDER, help="-- then benchmarks/scene_zoo.py's arguments")
    args = ap.parse_args(argv)
    EXTRA = [int(x) for x in args.extra_seeds.split(",") if x]
    NOISE_JSON = args.noise_json
    OWN_METRIC = args.metric == "own"
    mc._render = _render
    mc.ridge_line_search = _line_with_seeds
    import scene_zoo
    zoo_args = args.zoo[1:] if args.zoo[:1] == ["--"] else args.zoo
    return scene_zoo.main(zoo_args)


if __name__ == "__main__":
    raise SystemExit(main())
