"""The frames' noise of a capture folder (issue 16, "intervals from the frames' noise"): ``[noise]`` shot + read
noise or a per-frame standard-error image (``[[frames]] stderr_file``), read and checked with errors that name the
file and field; turned into per-frame standard-error images for :func:`estimation.gradients.uncertainty.
propagate_frame_noise`. Documented in ``docs/capture-folder.md`` (``[noise]``) and ``docs/gradients.md`` sec. 9.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.errors import ConfigError
from rig.files.imageio import ImageFileError, read_image

from .spec import FrameKey, _rel, _Table

__all__ = ["NoiseSpec", "read_frame_stderr", "read_noise"]


@dataclass(frozen=True)
class NoiseSpec:
    """``source`` "shot+read" (``electrons_per_value``, ``read_noise`` per channel, frame values) or
    "stderr_file" (``stderr`` by frame key, (H, W, 3) float32 in frame values, ``files`` their paths)."""

    source: str
    electrons_per_value: NDArray[np.float64] | None = None
    read_noise: NDArray[np.float64] | None = None
    stderr: dict[FrameKey, NDArray[np.float32]] = field(default_factory=dict)
    files: dict[FrameKey, Path] = field(default_factory=dict)

    def stderr_images(self, images: Any) -> dict[FrameKey, NDArray[np.float32]]:
        """Standard-error images (frame values) of every frame in ``images`` (by key)."""
        if self.source == "stderr_file":
            return dict(self.stderr)
        from estimation.gradients.uncertainty import shot_read_stderr
        assert self.electrons_per_value is not None and self.read_noise is not None
        return {k: shot_read_stderr(v, self.electrons_per_value, self.read_noise) for k, v in images.items()}

    def provenance(self, folder: Path) -> dict[str, Any]:
        if self.source == "stderr_file":
            return {"source": "stderr_file", "files": {f"{p}/{pol}": _rel(f, folder)
                                                        for (p, pol), f in self.files.items()}}
        assert self.electrons_per_value is not None and self.read_noise is not None
        return {"source": "shot+read", "electrons_per_value": self.electrons_per_value.tolist(),
                "read_noise": self.read_noise.tolist()}


def read_frame_stderr(t: _Table, folder: Path, shape: tuple[int, int]) -> tuple[NDArray[np.float32], Path]:
    """``[[frames]] stderr_file``: an EXR / float TIFF of the frame's size, 1 or 3 channels, standard errors >= 0
    in frame values (NaN: no information; such pixels get an infinite standard error)."""
    p = t.path("stderr_file", folder, "standard-error image (EXR or float TIFF)")
    try:
        a, _ = read_image(p, allow_nonfinite=True)
    except ImageFileError as exc:
        raise t.err("stderr_file", f"a readable standard-error image ({exc.reason})", _rel(p, folder)) from None
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.shape[:2] != shape or a.shape[-1] != 3:
        raise t.err("stderr_file", f"an image of the frames' size {shape[1]} x {shape[0]} px with 1 or 3 channels",
                    f"{_rel(p, folder)}: {a.shape[1]} x {a.shape[0]} px")
    fin = np.isfinite(a)
    if np.any(a[fin] < 0):
        raise t.err("stderr_file", "standard errors >= 0 (NaN where unknown)",
                    f"{_rel(p, folder)}: min {float(a[fin].min()):.3g}")
    return np.where(fin, a, np.inf).astype(np.float32), p


def read_noise(file: str, data: dict[str, Any], frame_stderr: dict[FrameKey, tuple[NDArray[np.float32], Path]],
               n_frames: int) -> NoiseSpec | None:
    """``[noise]`` (``electrons_per_value`` with optional ``read_noise``) or ``stderr_file`` on every frame (the
    two are exclusive), else None (the maps' intervals then come from the pixels' scatter alone)."""
    if frame_stderr and len(frame_stderr) != n_frames:
        raise ConfigError(file, "frames[].stderr_file", f"a standard-error image on every frame or on none "
                          f"({len(frame_stderr)} of {n_frames} frames have one)",
                          sorted(f"{p}/{pol}" for p, pol in frame_stderr))
    if "noise" not in data:
        if not frame_stderr:
            return None
        return NoiseSpec("stderr_file", stderr={k: v[0] for k, v in frame_stderr.items()},
                         files={k: v[1] for k, v in frame_stderr.items()})
    if not isinstance(data["noise"], dict):
        raise ConfigError(file, "noise", "a table [noise] with electrons_per_value (+ read_noise)",
                          type(data["noise"]).__name__)
    t = _Table(file, data["noise"], "noise.", ("electrons_per_value", "read_noise"))
    if frame_stderr:
        raise t.err("electrons_per_value", "nothing: give [noise] or a stderr_file on every frame, not both",
                    "both")
    g = t.rgb("electrons_per_value", positive=True)
    r = t.rgb("read_noise", 0.0, nonneg=True)
    return NoiseSpec("shot+read", electrons_per_value=g, read_noise=r)
