"""Time on a real-time rig under CPU load: does every run of the rig scenario come out complete and passing?

Each vendor-EDS simulated drive (config/benches/sim-generic-{cia402-slave,e35,technosoft}.toml) is served out of
process by `drivebench sim serve` (CANopen over socketcand, the dynamometer over Modbus TCP, on 127.0.0.1), and the
bench connects to it as a lab connects to a rig: a bench config without [services] or [simulator], `timing =
"realtime"`, socketcand with python-can's defaults plus what drivebench sets. `scenarios/rig/speed-step-20rads.toml`
runs `--runs` times per rig with two busy processes loading this machine's cores, after `--baseline-runs` runs per
rig without the load (the baseline, same session). Per phase and rig: runs complete (no `incomplete` verdict, no
missing rows), runs passed, and the record's SYNC statistics at the bench (p50/p99/max interval in ms, late =
intervals > 1.5 periods, skipped slots, SYNCs unanswered), worst over the runs.

    python benchmarks/rig_timing.py [--runs 20] [--baseline-runs 3] [--rigs e35,technosoft,cia402-slave]

Last line: RESULT runs=... <rig>_complete=... <rig>_pass=... <rig>_sync_p99_ms=... <rig>_sync_max_ms=...
           <rig>_late=... <rig>_skipped=... <rig>_unanswered=... baseline_<rig>_sync_p99_ms=... load_procs=2
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / "scenarios/rig/speed-step-20rads.toml"
RIGS = ("cia402-slave", "e35", "technosoft")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def absolute_paths(text: str) -> str:
    return re.sub(r'"(config/[^"]+)"', lambda m: f'"{(REPO / m.group(1)).as_posix()}"', text)


def section_removed(text: str, name: str) -> str:
    """The TOML text without table [name] (up to the next table header)."""
    return re.sub(rf"(?ms)^\[{re.escape(name)}\]\n.*?(?=^\[|\Z)", "", text)


def configs(rig: str, workdir: Path) -> tuple[Path, Path]:
    """(serve config, bench config) for one rig: the simulated drive served on free ports, the bench written as a
    lab writes it for a real drive (no [services], no [simulator], real time, socketcand)."""
    text = absolute_paths((REPO / f"config/benches/sim-generic-{rig}.toml").read_text())
    can_port, modbus_port = free_port(), free_port()
    serve = workdir / f"serve-{rig}.toml"
    serve.write_text(text + f'\n[simulator.serve]\ncanopen_socketcand = "127.0.0.1:{can_port}"\n'
                            f'modbus_tcp = "127.0.0.1:{modbus_port}"\n')
    bench_text = section_removed(section_removed(text, "services"), "simulator")
    bench_text = re.sub(r'(?m)^timing = "lockstep"', 'timing = "realtime"', bench_text)
    bench_text = re.sub(r'(?m)^interface = "virtual"', 'interface = "socketcand"', bench_text)
    bench_text = re.sub(r'(?m)^channel = "drivebench".*$', f'channel = "can0@127.0.0.1:{can_port}"', bench_text)
    bench_text = re.sub(r'(?m)^port = 0', f"port = {modbus_port}", bench_text)
    bench = workdir / f"bench-{rig}.toml"
    bench.write_text(bench_text)
    return serve, bench


def busy() -> None:
    while True:
        pass


def serve_process(serve: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "bench", "sim", "serve", "--config", str(serve)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    deadline = time.monotonic() + 60
    for line in proc.stdout:
        if line.startswith("ready"):
            return proc
        if time.monotonic() > deadline:
            break
    proc.kill()
    raise RuntimeError(f"sim serve --config {serve} did not get ready")


def one_run(bench: Path, out: Path) -> dict:
    done = subprocess.run([sys.executable, "-m", "bench", "run", str(SCENARIO), "--bench", str(bench), "--rerun", "off",
                           "--out", str(out), "--json"], capture_output=True, text=True, cwd=REPO, timeout=300)
    try:
        return json.loads(done.stdout.strip().splitlines()[-1])
    except (json.JSONDecodeError, IndexError):
        return {"verdict": "error", "abort_reason": (done.stderr or done.stdout)[-400:]}


def phase(rigs, n: int, workdir: Path, label: str) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for rig in rigs:
        serve, bench = configs(rig, workdir)
        proc = serve_process(serve)
        records = []
        try:
            for k in range(n):
                record = one_run(bench, workdir / f"runs-{label}-{rig}")
                records.append(record)
                sync = record.get("sync") or {}
                axis = record.get("time_axis") or {}
                print(f"  {label:8s} {rig:13s} run {k + 1:2d}: {record.get('verdict'):10s} missing rows "
                      f"{axis.get('missing_rows')}, SYNC p50 {sync.get('p50_ms')} p99 {sync.get('p99_ms')} max "
                      f"{sync.get('max_ms')} ms, late {sync.get('late')}, skipped {sync.get('skipped')}, unanswered "
                      f"{sync.get('unanswered')}" + (f" ({why(record)})" if record.get("verdict") != "pass" else ""),
                      flush=True)
        finally:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
        out[rig] = summarise(records)
    return out


def why(record: dict) -> str:
    failed = [f"{c.get('name')}: {c.get('value')} (limit {c.get('limit')})" for c in record.get("criteria") or []
              if not c.get("passed")]
    return "; ".join(filter(None, [record.get("abort_reason")] + failed))[:400]


def summarise(records: list[dict]) -> dict:
    syncs = [r.get("sync") or {} for r in records]

    def worst(key):
        values = [s.get(key) for s in syncs if s.get(key) is not None]
        return max(values) if values else None

    complete = sum(1 for r in records if r.get("verdict") not in ("incomplete", "error", "aborted")
                   and not (r.get("time_axis") or {}).get("missing_rows"))
    p50 = sorted(s.get("p50_ms") for s in syncs if s.get("p50_ms") is not None)
    return {"runs": len(records), "complete": complete, "pass": sum(r.get("verdict") == "pass" for r in records),
            "p50_ms": p50[len(p50) // 2] if p50 else None, "p99_ms": worst("p99_ms"), "max_ms": worst("max_ms"),
            "late": sum(s.get("late") or 0 for s in syncs), "skipped": sum(s.get("skipped") or 0 for s in syncs),
            "unanswered": sum(s.get("unanswered") or 0 for s in syncs), "period_ms": worst("period_ms")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=20, help="runs per rig under load (default 20)")
    parser.add_argument("--baseline-runs", type=int, default=3, help="runs per rig without load (default 3)")
    parser.add_argument("--rigs", default=",".join(RIGS), help=f"comma-separated, of {', '.join(RIGS)}")
    parser.add_argument("--load-procs", type=int, default=2, help="busy processes during the loaded phase")
    args = parser.parse_args()
    rigs = [r for r in args.rigs.split(",") if r]
    for rig in rigs:
        if rig not in RIGS:
            print(f"--rigs: {rig!r} is not one of {', '.join(RIGS)}", file=sys.stderr)
            return 2
    with tempfile.TemporaryDirectory(prefix="rig-timing-") as tmp:
        workdir = Path(tmp)
        print(f"baseline: {args.baseline_runs} runs per rig, no extra load", flush=True)
        baseline = phase(rigs, args.baseline_runs, workdir, "baseline") if args.baseline_runs else {}
        print(f"loaded: {args.runs} runs per rig, {args.load_procs} busy processes", flush=True)
        loaders = [multiprocessing.Process(target=busy, daemon=True) for _ in range(args.load_procs)]
        for proc in loaders:
            proc.start()
        try:
            loaded = phase(rigs, args.runs, workdir, "loaded")
        finally:
            for proc in loaders:
                proc.terminate()
                proc.join(5)
    print()
    print(f"{'rig':13s} {'phase':8s} complete  pass  SYNC p50/p99/max ms   late skipped unanswered")
    fields = [f"runs={args.runs}", f"load_procs={args.load_procs}"]
    for rig in rigs:
        for label, table in (("baseline", baseline), ("loaded", loaded)):
            s = table.get(rig)
            if s is None:
                continue
            print(f"{rig:13s} {label:8s} {s['complete']:3d}/{s['runs']:<3d} {s['pass']:3d}/{s['runs']:<3d} "
                  f"{s['p50_ms']}/{s['p99_ms']}/{s['max_ms']}   {s['late']:4d} {s['skipped']:6d} {s['unanswered']:6d}")
        s, b = loaded[rig], baseline.get(rig)
        key = rig.replace("-", "_")
        fields += [f"{key}_complete={s['complete']}", f"{key}_pass={s['pass']}", f"{key}_sync_p50_ms={s['p50_ms']}",
                   f"{key}_sync_p99_ms={s['p99_ms']}", f"{key}_sync_max_ms={s['max_ms']}", f"{key}_late={s['late']}",
                   f"{key}_skipped={s['skipped']}", f"{key}_unanswered={s['unanswered']}"]
        if b is not None:
            fields += [f"baseline_{key}_complete={b['complete']}", f"baseline_{key}_sync_p99_ms={b['p99_ms']}",
                       f"baseline_{key}_sync_max_ms={b['max_ms']}"]
            if s["p99_ms"] is not None and b["p99_ms"]:
                fields.append(f"{key}_p99_load_vs_baseline={s['p99_ms'] / b['p99_ms']:.3f}")
    print("RESULT " + " ".join(fields))
    return 0


if __name__ == "__main__":
    sys.exit(main())
