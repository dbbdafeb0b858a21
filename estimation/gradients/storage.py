"""Results of the gradient-map computation and their storage: in RAM or per-tile memory maps (bounded memory), the
derived and unit-vector map views, and the tile workers (``estimation.gradients``).
"""
from __future__ import annotations

import operator as _op
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


# --------------------------------------------------------------------------------------------------------------
# result types
# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GradientMasks:
    """Boolean masks; per-channel ones are (H, W, 3), per-pixel ones (H, W)."""

    saturated: NDArray[np.bool_]      # (H, W, 3) any input frame >= saturation * white_level in that channel
    dark: NDArray[np.bool_]           # (H, W, 3) full-on signal below dark_threshold * white_level
    inconsistent: NDArray[np.bool_]   # (H, W, 3) non-finite input, rho <= 0 or |n~| > max_length
    grazing: NDArray[np.bool_]        # (H, W) n.v < cos(grazing_deg)
    background: NDArray[np.bool_]     # (H, W) all channels dark, or outside object_mask

    @property
    def unknown(self) -> NDArray[np.bool_]:
        """(H, W, 3): no usable diffuse estimate (the union of all masks)."""
        return (self.saturated | self.dark | self.inconsistent
                | self.grazing[..., None] | self.background[..., None])


@dataclass(frozen=True)
class GradientMaps:
    """Maps from :func:`compute_maps`. Float maps are float32 and NaN wherever ``masks.unknown`` is set.

    ``diffuse_vectors`` (H, W, 3 channels, 3 xyz): ideal-equivalent gradient vector v (length tau_ratio for a
    flat surface, shorter where subsurface blur averages curved normals). ``diffuse_normals``: v normalized.
    ``albedo`` (H, W, 3): total diffuse reflectance R_d (see the module docstring). ``specular_*`` are None
    without parallel-polarized frames; ``specular_normals`` (H, W, 3) come from the channel-summed specular
    signal (halfway between the reflection vector and the view direction), ``specular_albedo`` (H, W, 3).
    ``consistency`` (H, W, 3): ideal mode with full + complements: max_i |(I_i + I~_i)/I_c - 1|; LED mode:
    relative RMS residual of the per-pixel least-squares solve (0 when exactly determined).
    """

    albedo: NDArray[np.float32]
    diffuse_vectors: NDArray[np.float32]
    diffuse_normals: NDArray[np.float32]
    masks: GradientMasks
    tau_ratio: float
    eta: float
    view_dirs: NDArray[np.float32]
    specular_albedo: NDArray[np.float32] | None = None
    specular_normals: NDArray[np.float32] | None = None
    reflection_vectors: NDArray[np.float32] | None = None
    specular_unknown: NDArray[np.bool_] | None = None
    consistency: NDArray[np.float32] | None = None
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def unknown(self) -> NDArray[np.bool_]:
        return self.masks.unknown

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.albedo.shape[0]), int(self.albedo.shape[1]))

    def diffuse_length(self) -> NDArray[np.float32]:
        """|v| / tau_ratio (H, W, 3): 1 for a flat Fresnel-Lambertian surface."""
        return (np.linalg.norm(self.diffuse_vectors, axis=-1) / self.tau_ratio).astype(np.float32)


# --------------------------------------------------------------------------------------------------------------
# output storage: RAM or per-tile memory maps (bounded memory)
# --------------------------------------------------------------------------------------------------------------
Allocator = Callable[[str, tuple[int, ...], Any], NDArray[Any]]


def map_allocator(out_dir: str | Path | None, prefix: str = "") -> Allocator:
    """``allocate(name, shape, dtype)`` for full-size output maps: ``np.empty`` in RAM when ``out_dir`` is None,
    otherwise a ``<prefix><name>.npy`` memory map (``np.lib.format.open_memmap``) in ``out_dir`` (created).

    With memory maps the maps are written tile by tile and never held whole in the process's memory; they stay
    readable as ordinary arrays (and with ``np.load(path, mmap_mode="r")`` later).
    """
    if out_dir is None:
        return lambda name, shape, dtype: np.empty(shape, dtype)
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)

    def allocate(name: str, shape: tuple[int, ...], dtype: Any) -> NDArray[Any]:
        return np.lib.format.open_memmap(folder / f"{prefix}{name}.npy", mode="w+", dtype=dtype, shape=shape)

    return allocate


class DerivedMap:
    """A read-only full-size map that is *not stored*: computed element-wise from stored maps on access.

    ``func(*sources)`` must be element-wise (so it commutes with indexing); every source has this map's
    ``shape`` (use ``np.broadcast_to`` views for lower-dimensional ones). Indexing (``m[r0:r1]``,
    ``m[..., c][mask]``) evaluates only the selection; ``np.asarray(m)`` materializes the whole map in RAM
    (row tiles of 256, so temporaries stay small); other ndarray attributes and arithmetic go through that
    materialization. ``definition`` says how the map is derived (copied into the provenance / sidecar).
    """

    __array_priority__ = 20.0
    _rows = 256

    def __init__(self, func: Callable[..., Any], sources: tuple[Any, ...], shape: tuple[int, ...],
                 dtype: Any = np.float32, definition: str = "") -> None:
        self._func = func
        self._sources = tuple(sources)
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self.definition = definition
        for src in self._sources:
            if tuple(np.shape(src)) != self.shape:
                raise ValueError(f"source of shape {np.shape(src)} for a derived map of shape {self.shape}")

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def _eval(self, key: Any) -> NDArray[Any]:
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return np.asarray(self._func(*(src[key] for src in self._sources)), dtype=self.dtype)

    def __getitem__(self, key: Any) -> NDArray[Any]:
        return self._eval(key)

    def __array__(self, dtype: Any = None, copy: Any = None) -> NDArray[Any]:
        out = np.empty(self.shape, self.dtype)
        for r0 in range(0, max(self.shape[0], 1), self._rows):
            out[r0:r0 + self._rows] = self._eval(slice(r0, r0 + self._rows))
        return out if dtype is None else out.astype(dtype, copy=False)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(np.asarray(self), name)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(shape={self.shape}, dtype={self.dtype}, {self.definition!r})"


def _binary(op: Callable[[Any, Any], Any], reflected: bool) -> Callable[[Any, Any], Any]:
    if reflected:
        return lambda self, other: op(other, np.asarray(self))
    return lambda self, other: op(np.asarray(self), other)


for _name, _f in (("add", _op.add), ("sub", _op.sub), ("mul", _op.mul), ("truediv", _op.truediv),
                  ("pow", _op.pow), ("matmul", _op.matmul), ("lt", _op.lt), ("le", _op.le), ("gt", _op.gt),
                  ("ge", _op.ge), ("eq", _op.eq), ("ne", _op.ne), ("and", _op.and_), ("or", _op.or_)):
    setattr(DerivedMap, f"__{_name}__", _binary(_f, False))
    if _name not in ("lt", "le", "gt", "ge", "eq", "ne"):
        setattr(DerivedMap, f"__r{_name}__", _binary(_f, True))


DerivedMap.__neg__ = lambda self: -np.asarray(self)  # type: ignore[attr-defined]


DerivedMap.__invert__ = lambda self: ~np.asarray(self)  # type: ignore[attr-defined]


DerivedMap.__hash__ = None  # type: ignore[assignment]


def _unit(v: NDArray[np.float32]) -> NDArray[np.float32]:
    """v / |v| over the last axis, in float32 exactly as compute_maps forms it (sqrt(x^2 + y^2 + z^2))."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    n = np.sqrt(x * x + y * y + z * z)
    return v / n[..., None]


class UnitVectorMap(DerivedMap):
    """``diffuse_normals`` = ``diffuse_vectors`` / |``diffuse_vectors``| (H, W, 3 channels, 3 xyz), derived on
    access (a normalization over the last axis: the leading part of a key selects the vectors first)."""

    def __init__(self, vectors: Any) -> None:
        super().__init__(_unit, (vectors,), np.shape(vectors), np.float32,
                         "diffuse_vectors / |diffuse_vectors| (per channel)")

    def _eval(self, key: Any) -> NDArray[Any]:
        src = self._sources[0]
        k = key if isinstance(key, tuple) else (key,)
        nd = self.ndim
        if any(e is None for e in k) or sum(e is Ellipsis for e in k) > 1:
            return np.asarray(self)[key]
        ell = [j for j, e in enumerate(k) if e is Ellipsis]
        if ell:
            i = ell[0]
            used = sum(np.ndim(e) if isinstance(e, np.ndarray) and e.dtype == bool else 1
                       for e in k if e is not Ellipsis)
            k = k[:i] + (slice(None),) * (nd - used) + k[i + 1:]
        used = sum(np.ndim(e) if isinstance(e, np.ndarray) and e.dtype == bool else 1 for e in k)
        if used < nd:  # the last axis is not indexed
            k = k + (slice(None),) * (nd - used)
        last = k[-1]
        lead = k[:-1]
        advanced = any(isinstance(e, (np.ndarray, list)) for e in lead)
        if advanced and not (isinstance(last, slice) and last == slice(None)):
            return np.asarray(self)[key]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return np.asarray(_unit(np.asarray(src[lead + (slice(None),)], dtype=np.float32))[..., last])


def tile_workers(workers: int | None) -> int:
    """Threads over row tiles: ``workers`` if given (>= 1), else min(2, CPUs). numpy releases the GIL inside its
    array operations, so tiles overlap; each tile writes only its own rows, so the result does not depend on it."""
    import os

    if workers is None:
        return max(1, min(2, os.cpu_count() or 1))
    if int(workers) < 1:
        raise ValueError("workers must be >= 1")
    return int(workers)


def _run_tiles(fn: Callable[[int, int], None], H: int, tile_rows: int, workers: int) -> None:
    """fn(r0, r1) over the row tiles, in ``workers`` threads (in order when 1); exceptions propagate."""
    starts = list(range(0, H, tile_rows))
    if workers <= 1 or len(starts) <= 1:
        for r0 in starts:
            fn(r0, min(H, r0 + tile_rows))
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=workers) as ex:
        for f in [ex.submit(fn, r0, min(H, r0 + tile_rows)) for r0 in starts]:
            f.result()


def _flat(a: NDArray[Any], n: int) -> NDArray[Any]:
    """(H, W, *rest) output array viewed as (H*W, *rest) without copying (outputs are allocated contiguous)."""
    if not a.flags.c_contiguous:  # pragma: no cover - allocators return C-contiguous arrays
        raise ValueError("output arrays must be C-contiguous")
    return a.reshape((n,) + a.shape[2:])
