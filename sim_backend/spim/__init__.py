"""Simulated single-phase induction motor drive (SPIM paper): plant, three-leg inverter, ISFOC firmware."""

from __future__ import annotations

import hashlib
from pathlib import Path


def _drop_stale_numba_cache() -> None:
    """numba's on-disk cache of a function is keyed on its own file only: a compiled kernel that inlines
    code from plant.py / inverter.py / firmware.py / mechanics.py / numerics.py would survive edits of those files.
    Keep a digest of all of them next to the cache and drop the cache when it changes."""
    here = Path(__file__).resolve().parent
    sources = sorted(here.glob("*.py")) + [here.parent / "mechanics.py", here.parent / "numerics.py"]
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sources if p.exists())).hexdigest()
    cache = here / "__pycache__"
    stamp = cache / "spim-sources.sha256"
    try:
        if stamp.read_text() == digest:
            return
    except OSError:
        pass
    try:
        cache.mkdir(exist_ok=True)
        for f in cache.glob("*.nb[ic]"):
            f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass  # read-only install: numba then falls back to compiling in memory


_drop_stale_numba_cache()
