"""Answers kept in memory for a while, read once however many ask at the same moment, and read again in the
background before they expire, so that a busy API seldom makes a client wait for a read (the answers come from
memory on the event loop; the reads run on worker threads).

An answer belongs to a version (the service's change counter; a token table's revocations) and is never served
once it is max_age_s old. From a quarter of that age on, the first caller starts one background read that
replaces it, and `changed` reads again at once every answer in steady use. After a change (a newer
version) the previous answer is still served while the new one is read (RFC 5861's stale-while-revalidate),
except to a reader that `show` says has learnt of the change (a websocket event delivered to it; without a
reader: everyone, as after a write through the API): it waits for the read (the service's readers are its
tokens). A caller that asks for a fresh answer gets a read that starts then. Answers of one key only move
forward: a read of an older version never replaces a newer answer. Callers that miss while a read of the same key
and version is under way wait for that read instead of starting their own.
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
        self._used: dict[Hashable, tuple[float, Callable[[], Awaitable[T]]]] = {}   # a kept answer's last asker
        self._reading: dict[tuple[Hashable, int], asyncio.Future] = {}
        self._background: set[asyncio.Task] = set()

    def clear(self) -> None:
        self._entries.clear()
        self._used.clear()

    def changed(self, version: int) -> None:
        """A newer version exists (on the event loop): the answers in steady use (asked for within the last quarter
        of their age) are read again now, so that the next callers find them read instead of being the ones who
        start the reads; the others are read when next asked for."""
        now = time.monotonic()
        for key, (used, read) in list(self._used.items()):
            hit = self._entries.get(key)
            if now - used < self.refresh_after_s and hit is not None and hit[1] < version \
                    and (key, version) not in self._reading:
                self._behind(key, version, read)

    def show(self, version: int, reader: Hashable | None = None) -> None:
        if reader is None:
            self.shown = max(self.shown, version)
        elif self._floors.get(reader, 0) < version:
            if len(self._floors) >= self.max_entries and reader not in self._floors:
                self._floors.clear()           # forgetting a floor only makes those readers wait for reads
                self.shown = max(self.shown, version)
            self._floors[reader] = version

    async def get(self, key: Hashable, version: int, read: Callable[[], Awaitable[T]],
                  reader: Hashable | None = None, fresh: bool = False) -> T:
        """fresh: a read that starts now (a client's Cache-Control: no-cache), kept for the others."""
        if fresh:
            return await self._read(key, version, read, self._claim(key, version))
        now = time.monotonic()
        hit = self._entries.get(key)
        if hit is not None:
            self._used[key] = (now, read)
        if hit is not None and now - hit[0] < self.max_age_s:
            born, was, value = hit
            if was == version or (not fresh and was >= max(self.shown, self._floors.get(reader, 0))):
                if (was != version or now - born >= self.refresh_after_s) and (key, version) not in self._reading:
                    self._behind(key, version, read)
                return value
        reading = self._reading.get((key, version))
        if reading is not None:
            done, value = await asyncio.shield(reading)
            if done:
                return value
        return await self._read(key, version, read, self._claim(key, version))

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
                    self.clear()
                self._entries[key] = (born, version, value)
                if not background:
                    self._used[key] = (born, read)
        return value
