"""Wire format of the drive-side trace recorder, shared by the drive (sim_backend.trace) and the clients.

A trace upload is a sequence of rows. Each row: the drive's step counter (uint32, little endian, in
control periods since power-up) followed by the selected signals as float32 little endian, in
drivers.contract.signals.SIGNAL_NAMES order. The selection is a bit mask over SIGNAL_NAMES (bit i = signal i).
"""

from __future__ import annotations

import numpy as np

from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN


def selected_names(mask: int) -> list[str]:
    return [name for i, name in enumerate(SIGNAL_NAMES) if mask >> i & 1]


def mask_for(names: list[str] | tuple[str, ...]) -> int:
    unknown = [n for n in names if n not in SIGNAL_NAMES]
    if unknown:
        raise ValueError(f"unknown signal(s) {', '.join(unknown)}")
    return sum(1 << SIGNAL_NAMES.index(n) for n in names)


def row_dtype(mask: int) -> np.dtype:
    return np.dtype([("step", "<u4")] + [(name, "<f4") for name in selected_names(mask)])


def encode_rows(steps: np.ndarray, block: np.ndarray, mask: int) -> bytes:
    """steps: (n,) step counters; block: (n, len(SIGNAL_NAMES)) values."""
    rows = np.empty(len(steps), dtype=row_dtype(mask))
    rows["step"] = steps
    for name in selected_names(mask):
        rows[name] = block[:, SIGNAL_NAMES.index(name)]
    return rows.tobytes()


def decode_rows(data: bytes, mask: int, control_period_s: float) -> dict[str, np.ndarray]:
    """Columns t_s (drive clock, s) and each selected signal as float64."""
    dtype = row_dtype(mask)
    if len(data) % dtype.itemsize:
        raise ValueError(f"trace data of {len(data)} bytes is not a whole number of {dtype.itemsize}-byte rows")
    rows = np.frombuffer(data, dtype=dtype)
    columns = {TIME_COLUMN: rows["step"].astype(np.float64) * control_period_s}
    for name in selected_names(mask):
        columns[name] = rows[name].astype(np.float64)
    return columns
