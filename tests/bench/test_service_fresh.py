"""The service's in-memory answers (bench.service.fresh): one read however many ask, a read ahead of expiry that
nobody waits for, the previous answer while a change is read (but not to a reader told of the change, nor to a
request for a fresh answer), and never an answer older than max_age_s."""

from __future__ import annotations

import asyncio

import pytest

from bench.service import fresh
from bench.service.fresh import FreshCache


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(fresh.time, "monotonic", c)
    return c


class Source:
    """A read that counts itself, answers the value it holds and can be held up until released."""

    def __init__(self, value: object = "v1") -> None:
        self.value = value
        self.reads = 0
        self.gate: asyncio.Event | None = None
        self.failures = 0

    async def read(self) -> object:
        self.reads += 1
        value = self.value
        if self.gate is not None:
            await self.gate.wait()
        if self.failures:
            self.failures -= 1
            raise RuntimeError("database gone")
        return value


def test_fifty_callers_that_miss_at_once_share_one_read(clock):
    async def main():
        cache, source = FreshCache(1.0, 10), Source()
        source.gate = asyncio.Event()
        callers = [asyncio.create_task(cache.get("k", 0, source.read)) for _ in range(50)]
        await asyncio.sleep(0)
        source.gate.set()
        return await asyncio.gather(*callers), source.reads
    answers, reads = asyncio.run(main())
    assert answers == ["v1"] * 50 and reads == 1


def test_an_answer_is_read_again_in_the_background_from_a_quarter_of_its_age_and_never_served_past_it(clock):
    async def main():
        cache, source = FreshCache(1.0, 10), Source("v1")
        assert await cache.get("k", 0, source.read) == "v1" and source.reads == 1
        source.value = "v2"
        clock.now += 0.2                          # young: from memory, no read
        assert await cache.get("k", 0, source.read) == "v1" and source.reads == 1
        clock.now += 0.2                          # past a quarter of its age: from memory, and one read behind it
        source.gate = asyncio.Event()
        assert [await cache.get("k", 0, source.read) for _ in range(5)] == ["v1"] * 5
        await asyncio.sleep(0)
        assert source.reads == 2
        source.gate.set()
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert await cache.get("k", 0, source.read) == "v2" and source.reads == 2
        source.value, source.gate = "v3", None
        clock.now += 1.0                          # expired: the caller waits for a read
        assert await cache.get("k", 0, source.read) == "v3" and source.reads == 3
    asyncio.run(main())


def test_after_a_change_the_previous_answer_is_served_while_the_new_one_is_read(clock):
    async def main():
        cache, source = FreshCache(1.0, 10), Source("before")
        assert await cache.get("k", 0, source.read) == "before"
        source.value, source.gate = "after", asyncio.Event()
        assert [await cache.get("k", 1, source.read) for _ in range(3)] == ["before"] * 3
        await asyncio.sleep(0)
        assert source.reads == 2                  # one read of the new version, behind the answers
        source.gate.set()
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert await cache.get("k", 1, source.read) == "after" and source.reads == 2
        clock.now += 1.0                          # a previous answer is never served past its age either
        source.gate, source.value = None, "later"
        assert await cache.get("k", 2, source.read) == "later"
    asyncio.run(main())


def test_a_reader_told_of_a_change_and_a_request_for_a_fresh_answer_wait_for_the_read(clock):
    async def main():
        cache, source = FreshCache(10.0, 10), Source("before")
        for key in ("runs", "rigs", "leases"):
            assert await cache.get(key, 0, source.read) == "before"
        source.value = "after"
        assert await cache.get("rigs", 1, source.read) == "before"          # the previous answer, read behind
        cache.show(2)                             # an event of version 2 delivered to everyone
        source.value = "event"
        assert await cache.get("runs", 2, source.read) == "event"
        source.value = "newest"
        assert await cache.get("leases", 2, source.read, fresh=True) == "newest"
        assert await cache.get("rigs", 3, source.read, fresh=True) == "newest"
        source.value = "unseen"                   # a change no version tells of: a fresh request reads it
        assert await cache.get("rigs", 3, source.read) == "newest"
        assert await cache.get("rigs", 3, source.read, fresh=True) == "unseen"
    asyncio.run(main())


def test_a_read_of_an_older_version_that_ends_late_does_not_replace_a_newer_answer(clock):
    async def main():
        cache, slow, quick = FreshCache(10.0, 10), Source("old"), Source("new")
        slow.gate = asyncio.Event()
        old = asyncio.create_task(cache.get("k", 0, slow.read))   # a read under way when a write happens
        await asyncio.sleep(0)
        assert await cache.get("k", 1, quick.read) == "new"        # the change's reader
        slow.gate.set()
        assert await old == "old"
        assert await cache.get("k", 1, Source("unused").read) == "new"
    asyncio.run(main())


def test_a_failed_read_reaches_its_caller_and_the_waiters_read_for_themselves(clock):
    async def main():
        cache, source = FreshCache(1.0, 10), Source("v")
        source.gate, source.failures = asyncio.Event(), 1
        first = asyncio.create_task(cache.get("k", 0, source.read))
        await asyncio.sleep(0)
        waiter = asyncio.create_task(cache.get("k", 0, source.read))
        await asyncio.sleep(0)
        source.gate.set()
        with pytest.raises(RuntimeError, match="database gone"):
            await first
        assert await waiter == "v" and source.reads == 2
    asyncio.run(main())


def test_an_answer_that_may_not_be_kept_is_read_every_time(clock):
    async def main():
        cache, source = FreshCache(1.0, 10, keep=lambda value: value != "error"), Source("error")
        for _ in range(3):
            assert await cache.get("k", 0, source.read) == "error"
        return source.reads
    assert asyncio.run(main()) == 3


def test_what_one_reader_was_shown_does_not_hold_up_another(clock):
    async def main():
        cache, source = FreshCache(10.0, 10), Source("before")
        for reader in ("ci", "lab"):
            assert await cache.get("runs", 0, source.read, reader) == "before"
        source.value, source.gate = "after", asyncio.Event()
        cache.show(1, "ci")                        # ci's own write
        assert await cache.get("runs", 1, source.read, "lab") == "before"   # lab: the previous answer at once
        ci = asyncio.create_task(cache.get("runs", 1, source.read, "ci"))  # ci: waits for the read lab started
        await asyncio.sleep(0)
        assert not ci.done() and source.reads == 2
        source.gate.set()
        assert await ci == "after" and source.reads == 2
    asyncio.run(main())


def test_a_change_reads_again_at_once_the_answers_in_use_and_only_those(clock):
    async def main():
        cache, used, idle = FreshCache(1.0, 10), Source("u0"), Source("i0")
        assert await cache.get("idle", 0, idle.read) == "i0"
        clock.now += 0.3                          # nobody asked for "idle" within a quarter of its age
        assert await cache.get("used", 0, used.read) == "u0"
        used.value, idle.value = "u1", "i1"
        cache.changed(1)
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert used.reads == 2 and idle.reads == 1
        assert await cache.get("used", 1, used.read, "ci") == "u1" and used.reads == 2   # read already, no wait
    asyncio.run(main())
