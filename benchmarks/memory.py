"""Memory of a long real-time run: the bench process's RSS must stay flat in run length (the telemetry lives in the
run's journal on disk, not in the orchestrator; the verdict, the plot and telemetry.parquet are made batch by batch).

The whole bench in process (`run_scenario` on the in-process simulated PMSM, real-time timing, SYNC every 10 ms,
trace at 1 kHz, Rerun file sink): a profile of speed steps. First a 60 s run of the same kind: it pays what every
run pays once, whatever its length (imports, numba, the first Parquet file and PNG: printed as its end-of-run
cost). Then the long run of `--duration` s. A sampler thread reads this process's VmRSS every 0.5 s.
Baseline from the same run: the RSS at the end of the long run's first minute; the figure is the growth after it,
through the end of the run (verdict, plot, files), split into the run loop and the end.

    python benchmarks/memory.py [--duration 1200]

Last line: RESULT duration_s=... rss_first_min_mb=... rss_max_loop_mb=... rss_max_end_mb=... rss_growth_mb=...
           growth_ratio=... warmup_end_cost_mb=... rows=... verdict=...
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from realtime import SCENARIO  # noqa: E402  (the same step profile, longer)


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def run_once(tmp: Path, name: str, duration: float, rerun: str, samples: list, marks: dict):
    from bench.run.orchestrator import run_scenario

    bench = tmp / "bench.toml"
    bench.write_text((REPO / "config/benches/sim-pmsm.toml").read_text()
                     .replace('timing = "lockstep"', 'timing = "realtime"')
                     .replace('"config/', f'"{REPO}/config/'))
    steps = "".join(f"\n[[speed]]\nkind = \"step\"\nat_s = {k + 0.5}\nspeed_mech_rad_s = {10.0 if k % 2 else 20.0}\n"
                    for k in range(0, int(duration), 5))
    scenario = tmp / f"{name}.toml"
    scenario.write_text(SCENARIO.format(bench=bench, duration=duration, steps=steps, max_duration=duration * 2 + 60))
    marks.clear()
    marks["start"] = len(samples)
    result = run_scenario(scenario, out_root=tmp / "runs", rerun_mode=rerun)
    marks["end"] = len(samples)
    return result


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--duration", type=float, default=1200.0)
    parser.add_argument("--rerun", default="save", choices=("save", "off"))
    args = parser.parse_args()
    import bench.run.orchestrator as orchestrator

    samples: list[tuple[float, float]] = []
    marks: dict[str, int] = {}
    stop = threading.Event()
    started = time.monotonic()

    def sample() -> None:
        while not stop.wait(0.5):
            samples.append((time.monotonic() - started, rss_mb()))

    real_finish = orchestrator._Run._finish

    def finish(self, *a, **k):                  # where the run loop ends and the end of the run begins
        marks["finish"] = len(samples)
        return real_finish(self, *a, **k)

    orchestrator._Run._finish = finish
    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run_once(tmp, "warmup", 60.0, args.rerun, samples, marks)
        w = dict(marks)
        warm_end_cost = max(r for _, r in samples[w["finish"]:w["end"] + 1]) - samples[w["finish"] - 1][1]
        result = run_once(tmp, "long", args.duration, args.rerun, samples, marks)
        stop.set()
        thread.join(5)
        rows = result.record["telemetry"]["rows"]
    long = samples[marks["start"]:]
    t0 = long[0][0]
    first_min = next(r for t, r in long if t - t0 >= 60.0)
    loop = [r for t, r in samples[marks["start"]:marks["finish"]] if t - t0 >= 60.0]
    end = [r for _, r in samples[marks["finish"]:marks["end"] + 1]] or [samples[-1][1]]
    peak_loop, peak_end = max(loop), max(end)
    growth = max(peak_loop, peak_end) - first_min
    print(f"warm-up 60 s run: end-of-run cost {warm_end_cost:.1f} MB (paid once per process)")
    print(f"long run: RSS after its first minute {first_min:.1f} MB; max in the run loop {peak_loop:.1f} MB; max at "
          f"the end (verdict, plot, files) {peak_end:.1f} MB; {rows} rows; verdict {result.verdict}")
    for t, r in long[:: max(1, len(long) // 24)]:
        print(f"  t={t - t0:7.1f} s  rss={r:7.1f} MB")
    print(f"RESULT duration_s={args.duration:g} rss_first_min_mb={first_min:.1f} rss_max_loop_mb={peak_loop:.1f} "
          f"rss_max_end_mb={peak_end:.1f} rss_growth_mb={growth:.1f} growth_ratio={max(peak_loop, peak_end) / first_min:.3f} "
          f"warmup_end_cost_mb={warm_end_cost:.1f} rows={rows} verdict={result.verdict}")
    return 0 if growth <= 20.0 else 1


if __name__ == "__main__":
    sys.exit(main())
