"""Memory of a long real-time run: the bench process's RSS must stay flat in run length (the telemetry lives in the
run's journal on disk, not in the orchestrator), apart from the recorded files.

The whole bench in process (`run_scenario` on the in-process simulated PMSM, real-time timing, SYNC every 10 ms,
trace at 1 kHz, Rerun file sink): a profile of speed steps for `--duration` s of wall time. A sampler thread reads
this process's VmRSS every 2 s. Baseline from the same run: the RSS at the end of the first minute (imports, numba,
the simulator and the first buffers all paid by then); the figure is the growth after it.

    python benchmarks/memory.py [--duration 1200]

Last line: RESULT duration_s=... rss_first_min_mb=... rss_end_mb=... rss_max_mb=... rss_growth_mb=...
           growth_ratio=... rows=... verdict=...
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


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--duration", type=float, default=1200.0)
    parser.add_argument("--rerun", default="save", choices=("save", "off"))
    args = parser.parse_args()
    from bench.orchestrator import run_scenario

    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    started = time.monotonic()

    def sample() -> None:
        while not stop.wait(2.0):
            samples.append((time.monotonic() - started, rss_mb()))

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bench = tmp / "bench.toml"
        bench.write_text((REPO / "config/benches/sim-pmsm.toml").read_text()
                         .replace('timing = "lockstep"', 'timing = "realtime"')
                         .replace('"config/', f'"{REPO}/config/'))
        steps = "".join(f"\n[[speed]]\nkind = \"step\"\nat_s = {k + 0.5}\nspeed_mech_rad_s = {10.0 if k % 2 else 20.0}\n"
                        for k in range(0, int(args.duration), 5))
        scenario = tmp / "long.toml"
        scenario.write_text(SCENARIO.format(bench=bench, duration=args.duration, steps=steps,
                                            max_duration=args.duration * 2 + 60))
        thread = threading.Thread(target=sample, daemon=True)
        thread.start()
        result = run_scenario(scenario, out_root=tmp / "runs", rerun_mode=args.rerun)
        stop.set()
        thread.join(5)
        end = rss_mb()
        rows = result.record["telemetry"]["rows"]
    first_min = next((r for t, r in samples if t >= 60.0), samples[-1][1] if samples else end)
    during = [r for t, r in samples if t >= 60.0] or [end]
    peak = max(during)
    growth = peak - first_min
    print(f"RSS after the first minute {first_min:.1f} MB; at the end {end:.1f} MB; max after the first minute "
          f"{peak:.1f} MB; {len(samples)} samples; {rows} rows recorded; verdict {result.verdict}")
    for t, r in samples[:: max(1, len(samples) // 20)]:
        print(f"  t={t:7.1f} s  rss={r:7.1f} MB")
    print(f"RESULT duration_s={args.duration:g} rss_first_min_mb={first_min:.1f} rss_end_mb={end:.1f} "
          f"rss_max_mb={peak:.1f} rss_growth_mb={growth:.1f} growth_ratio={peak / first_min:.3f} rows={rows} "
          f"verdict={result.verdict}")
    return 0 if growth <= 20.0 else 1


if __name__ == "__main__":
    sys.exit(main())
