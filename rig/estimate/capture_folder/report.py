"""The command line of ``rig estimate gradients FOLDER``: the human summary and :func:`run_cli`.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from drivers.errors import ConfigError

from .estimate import _check_reference, estimate_capture
from .reading import load_capture


# ------------------------------------------------------------------------------------------------ CLI
def _fmt(v: Any, spec: str = ".4g") -> str:
    return "-" if v is None else format(v, spec)


def format_summary(s: Mapping[str, Any]) -> str:
    """A short human-readable table of :func:`estimate_capture`'s summary."""
    lines = [f"capture {s['name']} ({s['capture']}): {s['image_px'][0]} x {s['image_px'][1]} px, mode {s['mode']}, "
             f"eta {s['eta']}",
             f"maps -> {s['out_dir']} ({s['format']}), {s['seconds']:.1f} s"]
    d = s["diffusion"]
    head = f"{'ch':<3}{'known px':>10}{'albedo':>10}{'|v|/tau':>10}{'D [mm]':>11}{'sigma_s_prime':>15}" \
           f"{'sigma_a':>12}  status"
    lines.append(head)
    m = s["maps"]
    for c, ch in enumerate("RGB"):
        D = d.get("D_mm", {}).get("value", [None] * 3)[c] if "D_mm" in d else None
        ss = d.get("sigma_s_prime_per_mm", {}).get("value", [None] * 3)[c] if "D_mm" in d else None
        sa = d.get("sigma_a_per_mm", {}).get("value", [None] * 3)[c] if "D_mm" in d else None
        lines.append(f"{ch:<3}{m['known_pixels'][c]:>10}{_fmt(m['albedo_median'][c]):>10}"
                     f"{_fmt(m['diffuse_length_median'][c]):>10}{_fmt(D):>11}{_fmt(ss):>15}{_fmt(sa):>12}  "
                     f"{d['status'][c]}")
    r = s.get("diffusion_reference_corrected")
    if r:
        ref = r["reference"]
        lines.append(f"reference-corrected sphere summary ({r['iterations']} Monte Carlo renders at {ref['spp']} spp, "
                     f"seed {ref['seed']}, {r['seconds']:.1f} s; {r['message']}); per-pixel maps uncorrected:")
        lines.append(f"{'ch':<3}{'D [mm]':>11}{'95 % interval':>22}{'sigma_s_prime':>15}{'sigma_a':>12}"
                     f"{'kappa_alb':>11}{'kappa_blur':>11}{'D uncorr.':>11}")
        for c, ch in enumerate("RGB"):
            lo, hi = r["D_mm"]["interval"][c]
            lines.append(f"{ch:<3}{_fmt(r['D_mm']['value'][c]):>11}{'[' + _fmt(lo) + ', ' + _fmt(hi) + ']':>22}"
                         f"{_fmt(r['sigma_s_prime_per_mm']['value'][c]):>15}"
                         f"{_fmt(r['sigma_a_per_mm']['value'][c]):>12}{_fmt(r['kappa_albedo'][c], '.3f'):>11}"
                         f"{_fmt(r['kappa_blur'][c], '.3g'):>11}{_fmt(r['uncorrected']['D_mm'][c]):>11}")
    from rig.estimate.folder_regions import format_regions
    lines += format_regions(s.get("regions"))
    if s.get("seed"):
        lines.append("seed D [mm] (relative, k calibrated elsewhere): "
                     + " ".join(_fmt(v) for v in s["seed"]["D_mm_median"]))
    nz = s.get("noise")
    if nz:
        lines.append(f"noise ({nz['source'].get('source')}): median standard error of the albedo "
                     + " ".join(_fmt(v) for v in nz["albedo_stderr_median"]) + ", of the diffuse normals "
                     + " ".join(_fmt(v) for v in nz["diffuse_normal_stderr_rad_median"]) + " rad (in the intervals)")
    for n in s.get("notes", []):
        lines.append(f"note: {n}")
    return "\n".join(lines)


def run_cli(args: Any) -> int:
    """``rig estimate gradients FOLDER [--out DIR] [--format exr|tiff] [--tile-rows N] [--model M] [--json]
    [--reference [--reference-spp N] [--reference-iterations K] [--reference-seed S] [--reference-mode M]]``."""
    folder = Path(args.folder)
    out = Path(args.out) if getattr(args, "out", None) else folder / "maps"
    tile_rows = getattr(args, "tile_rows", None)
    if tile_rows is not None and tile_rows < 1:
        raise ConfigError("--tile-rows", "tile_rows", "an integer >= 1", tile_rows)
    reference: dict[str, Any] | None = None
    ref_opts = {k: getattr(args, f"reference_{k}", None) for k in ("spp", "iterations", "seed", "mode")}
    if getattr(args, "reference", False):
        reference = ref_opts
    else:
        given = [k for k, v in ref_opts.items() if v is not None]
        if given:
            raise ConfigError(f"--reference-{given[0]}", given[0], "only together with --reference",
                              ref_opts[given[0]])
    cap = load_capture(folder)
    if reference is not None:
        _check_reference(cap, reference)      # before the maps: a missing sphere is a usage error, not a failure
    from rig.files.maps_io import select_maps

    try:
        sel = select_maps(getattr(args, "maps", None))
    except ValueError as exc:
        raise ConfigError("--maps", "maps", str(exc), getattr(args, "maps", None)) from None
    summary = estimate_capture(cap, out, getattr(args, "format", "exr") or "exr", tile_rows,
                               model=getattr(args, "model", None) or "dipole-jensen", maps=sel,
                               half=bool(getattr(args, "half", False)), reference=reference,
                               relief_window_px=getattr(args, "relief_window_px", None))
    if getattr(args, "json", False):
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
    return 0
