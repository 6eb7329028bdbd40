"""Served serial runs on a loaded host (issue 23): `drivebench sim serve` with config/benches/sim-pmsm-serial.toml's
drive on free ports, the drive's comm-loss watchdog at the default 300 ms (consumer_time_ms removed from the copy),
two busy loops (`python -c 'while 1: pass'`) beside it, and RUNS runs of a paper scenario one after the other through
`drivebench run`. A run the watchdog aborts ends `aborted` with EMCY 0x8130 (the drive stopped itself: the bench's
requests paused longer than 300 ms).

Baseline from the same run: the same scenario once without the busy loops (its wall time; the ratio shows the load).
Last line: `RESULT runs=... completed=... watchdog_aborts=... other=... wall_s_median=... wall_ratio=...`.
Usage: python benchmarks/served_serial_load.py [--runs 20] [--scenario scenarios/pmsm/fig10-startup-position-error.toml]
"""

from __future__ import annotations

import argparse
import json
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "config" / "benches" / "sim-pmsm-serial.toml"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bench_copy(work: Path) -> Path:
    serial, modbus = free_port(), free_port()
    text = BENCH.read_text()
    text = re.sub(r"(?m)^consumer_time_ms.*\n", "", text)                 # the default: 300 ms
    text = text.replace("29537", str(serial)).replace("29502", str(modbus))
    text = text.replace('eds = "config/', f'eds = "{ROOT}/config/').replace('map = "config/', f'map = "{ROOT}/config/')
    text = text.replace('motor = "config/', f'motor = "{ROOT}/config/')
    path = work / "sim-pmsm-serial-300ms.toml"
    path.write_text(text)
    return path


def one_run(scenario: str, bench: Path, out: Path) -> tuple[str, str, float]:
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "bench", "run", scenario, "--bench", str(bench), "--out", str(out),
                           "--rerun", "off", "--json"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    wall = time.monotonic() - t0
    try:
        record = json.loads(done.stdout.splitlines()[0])
    except (ValueError, IndexError):
        return "error", done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}", wall
    return record.get("verdict", "?"), str(record.get("abort_reason") or ""), wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--scenario", default="scenarios/pmsm/fig10-startup-position-error.toml")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="drivebench-served-serial-"))
    bench = bench_copy(work)
    sim = subprocess.Popen([sys.executable, "-m", "sim_backend.serve", "--config", str(bench)], cwd=ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    busy: list[subprocess.Popen] = []
    results = []
    try:
        for line in sim.stdout:
            if line.startswith("ready"):
                break
        verdict, reason, base_wall = one_run(args.scenario, bench, work / "runs")
        print(f"baseline (no busy loops): {verdict} in {base_wall:.1f} s {reason}")
        busy = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(2)]
        for i in range(args.runs):
            verdict, reason, wall = one_run(args.scenario, bench, work / "runs")
            results.append((verdict, reason, wall))
            print(f"run {i + 1}: {verdict} in {wall:.1f} s {reason[:120]}", flush=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
        sim.terminate()
        sim.wait(30)
    completed = sum(v in ("pass", "fail") for v, _, _ in results)
    watchdog = sum("8130" in r for _, r, _ in results)
    median = statistics.median(w for _, _, w in results)
    print(f"RESULT runs={len(results)} completed={completed} watchdog_aborts={watchdog} "
          f"other={len(results) - completed - watchdog} wall_s_median={median:.1f} wall_ratio={median / base_wall:.2f}")
    return 0 if completed == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
