"""The lab's instruments against the SYNC: does polling the power analyser at 10 Hz and capturing the scope move
the bench's SYNC timing, and how long does a 1 s x 4 channels x 50 kHz capture take to transfer and store?

Phase 1: `scenarios/rig/speed-step-20rads.toml` on the PMSM instruments rig in real time (`timing = "realtime"`:
the simulator paced to the wall clock, the bench's SYNC producer at 10 ms), alternately without [[instruments]]
(baseline) and with the analyser (10 Hz, its own thread) and the scope (armed, forced at the step, pulled after the
run), `--runs` times each; the record's SYNC interval p99 at the bench, worst and median over the runs.
Phase 2: a simulated rig with the scope, a 1 s record of CHAN1-4 at 50 kS/s forced and completed, then fetched over
SCPI (four int16 binary blocks) and written as Parquet: the wall time of fetch + store.

    python benchmarks/instruments.py [--runs 3]

Last line: RESULT sync_p99_ms_baseline=... sync_p99_ms_instruments=... sync_p99_ratio=... capture_points=...
           capture_fetch_store_s=...
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SCENARIO = REPO / "scenarios/rig/speed-step-20rads.toml"


def bench_text(instruments: bool) -> str:
    text = (REPO / "config/benches/sim-pmsm-instruments.toml").read_text()
    text = re.sub(r'"(config/[^"]+)"', lambda m: f'"{(REPO / m.group(1)).as_posix()}"', text)
    text = re.sub(r'(?m)^timing = "lockstep"', 'timing = "realtime"', text)
    if not instruments:
        text = re.sub(r"(?ms)^\[\[instruments\]\]\n.*?(?=^\[simulator\]\n)", "", text)
        text = re.sub(r"(?ms)^\[simulator\.lab_instruments\]\n.*?(?=^\[|\Z)", "", text)
    return text


def sync_p99(record: dict) -> float:
    sync = record.get("sync") or {}
    for key in ("interval_p99_ms", "p99_ms"):
        if key in sync:
            return float(sync[key])
    for value in sync.values():
        if isinstance(value, dict) and "p99_ms" in value:
            return float(value["p99_ms"])
    raise KeyError(f"no SYNC p99 in the record: {sync}")


def phase_sync(runs: int, work: Path) -> tuple[list[float], list[float], list[int]]:
    from bench.inputs.prepared import prepare_run
    from bench.run.orchestrator import run_scenario

    paths = {}
    for name, with_instruments in (("baseline", False), ("instruments", True)):
        paths[name] = work / f"{name}.toml"
        paths[name].write_text(bench_text(with_instruments))
    p99 = {"baseline": [], "instruments": []}
    readings = []
    for k in range(runs):
        for name in ("baseline", "instruments"):
            result = run_scenario(prepare_run(SCENARIO, paths[name], seed=1 + k), out_root=work / name,
                                  rerun_mode="off")
            record = json.loads((result.run_dir / "record.json").read_text())
            p99[name].append(sync_p99(record))
            if name == "instruments":
                lab = record.get("lab_instruments") or {}
                readings.append(int((lab.get("analysers", {}).get("analyser") or {}).get("readings", 0)))
                if lab.get("errors"):
                    print(f"  instruments errors: {lab['errors']}")
            print(f"  run {k + 1} {name}: verdict {result.verdict}, SYNC p99 {p99[name][-1]:.3f} ms")
    return p99["baseline"], p99["instruments"], readings


def phase_capture(work: Path) -> tuple[int, float]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from bench.inputs.benchconfig import load_bench_config
    from drivers.instruments import open_instrument
    from sim_backend.instruments import InstrumentSpec
    from sim_backend.lab_rig import LabSpec
    from sim_backend.rig import RigSpec, build

    cfg = load_bench_config(REPO / "config/benches/sim-pmsm-instruments.toml")
    spec = RigSpec(motor=REPO / "config/motors/pmsm-paper.toml", seed=1, instruments=InstrumentSpec(),
                   lab=LabSpec(analyser=False), instrument_names=(("scope", "scope"),))
    with build(spec) as rig:
        live = cfg.with_overrides({"instruments": rig.overrides["instruments"]})
        entry = next(i for i in live.instruments if i.name == "scope")
        entry = replace(entry, channels=entry.channels[:4], sample_rate_hz=50_000.0, timeout_s=10.0)
        scope = open_instrument(entry)
        try:
            with rig.device.lock:
                for word in (0x06, 0x07, 0x0F):
                    rig.device.write_controlword(word)
                rig.device.target_speed_mech_rad_s = 100.0
                rig.device.advance(5000)
            scope.arm(1.0, 0.0)
            scope.force()
            with rig.device.lock:
                rig.device.advance(10_100)
            scope.wait(10.0)
            t0 = time.perf_counter()
            cap = scope.fetch()
            pq.write_table(pa.table({"t_s": cap.t_s, **cap.signals}), work / "capture.parquet")
            took = time.perf_counter() - t0
        finally:
            scope.close()
    return int(cap.t_s.size) * len(cap.signals), took


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        print(f"phase 1: {SCENARIO.name} in real time, {args.runs} runs each, alternating")
        base, inst, readings = phase_sync(args.runs, work)
        print("phase 2: 1 s x 4 channels x 50 kS/s capture, fetched over SCPI and stored")
        points, took = phase_capture(work)
    b, i = statistics.median(base), statistics.median(inst)
    print(f"SYNC p99 baseline {base} ms, with instruments {inst} ms; analyser readings per run {readings}")
    print(f"capture: {points} samples fetched and stored in {took:.3f} s")
    print(f"RESULT sync_p99_ms_baseline={b:.3f} sync_p99_ms_instruments={i:.3f} sync_p99_ratio={i / b:.3f} "
          f"sync_p99_ms_worst_baseline={max(base):.3f} sync_p99_ms_worst_instruments={max(inst):.3f} "
          f"analyser_readings_min={min(readings) if readings else 0} capture_points={points} "
          f"capture_fetch_store_s={took:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
