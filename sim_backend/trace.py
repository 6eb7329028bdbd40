"""The drive-side trace recorder: a ring buffer of control-rate samples the bench uploads in blocks."""

from __future__ import annotations

import numpy as np

from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract.trace_format import encode_rows, row_dtype

TRIGGER_IMMEDIATE = 0       # records from start()
TRIGGER_ON_ENABLE = 1       # records from the first sample with the power stage enabled


CAPACITY_ROWS = 65_536      # 65 s at the benches' 1 kHz trace rate, 4.5 MB (a real drive's is smaller)


class TraceRecorder:
    def __init__(self, capacity_rows: int = CAPACITY_ROWS):
        self.capacity_rows = capacity_rows
        self.mask = (1 << len(SIGNAL_NAMES)) - 1
        self.decimation = 1
        self.trigger = TRIGGER_IMMEDIATE
        self.running = False
        self.triggered = False
        self.lost_rows = 0
        # the drive's RAM is all there from the start: zeros written, not lazily mapped pages that a long run would
        # touch one by one as the ring's write position first goes round (RSS growing for as long as that takes)
        self._steps = np.empty(capacity_rows, dtype=np.uint32)
        self._steps.fill(0)
        self._rows = np.empty((capacity_rows, len(SIGNAL_NAMES)), dtype=np.float32)
        self._rows.fill(0.0)
        self._head = 0      # next row to read
        self._count = 0     # rows held

    def configure(self, mask: int, decimation: int, trigger: int = TRIGGER_IMMEDIATE) -> None:
        if mask <= 0 or mask >> len(SIGNAL_NAMES):
            raise ValueError(f"signal mask 0x{mask:x} selects no or unknown signals")
        if decimation < 1:
            raise ValueError("decimation must be >= 1")
        self.mask, self.decimation, self.trigger = mask, decimation, trigger
        self.clear()

    def clear(self) -> None:
        self._head = self._count = 0
        self.lost_rows = 0
        self.triggered = False

    def start(self) -> None:
        self.running = True
        self.triggered = self.trigger == TRIGGER_IMMEDIATE

    def stop(self) -> None:
        self.running = False

    @property
    def row_size(self) -> int:
        return row_dtype(self.mask).itemsize

    @property
    def rows_available(self) -> int:
        return self._count

    def push(self, first_step: int, block: np.ndarray, enabled: bool) -> None:
        """block row k is the sample after drive step first_step + k."""
        if not self.running:
            return
        if not self.triggered:
            if self.trigger == TRIGGER_ON_ENABLE and enabled:
                self.triggered = True
            else:
                return
        # the rows whose step is a multiple of the decimation: a strided view, not a mask over every step
        decimation = self.decimation
        offset = (-first_step) % decimation
        block = block[offset::decimation]
        n = len(block)
        steps = np.arange(first_step + offset, first_step + offset + n * decimation, decimation, dtype=np.int64)
        if n > self.capacity_rows:     # more than the ring holds: only the newest rows survive
            self.lost_rows += n - self.capacity_rows
            steps, block, n = steps[-self.capacity_rows:], block[-self.capacity_rows:], self.capacity_rows
        overflow = self._count + n - self.capacity_rows
        if overflow > 0:               # ring full: the oldest rows are overwritten
            self._head = (self._head + overflow) % self.capacity_rows
            self._count -= overflow
            self.lost_rows += overflow
        start = (self._head + self._count) % self.capacity_rows
        if start + n <= self.capacity_rows:        # the usual case: one stretch of the ring
            self._steps[start:start + n] = steps
            self._rows[start:start + n] = block
        else:
            idx = (start + np.arange(n)) % self.capacity_rows
            self._steps[idx] = steps
            self._rows[idx] = block
        self._count += n

    def read(self, max_rows: int) -> bytes:
        """Remove and return up to max_rows of the oldest rows, encoded (drivers.contract.trace_format)."""
        n = min(max_rows, self._count)
        idx = (self._head + np.arange(n)) % self.capacity_rows
        self._head = (self._head + n) % self.capacity_rows
        self._count -= n
        return encode_rows(self._steps[idx], self._rows[idx].astype(np.float64), self.mask)
