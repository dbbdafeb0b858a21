"""Atomic file writes: the one writer of every layer (drivers' downloads, simulators' frames and tables, the rig's
sessions, calibration files, maps and reports).

A file is written to a temporary name beside its target, flushed and fsync'd, then renamed onto the target (or,
with ``overwrite=False``, hard-linked to it, which fails if the target appeared meanwhile: no silent clobbering),
and the directory is fsync'd so the rename survives a power cut. On any failure, including KeyboardInterrupt, the
temporary file is removed and the target is untouched: a reader sees the old file or the whole new one, never a
part (POSIX rename semantics; docs/capture-and-resume.md).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable

__all__ = ["atomic_write", "atomic_write_bytes", "fsync_dir"]

#: permissions of a written file (mkstemp creates 0600; frames, maps and reports are ordinary data files)
FILE_MODE = 0o644


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """fsync a directory (its entries: a rename or link into it is durable afterwards)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], None], *, overwrite: bool = True) -> Path:
    """Call ``write(tmp_path)`` on a temporary file next to ``path`` (missing parent folders are made), fsync it
    and move it onto ``path``. ``overwrite=False`` raises FileExistsError if ``path`` exists (also if it appears
    while writing). Returns ``path``."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not overwrite and p.exists():
        raise FileExistsError(f"{p}: refusing to overwrite an existing file")
    # the temporary keeps the target's extension: writers that infer the format from the name (OpenCV) need it
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=p.suffix, dir=p.parent)
    os.close(fd)
    tmp_p = Path(tmp)
    try:
        write(tmp_p)
        with open(tmp_p, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp_p, FILE_MODE)
        if overwrite:
            os.replace(tmp_p, p)
        else:
            try:
                os.link(tmp_p, p)
            except FileExistsError:
                raise FileExistsError(f"{p}: refusing to overwrite an existing file") from None
            tmp_p.unlink()
    except BaseException:
        tmp_p.unlink(missing_ok=True)
        raise
    fsync_dir(p.parent)
    return p


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, overwrite: bool = True) -> Path:
    """:func:`atomic_write` of ``data``."""
    return atomic_write(path, lambda tmp: tmp.write_bytes(data), overwrite=overwrite)
