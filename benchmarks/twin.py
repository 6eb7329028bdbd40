"""The twin's speed (issue 26 targets: a 10 s run replayed in under 2 s, a fit in under a minute on the 2-core machine).

Records scenarios/identify/pmsm-identify.toml (10 s) on the simulated lab rig config/benches/sim-pmsm-lab.toml (its
motor: R_s +30 %, J +25 %, B x2 against the paper motor) through the whole bench; baseline from the same run: that
run's own wall time (CANopen lockstep, trace uploads, Modbus load machine, record). Then, with the paper motor:
the replay (best of --repeats, kernels compiled before), and one fit of the five PMSM parameters, with the recovered
values against the lab motor's.

    python benchmarks/twin.py [--repeats 5]

Last line: RESULT run_wall_s=... replay_s=... replay_target_s=2 replay_vs_run=... fit_s=... fit_target_s=60
           fit_vs_run=... fit_replays=... max_param_error_pct=... inside_before=... inside_after=...
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.run.orchestrator import run_scenario  # noqa: E402
from sim_backend import twin as tw  # noqa: E402
from sim_backend.twin_fit import fit  # noqa: E402

SCENARIO = REPO / "scenarios/identify/pmsm-identify.toml"
BENCH = REPO / "config/benches/sim-pmsm-lab.toml"
PAPER = REPO / "config/motors/pmsm-paper.toml"
LAB = REPO / "config/motors/pmsm-lab-example.toml"


def _wall_s(record: dict) -> float:
    start, end = (dt.datetime.fromisoformat(record[k].replace("Z", "+00:00")) for k in ("started_utc", "ended_utc"))
    return (end - start).total_seconds()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out:
        result = run_scenario(SCENARIO, BENCH, out_root=out, rerun_mode="off")
        run_wall = _wall_s(result.record)
        run = tw.read_run(result.run_dir)
        paper = tw.read_motor(PAPER)
        tw.build_drive(paper).step(1)                  # numba kernels compiled (cached on disk after the first time)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            twin = tw.replay(paper, run)
            times.append(time.perf_counter() - t0)
        replay_s = min(times)
        before = tw.compare(run, twin)
        fitted = fit(paper, run)
        after = tw.compare(run, tw.replay(tw.with_values(paper, fitted.values), run))
    truth = tw.read_motor(LAB)
    print(f"recorded run: {run.t[-1]:.1f} s of drive time, {run.t.size} rows, wall {run_wall:.2f} s (the bench, "
          f"lockstep over CANopen + Modbus)")
    print(f"replay: best {replay_s:.3f} s of {args.repeats} (all: {', '.join(f'{t:.3f}' for t in times)}); "
          f"{replay_s / run_wall:.3f} x the run's wall time; target < 2 s")
    print(f"fit: {fitted.time_s:.1f} s, {fitted.replays} replays (Jacobians included), "
          f"{fitted.time_s / run_wall:.2f} x the run's wall time; target < 60 s")
    errors = []
    print(f"  {'parameter':<28} {'paper':>10} {'fitted':>10} {'truth':>10} {'error':>8}")
    for p in fitted.params:
        true_value = tw.get_key(truth, p.key)
        errors.append(abs(p.value / true_value - 1.0) * 100.0)
        print(f"  {p.key:<28} {p.start:>10.5g} {p.value:>10.5g} {true_value:>10.5g} {errors[-1]:>7.2f}%"
              f"  [{p.low:.5g}, {p.high:.5g}]")
    for label, results in (("paper motor", before), ("fitted motor", after)):
        print(f"tube with the {label}: " + ", ".join(
            f"{r.signal} {'inside' if r.inside else f'OUT max {r.max_excess:.3g}'}" for r in results))
    print(f"RESULT run_wall_s={run_wall:.3f} replay_s={replay_s:.4f} replay_target_s=2 "
          f"replay_vs_run={replay_s / run_wall:.4f} fit_s={fitted.time_s:.2f} fit_target_s=60 "
          f"fit_vs_run={fitted.time_s / run_wall:.3f} fit_replays={fitted.replays} "
          f"max_param_error_pct={max(errors):.3f} inside_before={all(r.inside for r in before)} "
          f"inside_after={all(r.inside for r in after)}")


if __name__ == "__main__":
    main()
