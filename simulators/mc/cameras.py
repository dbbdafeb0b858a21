"""Cameras of the Monte Carlo renderer: :class:`estimation.camera.PinholeCamera` and
:class:`estimation.camera.OrthographicCamera` (re-exported here); the renderer needs only ``width_px``,
``height_px`` and ``pixel_rays()``."""
from __future__ import annotations

from estimation.camera import OrthographicCamera

__all__ = ["OrthographicCamera"]
