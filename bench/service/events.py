"""Run events (state, progress) from the runner thread to websocket subscribers on the event loop."""

from __future__ import annotations

import asyncio
import threading
from typing import Callable

QUEUE_LIMIT = 1000    # a subscriber that does not read loses events rather than growing without bound


class EventHub:
    def __init__(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._subscribers: dict[asyncio.Queue, object] = {}     # queue -> its reader (a token id)
        self._lock = threading.Lock()
        self.generation = 0   # counts changes (events, API writes): cached API reads of an older generation are stale
        self.on_shown: Callable[[int, object], None] = lambda generation, reader: None   # an event was delivered
        self.on_changed: Callable[[int], None] = lambda generation: None     # on the loop, after every change

    def changed(self) -> int:
        """A change: the new generation, also handed to on_changed on the loop."""
        with self._lock:
            self.generation += 1
            generation = self.generation
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self.on_changed, generation)
            except RuntimeError:      # the loop closed in between
                pass
        return generation

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    def subscribe(self, reader: object = None) -> asyncio.Queue:
        queue: asyncio.Queue = asyncio.Queue(QUEUE_LIMIT)
        with self._lock:
            self._subscribers[queue] = reader
        return queue

    def unsubscribe(self, queue: asyncio.Queue) -> None:
        with self._lock:
            self._subscribers.pop(queue, None)

    def publish(self, event: dict, changed: bool = True) -> None:
        """Thread-safe; a no-op before the loop is bound or after it closed. changed=False: the event tells
        subscribers something the database does not hold yet (a progress tick), so cached reads stay valid."""
        generation = self.changed() if changed else None
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._fan_out, event, generation)
        except RuntimeError:      # the loop closed in between
            pass

    def _fan_out(self, event: dict, generation: int | None) -> None:
        with self._lock:
            subscribers = list(self._subscribers.items())
        for queue, reader in subscribers:
            if generation is not None:    # a subscriber that reads the API next must not get an older answer
                self.on_shown(generation, reader)
            try:
                queue.put_nowait(event)
            except asyncio.QueueFull:
                pass
