"""``rig report``: one page per session (HTML, or Markdown) with PNGs, read only from the session folder.

Contents: the session's identity and run history (journal), frame thumbnails, the gradient maps (albedo,
diffuse and specular normals), the fitted profiles R(d) with their data points, the parameter table with
intervals, and, for simulated sessions (ground truth in the manifest), the error-against-run-time table.

The maps are computed here with the continuous-gradient formulas (Ma et al. 2007), for display; the numbers in
the tables are the estimators' (``estimates/*.json``, discrete-LED correction). The data points of R(d) are the
binned profile R'(d) of the single-image method's Tikhonov variant (distance bins deconvolved from the
key-light frame), shown against the dipole profiles of every estimate. Plots need matplotlib (the ``plots``
extra); without it the page says so and keeps the images and tables.
"""
from __future__ import annotations

import html
import io
import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivers.camera.raw import load_linear

from rig.files.session import Session, atomic_write_bytes

THUMB_PX = 160


# ----------------------------------------------------------------------------------------------- images
def _png(rgb01: np.ndarray) -> bytes:
    import cv2

    a = np.clip(np.nan_to_num(np.asarray(rgb01, float), nan=0.0), 0.0, 1.0)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    scale = max(1, THUMB_PX // max(a.shape[:2]))
    if scale > 1:
        a = np.kron(a, np.ones((scale, scale, 1)))
    ok, buf = cv2.imencode(".png", np.round(a[..., ::-1] * 255).astype(np.uint8))
    if not ok:  # pragma: no cover
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _display(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB -> display: scaled so the 99.5th percentile is white, sRGB-like gamma (display only)."""
    a = np.maximum(np.nan_to_num(rgb, nan=0.0), 0.0)
    top = float(np.percentile(a, 99.5)) or 1.0
    return (a / top) ** (1 / 2.2)


def _normals_png(n: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(n), (n + 1.0) / 2.0, 0.0)


# ------------------------------------------------------------------------------------------------- maps
def gradient_maps(session: Session):
    """Albedo / normal maps of the session's gradient frames (continuous formulas), or None."""
    from estimation.gradients import compute_maps

    frames = {}
    for rec in session.frames():
        if rec.pattern == "key":
            continue
        frames[(rec.pattern, rec.polarization)] = load_linear(session.root / rec.file)[0].astype(np.float64)
    have = {p for p, pol in frames if pol == "cross"}
    if ("ambient", "cross") not in frames or not {"x", "y", "z"} <= have:
        return None
    return compute_maps(frames, albedo_scale=1.0, ideal=True)


# ---------------------------------------------------------------------------------------------- profile
def single_image_profile(session: Session) -> dict[str, Any] | None:
    """Data points for the R(d) plot: the binned profile R'(d) of the single-image method's Tikhonov variant
    on the session's key-light frame, through the same inputs (and calibration) as its estimate
    (rig.estimate.sessions.run_single_image). None without a key-light frame or its surveys."""
    from rig.estimate.sessions import _Frames, resolve_calibration, run_single_image

    surveys = session.surveys()
    frames = _Frames(session, resolve_calibration(session))
    if not frames.has("key") or "key_led" not in surveys:
        return None
    est = run_single_image(frames, session.manifest, surveys, method="tikhonov")
    prof = est.get("profile") if est.get("success") else None
    if not prof:
        return None
    values = np.array([[np.nan if v is None else v for v in row] for row in prof["values"]], float)
    return {"bins_mm": prof["bins_mm"], "values": values.tolist(), "method": "tikhonov"}


def _profile_png(estimates: dict[str, Any], truth: dict[str, Any] | None, points: dict[str, Any] | None
                 ) -> bytes | None:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return None
    from estimation.dipole import profile

    fig = Figure(figsize=(9, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3, sharey=True)
    colours = ("tab:red", "tab:green", "tab:blue")
    d_max = 5.0
    if points:
        d_max = max(d_max, float(np.max(points["bins_mm"])))
    d = np.linspace(0.02, d_max, 300)
    styles = {"gradients": "-", "single-image": "--"}
    for c, ax in enumerate(axes):
        curves = []
        for name, est in estimates.items():
            ssp, sa = est.get("sigma_s_prime_per_mm"), est.get("sigma_a_per_mm")
            if ssp is None or sa is None or ssp[c] is None or sa[c] is None:
                continue
            eta = est.get("eta", 1.3)
            curves.append(profile(d, ssp[c], sa[c], eta))
            ax.semilogy(d, curves[-1], styles.get(name, "-."), color=colours[c], label=f"{name} fit")
        if truth:
            curves.append(profile(d, truth["sigma_s_prime_per_mm"][c], truth["sigma_a_per_mm"][c], truth["eta"]))
            ax.semilogy(d, curves[-1], ":", color="k", label="truth")
        if points:
            b = np.asarray(points["bins_mm"], float)
            v = np.asarray(points["values"], float)[:, c]
            keep = (b > 0) & (v > 0) & np.isfinite(v)
            ax.semilogy(b[keep], v[keep], "o", ms=3, color=colours[c], label="data: binned R'(d)")
        if curves:      # frame the fitted curves; deconvolution outliers at the far edge fall off the plot
            y = np.concatenate(curves)
            y = y[np.isfinite(y) & (y > 0)]
            if y.size:
                ax.set_ylim(float(y.min()) / 30, float(y.max()) * 30)
        ax.set_title("RGB"[c])
        ax.set_xlabel("d [mm]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("R(d) [1/mm^2]")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------ tables
_PARAMS = (("R_d", "R_d", ""), ("sigma_s_prime_per_mm", "sigma_s'", "1/mm"), ("sigma_a_per_mm", "sigma_a", "1/mm"),
           ("D_mm", "D", "mm"), ("l_d_mm", "l_d", "mm"))


def parameter_rows(estimates: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for name, est in estimates.items():
        if not est.get("success"):
            rows.append({"estimator": name, "parameter": f"failed: {est.get('message')}", "channel": "",
                         "value": None, "interval": None})
            continue
        for key, label, unit in _PARAMS:
            vals = est.get(key)
            if vals is None:
                continue
            iv = est.get(key + "_interval")
            if iv is None and key in ("sigma_s_prime_per_mm", "sigma_a_per_mm"):
                iv = est.get(key.replace("_per_mm", "_ci_per_mm"))
            for c, ch in enumerate("RGB"):
                if ch not in est.get("channels", "RGB"):
                    continue        # not requested: not captured, not processed
                rows.append({"estimator": name, "parameter": label + (f" [{unit}]" if unit else ""), "channel": ch,
                             "value": None if vals[c] is None else float(vals[c]),
                             "interval": None if iv is None or iv[c] is None else [float(iv[c][0]), float(iv[c][1])]})
    return rows


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


# ------------------------------------------------------------------------------------------------ report
def write_report(root: str | Path, *, out_dir: str | Path | None = None, fmt: str = "html",
                 run_estimators: bool = True, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write the report of the session at ``root``; returns its summary (``index``: the page's path)."""
    if fmt not in ("html", "md"):
        raise ValueError(f"report format {fmt!r}: expected 'html' or 'md'")
    say = log or (lambda m: None)
    t0 = time.perf_counter()
    session = Session.open(root)
    m = session.manifest
    out = Path(out_dir) if out_dir is not None else session.root / "report"
    out.mkdir(parents=True, exist_ok=True)
    estimates = session.estimates()
    if not estimates and run_estimators and session.frames():
        from rig.estimate.sessions import estimate_session
        say("no estimates yet: running the estimators")
        estimate_session(session.root, log=say)
        estimates = session.estimates()
    truth = m.get("truth")
    images: list[str] = []

    def save(name: str, data: bytes) -> str:
        atomic_write_bytes(out / name, data, overwrite=True)
        images.append(name)
        return name

    thumbs = []
    for rec in session.frames():
        rgb, _ = load_linear(session.root / rec.file)
        thumbs.append((f"{rec.pattern} / {rec.polarization}, {rec.exposure_s:g} s",
                       save(f"frame_{Path(rec.file).stem}.png", _png(_display(rgb)))))
    maps = []
    gm = gradient_maps(session)
    if gm is not None:
        maps.append(("albedo (relative)", save("map_albedo.png", _png(_display(gm.albedo)))))
        chans = (m.get("request") or {}).get("channels") or "RGB"
        ch = "G" if "G" in chans else chans[0]             # a requested channel (the others are dark)
        maps.append((f"diffuse normals ({ch})", save("map_diffuse_normals.png", _png(_normals_png(
            gm.diffuse_normals[:, :, "RGB".index(ch), :])))))
        if gm.specular_normals is not None:
            maps.append(("specular normals", save("map_specular_normals.png", _png(_normals_png(gm.specular_normals)))))
    points = single_image_profile(session) if "single-image" in estimates else None
    prof = _profile_png(estimates, truth, points)
    profile_name = save("profile.png", prof) if prof is not None else None
    params = parameter_rows(estimates)
    errors = []
    if truth:
        from rig.estimate.sessions import _rows
        for name, est in estimates.items():
            errors += _rows(name, est, truth)
    events = list(session.events())
    counts: dict[str, int] = {}
    for e in events:
        counts[e.get("type", "?")] = counts.get(e.get("type", "?"), 0) + 1
    summary = {"session": str(session.root), "name": m["name"], "status": session.status(),
               "created": m["created"], "software_version": m.get("software_version"),
               "frames": len(session.frames()), "frames_planned": sum(1 for s in m["plan"] if s["kind"] == "fetch"),
               "verify": session.verify(), "events": counts, "estimates": sorted(estimates),
               "parameters": params, "errors": errors, "images": images,
               "profile_points": points is not None}
    page = (_html if fmt == "html" else _markdown)(summary, m, thumbs, maps, profile_name, points)
    index = out / ("index.html" if fmt == "html" else "report.md")
    atomic_write_bytes(index, page.encode(), overwrite=True)
    summary["index"] = str(index)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    atomic_write_bytes(out / "summary.json", json.dumps(summary, indent=2).encode(), overwrite=True)
    return summary


def _html(s: dict[str, Any], m: dict[str, Any], thumbs, maps, profile_name, points) -> str:
    e = html.escape

    def table(head: list[str], rows: list[list[Any]]) -> str:
        h = "".join(f"<th>{e(x)}</th>" for x in head)
        body = "".join("<tr>" + "".join(f"<td>{e(_fmt(v))}</td>" for v in r) + "</tr>" for r in rows)
        return f"<table><tr>{h}</tr>{body}</table>"

    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(s['name'])}</title><style>"
             "body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
             "td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}figure{display:inline-block;margin:4px}"
             "figcaption{font-size:small}</style></head><body>",
             f"<h1>Session {e(s['name'])}</h1>",
             table(["field", "value"], [["status", s["status"]], ["created", s["created"]],
                                        ["software", s["software_version"]],
                                        ["frames", f"{s['frames']} of {s['frames_planned']} planned"],
                                        ["integrity", "ok" if not s["verify"] else "; ".join(s["verify"])],
                                        ["journal", ", ".join(f"{k} {v}" for k, v in s["events"].items())]]),
             "<h2>Devices</h2>",
             table(["role", "model", "firmware", "serial", "url"],
                   [[r, d.get("model"), d.get("firmware"), d.get("serial_number"), d.get("url")]
                    for r, d in (m.get("devices") or {}).items()]),
             "<h2>Frames</h2>"]
    parts += [f"<figure><img src='{e(f)}'><figcaption>{e(c)}</figcaption></figure>" for c, f in thumbs]
    parts.append("<h2>Maps</h2>")
    if maps:
        parts += [f"<figure><img src='{e(f)}'><figcaption>{e(c)}</figcaption></figure>" for c, f in maps]
        parts.append("<p>Continuous-gradient formulas (Ma et al. 2007), for display.</p>")
    else:
        parts.append("<p>No gradient frames in this session.</p>")
    parts.append("<h2>Profile R(d)</h2>")
    if profile_name:
        parts.append(f"<img src='{e(profile_name)}'>")
        parts.append("<p>Lines: dipole profiles of the fitted parameters" + (" and the truth (dotted)" if m.get("truth")
                     else "") + (". Points: binned R'(d) deconvolved from the key-light frame (Tikhonov)."
                                 if points else ". No key-light frame: no data points.") + "</p>")
    else:
        parts.append("<p>matplotlib is not installed (pip install sssrig[plots]): no plot.</p>")
    parts.append("<h2>Parameters</h2>")
    parts.append(table(["estimator", "parameter", "channel", "value", "95% interval"],
                       [[r["estimator"], r["parameter"], r["channel"], r["value"],
                         "-" if r["interval"] is None else f"{r['interval'][0]:.4g} - {r['interval'][1]:.4g}"]
                        for r in s["parameters"]]) if s["parameters"] else "<p>No estimates.</p>")
    if s["errors"]:
        parts.append("<h2>Error against run time (simulated truth)</h2>")
        parts.append(table(["quantity", "truth", "estimate", "error", "seconds"],
                           [[r["quantity"], r["truth"], r["estimate"],
                             "-" if r["error"] is None else f"{100 * r['error']:+.2f}%", r["seconds"]]
                            for r in s["errors"]]))
    parts.append("</body></html>\n")
    return "\n".join(parts)


def _markdown(s: dict[str, Any], m: dict[str, Any], thumbs, maps, profile_name, points) -> str:
    def table(head: list[str], rows: list[list[Any]]) -> str:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(_fmt(v).replace("|", "/") for v in r) + " |" for r in rows]
        return "\n".join(lines)

    parts = [f"# Session {s['name']}", "",
             table(["field", "value"], [["status", s["status"]], ["created", s["created"]],
                                        ["software", s["software_version"]],
                                        ["frames", f"{s['frames']} of {s['frames_planned']} planned"],
                                        ["integrity", "ok" if not s["verify"] else "; ".join(s["verify"])]]),
             "", "## Frames", ""]
    parts += [f"![{c}]({f})" for c, f in thumbs]
    parts += ["", "## Maps", ""]
    parts += [f"![{c}]({f})" for c, f in maps] or ["No gradient frames in this session."]
    parts += ["", "## Profile R(d)", ""]
    parts.append(f"![R(d)]({profile_name})" if profile_name else "matplotlib is not installed: no plot.")
    parts += ["", "## Parameters", ""]
    parts.append(table(["estimator", "parameter", "channel", "value", "95% interval"],
                       [[r["estimator"], r["parameter"], r["channel"], r["value"],
                         "-" if r["interval"] is None else f"{r['interval'][0]:.4g} - {r['interval'][1]:.4g}"]
                        for r in s["parameters"]]) if s["parameters"] else "No estimates.")
    if s["errors"]:
        parts += ["", "## Error against run time (simulated truth)", ""]
        parts.append(table(["quantity", "truth", "estimate", "error", "seconds"],
                           [[r["quantity"], r["truth"], r["estimate"],
                             "-" if r["error"] is None else f"{100 * r['error']:+.2f}%", r["seconds"]]
                            for r in s["errors"]]))
    return "\n".join(parts) + "\n"
