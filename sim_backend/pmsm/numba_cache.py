"""Numba's on-disk cache keys a function on its own file only: a cached kernel keeps the old code of the
functions it calls from other modules. Call drop_stale_cache(__file__, deps) at import, before the first
call of any cached function, to remove this module's cache entries when a dependency's source changed."""

from __future__ import annotations

import hashlib
from pathlib import Path

from numba.core import config
from numba.core.caching import UserProvidedCacheLocator


def _cache_dir(module_file: str) -> Path:
    """Where numba caches this module's functions (in-tree __pycache__ or NUMBA_CACHE_DIR)."""
    if config.CACHE_DIR:
        return Path(config.CACHE_DIR) / UserProvidedCacheLocator.get_suitable_cache_subpath(module_file)
    return Path(module_file).parent / "__pycache__"


def drop_stale_cache(module_file: str, dependency_files: list[str]) -> None:
    module = Path(module_file)
    digest = hashlib.sha256()
    for dep in sorted(dependency_files):
        digest.update(Path(dep).read_bytes())
    cache_dir = _cache_dir(module_file)
    stamp = cache_dir / f"{module.stem}.deps.sha256"
    current = digest.hexdigest()
    try:
        if stamp.read_text() == current:
            return
    except OSError:
        pass
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        for entry in cache_dir.glob(f"{module.stem}.*.nb[ic]"):
            entry.unlink(missing_ok=True)
        stamp.write_text(current)
    except OSError:
        pass  # read-only install: numba then cannot cache either
