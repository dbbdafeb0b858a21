"""Keep numba's on-disk cache consistent across the package's modules.

numba (``cache=True``) keys a cached function by the timestamp of *its own* source file only, so a kernel that
inlines functions from a sibling module (render -> walk -> nee -> shapes) would keep stale machine code after
that sibling changes. At import, this hashes every source file of the package and, when the hash differs from
the one stored next to the cache, deletes the package's cached kernels (``__pycache__/*.nbi|*.nbc``) so they are
recompiled once. Honours NUMBA_CACHE_DIR only in the default layout; failures (read-only trees) are ignored.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

_HERE = Path(__file__).resolve().parent


def sources_hash() -> str:
    h = hashlib.sha256()
    for p in sorted(_HERE.glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def ensure_fresh_cache() -> None:
    cache = _HERE / "__pycache__"
    stamp = cache / "mc_sources.sha256"
    digest = sources_hash()
    try:
        if stamp.exists() and stamp.read_text().strip() == digest:
            return
        cache.mkdir(exist_ok=True)
        for f in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
            f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass
