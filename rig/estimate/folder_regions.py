"""Per-region summaries of ``rig estimate gradients FOLDER`` from a labelled region image (issue 16, build item 1).

``capture.toml`` may name a label image in ``[object]``: ``regions = "regions.png"`` (an 8- or 16-bit
single-channel PNG, or an ``.npy`` integer array, of the frames' size; 0 = no region, 1..N = regions, every
label 1..N present) and optionally ``[object.region_names]`` (``1 = "cheek"``, ...). :func:`read_regions` validates
them with the capture folder's strict table access (``rig.estimate.capture_folder._Table``: every error names the file,
the field and what was expected). :func:`region_summaries` then adds to the summary one entry per region: its
label, name, pixel count, the map medians (R_d, apparent albedo) and the diffusion summary of the whole-object
path restricted to the region, made by the same code:

- **sphere** (grounded estimator): :func:`estimation.diffusion.summarize` on the per-pixel maps of
  :func:`estimation.diffusion.estimate_sphere` with ``region`` = the label. Those maps are unknown outside the
  sphere x mask eroded by 2 px, so the pixels used are (eroded sphere x mask) x label, minus each channel's
  unknown pixels; then the dipole's shortening-bias widening (:func:`estimation.sphere_bias.widen_sphere_summary`)
  as for the whole object (:func:`grounded_summary`, used by both). A channel with fewer than
  :data:`MIN_REGION_PIXELS` usable pixels is "unknown" with the reason: below 6 samples no distribution-free
  95 % interval of a median exists (the interval [x_(1), x_(n)] covers with 1 - 2^(1-n) < 0.95 for n <= 5).
- **relief / unknown shape** (relief blur, ``docs/gradients.md`` sec. 9): :func:`estimation.relief.
  summarize_relief` pools the per-window fits whose window lies at least half (:data:`MIN_WINDOW_FRACTION`)
  inside the label; a channel without a usable ("ok" or "weak") window among them is "unknown" with the reason.

Label boundaries are not eroded: a pixel within ~l_d of another region mixes both materials (subsurface transport
crosses the boundary); the medians are robust to a thin such rim, a region narrower than a few l_d is not.

References: Ma et al. 2007 (polarized spherical gradients); ``docs/gradients.md`` sec. 5, 9;
``docs/capture-folder.md`` sec. 3 ``[object]`` and sec. 5 (summary).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np
from numpy.typing import NDArray

__all__ = ["RegionLabels", "read_regions", "grounded_summary", "region_summaries", "format_regions",
           "MIN_REGION_PIXELS", "MIN_WINDOW_FRACTION"]

MIN_REGION_PIXELS = 6
"""Fewest usable pixels per channel for a sphere region summary (a distribution-free 95 % median interval)."""
MIN_WINDOW_FRACTION = 0.5
"""A relief window belongs to a region when at least this fraction of its pixels carries the region's label."""
MAX_LABEL = 65535


@dataclass(frozen=True)
class RegionLabels:
    """``[object] regions``: ``labels`` (H, W) uint16 (0 = no region), ``names`` {label: name} for 1..N."""

    labels: NDArray[np.uint16]
    names: dict[int, str]
    file: Path
    sha256: str

    def masks(self) -> Iterator[tuple[int, str, NDArray[np.bool_]]]:
        """(label, name, (H, W) bool mask) per region, by label; one mask at a time (24 MB each at 24 MP)."""
        for k, n in sorted(self.names.items()):
            yield k, n, self.labels == k

    def provenance(self, folder: Path) -> dict[str, Any]:
        try:
            rel = str(self.file.relative_to(folder))
        except ValueError:
            rel = str(self.file)
        return {"file": rel, "sha256": self.sha256, "labels": sorted(self.names),
                "names": {str(k): v for k, v in sorted(self.names.items())}}


def _load_label_image(t: Any, p: Path) -> NDArray[Any]:
    """The raw array of a label file (PNG via OpenCV unchanged, TIFF via tifffile, or .npy); errors name the key
    and the file."""
    expected = ("an 8- or 16-bit single-channel PNG or TIFF, or an .npy integer array (0 = no region, "
                "1..N = regions)")
    suffix = p.suffix.lower()
    if suffix not in (".png", ".tif", ".tiff", ".npy"):
        raise t.err("regions", expected, f"{p.name} (suffix {suffix or 'none'})")
    try:
        if suffix == ".png":
            import cv2
            a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if a is None:
                raise ValueError("not a readable PNG")
        elif suffix in (".tif", ".tiff"):
            import tifffile
            a = tifffile.imread(str(p))
        else:
            a = np.load(p, allow_pickle=False)
    except Exception as exc:
        raise t.err("regions", expected, f"{p.name} ({exc})") from None
    a = np.asarray(a)
    if a.ndim != 2:
        raise t.err("regions", expected, f"{p.name}: {a.ndim}-D array of shape {a.shape}"
                    + (" (a colour / multi-channel image)" if a.ndim == 3 else ""))
    if suffix != ".npy" and a.dtype not in (np.uint8, np.uint16):
        raise t.err("regions", expected, f"{p.name}: dtype {a.dtype}")
    if suffix == ".npy" and not np.issubdtype(a.dtype, np.integer):
        raise t.err("regions", expected + f" (integer dtype, labels 0..{MAX_LABEL})", f"{p.name}: dtype {a.dtype}")
    return a


def read_regions(t: Any, folder: Path, shape: tuple[int, int]) -> RegionLabels | None:
    """Read ``regions`` and ``region_names`` of an ``[object]`` table ``t`` (``rig.estimate.capture_folder._Table``).

    The label image must have the frames' size (H, W), an integer type, labels in 0..65535, at least one region,
    and every label 1..N (N = its largest label) present; ``region_names`` may name only present labels, each
    with a non-empty string (names default to "region K"). Errors are ``ConfigError`` s naming the file, the
    field and what was expected. Returns None when neither key is given."""
    from rig.files.provenance import sha256_file

    if not t.has("regions"):
        if t.has("region_names"):
            raise t.err("region_names", "nothing unless regions = \"<label image>\" is given", "region_names")
        return None
    p = t.path("regions", folder, "label image (.png, .tif or .npy)")
    a = _load_label_image(t, p)
    H, W = shape
    if a.shape != (H, W):
        raise t.err("regions", f"a label image of the frames' size {W} x {H} px (W x H)",
                    f"{p.name}: {a.shape[1]} x {a.shape[0]} px")
    lo, hi = int(a.min()), int(a.max())
    if lo < 0 or hi > MAX_LABEL:
        raise t.err("regions", f"labels in 0..{MAX_LABEL} (0 = no region)", f"{p.name}: labels {lo}..{hi}")
    if hi == 0:
        raise t.err("regions", "at least one region (labels 1..N; 0 = no region)", f"{p.name}: all pixels 0")
    present = np.flatnonzero(np.bincount(a.ravel().astype(np.int64), minlength=hi + 1))
    absent = sorted(set(range(1, hi + 1)) - set(present.tolist()))
    if absent:
        shown = ", ".join(map(str, absent[:10])) + (f" (+{len(absent) - 10} more)" if len(absent) > 10 else "")
        raise t.err("regions", f"every label 1..{hi} present (0 = no region; number the regions 1..N without gaps)",
                    f"{p.name}: label(s) {shown} absent")
    names = {k: f"region {k}" for k in range(1, hi + 1)}
    raw = t.data.get("region_names")
    if raw is not None:
        if not isinstance(raw, dict):
            raise t.err("region_names", "a table [object.region_names] mapping labels to names (1 = \"cheek\")",
                        type(raw).__name__)
        for key, val in raw.items():
            field = f"region_names.{key}"
            if not (key.isdigit() and 1 <= int(key) <= hi):
                raise t.err(field, f"a label present in {p.name} (1..{hi})", key)
            if not (isinstance(val, str) and val.strip()):
                raise t.err(field, "a non-empty string (the region's name)", val)
            names[int(key)] = val
    return RegionLabels(a.astype(np.uint16), names, p, sha256_file(p))


# ------------------------------------------------------------------------------------------------ summaries
def grounded_summary(summary: Any, radius_mm: float, eta: float) -> dict[str, Any]:
    """The capture folder's grounded sphere summary dict from an :class:`estimation.diffusion.DiffusionSummary`:
    its :meth:`as_dict`, and for the exact sphere method the dipole's measured shortening bias widening
    (:func:`estimation.sphere_bias.widen_sphere_summary`; "weak" where D spans > 3x). The whole-object summary and
    every region's use this one function."""
    out = {"estimator": f"grounded {summary.method} (docs/gradients.md sec. 5)", **summary.as_dict()}
    if summary.method == "sphere":
        from estimation.sphere_bias import widen_sphere_summary
        out = widen_sphere_summary(out, radius_mm, eta)
    return out


def _sphere_region(dmaps: Any, region: NDArray[np.bool_], radius_mm: float, eta: float, min_pixels: int,
                   pixel_stderr: Any = None) -> dict[str, Any]:
    """:func:`estimation.diffusion.summarize` over ``region`` (channels with < ``min_pixels`` usable pixels:
    unknown, values NaN, with a reason), then :func:`grounded_summary`'s widening."""
    from estimation.diffusion import summarize

    unknown = np.asarray(dmaps.unknown)
    counts = np.array([int(np.count_nonzero(region & ~unknown[..., c])) for c in range(3)])
    few = counts < min_pixels
    summ = summarize(dmaps, region if not few.all() else np.zeros_like(region), pixel_stderr=pixel_stderr)
    if few.any():       # NaN the channels below the minimum before the widening (which skips unknown channels)
        from dataclasses import replace

        from estimation.diffusion import ParameterSummary, grounded_model_bias
        params = {}
        for k, p in summ.params.items():
            v, iv = p.value.copy(), p.interval.copy()
            v[few], iv[few] = np.nan, np.nan
            params[k] = ParameterSummary(v, iv)
        status = tuple("unknown" if few[c] else summ.status[c] for c in range(3))
        prov = dict(summ.provenance)
        if "model_bias" in prov and not few.all():      # evaluated again without the dropped channels
            prov["model_bias"] = grounded_model_bias(params["sigma_s_prime_per_mm"].value,
                                                     params["sigma_a_per_mm"].value, dmaps.eta, prov["model"])
        summ = replace(summ, params=params, status=status, provenance=prov)
    out = grounded_summary(summ, radius_mm, eta)
    out["n_pixels"] = counts.tolist()
    if few.any():
        out["reason"] = [f"{counts[c]} usable pixel(s) < {min_pixels}: no distribution-free 95 % interval of the "
                         "median" if few[c] else None for c in range(3)]
    return out


def _relief_region(fit: Any, region: NDArray[np.bool_]) -> dict[str, Any]:
    """:func:`estimation.relief.summarize_relief` over the windows lying >= :data:`MIN_WINDOW_FRACTION` inside
    ``region``; unknown channels get the reason."""
    from estimation.relief import summarize_relief

    reg = summarize_relief(fit, region, min_in_region=MIN_WINDOW_FRACTION)
    out = {"estimator": "relief blur (estimation.relief; docs/gradients.md sec. 9)",
           "window_rule": f"windows of {fit.window_px} px with >= {MIN_WINDOW_FRACTION:.0%} of their pixels in the "
                          "region", **reg.as_dict()}
    n_in = int(reg.provenance.get("windows_in_region", 0))
    if "unknown" in reg.status:
        out["reason"] = [None if s != "unknown" else
                         (f"no window of {fit.window_px} px lies >= {MIN_WINDOW_FRACTION:.0%} inside the region "
                          "(use a smaller --relief-window-px or a larger region)" if n_in == 0 else
                          f"none of the {n_in} window(s) in the region is usable in this channel (dark, too few "
                          "valid pixels, or relief below its noise)") for s in reg.status]
    return out


def channel_medians(a: Any, known: NDArray[np.bool_]) -> list[float | None]:
    """Per channel, the median of ``a[..., c]`` over the ``known[..., c]`` pixels (None where none is known): the
    summaries of the whole object and of each region."""
    out: list[float | None] = []
    for c in range(3):
        v = np.asarray(a[..., c], dtype=np.float64)[known[..., c]]
        out.append(float(np.median(v)) if v.size else None)
    return out


def region_summaries(regions: RegionLabels, maps: Any, albedo_apparent: Any, *, diffusion: Any = None,
                     relief_fit: Any = None, radius_mm: float | None = None, eta: float | None = None,
                     unknown_reason: str | None = None, min_pixels: int = MIN_REGION_PIXELS,
                     pixel_stderr: Any = None) -> list[dict[str, Any]]:
    """One summary per region: ``label``, ``name``, ``n_pixels_label`` (pixels carrying the label), ``maps``
    (``known_pixels``, ``R_d_median``, ``albedo_apparent_median`` per channel over the label's known pixels) and
    ``diffusion``: with a sphere's grounded maps (``diffusion``, ``radius_mm``, ``eta``) the sphere region summary,
    with a relief fit (``relief_fit``: :class:`estimation.relief.ReliefFit`) the relief region summary, otherwise
    unknown with the whole object's reason (``unknown_reason``)."""
    known = ~np.asarray(maps.unknown)
    out: list[dict[str, Any]] = []
    for label, name, m in regions.masks():
        k = known & m[..., None]
        entry: dict[str, Any] = {
            "label": label, "name": name, "n_pixels_label": int(np.count_nonzero(m)),
            "maps": {"known_pixels": [int(np.count_nonzero(k[..., c])) for c in range(3)],
                     "R_d_median": channel_medians(maps.albedo, k),
                     "albedo_apparent_median": channel_medians(albedo_apparent, k)}}
        if diffusion is not None:
            assert radius_mm is not None and eta is not None
            entry["diffusion"] = _sphere_region(diffusion, m, radius_mm, eta, min_pixels, pixel_stderr)
        elif relief_fit is not None:
            entry["diffusion"] = _relief_region(relief_fit, m)
        else:
            entry["diffusion"] = {"status": ["unknown"] * 3,
                                  "reason": f"as the whole object: {unknown_reason or 'diffusion unknown'}"}
        out.append(entry)
    return out


def _num(v: Any) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, ".4g")


def format_regions(regions: list[Mapping[str, Any]] | None) -> list[str]:
    """Table lines of the per-region summaries (``rig estimate gradients`` without ``--json``)."""
    if not regions:
        return []
    lines = [f"regions ({len(regions)}): D [mm] with 95 % interval per channel",
             f"{'label':>5}  {'name':<16}{'pixels':>8}  {'ch':<3}{'R_d':>8}{'D [mm]':>10}{'95 % interval':>22}"
             f"{'sigma_s_prime':>15}{'sigma_a':>11}  status"]
    for r in regions:
        d = r.get("diffusion", {})
        for c, ch in enumerate("RGB"):
            D = d.get("D_mm", {}).get("value", [None] * 3)[c]
            iv = d.get("D_mm", {}).get("interval", [[None, None]] * 3)[c]
            ss = d.get("sigma_s_prime_per_mm", {}).get("value", [None] * 3)[c]
            sa = d.get("sigma_a_per_mm", {}).get("value", [None] * 3)[c]
            head = f"{r['label']:>5}  {str(r['name'])[:15]:<16}{r['n_pixels_label']:>8}" if c == 0 else " " * 31
            ivs = "-" if iv is None or iv[0] is None else f"[{_num(iv[0])}, {_num(iv[1])}]"
            lines.append(f"{head}  {ch:<3}{_num(r['maps']['R_d_median'][c]):>8}{_num(D):>10}{ivs:>22}"
                         f"{_num(ss):>15}{_num(sa):>11}  {d.get('status', ['unknown'] * 3)[c]}")
    return lines
