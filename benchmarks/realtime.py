"""Real time on this machine: SYNC jitter and command latency, measured on the wire (python-can virtual bus).

1. SYNC producer alone: a CANopen link in real-time timing against the in-process simulated drive, SYNC every
   `--period-ms` for `--duration` s; a passive listener on the bus stamps every SYNC frame. Figures: interval error
   (interval - period) median / p99 / max in ms, the closest two SYNCs (must stay above half a period), skipped slots.
   Baseline from the same run: a plain `time.sleep(period)` loop sending the same frames (what a naive producer
   does), so the ratio shows what the producer buys on this machine.
2. The whole bench: `drivebench run` (orchestrator, recorder, Rerun file sink) in real time on a scenario with a
   speed step every second; for each step, the time from the SYNC whose TPDOs carry the drive time at which the step
   is due to the first RPDO carrying the new target (must be within one SYNC period).

    python benchmarks/realtime.py [--duration 20] [--period-ms 10]

Last line: RESULT sync_p99_ms=... sync_max_ms=... sync_min_interval_ms=... skipped=... naive_p99_ms=...
           cmd_latency_median_ms=... cmd_latency_max_ms=... steps=... late_steps=...
"""

from __future__ import annotations

import argparse
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

import can
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from drivers.api import LinkSettings  # noqa: E402
from drivers.canopen.link import CanopenDriveLink  # noqa: E402
from sim_backend.rig import RigSpec, build  # noqa: E402

MOTOR = REPO / "config/motors/pmsm-paper.toml"
EDS = REPO / "config/od/drivebench-pmsm.eds"


class Listener(can.Listener):
    """Wire log: (perf_counter at receipt, arbitration id, data) for the frames we care about."""

    def __init__(self, ids: set[int] | None = None):
        self.frames: list[tuple[float, int, bytes]] = []
        self.ids = ids

    def on_message_received(self, msg: can.Message) -> None:
        if self.ids is None or msg.arbitration_id in self.ids:
            self.frames.append((time.perf_counter(), msg.arbitration_id, bytes(msg.data)))


def interval_stats(times: list[float], period: float) -> dict[str, float]:
    intervals = np.diff(np.asarray(times))
    error = np.abs(intervals - period) * 1e3
    return {"median_ms": float(np.median(error)), "p99_ms": float(np.percentile(error, 99)),
            "max_ms": float(error.max()), "min_interval_ms": float(intervals.min() * 1e3), "n": len(intervals)}


def sync_jitter(duration: float, period: float) -> tuple[dict, dict]:
    with build(RigSpec(motor=MOTOR, seed=1, eds=EDS)) as rig:
        bus = can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False)
        listener = Listener({0x80})
        notifier = can.Notifier(bus, [listener], timeout=0.01)
        link = CanopenDriveLink(dict(transport="canopen", interface="virtual", channel=rig.channel, node_id=1,
                                     eds=str(EDS), sync_period_s=period, heartbeat_timeout_s=5.0, sdo_timeout_s=5.0,
                                     consumer_time_ms=5000), REPO, LinkSettings(timing="realtime"))
        try:
            link.open()
            link.configure(["speed_est_mech_rad_s", "speed_true_mech_rad_s"], [], 10)
            link.enable_velocity_mode()
            link.set_speed_ref(20.0)
            end = time.monotonic() + duration
            while time.monotonic() < end:
                link.sync()
            skipped = link.sync_producer.skipped
            link.quick_stop()
            link.disable()
        finally:
            link.close()
        producer = interval_stats([t for t, _, _ in listener.frames], period) | {"skipped": skipped}

        # naive baseline: sleep(period) between sends, same bus, same simulator answering
        listener.frames.clear()
        sender = can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False)
        end = time.monotonic() + min(duration, 5.0)
        while time.monotonic() < end:
            sender.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
            time.sleep(period)
        sender.shutdown()
        time.sleep(0.05)
        naive = interval_stats([t for t, _, _ in listener.frames], period)
        notifier.stop()
        bus.shutdown()
    return producer, naive


SCENARIO = """schema_version = 1
name = "realtime-steps"
bench = "{bench}"
duration_s = {duration}
seed = 1
{steps}
[limits]
overspeed_mech_rad_s = 60.0
overcurrent_a = 10.0
max_duration_s = {max_duration}
"""


def command_latency(duration: float, period: float) -> dict:
    """The whole bench in real time; latency from the step's due SYNC to the first RPDO with its new target."""
    from bench.run.orchestrator import run_scenario
    import bench.run.links as links

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bench = tmp / "bench.toml"
        bench.write_text((REPO / "config/benches/sim-pmsm.toml").read_text()
                         .replace('timing = "lockstep"', 'timing = "realtime"')
                         .replace("sync_period_s = 0.01", f"sync_period_s = {period}"))
        targets = [10.0 if k % 2 else 20.0 for k in range(int(duration))]
        steps = "".join(f"\n[[speed]]\nkind = \"step\"\nat_s = {k + 0.5}\nspeed_mech_rad_s = {v}\n"
                        for k, v in enumerate(targets))
        scenario = tmp / "steps.toml"
        scenario.write_text(SCENARIO.format(bench=bench, duration=duration, steps=steps,
                                            max_duration=duration * 3 + 30))
        listeners: list[Listener] = []
        real_make_links = links.make_links

        def make_links(cfg, base):                 # listen on the run's private channel
            drive, load = real_make_links(cfg, base)
            bus = can.Bus(interface="virtual", channel=cfg.drive["channel"], receive_own_messages=False)
            listener = Listener({0x80, 0x181, 0x201})
            listeners.append(listener)
            can.Notifier(bus, [listener], timeout=0.01)
            return drive, load

        import bench.run.orchestrator as orchestrator
        orchestrator.make_links = make_links
        try:
            result = run_scenario(scenario, out_root=tmp / "runs", rerun_mode="save")
        finally:
            orchestrator.make_links = real_make_links
        frames = listeners[0].frames
        start = result.record["drive_clock_start_s"]
        control = 1e-4
        tpdo1 = [(t, struct.unpack_from("<L", d, 3)[0] * control - start) for t, cob, d in frames if cob == 0x181]
        rpdo = [(t, struct.unpack_from("<l", d, 2)[0] / 1000.0) for t, cob, d in frames if cob == 0x201]
        latencies = []
        for k, target in enumerate(targets):
            due = k + 0.5
            seen = next((t for t, drive_t in tpdo1 if drive_t >= due - 1e-9), None)
            sent = next((t for t, value in rpdo if abs(value - target) < 1e-6 and seen is not None
                         and t >= seen - period), None)
            if seen is not None and sent is not None:
                latencies.append((sent - seen) * 1e3)
    late = sum(1 for lat in latencies if lat > period * 1e3)
    return {"steps": len(latencies), "median_ms": statistics.median(latencies) if latencies else float("nan"),
            "max_ms": max(latencies) if latencies else float("nan"), "late": late, "verdict": result.verdict}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--period-ms", type=float, default=10.0)
    args = parser.parse_args()
    period = args.period_ms / 1000.0
    producer, naive = sync_jitter(args.duration, period)
    print(f"SYNC producer, {producer['n']} intervals of {args.period_ms:g} ms: |error| median "
          f"{producer['median_ms']:.3f} ms, p99 {producer['p99_ms']:.3f} ms, max {producer['max_ms']:.3f} ms, "
          f"closest two {producer['min_interval_ms']:.3f} ms, skipped slots {producer['skipped']}")
    print(f"naive sleep loop (baseline): |error| median {naive['median_ms']:.3f} ms, p99 {naive['p99_ms']:.3f} ms, "
          f"max {naive['max_ms']:.3f} ms -> p99 ratio naive/producer {naive['p99_ms'] / producer['p99_ms']:.1f}")
    cmd = command_latency(min(args.duration, 10.0), period)
    print(f"whole bench, {cmd['steps']} speed steps: first RPDO after the due SYNC's TPDO: median "
          f"{cmd['median_ms']:.2f} ms, max {cmd['max_ms']:.2f} ms, later than one SYNC period: {cmd['late']} "
          f"(run verdict {cmd['verdict']})")
    print(f"RESULT sync_p99_ms={producer['p99_ms']:.3f} sync_max_ms={producer['max_ms']:.3f} "
          f"sync_min_interval_ms={producer['min_interval_ms']:.3f} skipped={producer['skipped']} "
          f"naive_p99_ms={naive['p99_ms']:.3f} cmd_latency_median_ms={cmd['median_ms']:.2f} "
          f"cmd_latency_max_ms={cmd['max_ms']:.2f} steps={cmd['steps']} late_steps={cmd['late']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
