"""Answers kept in memory for a while, read once however many ask at the same moment, and read again in the
background before they expire, so that a busy API seldom makes a client wait for a read (the answers come from
memory on the event loop; the reads run on worker threads).

An answer belongs to a version (the service's change counter; a token table's revocations) and is never served
once it is max_age_s old. From a quarter of that age on, the first caller starts one background read that
replaces it. After a change (a newer version) the previous answer is still served while the new one is read
(RFC 5861's stale-while-revalidate), but never older than anything its reader was already shown (the session
guarantees of read-your-writes and monotonic reads, per reader: the service's readers are its tokens): once a
reader got an answer of a version, or `show` says it learnt of one another way (a websocket event delivered to
it, its own write answered), it gets no answer of an older version and waits for the read instead. `show` without
a reader is for everyone. Callers that miss while a read of the same key and version is under way wait for that
read instead of starting their own.
"""

from __future__ import annotations

import asyncio
import time
from typing import Awaitable, Callable, Generic, Hashable, TypeVar

T = TypeVar("T")


class FreshCache(Generic[T]):
    def __init__(self, max_age_s: float, max_entries: int, keep: Callable[[T], bool] = lambda value: True):
        self.max_age_s = max_age_s
        self.refresh_after_s = max_age_s / 4
        self.shown = 0                                    # the newest version everyone has been shown
        self._floors: dict[Hashable, int] = {}           # the newest version each reader has been shown
        self.max_entries = max_entries
        self.keep = keep                                  # whether an answer may be kept (an error is not)
        self._entries: dict[Hashable, tuple[float, int, T]] = {}
        self._reading: dict[tuple[Hashable, int], asyncio.Future] = {}
        self._background: set[asyncio.Task] = set()

    def clear(self) -> None:
        self._entries.clear()

    def show(self, version: int, reader: Hashable | None = None) -> None:
        if reader is None:
            self.shown = max(self.shown, version)
        elif self._floors.get(reader, 0) < version:
            if len(self._floors) >= self.max_entries and reader not in self._floors:
                self._floors.clear()           # forgetting a floor only makes those readers wait for reads
                self.shown = max(self.shown, version)
            self._floors[reader] = version

    async def get(self, key: Hashable, version: int, read: Callable[[], Awaitable[T]],
                  reader: Hashable | None = None) -> T:
        now = time.monotonic()
        hit = self._entries.get(key)
        if hit is not None and now - hit[0] < self.max_age_s:
            born, was, value = hit
            if was == version or was >= max(self.shown, self._floors.get(reader, 0)):
                if (was != version or now - born >= self.refresh_after_s) and (key, version) not in self._reading:
                    self._behind(key, version, read)
                self.show(was, reader)
                return value
        reading = self._reading.get((key, version))
        if reading is not None:
            done, value = await asyncio.shield(reading)
            if done:
                self.show(version, reader)
                return value
        value = await self._read(key, version, read, self._claim(key, version))
        self.show(version, reader)
        return value

    def _behind(self, key: Hashable, version: int, read: Callable[[], Awaitable[T]]) -> None:
        task = asyncio.ensure_future(self._read(key, version, read, self._claim(key, version), background=True))
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def _claim(self, key: Hashable, version: int) -> asyncio.Future:
        """Marks the read as under way before it runs: the callers of the same turn of the loop wait for it."""
        future: asyncio.Future = asyncio.get_running_loop().create_future()
        self._reading[(key, version)] = future
        return future

    async def _read(self, key: Hashable, version: int, read: Callable[[], Awaitable[T]], future: asyncio.Future,
                    background: bool = False) -> T:
        born = time.monotonic()
        outcome: tuple[bool, T | None] = (False, None)     # waiters of a read that failed read for themselves
        try:
            value = await read()
            outcome = (True, value)
        except Exception:
            if background:         # the next caller that misses reads in the foreground and sees the error itself
                return None        # type: ignore[return-value]
            raise
        finally:
            if self._reading.get((key, version)) is future:
                del self._reading[(key, version)]
            future.set_result(outcome)
        if self.keep(value):
            old = self._entries.get(key)
            if old is None or (old[1], old[0]) <= (version, born):
                if old is None and len(self._entries) >= self.max_entries:
                    self._entries.clear()
                self._entries[key] = (born, version, value)
        return value
