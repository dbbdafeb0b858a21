"""Light specifications understood by the Monte Carlo renderer, and their conversion to kernel arrays.

- :class:`estimation.single_image.PointLights`: isotropic points, radiant intensity (L, C) or (L,).
- :class:`estimation.single_image.EnvironmentMap`: a distant lat-long radiance map in the rig frame, looked up
  at full resolution as piecewise constant per pixel (its ``max_size`` only concerns the estimators).
- :class:`GradientPattern`: the LED sphere's continuous patterns (Ma et al. 2007; docs/gradients.md) as a distant
  radiance L(w) = radiance * P(w): "full" P = 1, "x"/"y"/"z" P = (w_i + 1)/2, "x_c"/"y_c"/"z_c" P = (1 - w_i)/2,
  with w the unit direction from the object towards the sphere. :func:`uniform_environment` = "full".

Distant radiance and point lights may be combined (a list); all maps/patterns add up.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np
import numpy.typing as npt

from estimation.single_image import EnvironmentMap, PointLights

__all__ = ["GradientPattern", "uniform_environment", "KernelLights", "kernel_lights", "PATTERN_COEFFS",
           "env_nee_table", "ENV_NEE_FACTOR"]

FloatArray = npt.NDArray[np.float64]

PATTERN_COEFFS: dict[str, tuple[float, tuple[float, float, float]]] = {
    "full": (1.0, (0.0, 0.0, 0.0)),
    "x": (0.5, (0.5, 0.0, 0.0)), "y": (0.5, (0.0, 0.5, 0.0)), "z": (0.5, (0.0, 0.0, 0.5)),
    "x_c": (0.5, (-0.5, 0.0, 0.0)), "y_c": (0.5, (0.0, -0.5, 0.0)), "z_c": (0.5, (0.0, 0.0, -0.5)),
}


@dataclass(frozen=True)
class GradientPattern:
    """Distant radiance ``radiance`` * P(w) of a spherical gradient pattern (see module docstring)."""

    pattern: str
    radiance: Any = 1.0  # scalar or (C,)

    def __post_init__(self) -> None:
        if self.pattern not in PATTERN_COEFFS:
            raise ValueError(f"unknown pattern {self.pattern!r}; valid: {', '.join(PATTERN_COEFFS)}")


def uniform_environment(radiance: Any = 1.0) -> GradientPattern:
    """Constant distant radiance (the white furnace when radiance = 1)."""
    return GradientPattern("full", radiance)


class KernelLights(NamedTuple):
    """Per-channel arrays for the kernels."""

    positions_mm: FloatArray   # (L, 3)
    intensity: FloatArray      # (L,)
    cdf: FloatArray            # (L,) light-selection CDF (proportional to intensity)
    env_map: FloatArray        # (H, W) radiance or (1, 1) zeros
    has_map: bool
    affine: FloatArray         # (4,): radiance a + b.w
    has_affine: bool
    # next-event estimation of the map's bright pixels (:func:`env_nee_table`): (n, 5) rows of [CDF, row, column,
    # radiance, solid angle] ((0, 5) when none), and the map without those pixels (what escaping paths look up)
    env_nee: FloatArray
    env_rest: FloatArray


def _per_channel(value: Any, n_channels: int, what: str) -> FloatArray:
    v = np.asarray(value, float)
    if v.ndim == 0:
        return np.full(n_channels, float(v))
    v = v.reshape(-1)
    if v.size == 1:
        return np.full(n_channels, float(v[0]))
    if v.size != n_channels:
        raise ValueError(f"{what} has {v.size} channels, the media {n_channels}")
    return v


#: map pixels brighter than this many times the map's mean radiance (4 pi average) are sampled by next-event
#: estimation (a sun, a window, a studio light) instead of being found by escaping paths
ENV_NEE_FACTOR: float = 4.0


def env_nee_table(env_map: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The bright pixels of a lat-long map (module docstring of :mod:`.walk`, "environment next-event estimation")
    as (n, 5) rows [CDF by power, row, column, radiance, solid angle], and the map with them zeroed."""
    h, w = env_map.shape
    theta = np.pi * np.arange(h + 1) / h
    omega = ((np.cos(theta[:-1]) - np.cos(theta[1:])) * (2.0 * np.pi / w))[:, None] * np.ones((1, w))
    total = float(np.sum(env_map * omega))
    if not total > 0:
        return np.zeros((0, 5)), env_map
    bright = env_map > ENV_NEE_FACTOR * total / (4.0 * np.pi)
    if not bright.any():
        return np.zeros((0, 5)), env_map
    rows, cols = np.nonzero(bright)
    power = env_map[rows, cols] * omega[rows, cols]
    cdf = np.cumsum(power) / power.sum()
    cdf[-1] = 1.0
    table = np.stack([cdf, rows.astype(float), cols.astype(float), env_map[rows, cols], omega[rows, cols]], axis=1)
    rest = np.where(bright, 0.0, env_map)
    return np.ascontiguousarray(table), np.ascontiguousarray(rest)


def kernel_lights(lights: Any, n_channels: int) -> list[KernelLights]:
    """Convert one light spec or a sequence of them into one :class:`KernelLights` per channel."""
    items: Sequence[Any] = lights if isinstance(lights, (list, tuple)) else [lights]
    pos: list[FloatArray] = []
    inten: list[FloatArray] = []
    env: FloatArray | None = None
    aff = np.zeros((n_channels, 4))
    has_aff = False
    for it in items:
        if isinstance(it, PointLights):
            p = np.asarray(it.positions_mm, float).reshape(-1, 3)
            i = np.asarray(it.intensity, float)
            if i.ndim <= 1 and i.size == len(p):
                i = np.repeat(i.reshape(-1, 1), n_channels, axis=1)
            elif i.shape == (len(p), 1):
                i = np.repeat(i, n_channels, axis=1)
            elif i.shape != (len(p), n_channels):
                raise ValueError("PointLights.intensity must be (L,) or (L, C) with C the number of media")
            if np.any(i < 0):
                raise ValueError("light intensities must be >= 0")
            pos.append(p)
            inten.append(np.asarray(i, float))
        elif isinstance(it, EnvironmentMap):
            if env is not None:
                raise ValueError("at most one EnvironmentMap")
            img = np.asarray(it.radiance, float)
            if img.ndim == 2:
                img = img[:, :, None]
            if img.shape[2] == 1 and n_channels > 1:
                img = np.repeat(img, n_channels, axis=2)
            if img.shape[2] != n_channels:
                raise ValueError("EnvironmentMap channels do not match the media")
            env = img
        elif isinstance(it, GradientPattern):
            a, b = PATTERN_COEFFS[it.pattern]
            rad = _per_channel(it.radiance, n_channels, "GradientPattern.radiance")
            aff += rad[:, None] * np.array([a, *b])[None, :]
            has_aff = True
        else:
            raise TypeError(f"unsupported light {type(it).__name__}; use PointLights, EnvironmentMap, "
                            "GradientPattern")
    P = np.concatenate(pos) if pos else np.zeros((0, 3))
    I = np.concatenate(inten) if inten else np.zeros((0, n_channels))
    out = []
    for c in range(n_channels):
        ic = np.ascontiguousarray(I[:, c]) if len(P) else np.zeros(0)
        tot = ic.sum()
        cdf = np.cumsum(ic) / tot if tot > 0 else np.zeros_like(ic)
        if len(cdf):
            cdf[-1] = 1.0 if tot > 0 else 0.0
        m = np.ascontiguousarray(env[:, :, c]) if env is not None else np.zeros((1, 1))
        table, rest = env_nee_table(m) if env is not None else (np.zeros((0, 5)), m)
        out.append(KernelLights(np.ascontiguousarray(P), ic, cdf, m, env is not None,
                                np.ascontiguousarray(aff[c]), has_aff, table, rest))
    return out
