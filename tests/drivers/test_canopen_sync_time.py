"""Time on a real-time CANopen rig: samples placed on the SYNC they answer (late frames are jitter, a missing answer
is a gap), SYNC interval statistics, the SYNC counter on the wire, and the standard drive behaviours a vendor drive
may have (cyclic synchronous velocity only, event-driven TPDOs only, a slow boot) run instead of being refused."""

from __future__ import annotations

import contextlib
import heapq
import random
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from bench.inputs.criteria import time_axis
from drivers.contract.errors import LinkError
from drivers.api import LinkSettings
from drivers.contract import objects as o
from drivers.canopen.bus import bus_kwargs
from drivers.canopen.link import CanopenDriveLink
from drivers.canopen.sync import IntervalStats, SyncProducer, SyncTimeline
from drivers.contract.cia402 import Mode
from sim_backend.canopen.generic import DriveSpec
from sim_backend.rig import RigSpec, build, private_channel

REPO = Path(__file__).resolve().parents[2]
MOTOR = REPO / "config/motors/pmsm-paper.toml"
LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a", "vdc_v"]
E35 = DriveSpec(velocity_unit="rpm", rated_current_a=3.5355, rated_torque_nm=3.9)
PERIOD = 0.01


def eds_path(name: str) -> Path:
    return REPO / "config/od/third-party" / f"{name}.eds"


# -- the placement rule on its own ------------------------------------------------------------------------------------

class FakeSyncs:
    """SYNC n sent at t0 + (n - 1) * period (what SyncProducer.sent_before / epoch_of give)."""

    def __init__(self, period: float, t0: float = 1000.0):
        self.period, self.t0, self.sent = period, t0, 0

    def epoch_of(self, seq: int) -> float | None:
        return self.t0 + (seq - 1) * self.period if 1 <= seq <= self.sent else None

    def sent_before(self, t: float) -> tuple[int, float | None]:
        n = min(self.sent, int((t - self.t0) // self.period) + 1) if t >= self.t0 else 0
        return n, self.epoch_of(n)


def answers(n: int, period: float, delay, lost=(), stamped=True, t0: float = 1000.0):
    """(seq, stamp, received) of each answer the bench gets: the drive answers SYNC k 0.3 ms after it, the wire
    delivers it `delay(k)` later, in order; `lost`: SYNCs never answered."""
    out, last = [], 0.0
    for k in range(1, n + 1):
        if k in lost:
            continue
        on_bus = t0 + (k - 1) * period + 0.0003
        last = max(last, on_bus + delay(k))
        out.append((k, on_bus if stamped else None, last))
    return out


@pytest.mark.parametrize("stamped", [True, False], ids=["bus-stamps", "receive-time"])
def test_frames_delayed_1_5_to_3_sync_periods_keep_their_sync(stamped):
    rng = random.Random(3)
    syncs = FakeSyncs(PERIOD)
    timeline = SyncTimeline(PERIOD, syncs.sent_before, syncs.epoch_of)
    placed = []
    for seq, stamp, received in answers(500, PERIOD, lambda k: rng.uniform(1.5, 3.0) * PERIOD, stamped=stamped):
        syncs.sent = max(syncs.sent, int((received - syncs.t0) // PERIOD) + 1)     # what the bench sent by then
        placed.append((seq, timeline.place(stamp, received)))
    assert all(want == got for want, got in placed)
    assert timeline.unanswered == 0


@pytest.mark.parametrize("stamped", [True, False], ids=["bus-stamps", "receive-time"])
def test_a_missing_answer_is_counted_and_leaves_a_gap(stamped):
    syncs = FakeSyncs(PERIOD)
    timeline = SyncTimeline(PERIOD, syncs.sent_before, syncs.epoch_of)
    t = []
    for seq, stamp, received in answers(300, PERIOD, lambda k: 0.001, lost={100}, stamped=stamped):
        syncs.sent = max(syncs.sent, int((received - syncs.t0) // PERIOD) + 1)
        t.append(timeline.place(stamp, received) * PERIOD)
    assert timeline.unanswered == 1
    holes = time_axis(np.array(t), PERIOD, 1.5)
    assert holes["missing_rows"] == 1 and holes["duplicates"] == 0
    assert t[-1] == pytest.approx(300 * PERIOD)              # after the gap every answer is on its own SYNC again


def test_a_silence_before_the_run_is_not_the_runs_gap():
    """The drive is silent on purpose for SYNCs 101-107 (pre-operational during the comm-loss drill); the run starts
    (rebase) and its answers are placed on the SYNCs they answer: no gap in the run, nothing unanswered in it."""
    syncs = FakeSyncs(PERIOD)
    timeline = SyncTimeline(PERIOD, syncs.sent_before, syncs.epoch_of)
    t = []
    for seq, stamp, received in answers(300, PERIOD, lambda k: 0.001, lost=set(range(101, 108)), stamped=True):
        syncs.sent = max(syncs.sent, int((received - syncs.t0) // PERIOD) + 1)
        if seq == 108:
            timeline.rebase()                                   # enable: the run's time starts here
        placed = timeline.place(stamp, received)
        if seq >= 108:
            t.append(placed * PERIOD)
        assert placed == seq
    assert timeline.unanswered == 0 and timeline.report()["unanswered_before_run"] == 0
    holes = time_axis(np.array(t), PERIOD, 1.5)
    assert holes["missing_rows"] == 0 and holes["duplicates"] == 0


def test_interval_statistics():
    stats = IntervalStats(0.01)
    for _ in range(98):
        stats.add(0.0100)
    stats.add(0.0160)                     # late: > 1.5 periods
    stats.add(0.0300)
    s = stats.summary()
    assert s["intervals"] == 100 and s["late"] == 2 and s["max_ms"] == 30.0
    assert s["p50_ms"] == pytest.approx(10.0, abs=0.011) and s["p99_ms"] == pytest.approx(16.0, abs=0.011)


def test_sync_counter_on_the_wire_and_absolute_deadlines():
    """SYNC frames carry the CiA 301 counter 1..overflow; the producer keeps its schedule (absolute deadlines): the
    n-th SYNC leaves at start + n periods, not later and later."""
    channel = private_channel()
    sender = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    listener = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    producer = SyncProducer(lambda data: sender.send(can.Message(arbitration_id=0x80, data=data,
                                                                 is_extended_id=False)),
                            0.005, lambda e: None, counter_overflow=4)
    try:
        producer.start()
        frames = []
        while len(frames) < 40:
            msg = listener.recv(1.0)
            assert msg is not None
            frames.append(msg)
        producer.stop()
    finally:
        sender.shutdown()
        listener.shutdown()
    counters = [m.data[0] for m in frames]
    assert counters[:9] == [1, 2, 3, 4, 1, 2, 3, 4, 1] and all(len(m.data) == 1 for m in frames)
    span = frames[-1].timestamp - frames[0].timestamp
    sent = producer.count
    assert span == pytest.approx(39 * 0.005, abs=0.005 + producer.skipped * 0.005)
    assert producer.report()["sent"] == sent and producer.report()["intervals"] == sent - 1


def test_socketcand_connections_are_tuned_for_latency_unless_told_not_to():
    section = {"interface": "socketcand", "channel": "can0@127.0.0.1:29536"}
    assert bus_kwargs(section)["tcp_tune"] is True
    assert bus_kwargs({**section, "can": {"tcp_tune": False}})["tcp_tune"] is False


# -- the link in real time behind a wire that delays or loses TPDOs -------------------------------------------------

class DelayingWire:
    """Relays frames between the drive's channel and the bench's: TPDOs delayed 1.5-3 SYNC periods (in order);
    everything else at once. `preserve`: frames keep the drive's send stamp (an interface that stamps on the bus),
    else they are stamped on delivery (receive time)."""

    def __init__(self, drive_channel: str, preserve: bool, seed: int = 5):
        self.channel = private_channel()
        self.drive_side = can.Bus(interface="virtual", channel=drive_channel, receive_own_messages=False)
        self.bench_side = can.Bus(interface="virtual", channel=self.channel, receive_own_messages=False,
                                  preserve_timestamps=preserve)
        self.rng = random.Random(seed)
        self._heap: list = []
        self._order = 0
        self._last = 0.0
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=f, daemon=True) for f in (self._up, self._down, self._deliver)]
        for thread in self._threads:
            thread.start()

    def _up(self):                         # bench -> drive, at once
        while not self._stop.is_set():
            msg = self.bench_side.recv(0.01)
            if msg is not None:
                self.drive_side.send(msg)

    def _down(self):                       # drive -> bench
        while not self._stop.is_set():
            msg = self.drive_side.recv(0.01)
            if msg is None:
                continue
            now = time.monotonic()
            if 0x180 < msg.arbitration_id < 0x500:
                at = max(self._last, now + self.rng.uniform(1.5, 3.0) * PERIOD)
                self._last = at
            else:
                at = now
            with self._cv:
                self._order += 1
                heapq.heappush(self._heap, (at, self._order, msg))
                self._cv.notify()

    def _deliver(self):
        while not self._stop.is_set():
            with self._cv:
                if not self._heap:
                    self._cv.wait(0.01)
                    continue
                at, _, msg = self._heap[0]
                if at > time.monotonic():
                    self._cv.wait(at - time.monotonic())
                    continue
                heapq.heappop(self._heap)
            self.bench_side.send(msg)

    def stop(self):
        self._stop.set()
        for thread in self._threads:
            thread.join(1.0)
        self.drive_side.shutdown()
        self.bench_side.shutdown()


def record_answers(node, lose: dict | None = None) -> dict[int, dict[int, bytes]]:
    """The drive's TPDO payloads per SYNC it answered (its own SYNC count); lose["sync"]: that SYNC goes unanswered."""
    sent: dict[int, dict[int, bytes]] = {}
    frames_for = node.pdos.tpdo_frames

    def wrapped(sync_count, *args):
        frames = frames_for(sync_count, *args)
        if node.nmt_state == o.NMT_OPERATIONAL and frames:
            if lose is not None and sync_count == lose.get("sync"):
                return []
            sent[sync_count] = dict(frames)
        return frames

    node.pdos.tpdo_frames = wrapped
    return sent


@contextlib.contextmanager
def realtime_link_behind(wire_kwargs: dict, spec: DriveSpec = E35, eds: str = "e35", **section):
    with build(RigSpec(motor=MOTOR, seed=1, eds=eds_path(eds), drive=spec)) as rig:
        wire = DelayingWire(rig.channel, **wire_kwargs)
        fields = dict(transport="canopen", interface="virtual", channel=wire.channel, node_id=1,
                      eds=str(eds_path(eds)), sync_period_s=PERIOD, heartbeat_timeout_s=2.0, sdo_timeout_s=2.0,
                      consumer_time_ms=2000)
        link = CanopenDriveLink(fields | section, REPO, LinkSettings(timing="realtime"))
        try:
            yield link, rig, wire
        finally:
            link.close()
            wire.stop()


def run_for(link, seconds: float) -> list:
    samples, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        samples.extend(link.sync())
    return samples


@pytest.mark.slow
@pytest.mark.parametrize("preserve", [True, False], ids=["bus-stamps", "receive-time"])
def test_tpdos_delayed_on_the_wire_still_give_a_complete_run_with_the_right_times(preserve):
    with realtime_link_behind({"preserve": preserve}) as (link, rig, wire):
        sent = record_answers(rig.node)
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        samples = run_for(link, 2.0)
        link.quick_stop()
        link.disable()
        report = link.sync_report()
    assert report["time_base"] == "sync answered" and report["unanswered"] == 0
    t = np.array([s.t_s for s in samples])
    holes = time_axis(t, PERIOD, 1.5)
    assert holes["missing_rows"] == 0 and holes["duplicates"] == 0 and len(t) > 100
    # each sample carries what the drive sent after the SYNC its time names
    tpdo = next(tp for tp in link.plan.tpdos if any(e.role == "speed_est_mech_rad_s" for e in tp.entries))
    k = [e.role for e in tpdo.entries if e.code].index("speed_est_mech_rad_s")
    factor = next(e.factor for e in tpdo.entries if e.role == "speed_est_mech_rad_s")
    checked = 0
    for sample in samples:
        payload = sent.get(round(sample.t_s / PERIOD), {}).get(tpdo.cob)   # SYNC n is the drive's n-th
        if payload is not None:
            assert sample.values["speed_est_mech_rad_s"] == pytest.approx(tpdo.layout.unpack(payload)[k] * factor)
            checked += 1
    assert checked > 100
    assert max(s.values["speed_est_mech_rad_s"] for s in samples) > 5.0      # it moved: the values differ per SYNC


@pytest.mark.slow
def test_a_truly_missing_answer_makes_the_run_incomplete():
    lose: dict = {}
    with realtime_link_behind({"preserve": True}) as (link, rig, wire):
        record_answers(rig.node, lose)
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        lose["sync"] = rig.node._sync_count + 30           # 0.3 s into the run: the drive does not answer it
        samples = run_for(link, 3.0)
        link.quick_stop()
        link.disable()
        report = link.sync_report()
    assert report["unanswered"] == 1, report
    t = np.array([s.t_s for s in samples])
    holes = time_axis(t, PERIOD, 1.5)
    assert holes["missing_rows"] == 1 and holes["duplicates"] == 0


# -- vendor quirks: supported, not refused ----------------------------------------------------------------------------

@contextlib.contextmanager
def quirky_link(spec: DriveSpec, timing: str = "lockstep", **section):
    with build(RigSpec(motor=MOTOR, seed=1, eds=eds_path("e35"), drive=spec)) as rig:
        fields = dict(transport="canopen", interface="virtual", channel=rig.channel, node_id=1,
                      eds=str(eds_path("e35")), sync_period_s=PERIOD, heartbeat_timeout_s=2.0, sdo_timeout_s=1.0,
                      consumer_time_ms=2000)
        link = CanopenDriveLink(fields | section, REPO, LinkSettings(timing=timing))
        try:
            yield link, rig
        finally:
            link.close()


CSV_ONLY = DriveSpec(**{**E35.__dict__, "csv_only": True})


def test_a_csv_only_drive_runs_in_cyclic_synchronous_velocity_with_a_target_every_sync():
    listener = None
    with quirky_link(CSV_ONLY) as (link, rig):
        listener = can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False)
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        assert link.mode is Mode.CYCLIC_SYNC_VELOCITY and rig.device.mode_of_operation == 9
        assert link.report["supported_modes_0x6502"] == "0x00000100"
        while listener.recv(0) is not None:
            pass
        link.set_speed_ref(20.0)
        for _ in range(300):
            link.sync()
        frames = []
        while (msg := listener.recv(0)) is not None:
            frames.append(msg)
        assert rig.device.model.load_feedback()[0] == pytest.approx(20.0, rel=0.01)
        link.quick_stop()
        link.disable()
        assert not rig.device.device.power_enabled
    listener.shutdown()
    rpdo_cob = link.plan.rpdo.cob
    ids = [m.arbitration_id for m in frames if m.arbitration_id in (o.SYNC, rpdo_cob)]
    syncs = [i for i, a in enumerate(ids) if a == o.SYNC]
    assert len(syncs) == 300 and all(ids[i - 1] == rpdo_cob for i in syncs[1:])      # a target before every SYNC
    mode_entry = [e.index for e in link.plan.rpdo.entries].index(o.MODES_OF_OPERATION)
    rpdo = next(m for m in frames if m.arbitration_id == rpdo_cob)
    assert link.plan.rpdo.entries[mode_entry].index == o.MODES_OF_OPERATION
    offset = sum(e.bits for e in link.plan.rpdo.entries[:mode_entry]) // 8
    assert rpdo.data[offset] == 9


def test_profile_velocity_forced_on_a_csv_only_drive_is_refused_with_what_to_write():
    with quirky_link(CSV_ONLY, velocity_mode="pv") as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        with pytest.raises(LinkError) as info:
            link.enable_velocity_mode()
        text = str(info.value)
        assert "0x6060" in text and "0x06090030" in text and "0x6502 (supported drive modes)" in text
        assert 'velocity_mode = "csv"' in text
        assert not rig.device.device.power_enabled


@pytest.mark.slow
@pytest.mark.parametrize("timing", ["lockstep", "realtime"])
def test_event_driven_tpdos_are_used_where_the_drive_refuses_sync_transmission(timing):
    spec = DriveSpec(**{**E35.__dict__, "event_tpdos_only": True})
    with quirky_link(spec, timing) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        assert link.plan.tpdos and all(t.trans_type == 255 and t.event_timer_ms == 10 for t in link.plan.tpdos)
        assert all(tp["transmission_type"] == 255 for tp in link.report["pdo"]["tpdos"])
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        if timing == "lockstep":
            samples = [s for _ in range(300) for s in link.sync()]
        else:
            samples = run_for(link, 3.0)
        assert rig.device.model.load_feedback()[0] == pytest.approx(20.0, rel=0.01)
        assert samples[-1].values["speed_est_mech_rad_s"] == pytest.approx(20.0, rel=0.02)
        link.quick_stop()
        link.disable()
        report = link.sync_report()
    if timing == "realtime":
        assert report["time_base"] == "receive time"
        assert report["answers"] > 200 and report["interval_p50_ms"] == pytest.approx(10.0, abs=3.0)
        assert report["interval_p99_ms"] is not None and report["interval_max_ms"] >= report["interval_p50_ms"]
        t = np.array([s.t_s for s in samples])      # receive time on the bench clock: increasing, about 10 ms apart
        assert np.all(np.diff(t) > 0) and len(t) > 200 and float(np.median(np.diff(t))) == pytest.approx(0.01, abs=0.003)


@pytest.mark.slow
def test_a_booting_drive_is_waited_for_up_to_boot_timeout_s():
    spec = DriveSpec(**{**E35.__dict__, "boot_delay_s": 2.0})
    with quirky_link(spec, boot_timeout_s=5.0) as (link, rig):
        started = time.monotonic()
        identity = link.open()
        assert 1.9 < time.monotonic() - started < 5.0
        assert identity.vendor_id and 1.0 < link.report["boot_up_after_s"] < 5.0
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        assert rig.device.device.state.name == "OPERATION_ENABLED"
        link.disable()


@pytest.mark.slow
def test_without_boot_timeout_s_a_booting_drive_fails_with_the_line_to_write():
    spec = DriveSpec(**{**E35.__dict__, "boot_delay_s": 3.0})
    with quirky_link(spec) as (link, rig):
        with pytest.raises(LinkError) as info:
            link.open()
        text = str(info.value)
        assert "0x1018" in text and "boot-up" in text and "boot_timeout_s = 5" in text


def test_drivebench_show_prints_the_sync_statistics():
    import io

    from rich.console import Console

    from bench.faces.cli import print_record

    out = io.StringIO()
    record = {"verdict": "pass", "criteria": [], "scenario": {"name": "x"},
              "sync": {"period_ms": 10.0, "intervals": 299, "p50_ms": 10.0, "p99_ms": 10.4, "max_ms": 12.1, "late": 0,
                       "skipped": 1, "time_base": "sync answered", "unanswered": 0}}
    print_record(Console(file=out, width=200), record, "runs/x")
    assert ("SYNC 10.0 ms at the bench: p50 10.0 ms, p99 10.4 ms, max 12.1 ms, late 0 (> 1.5 periods), skipped 1; "
            "time base: sync answered, 0 SYNCs unanswered") in out.getvalue()


@pytest.mark.slow
@pytest.mark.parametrize("quirk, drive_line, expect", [
    ("csv_only = true", "", {"velocity_mode": "cyclic synchronous velocity (9): a target with every SYNC"}),
    ("event_tpdos_only = true", "", {"transmission_type": 255}),
    ("boot_delay_s = 2.0", "boot_timeout_s = 10", {"boot": True}),
], ids=["csv-only", "event-tpdos-only", "boot-delay"])
def test_the_rig_scenario_passes_on_a_drive_with_each_quirk(tmp_path, quirk, drive_line, expect):
    """The whole bench (drivebench run's path) on the simulated e35 with one vendor quirk: it runs and passes."""
    from bench.run.orchestrator import run_scenario

    text = (REPO / "config/benches/sim-generic-e35.toml").read_text()
    text = text.replace("[simulator]\n", f"[simulator]\n{quirk}\n")
    if drive_line:
        text = text.replace("[drive]\n", f"[drive]\n{drive_line}\n")
    bench = tmp_path / "bench.toml"
    bench.write_text(text.replace('"config/', f'"{REPO.as_posix()}/config/'))
    result = run_scenario(REPO / "scenarios/rig/speed-step-20rads.toml", bench, out_root=tmp_path / "runs",
                          rerun_mode="off")
    record = result.record
    assert result.verdict == "pass", (record.get("abort_reason"), [(c["name"], c["value"]) for c in record["criteria"]])
    settings = record["drive_settings"]
    if "velocity_mode" in expect:
        assert settings["velocity_mode"] == expect["velocity_mode"]
        assert settings["supported_modes_0x6502"] == "0x00000100"
    if "transmission_type" in expect:
        assert all(t["transmission_type"] == 255 and t["event_timer_ms"] == 10 for t in settings["pdo"]["tpdos"])
    if "boot" in expect:
        assert settings["boot_up_after_s"] > 0.5
    assert record["sync"]["time_base"] == "sync count"
