"""Strict runs of the three vendor-EDS simulated drives under two busy loops: passes and false trips (issue 32).

Each drive (config/benches/sim-generic-{cia402-slave,e35,technosoft}.toml) is served out of process by `drivebench sim
serve` and run as a lab runs a real rig (benchmarks/rig_timing.py's configs: no [services], no [simulator], real
time, socketcand, Modbus TCP) and strictly: the comm-loss drill before every run (drill_valid_s = 0),
`fault_reset = "never"`, the configs' consumer heartbeat time (2000 ms) or `--consumer-ms` (a rig uses 200-500 ms:
then a bench process the host does not schedule for that long is, correctly, stopped by the drive). `scenarios/rig/speed-step-20rads.toml` runs `--runs`
times per drive with `--load-procs` busy processes on this machine's cores, after `--baseline-runs` runs per drive
without them (the same session's baseline). Per drive and phase: passes, false trips (an aborted run of a healthy
drive: any trip — unit_mismatch, feedback_lost, remote_lost, a refused drill...), incomplete runs, errors, with the
reason of each run that did not pass. Ratios: loaded pass rate against the baseline's.

    python benchmarks/strict_vendor_drives.py [--runs 20] [--baseline-runs 2] [--rigs e35,technosoft,cia402-slave]
                                              [--consumer-ms 300]

Last line: RESULT runs=... load_procs=... <rig>_pass=... <rig>_false_trips=... <rig>_incomplete=... <rig>_error=...
           <rig>_pass_rate_vs_baseline=... baseline_<rig>_pass=...
"""

from __future__ import annotations

import argparse
import multiprocessing
import re
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.rig_timing import RIGS, busy, configs, one_run, serve_process, why  # noqa: E402

def strict(bench: Path, consumer_ms: int | None) -> None:
    """The rig's bench config made strict: a drill before every run; optionally a rig's consumer heartbeat time."""
    text = bench.read_text()
    text = re.sub(r"(?m)^drill_valid_s = .*\n", "", text)
    if consumer_ms is not None:
        text = re.sub(r"(?m)^consumer_time_ms = .*$", f"consumer_time_ms = {consumer_ms}", text)
    bench.write_text(text)


def outcome(record: dict) -> str:
    verdict = record.get("verdict")
    if verdict == "pass":
        return "pass"
    if verdict == "aborted" or (verdict == "error" and record.get("trips")):
        return "false_trip"          # every drive here is healthy: any trip or refusal is a false one
    return {"incomplete": "incomplete", "fail": "fail"}.get(verdict, "error")


def start_serves(rigs, workdir: Path, consumer_ms: int | None) -> dict[str, tuple[subprocess.Popen, Path]]:
    """Every drive served before the load starts (a simulator starting under two busy loops can take minutes)."""
    served = {}
    for rig in rigs:
        serve, bench = configs(rig, workdir)
        strict(bench, consumer_ms)
        served[rig] = (serve_process(serve), bench)
    return served


def stop_serves(served) -> None:
    for proc, _ in served.values():
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


def phase(served, n: int, workdir: Path, label: str) -> dict[str, Counter]:
    out: dict[str, Counter] = {}
    for rig, (_, bench) in served.items():
        counts: Counter = Counter()
        for k in range(n):
            record = one_run(bench, workdir / f"runs-{label}-{rig}")
            kind = outcome(record)
            counts[kind] += 1
            trips = [t.get("reason") for t in record.get("trips") or []]
            print(f"  {label:8s} {rig:13s} run {k + 1:2d}: {kind:10s}"
                  + (f" trips {trips}: {why(record)}" if kind != "pass" else ""), flush=True)
        counts["runs"] = n
        out[rig] = counts
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=20, help="runs per drive under load (default 20)")
    parser.add_argument("--baseline-runs", type=int, default=2, help="runs per drive without load (default 2)")
    parser.add_argument("--rigs", default=",".join(RIGS), help=f"comma-separated, of {', '.join(RIGS)}")
    parser.add_argument("--load-procs", type=int, default=2, help="busy processes during the loaded phase")
    parser.add_argument("--consumer-ms", type=int, default=None, help="consumer heartbeat time (default: the configs')")
    args = parser.parse_args()
    rigs = [r for r in args.rigs.split(",") if r]
    bad = [r for r in rigs if r not in RIGS]
    if bad or args.runs < 1 or args.baseline_runs < 0:
        print(f"--rigs: must be of {', '.join(RIGS)}; --runs >= 1", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="strict-drives-") as tmp:
        workdir = Path(tmp)
        served = start_serves(rigs, workdir, args.consumer_ms)
        try:
            print(f"baseline: {args.baseline_runs} strict runs per drive, no extra load", flush=True)
            baseline = phase(served, args.baseline_runs, workdir, "baseline") if args.baseline_runs else {}
            print(f"loaded: {args.runs} strict runs per drive, {args.load_procs} busy processes", flush=True)
            loaders = [multiprocessing.Process(target=busy, daemon=True) for _ in range(args.load_procs)]
            for proc in loaders:
                proc.start()
            try:
                loaded = phase(served, args.runs, workdir, "loaded")
            finally:
                for proc in loaders:
                    proc.terminate()
                    proc.join(5)
        finally:
            stop_serves(served)
    print()
    print(f"{'drive':13s} {'phase':8s} pass   false trips  incomplete  fail  error")
    fields = [f"runs={args.runs}", f"load_procs={args.load_procs}", f"consumer_ms={args.consumer_ms or 'config'}"]
    for rig in rigs:
        for label, table in (("baseline", baseline), ("loaded", loaded)):
            c = table.get(rig)
            if c is not None:
                print(f"{rig:13s} {label:8s} {c['pass']:2d}/{c['runs']:<3d} {c['false_trip']:6d} {c['incomplete']:11d} "
                      f"{c['fail']:6d} {c['error']:5d}")
        c, b = loaded[rig], baseline.get(rig)
        key = rig.replace("-", "_")
        fields += [f"{key}_pass={c['pass']}", f"{key}_false_trips={c['false_trip']}",
                   f"{key}_incomplete={c['incomplete']}", f"{key}_fail={c['fail']}", f"{key}_error={c['error']}"]
        if b is not None and b["runs"]:
            fields.append(f"baseline_{key}_pass={b['pass']}")
            if b["pass"]:
                fields.append(f"{key}_pass_rate_vs_baseline={(c['pass'] / c['runs']) / (b['pass'] / b['runs']):.3f}")
    print("RESULT " + " ".join(fields))
    return 0


if __name__ == "__main__":
    sys.exit(main())
