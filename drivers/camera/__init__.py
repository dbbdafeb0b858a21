"""Cameras: linear RAW frames (``contracts.Camera``).

* :mod:`.raw` - RAW/DNG -> linear float32 RGB by 2x2 CFA superpixel binning (rawpy).
* :mod:`.folder` - ``FolderCamera``: frames are RAW files dropped into a folder by tethering software or by
  the simulated camera.
"""
from __future__ import annotations

from .folder import FolderCamera
from .raw import RawFileError, load_linear

__all__ = ["FolderCamera", "RawFileError", "load_linear"]
