"""Bench overhead: recording + Rerun logging + evaluation (+ summary plot) as % of the run time.

Runs the same scenario through the same orchestrator loop twice per round, alternating:
  baseline  - telemetry not recorded, no Rerun stream, no evaluation, no plot
  full      - the real thing: journal + parquet, run.rrd (--rerun save), criteria, summary.png
overhead_pct = wall time the run loop spends inside recording, Rerun and evaluation calls (measured around
each call in the full runs) / the rest of those runs; with_plot_pct adds the fixed-cost summary.png.
Cross-checks against the baseline runs of the same invocation: wall_diff_pct (fastest runs; noisy on a
shared machine) and cpu_diff_pct (median paired process-CPU difference, all threads: Rerun's encoder and
the journal flusher count; plot included). Target <= 10 %.

Drive path: the in-process CANopen simulator of config/benches/sim-pmsm.toml when drivers.canopen.link and
sim_backend.rig exist; otherwise the PMSM model stepped directly through the in-memory fake links of
tests/fakes.py (no protocol cost, so the base is cheaper and the percentage pessimistic).

    python benchmarks/overhead.py [--rounds N] [--scenario FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bench.run.orchestrator as orch  # noqa: E402
import bench.run.verdict as verdict_mod  # noqa: E402
from bench.run.orchestrator import run_scenario  # noqa: E402

ending = sys.modules[orch._Run._finish.__module__]   # where the run's ending (and its plot call) lives

DEFAULT_SCENARIO = REPO / "scenarios/examples/pmsm-rs-step.toml"


def inprocess_available() -> bool:
    return all(importlib.util.find_spec(m) is not None for m in ("drivers.canopen.link", "sim_backend.rig"))


@contextlib.contextmanager
def instrumentation_off():
    """Baseline: the run loop as is, minus recording, Rerun, evaluation and plot."""
    saved = (orch._Run._append, orch.RerunStream, verdict_mod.evaluate, ending.write_summary_png)
    orch._Run._append = lambda self, block: None
    orch.RerunStream = lambda mode, path, **kw: saved[1]("off", None)
    verdict_mod.evaluate = lambda *a, **kw: []
    ending.write_summary_png = lambda *a, **kw: None
    try:
        yield
    finally:
        orch._Run._append, orch.RerunStream, verdict_mod.evaluate, ending.write_summary_png = saved


class Timed:
    """Wall time spent inside the instrumented parts during a full run, for the breakdown."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def patch(self):
        saved = {}
        targets = {
            "record.append": (orch.RunRecorder, "append"),
            "record.finish": (orch.RunRecorder, "finish"),
            "record.read_back": (orch.RunRecorder, "read_back"),
            "rerun.open": (orch.RerunStream, "__init__"),
            "rerun.log": (orch.RerunStream, "log_columns"),
            "rerun.close": (orch.RerunStream, "close"),
            "evaluate": (verdict_mod, "evaluate"),
            "plot": (ending, "write_summary_png"),
        }
        for label, (owner, name) in targets.items():
            original = getattr(owner, name)
            saved[label] = (owner, name, original)
            setattr(owner, name, self._wrap(label, original))
            self.seconds.setdefault(label, 0.0)   # accumulates over rounds
        try:
            yield
        finally:
            for owner, name, original in saved.values():
                setattr(owner, name, original)

    def _wrap(self, label, fn):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - t0
        return timed


def make_runner(scenario: Path, out_root: Path, drive_path: str = "auto"):
    if drive_path == "auto" and inprocess_available():
        # the scenario's own bench, with SDO/heartbeat timeouts for a loaded 2-core machine
        from bench.inputs.scenario import load_scenario

        bench_src = Path(load_scenario(scenario).bench)
        bench = out_root / f"patient-{bench_src.name}"
        bench.write_text(bench_src.read_text().replace("sdo_timeout_s = 0.5", "sdo_timeout_s = 3.0")
                         .replace("heartbeat_timeout_s = 0.5", "heartbeat_timeout_s = 3.0"))

        def run_once():
            return run_scenario(scenario, bench, out_root=out_root, rerun_mode="save")
        return run_once, f"in-process simulator of {bench_src.name} (SDO timeout 3 s)"

    from bench.inputs.scenario import load_scenario
    from sim_backend.drive import make_drive
    from tests.fakes import FakeRig

    scen = load_scenario(scenario)
    from bench.inputs.benchconfig import load_bench_config

    motor = load_bench_config(scen.bench)["simulator"]["motor"]
    sync_period = load_bench_config(scen.bench)["drive"]["sync_period_s"]

    def run_once():
        rig = FakeRig(model=make_drive(motor, seed=1), sync_period_s=sync_period)
        return run_scenario(scenario, out_root=out_root, rerun_mode="save", links=rig.links())
    return run_once, "PMSM model through in-memory fake links (no protocol; pessimistic)"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO)
    parser.add_argument("--drive-path", choices=("auto", "model"), default="auto",
                        help="auto: the in-process protocol simulator when present; model: the drive model "
                             "stepped through in-memory links (fast, no protocol: many rounds, pessimistic %%)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        run_once, path_label = make_runner(args.scenario, Path(tmp), args.drive_path)
        print(f"scenario: {args.scenario.relative_to(REPO) if args.scenario.is_relative_to(REPO) else args.scenario}")
        print(f"drive path: {path_label}")
        run_once()  # warm-up: JIT compilation, imports
        base_times, full_times, base_cpu, full_cpu = [], [], [], []
        breakdown = Timed()
        for _ in range(args.rounds):
            with instrumentation_off():
                t0, c0 = time.perf_counter(), time.process_time()
                base = run_once()
                base_times.append(time.perf_counter() - t0)
                base_cpu.append(time.process_time() - c0)
            with breakdown.patch():
                t0, c0 = time.perf_counter(), time.process_time()
                full = run_once()
                full_times.append(time.perf_counter() - t0)
                full_cpu.append(time.process_time() - c0)
        for result in (base, full):
            if result.verdict == "error":
                print(f"run failed: {result.record.get('abort_reason')}")
                return 2
        rows = full.record.get("telemetry", {}).get("rows")
        print(f"verdicts: baseline {base.verdict}, full {full.verdict}; recorded rows per run: {rows}")

    # 1) direct: time spent inside the instrumented parts of the full runs, against the rest of those runs
    spent = {label: seconds / args.rounds for label, seconds in breakdown.seconds.items()}
    full_med = statistics.median(full_times)
    plot_s = spent["plot"]
    instr_s = sum(spent.values()) - plot_s
    rest_s = full_med - instr_s - plot_s
    overhead_pct = 100.0 * instr_s / rest_s
    with_plot_pct = 100.0 * (instr_s + plot_s) / rest_s
    print("time inside the instrumented parts, per full run:")
    for label, seconds in spent.items():
        print(f"  {label:14s} {seconds:7.3f} s  {100 * seconds / rest_s:5.1f} %")
    print(f"  {'total (no plot)':14s} {instr_s:7.3f} s  {overhead_pct:5.1f} %   of the run without them "
          f"({rest_s:.3f} s)")
    # 2) cross-check by difference (noisy on a shared machine: min over rounds)
    base_min, full_min = min(base_times), min(full_times)
    diff_pct = 100.0 * (full_min - base_min) / base_min
    print(f"baseline runs (no recording/Rerun/evaluation/plot): {['%.2f' % t for t in base_times]} s")
    print(f"full runs:                                          {['%.2f' % t for t in full_times]} s")
    print(f"by difference of the fastest runs: {diff_pct:+.1f} % (plot included; noise of a shared machine)")
    # 3) CPU time of this process (all its threads: simulator, links, Rerun's encoder, the journal flusher)
    cpu_base = statistics.median(base_cpu)
    cpu_extra = statistics.median(f - b for f, b in zip(full_cpu, base_cpu))   # paired by round
    cpu_diff_pct = 100.0 * cpu_extra / cpu_base
    print(f"process CPU per run: baseline {['%.2f' % c for c in base_cpu]} s, full {['%.2f' % c for c in full_cpu]} s")
    print(f"  median paired extra {cpu_extra:.3f} s on a median baseline of {cpu_base:.2f} s -> {cpu_diff_pct:+.1f} % "
          f"(plot included; counts background threads the direct timing misses)")
    print("summary.png is a fixed cost per run, reported apart (with_plot_pct)")
    print("machine: 2 cores shared with other engineers' work; figures are pessimistic")
    print(f"RESULT overhead_pct={overhead_pct:.1f} with_plot_pct={with_plot_pct:.1f} plot_s={plot_s:.3f} "
          f"wall_diff_pct={diff_pct:.1f} cpu_diff_pct={cpu_diff_pct:.1f} run_s={full_med:.2f} target_pct=10 "
          f"rounds={args.rounds}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
