"""Memory housekeeping for processes that run many runs (campaign workers, test sessions, the service's workers):
what the first run leaves alive is frozen out of the garbage collector, and what a run frees goes back to the OS."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc

import pyarrow as pa

# reading the journal back and writing telemetry.parquet at the end of a run: the system allocator hands the buffers
# back to the OS (Arrow's default pool keeps them: +25-40 MB after every long run)
RELEASING_POOL = pa.system_memory_pool()


_RUNS_STARTED = 0


def freeze_long_lived() -> None:
    """At the start of a process's second run: what is alive then (imports and JIT, paid by the first run; a test
    session's objects) is collected and moved out of the cyclic garbage collector's generations (gc.freeze), so
    the full collection after each later run's plot walks only what that run created. Once only: freezing before
    every run would keep each earlier run's cyclic garbage for good (+5 MB a run, measured). A process with one
    run (drivebench run) never pays it."""
    global _RUNS_STARTED
    _RUNS_STARTED += 1
    if _RUNS_STARTED == 2:
        gc.collect()
        gc.freeze()


def release_freed_memory(collect: bool = True) -> None:
    """After the end-of-run steps (the plot, Parquet): freed buffers go back to the OS instead of staying in the
    allocators' free lists, so a process that runs many runs (a campaign worker, a long session) stays flat.
    collect: first a full garbage collection (~25 ms; a matplotlib figure is a web of cycles)."""
    if collect:
        gc.collect()
    pa.default_memory_pool().release_unused()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _load_libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None      # glibc only
    except OSError:
        return None


_LIBC = _load_libc()

