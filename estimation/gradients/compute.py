"""Per-pixel gradient maps (:func:`compute_maps`): ideal and LED-rig normal solves vectorized over blocks of pixels
(float32, channel last), streamed by tiles (``estimation.gradients``; Ma et al. 2007).
"""
from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..fresnel import fresnel_transmittance
from .response import (_AXES, _DEFAULT_VIEW, GRADIENT_PATTERNS, Array, LedRig, ResponseLUT, _solve_table, _SolveTable,
                       build_response_lut, frame_key, tau_ratio)
from .storage import GradientMaps, GradientMasks, UnitVectorMap, _flat, _run_tiles, map_allocator, tile_workers


# --------------------------------------------------------------------------------------------------------------
# per-pixel computations (vectorized over blocks of pixels; float32; channel last)
# --------------------------------------------------------------------------------------------------------------
_BLOCK_PX = 1 << 14  # pixels per vectorized block: (M, 3) float32 temporaries of 192 kB stay in the L2 cache


def _ideal_vectors(I: Mapping[str, Array]) -> tuple[Array, Array, Array | None]:
    """Continuous formulas: v (..., 3ch, 3xyz), full-on signal (..., 3ch), complement consistency or None."""
    comps, full_sig, cons = _ideal_components(I)
    return np.stack(comps, axis=-1), full_sig, cons


def _ideal_components(I: Mapping[str, Array]) -> tuple[list[Array], Array, Array | None]:
    """v_x, v_y, v_z (each (..., 3ch)), the full-on signal and max_i |(I_i + I~_i)/I_c - 1| (or None)."""
    full = I.get("full")
    if full is None:
        sums = [I[a] + I[a + "_c"] for a in _AXES if a in I and a + "_c" in I]
        full_sig = sums[0] if len(sums) == 1 else sum(sums[1:], sums[0]) / len(sums)
    else:
        full_sig = full
    comps = []
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for a in _AXES:
            if a in I and a + "_c" in I:
                comps.append((I[a] - I[a + "_c"]) / (I[a] + I[a + "_c"]))
            elif a in I and full is not None:
                comps.append(2.0 * I[a] / full - 1.0)
            elif a + "_c" in I and full is not None:
                comps.append(1.0 - 2.0 * I[a + "_c"] / full)
            else:
                raise ValueError(f"axis {a!r}: need '{a}' and '{a}_c', or either one with 'full'")
        cons = None
        if full is not None:
            for a in _AXES:
                if a in I and a + "_c" in I:
                    t = np.abs((I[a] + I[a + "_c"]) / full - 1.0)
                    cons = t if cons is None else np.fmax(cons, t)
    return comps, full_sig, cons


def _norm3(x: Array, y: Array, z: Array) -> Array:
    return np.sqrt(x * x + y * y + z * z)


def _mean_direction(comps: list[Array], w: Array) -> Array:
    """Weighted mean direction (M, 3) of per-channel vectors ``comps`` = [x, y, z] (each (M, 3ch)); NaN rows where
    no channel has a finite vector with weight > 0."""
    inv = 1.0 / _norm3(*comps)
    ok = np.isfinite(inv) & (w > 0)
    wn = np.where(ok, w * inv, 0.0)
    s = np.stack([np.einsum("mc,mc->m", wn, np.where(ok, c, 0.0)) for c in comps], axis=-1)
    n = np.sqrt(np.einsum("mk,mk->m", s, s))[:, None]
    return np.where(n > 0, s / n, np.nan)


def _finite_or(n: Array, fallback: Array) -> Array:
    """Rows of ``n`` (M, 3) that are finite, else ``fallback``."""
    return np.where(np.isfinite(n[:, 0] + n[:, 1] + n[:, 2])[:, None], n, fallback)


def _oct_index(n: Array, size: int) -> NDArray[np.intp]:
    """Index of the nearest node of a size x size octahedral grid (row-major) for unit vectors ``n`` (M, 3)."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    a = np.abs(x) + np.abs(y) + np.abs(z)
    u, w, z = x / a, y / a, z / a
    lower = z < 0
    uu = np.where(lower, (1.0 - np.abs(w)) * np.where(u >= 0, 1.0, -1.0), u)
    ww = np.where(lower, (1.0 - np.abs(u)) * np.where(w >= 0, 1.0, -1.0), w)
    h = 0.5 * (size - 1)
    with np.errstate(invalid="ignore"):  # NaN normals -> clipped index, their pixels are masked
        iu = np.clip(np.rint((uu + 1.0) * h).astype(np.intp), 0, size - 1)
        iv = np.clip(np.rint((ww + 1.0) * h).astype(np.intp), 0, size - 1)
    return iu * size + iv


def _led_solve(table: _SolveTable, Y4: Array, n0: Array, residual: bool) -> tuple[Array, list[Array], Array | None]:
    """Per pixel and channel least squares I_P = rho a_P + b_P.(rho n~) at the lookup normals ``n0`` (M, 3).

    ``Y4`` (P, M, 4): the ambient-subtracted signals in four lanes (R, G, B, 0). Returns rho (M, 3) (in units of
    the reference full-on response), [n~_x, n~_y, n~_z] (each (M, 3)) and the relative RMS residual (M, 3)
    (None unless ``residual``).
    """
    P = table.n_patterns
    M = n0.shape[0]
    idx = _oct_index(n0, table.size)
    Gg = np.take(table.G, idx, axis=1).view(np.float32).reshape(4 * P, M, 4)
    x = [np.einsum("pml,pml->ml", Gg[i * P:(i + 1) * P], Y4) for i in range(4)]
    res = None
    if residual:
        if table.AtA is None:
            res = np.zeros((M, 3), np.float32)
        else:  # |I - A x|^2 = |I|^2 - x^T (A^T A) x (x solves the normal equations); > 0 up to rounding
            Ng = np.take(table.AtA, idx, axis=1).view(np.float32).reshape(10, M, 4)
            yy = np.einsum("pml,pml->ml", Y4, Y4)
            xAx = np.zeros_like(yy)
            for k, (i, j) in enumerate(zip(*np.triu_indices(4))):
                xAx += Ng[k] * x[i] * x[j]
            res = np.sqrt(np.maximum(yy - xAx, 0.0) / yy)[:, :3]
    rho = x[0][:, :3]
    return np.ascontiguousarray(rho), [x[1][:, :3] / rho, x[2][:, :3] / rho, x[3][:, :3] / rho], res


@lru_cache(maxsize=16)
def _exit_fresnel_table(eta: float, n: int = 4097) -> NDArray[np.float32]:
    """F_t(eta, t) on a uniform grid of t in [0, 1] (linear interpolation error < 1e-7 for t > cos 85 deg)."""
    return fresnel_transmittance(eta, np.linspace(0.0, 1.0, n)).astype(np.float32)


def _exit_fresnel(cos: Array, table: NDArray[np.float32]) -> Array:
    n = table.size - 1
    x = np.clip(np.nan_to_num(cos), 0.0, 1.0) * n
    i = np.minimum(x.astype(np.intp), n - 1)
    f = (x - i).astype(np.float32)
    return table[i] * (1.0 - f) + table[i + 1] * f


def _read(a: Any, r0: int, r1: int) -> NDArray[Any]:
    """Rows r0:r1 of an (H, W, C) frame as an (h*W, C) array (a view of a memory map when contiguous)."""
    t = np.asarray(a[r0:r1])
    return t.reshape((-1,) + t.shape[2:])


def compute_maps(frames: Mapping[Any, ArrayLike], *, albedo_scale: ArrayLike, leds: LedRig | None = None,
                 ideal: bool = False, eta: float = 1.3, view_dirs: ArrayLike | None = None,
                 tile_rows: int = 256, white_level: float = 1.0, saturation: float = 0.98,
                 dark_threshold: float = 0.01, grazing_deg: float = 70.0,
                 object_mask: ArrayLike | None = None, geometry_normals: ArrayLike | None = None,
                 reference_normal: ArrayLike = _DEFAULT_VIEW, surface_center_mm: ArrayLike = (0.0, 0.0, 0.0),
                 surface_radius_mm: float = 0.0, lut: ResponseLUT | None = None, lut_size: int = 65,
                 lut_smoothing_rad: float | None = None, iterations: int = 2,
                 max_length: float = 1.3, exposure_s: Mapping[Any, float] | None = None,
                 out_dir: str | Path | None = None, workers: int | None = None,
                 consistency: bool = True) -> GradientMaps:
    """Diffuse albedo / normals (per RGB channel) and specular albedo / normals from gradient frames.

    ``frames``: {key: (H, W, 3) linear array} with keys ``(pattern, polarization)`` or bare pattern names
    (cross-polarized); patterns ``ambient``, ``full``, ``x``, ``y``, ``z``, ``x_c``, ``y_c``, ``z_c``. Needed:
    an ambient frame and, per axis, the gradient and its complement or either one with ``full`` (all
    cross-polarized). Parallel-polarized frames of the same patterns add the specular maps; a parallel ambient
    frame is used for them if given, otherwise the cross one. Arrays may be memory maps: they are read in
    ``tile_rows`` row tiles (and processed in blocks of 16384 pixels), so the working memory is bounded by the tile.

    ``albedo_scale`` (3,) or scalar: see the module docstring. ``leds``: discrete-LED correction (required
    unless ``ideal=True``); ``lut``: a prebuilt :func:`build_response_lut` (else built from ``leds`` with
    ``lut_size``, ``lut_smoothing_rad``, ``reference_normal``, ``surface_center_mm``, ``surface_radius_mm``).
    The per-pixel solve uses the LUT's least-squares inverse tabulated on a 4x finer octahedral grid (nearest
    node; built once per LUT and pattern set, ~0.3 s). ``iterations``: solves per pixel, each at the normal of
    the previous one (the first at the normal of the continuous formulas).
    ``view_dirs`` (H, W, 3) or (3,): unit vectors from the surface towards the camera (default (0, -1, 0), the
    rig's camera side). ``geometry_normals`` (H, W, 3): known normals, used (instead of the specular or mean
    diffuse normal) for the grazing mask and the exit-Fresnel correction of the albedo.
    Masks: saturated (>= ``saturation`` * ``white_level`` in any frame), dark (full-on signal
    < ``dark_threshold`` * ``white_level``), grazing (n.v < cos ``grazing_deg``), background (all channels dark
    or outside ``object_mask``), inconsistent (non-finite, rho <= 0, |n~| = 0 or |n~| > ``max_length``).
    ``exposure_s``: {key: exposure time} for every frame when exposures differ; each frame is then divided by its
    exposure after the saturation test (so ``albedo_scale`` converts value *per second*). Without it all frames
    must share one exposure.
    ``out_dir``: write every output map tile by tile into ``<name>.npy`` memory maps in this folder
    (:func:`map_allocator`) instead of RAM; then nothing of frame size is held in memory (``view_dirs`` given as a
    (3,) vector is stored as a zero-stride broadcast view either way). ``diffuse_normals`` is not stored: it is a
    :class:`UnitVectorMap` of ``diffuse_vectors`` (normalized on access, bit-identical to normalizing in the
    loop); ``provenance["stored"]`` / ``["derived"]`` list what was written and how the rest is derived.
    ``workers``: threads over row tiles (:func:`tile_workers`; default min(2, CPUs)); results do not depend on it.
    ``consistency=False``: skip the diagnostic ``consistency`` map (None; LED mode then also skips the residual).
    """
    if not ideal and leds is None and lut is None:
        raise ValueError("pass leds= (discrete LED correction) or ideal=True (continuous formulas)")
    keyed: dict[tuple[str, str], Any] = {}
    for k, v in frames.items():
        nk = frame_key(k)
        if nk in keyed:
            raise ValueError(f"duplicate frame for {nk}")
        keyed[nk] = v
    cross = {p: a for (p, pol), a in keyed.items() if pol == "cross" and p != "ambient"}
    par = {p: a for (p, pol), a in keyed.items() if pol == "parallel" and p != "ambient"}
    amb_c = keyed.get(("ambient", "cross"), keyed.get(("ambient", "parallel")))
    if amb_c is None:
        raise ValueError("an ambient (all-off) frame is required: key 'ambient' or ('ambient', pol)")
    if not cross:
        raise ValueError("no cross-polarized gradient frames given")
    shape = np.shape(amb_c)
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"frames must be (H, W, 3), got {shape}")
    for k, a in keyed.items():
        if np.shape(a) != shape:
            raise ValueError(f"frame {k} has shape {np.shape(a)}, expected {shape}")
    H, W = int(shape[0]), int(shape[1])
    expo: dict[tuple[str, str], float] = {k: 1.0 for k in keyed}
    if exposure_s is not None:
        given_e = {frame_key(k): float(v) for k, v in exposure_s.items()}
        missing = [k for k in keyed if k not in given_e]
        if missing:
            raise ValueError(f"exposure_s lacks frames {missing}")
        if any(not (v > 0 and np.isfinite(v)) for v in given_e.values()):
            raise ValueError("exposures must be finite and > 0")
        expo = {k: given_e[k] for k in keyed}
    inv_e = {k: 1.0 / v for k, v in expo.items()}
    amb_c_key = ("ambient", "cross") if ("ambient", "cross") in keyed else ("ambient", "parallel")
    amb_p_key = ("ambient", "parallel") if ("ambient", "parallel") in keyed else amb_c_key
    scale = np.broadcast_to(np.asarray(albedo_scale, dtype=np.float64).reshape(-1), (3,)).copy()
    if np.any(~np.isfinite(scale)) or np.any(scale <= 0):
        raise ValueError("albedo_scale must be finite and > 0")
    if tile_rows < 1:
        raise ValueError("tile_rows must be >= 1")
    n_workers = tile_workers(workers)
    # validate pattern completeness early (raises a clear ValueError)
    _ideal_vectors({p: np.ones((1, 1, 3)) for p in cross})
    spec_pats = [p for p in par if p in cross]
    want_spec = False
    if spec_pats:
        try:
            _ideal_vectors({p: np.ones((1, 1, 3)) for p in spec_pats})
            want_spec = True
        except ValueError:
            want_spec = False
    tau = tau_ratio(eta)
    if not ideal and lut is None:
        assert leds is not None
        lut = build_response_lut(leds, eta=eta, size=lut_size, smoothing_rad=lut_smoothing_rad,
                                 reference_normal=reference_normal, surface_center_mm=surface_center_mm,
                                 surface_radius_mm=surface_radius_mm)
    if lut is not None and abs(lut.eta - eta) > 1e-9:
        raise ValueError(f"lut was built for eta={lut.eta}, not {eta}")
    used = [p for p in GRADIENT_PATTERNS if p in cross]
    table = None
    if not ideal:
        assert lut is not None
        table = _solve_table(lut, tuple(lut.patterns.index(p) for p in used))

    vd_given = view_dirs is not None
    vd_in = None
    if vd_given and np.shape(view_dirs) == (H, W, 3):
        vd_in = view_dirs
    else:
        v3 = np.asarray(view_dirs if vd_given else _DEFAULT_VIEW, dtype=np.float64)
        if v3.shape != (3,):
            raise ValueError("view_dirs must be (3,) or (H, W, 3)")
        v3 = (v3 / np.linalg.norm(v3)).astype(np.float32)
    omask = None
    if object_mask is not None:
        if np.shape(object_mask) != (H, W):
            raise ValueError("object_mask must be (H, W)")
        omask = object_mask
    gnorm = None
    if geometry_normals is not None:
        if np.shape(geometry_normals) != (H, W, 3):
            raise ValueError("geometry_normals must be (H, W, 3)")
        gnorm = geometry_normals

    f32 = np.float32
    alloc = map_allocator(out_dir)
    npx = H * W
    have_cons = consistency and ((not ideal) or ("full" in cross and any(a in cross and a + "_c" in cross
                                                                         for a in _AXES)))
    albedo = alloc("albedo", (H, W, 3), f32)
    dvec = alloc("diffuse_vectors", (H, W, 3, 3), f32)
    cons_out = alloc("consistency", (H, W, 3), f32) if have_cons else None
    m_sat = alloc("mask_saturated", (H, W, 3), bool)
    m_dark = alloc("mask_dark", (H, W, 3), bool)
    m_inc = alloc("mask_inconsistent", (H, W, 3), bool)
    m_graz = alloc("mask_grazing", (H, W), bool)
    m_bg = alloc("mask_background", (H, W), bool)
    s_alb = s_norm = s_refl = s_unk = None
    if want_spec:
        s_alb = alloc("specular_albedo", (H, W, 3), f32)
        s_norm = alloc("specular_normals", (H, W, 3), f32)
        s_refl = alloc("reflection_vectors", (H, W, 3), f32)
        s_unk = alloc("specular_unknown", (H, W), bool)
    if vd_in is not None and not (isinstance(vd_in, np.ndarray) and vd_in.dtype == f32):
        vd_store = alloc("view_dirs", (H, W, 3), f32)
    elif vd_in is not None:
        vd_store = vd_in
    else:
        vd_store = np.broadcast_to(v3, (H, W, 3))
    out = {"albedo": _flat(albedo, npx), "dvec": _flat(dvec, npx),
           "sat": _flat(m_sat, npx), "dark": _flat(m_dark, npx), "inc": _flat(m_inc, npx),
           "graz": _flat(m_graz, npx), "bg": _flat(m_bg, npx)}
    if cons_out is not None:
        out["cons"] = _flat(cons_out, npx)
    if want_spec:
        assert s_alb is not None and s_norm is not None and s_refl is not None and s_unk is not None
        out.update(s_alb=_flat(s_alb, npx), s_norm=_flat(s_norm, npx), s_refl=_flat(s_refl, npx),
                   s_unk=_flat(s_unk, npx))
    vd_out = _flat(vd_store, npx) if vd_store is not vd_in and vd_in is not None else None

    sat_level = float(saturation * white_level)
    dark_level = float(dark_threshold * white_level * (inv_e[("full", "cross")] if ("full", "cross") in inv_e
                                                       else min(inv_e.values())))
    cos_graz = float(np.cos(np.deg2rad(grazing_deg)))
    scale32 = scale.astype(f32)
    ft_table = _exit_fresnel_table(float(eta))
    nan = f32(np.nan)
    cross_keys = [("ambient", amb_c_key)] + [(p, (p, "cross")) for p in used]
    par_keys = ([("ambient", amb_p_key)] + [(p, (p, "parallel")) for p in spec_pats]) if want_spec else []

    def tile(r0: int, r1: int) -> None:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # garbage pixels become NaN + masks
            t_c = {p: _read(keyed[k], r0, r1) for p, k in cross_keys}
            t_p = {p: _read(keyed[k], r0, r1) for p, k in par_keys}
            t_vd = _read(vd_in, r0, r1) if vd_in is not None else None
            t_om = _read(omask, r0, r1) if omask is not None else None
            t_gn = _read(gnorm, r0, r1) if gnorm is not None else None
            n_tile = (r1 - r0) * W
            for b0 in range(0, n_tile, _BLOCK_PX):
                b1 = min(n_tile, b0 + _BLOCK_PX)
                o0, o1 = r0 * W + b0, r0 * W + b1
                raw_c = {p: np.asarray(a[b0:b1], dtype=f32) for p, a in t_c.items()}
                raw_p = {p: np.asarray(a[b0:b1], dtype=f32) for p, a in t_p.items()}
                frames_used = list(raw_c.values()) + list(raw_p.values())
                mx = frames_used[0]
                tot = frames_used[0]
                for a in frames_used[1:]:
                    mx = np.fmax(mx, a)
                    tot = tot + a
                sat = mx >= sat_level
                bad = ~np.isfinite(tot)
                a_c = raw_c.pop("ambient")
                if inv_e[amb_c_key] != 1.0:
                    a_c = a_c * f32(inv_e[amb_c_key])
                I = {p: (a * f32(inv_e[(p, "cross")]) if inv_e[(p, "cross")] != 1.0 else a) - a_c
                     for p, a in raw_c.items()}
                comps, full_sig, cons = _ideal_components(I)
                dark = ~(full_sig >= dark_level)
                bg = dark[:, 0] & dark[:, 1] & dark[:, 2]
                if t_om is not None:
                    bg |= ~np.asarray(t_om[b0:b1], dtype=bool)
                vt = np.asarray(t_vd[b0:b1], dtype=f32) if t_vd is not None else v3
                if ideal:
                    rho_full, vc, res = full_sig, comps, cons
                else:
                    assert table is not None
                    Y = np.zeros((len(used), b1 - b0, 4), f32)
                    for k, p in enumerate(used):
                        Y[k, :, :3] = I[p]
                    w0 = np.where(full_sig > 0, full_sig, 0.0)
                    n0 = _finite_or(_mean_direction(comps, w0), vt)
                    n_it = max(1, iterations)
                    for it in range(n_it):
                        rho_full, nt, res = _led_solve(table, Y, n0, residual=have_cons and it == n_it - 1)
                        if it < n_it - 1:
                            n0 = _finite_or(_mean_direction(nt, np.where(rho_full > 0, rho_full, 0.0)), n0)
                    vc = [tau * c for c in nt]
                vlen = _norm3(*vc)
                length = vlen / tau
                inc = bad | ~np.isfinite(length) | ~(rho_full > 0) | ~(length > 0) | (length > max_length)
                unit = [c / vlen for c in vc] if t_gn is None else None
                # specular
                spec_n = None
                if want_spec:
                    a_p = raw_p.pop("ambient")
                    if inv_e[amb_p_key] != 1.0:
                        a_p = a_p * f32(inv_e[amb_p_key])
                    S = {}
                    for p, a in raw_p.items():
                        ap = a * f32(inv_e[(p, "parallel")]) if inv_e[(p, "parallel")] != 1.0 else a
                        S[p] = np.maximum((ap - a_p) - I[p], 0.0)
                    Ssum = {p: np.sum(a, axis=-1) for p, a in S.items()}
                    rc, _, _ = _ideal_components(Ssum)
                    sfull = _ideal_components(S)[1]
                    rn = _norm3(*rc)
                    r = np.stack([c / rn for c in rc], axis=-1)
                    hvec = r + vt
                    spec_n = hvec / np.sqrt(np.einsum("mk,mk->m", hvec, hvec))[:, None]
                    s_ok = (np.isfinite(spec_n).all(-1) & (np.sum(sfull, -1) >= dark_level)
                            & ~np.any(sat | bad, -1) & ~bg)
                    out["s_alb"][o0:o1] = np.where(s_ok[:, None], scale32 * sfull / 2.0, nan)
                    out["s_norm"][o0:o1] = np.where(s_ok[:, None], spec_n, nan)
                    out["s_refl"][o0:o1] = np.where(s_ok[:, None], r, nan)
                    out["s_unk"][o0:o1] = ~s_ok
                    spec_n = np.where(s_ok[:, None], spec_n, nan)
                # geometry for grazing + exit Fresnel: known > specular > mean diffuse
                if t_gn is not None:
                    n_geo = np.asarray(t_gn[b0:b1], dtype=f32)
                else:
                    assert unit is not None
                    n_geo = _mean_direction(unit, np.where(dark | inc, 0.0, 1.0).astype(f32))
                    if spec_n is not None:
                        n_geo = np.where(np.isfinite(spec_n), spec_n, n_geo)
                cos_v = np.einsum("mk,mk->m", n_geo, np.broadcast_to(vt, n_geo.shape))
                graz = ~(cos_v >= cos_graz)
                # ideal: rho_full is the full-on signal; LED mode: the LUT is normalized by E_full(n_ref), so rho is
                # the full-on signal this surface would give facing reference_normal at the origin.
                alb = scale32 * rho_full / _exit_fresnel(cos_v, ft_table)[:, None]
                inc |= ~np.isfinite(alb) & ~graz[:, None]
                unk = sat | dark | inc | graz[:, None] | bg[:, None]
                o_alb = out["albedo"][o0:o1]
                o_alb[...] = alb
                np.copyto(o_alb, nan, where=unk)
                dv = out["dvec"][o0:o1]
                for k in range(3):
                    dv[..., k] = vc[k]
                np.copyto(dv, nan, where=unk[..., None])
                if cons_out is not None:
                    assert res is not None
                    o_c = out["cons"][o0:o1]
                    o_c[...] = res
                    np.copyto(o_c, nan, where=unk)
                nbg = ~bg
                out["sat"][o0:o1] = sat
                out["dark"][o0:o1] = dark & nbg[:, None]
                out["inc"][o0:o1] = inc & nbg[:, None]
                out["graz"][o0:o1] = graz & nbg
                out["bg"][o0:o1] = bg
                if vd_out is not None:
                    vd_out[o0:o1] = vt

    _run_tiles(tile, H, tile_rows, n_workers)
    masks = GradientMasks(m_sat, m_dark, m_inc, m_graz, m_bg)
    prov: dict[str, Any] = {
        "module": "estimation.gradients", "version": 2, "method": "Ma2007",
        "mode": "ideal" if ideal else "leds", "eta": float(eta), "tau_ratio": tau,
        "patterns_cross": sorted(cross), "patterns_parallel": sorted(spec_pats) if want_spec else [],
        "albedo_scale": scale.tolist(), "reference_normal": list(map(float, np.ravel(reference_normal))),
        "view_dirs": "given" if vd_given else f"default {_DEFAULT_VIEW}",
        "geometry_normals": gnorm is not None, "white_level": white_level, "saturation": saturation,
        "dark_threshold": dark_threshold, "grazing_deg": grazing_deg, "max_length": max_length,
        "tile_rows": tile_rows, "iterations": iterations,
        "exposure_s": None if exposure_s is None else {f"{k[0]}/{k[1]}": v for k, v in expo.items()},
        "storage": "RAM" if out_dir is None else f"memory maps in {out_dir}",
        "stored": sorted(["albedo", "diffuse_vectors", "mask_saturated", "mask_dark", "mask_inconsistent",
                          "mask_grazing", "mask_background"] + (["consistency"] if cons_out is not None else [])
                         + (["specular_albedo", "specular_normals", "reflection_vectors", "specular_unknown"]
                            if want_spec else [])),
        "derived": {"diffuse_normals": "diffuse_vectors / |diffuse_vectors| (per channel), on access"},
        "workers": n_workers,
    }
    if table is not None and lut is not None:
        prov["lut"] = {"size": lut.size, "smoothing_rad": lut.smoothing_rad, "solve_grid": table.size,
                       **lut.provenance}
    return GradientMaps(
        albedo=albedo, diffuse_vectors=dvec, diffuse_normals=UnitVectorMap(dvec), masks=masks, tau_ratio=tau, eta=float(eta),
        view_dirs=vd_store, specular_albedo=s_alb, specular_normals=s_norm, reflection_vectors=s_refl,
        specular_unknown=s_unk, consistency=cons_out, provenance=prov)
