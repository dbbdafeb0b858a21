"""Issue 15's acceptance rules on the zoo's (scene, channel) pairs, and the one reader of a result's status.

Status contract (:func:`channel_status`): a result JSON (``rig.estimate.scenes.estimate_scene``) with a ``status``
field {"sigma_s_prime_per_mm": [...], "sigma_a_per_mm": [...]} of per-channel "ok" | "weak" | "unknown" (and
``status_reasons``) is read as it is; without it, today's fields decide: ``success`` false -> "failed";
mc-table+reference with ``converged`` false -> sigma_s' and sigma_a "weak"; ``sigma_a_identifiable`` false ->
sigma_a "weak". Anything but "ok" is *flagged*. A failed result counts as flagged; its interval is what it
reports, and (0, inf) only where it reports none (the row says so).

Rules per model, over all (scene, channel) pairs:

- S90: sigma_s' within 10 % in >= 90 % of the pairs;
- S-all: every pair within 10 %, or flagged with a 95 % interval that covers the truth;
- A-all: sigma_a within 50 %, or flagged with an interval that covers the truth, in every pair;
- C90: the 95 % intervals cover the truth in >= 90 % of the (scene, channel, parameter) pairs;
- W0: no pair reported ok (sigma_s' or sigma_a "ok": converged / identifiable) with sigma_s' more than 25 % off;
- E0: no Python warning and nothing on stderr during any estimate.
"""
from __future__ import annotations

import math
from typing import Any

TOL_SSP, TOL_SA, WRONG_SSP = 0.10, 0.50, 0.25
MIN_WITHIN, MIN_COVERAGE = 0.90, 0.90
REFERENCE_MODEL = "mc-table+reference"
PARAMS = ("sigma_s_prime_per_mm", "sigma_a_per_mm")


def channel_status(result: dict[str, Any], model: str) -> tuple[dict[str, list[str]], str, list[str]]:
    """(per-parameter per-channel status, "status" or "fallback", reasons) -- the module docstring's contract."""
    n = len(result.get("channels") or [1])
    if not result.get("success", False):
        return {p: ["failed"] * n for p in PARAMS}, "fallback", [str(result.get("message", ""))]
    st = result.get("status")
    if isinstance(st, dict) and all(p in st for p in PARAMS):
        reasons = result.get("status_reasons") or []
        return {p: [str(x) for x in st[p]] for p in PARAMS}, "status", [str(r) for r in reasons]
    out = {p: ["ok"] * n for p in PARAMS}
    reasons = []
    ident = result.get("sigma_a_identifiable") or [True] * n
    for c in range(n):
        if not ident[c]:
            out["sigma_a_per_mm"][c] = "weak"
            reasons.append(f"ch{c}: sigma_a not identifiable")
    if model == REFERENCE_MODEL and result.get("converged") is False:
        out = {p: ["weak"] * n for p in PARAMS}
        reasons.append("reference iteration not converged")
    return out, "fallback", reasons


def _interval(result: dict[str, Any], param: str, c: int) -> tuple[float, float, str]:
    ci = ((result.get("parameters") or {}).get(param) or {}).get("ci95")
    if ci is None:
        return 0.0, math.inf, "no interval reported: (0, inf)"
    lo, hi = ci[c]
    note = "" if lo is not None and hi is not None else "null bound read as 0 / inf"
    return (0.0 if lo is None else float(lo)), (math.inf if hi is None else float(hi)), note


def evaluate(result: dict[str, Any], model: str, truth_s: list[float], truth_a: list[float]) -> list[dict[str, Any]]:
    """One row per channel: values, relative errors, intervals, coverage, status and the per-pair verdicts."""
    status, source, reasons = channel_status(result, model)
    params = result.get("parameters") or {}
    rows = []
    for c, (ts, ta) in enumerate(zip(truth_s, truth_a)):
        row: dict[str, Any] = {"channel": c, "status_source": source, "status_reasons": reasons,
                               "success": bool(result.get("success"))}
        for p, truth, key in ((PARAMS[0], ts, "s"), (PARAMS[1], ta, "a")):
            v = (params.get(p) or {}).get("value")
            val = math.nan if v is None or v[c] is None else float(v[c])
            lo, hi, note = _interval(result, p, c)
            row.update({f"value_{key}": val, f"err_{key}": val / truth - 1, f"ci_{key}": [lo, hi],
                        f"covers_{key}": bool(lo <= truth <= hi), f"status_{key}": status[p][c],
                        f"flagged_{key}": status[p][c] != "ok", f"ci_note_{key}": note})
        within = abs(row["err_s"]) <= TOL_SSP  # NaN (failed) compares False
        row["within_s"] = bool(within)
        row["pass_s"] = bool(within or (row["flagged_s"] and row["covers_s"]))
        row["pass_a"] = bool(abs(row["err_a"]) <= TOL_SA or (row["flagged_a"] and row["covers_a"]))
        row["confident_wrong"] = bool((not row["flagged_s"] or not row["flagged_a"]) and abs(row["err_s"]) > WRONG_SSP)
        rows.append(row)
    return rows


def acceptance(rows: list[dict[str, Any]], warnings: int) -> dict[str, Any]:
    """Counts and PASS/FAIL of the rules over one model's rows (module docstring)."""
    n = len(rows)
    within = sum(r["within_s"] for r in rows)
    cover = sum(r["covers_s"] for r in rows) + sum(r["covers_a"] for r in rows)
    out = {
        "S90": (within >= MIN_WITHIN * n and n > 0, f"sigma_s' within 10 %: {within}/{n} (need >= 90 %)"),
        "S-all": (all(r["pass_s"] for r in rows), f"sigma_s' within 10 % or flagged+covering: "
                  f"{sum(r['pass_s'] for r in rows)}/{n}"),
        "A-all": (all(r["pass_a"] for r in rows), f"sigma_a within 50 % or flagged+covering: "
                  f"{sum(r['pass_a'] for r in rows)}/{n}"),
        "C90": (cover >= MIN_COVERAGE * 2 * n and n > 0, f"95 % intervals cover the truth: {cover}/{2 * n} "
                "(scene, channel, parameter) pairs (need >= 90 %)"),
        "W0": (not any(r["confident_wrong"] for r in rows), f"reported ok with sigma_s' > 25 % off: "
               f"{sum(r['confident_wrong'] for r in rows)} (need 0)"),
        "E0": (warnings == 0, f"warnings + stderr lines during estimation: {warnings} (need 0)"),
    }
    return {k: {"pass": bool(v[0]), "text": v[1]} for k, v in out.items()}


def worst_sigma_s(rows: list[dict[str, Any]]) -> float:
    errs = [r["err_s"] for r in rows]
    return max(errs, key=lambda e: abs(e) if e == e else math.inf) if errs else math.nan
