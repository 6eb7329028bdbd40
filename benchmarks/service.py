"""The bench service under load: the paper suite (scenarios/pmsm + scenarios/spim) submitted REPEAT times to four
simulated rigs of one `drivebench serve`, while a poller measures API latency; then submit-to-start on an idle rig
and how soon a rig is free after its lease holder is SIGKILLed (a CI job holding a real rig, a run process).
As benchmarks/campaign.py pays its workers' imports and drills before its timing, each service is timed once its
run processes are warm (/api/health) and one run per bench config has passed its drill; both are printed.

Baselines from the same run: the same submissions to a service whose every run starts a cold process
(`serve --run-start cold`, as before warm run processes), printed as the ratio warm/cold; `benchmarks/campaign.py --no-ray`
(the campaign figure, runs/min with two local workers); with --serial, each suite scenario once through
`drivebench run` directly, one after the other (the ideal makespan: their sum times REPEAT divided by the parallel
run processes). The machine's load average is printed with each figure (other work on the host moves them).
Last line: `RESULT runs=... lost=... stuck=... runs_per_min=... cold_runs_per_min=... warm_vs_cold=...
campaign_runs_per_min=... api_p99_ms=... submit_to_start_ms=... lease_free_s=... ready_s=... warm_up_s=...
load=...`.
Usage: python benchmarks/service.py [--repeat 1] [--full (= --repeat 10: 200 runs)] [--parallel 2] [--ttl 2]
                                    [--no-cold] [--no-campaign] [--serial]
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.service.client import Client, FINAL  # noqa: E402

SIMULATED_RIGS = [("pmsm-sim-1", "pmsm"), ("pmsm-sim-2", "pmsm"), ("spim-sim-1", "spim"), ("spim-sim-2", "spim")]


def rigs_toml() -> str:
    rigs = [f'[[rig]]\nname = "{name}"\nbench = "{ROOT}/config/benches/sim-{kind}.toml"\n'
            f'tags = ["{kind}", "paper"]\nmax_concurrent = 2\n' for name, kind in SIMULATED_RIGS]
    rigs.append(f'[[rig]]\nname = "real-rig"\nbench = "{ROOT}/config/benches/sim-pmsm.toml"\n'
                'tags = ["lease-test"]\nsimulated = false\n')
    return "\n".join(rigs)


def suite() -> list[Path]:
    return sorted((ROOT / "scenarios" / "pmsm").glob("*.toml")) + sorted((ROOT / "scenarios" / "spim").glob("*.toml"))


def baseline(scenarios: list[Path], out: Path) -> dict[str, float]:
    walls = {}
    for path in scenarios:
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "bench", "run", str(path), "--out", str(out)], cwd=ROOT,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
        walls[path.stem] = time.monotonic() - t0
        print(f"  baseline {path.relative_to(ROOT)}: {walls[path.stem]:.1f} s")
    return walls


def load_average() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def start_service(work: Path, port: int, parallel: int, ttl: float,
                  run_start: str = "forkserver") -> tuple[subprocess.Popen, dict[str, str], float]:
    """The service started; (process, tokens by role, seconds from its start until its run processes were ready:
    /api/health's run_processes no longer "warming", i.e. the fork server's preload done)."""
    (work / "rigs.toml").write_text(rigs_toml())
    tokens = {}
    for role in ("operator", "viewer", "admin"):
        made = subprocess.run([sys.executable, "-m", "bench", "token", "create", "--role", role, "--name",
                               f"bench-{role}", "--data", str(work / "data")], cwd=ROOT, capture_output=True,
                              text=True, timeout=60, check=True)
        tokens[role] = made.stdout.strip()
    log = open(work / "serve.log", "ab")
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "bench", "serve", "--data", str(work / "data"), "--port", str(port),
                             "--rigs", str(work / "rigs.toml"), "--max-parallel", str(parallel), "--lease-ttl",
                             str(ttl), "--run-start", run_start], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    client = Client(f"http://127.0.0.1:{port}", tokens["viewer"], timeout_s=5)
    deadline = time.monotonic() + 60
    while True:
        try:
            client.request("GET", "/api/health")
            break
        except Exception:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit(f"drivebench serve did not start; see {work / 'serve.log'}")
            time.sleep(0.2)
    while client.request("GET", "/api/health").get("run_processes") == "warming" and time.monotonic() < deadline:
        time.sleep(0.1)
    return proc, tokens, time.monotonic() - t0


class Poller(threading.Thread):
    """GET /api/rigs, /api/runs?limit=20 and one run, every 50 ms, timing each request."""

    def __init__(self, client: Client):
        super().__init__(daemon=True)
        self.client = client
        self.latencies_ms: list[float] = []
        self.slowest: list[tuple[float, str, float]] = []
        self.errors = 0
        self.stop = threading.Event()

    def run(self) -> None:
        paths = ["/api/rigs", "/api/runs?limit=20", "/api/runs/1", "/api/leases"]
        i = 0
        while not self.stop.wait(0.05):
            t0 = time.perf_counter()
            try:
                self.client.request("GET", paths[i % len(paths)])
                self.latencies_ms.append((time.perf_counter() - t0) * 1000)
                self.slowest = sorted([*self.slowest, (self.latencies_ms[-1], paths[i % len(paths)],
                                                       time.monotonic())], reverse=True)[:5]
            except Exception:
                self.errors += 1
            i += 1


def stop_service(server: subprocess.Popen) -> None:
    """SIGTERM (the service stops its runs safely), then SIGKILL after a minute."""
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=60)
    except subprocess.TimeoutExpired:
        server.kill()


def p99(values: list[float]) -> float:
    return statistics.quantiles(values, n=100)[98] if len(values) >= 100 else max(values, default=float("nan"))


def throughput(work: Path, port: int, parallel: int, ttl: float, repeat: int, scenarios: list[Path],
               run_start: str) -> dict:
    """The suite submitted `repeat` times to a fresh service once it is warm; runs/min, API latency while they ran,
    lost and stuck. Like benchmarks/campaign.py, what a service pays once is paid before the timing and printed: its
    run processes' preload, and one run per bench config first (its bench-death drill, proved once per config)."""
    work.mkdir(parents=True, exist_ok=True)
    server, tokens, ready_s = start_service(work, port, parallel, ttl, run_start)
    url = f"http://127.0.0.1:{port}"
    operator, viewer = Client(url, tokens["operator"]), Client(url, tokens["viewer"], timeout_s=5)
    watcher = Client(url, tokens["viewer"], timeout_s=60)      # the completion poll: not a latency probe
    poller = Poller(viewer)
    try:
        t_warm = time.monotonic()
        first_of_kind = {path.parent: path for path in reversed(scenarios)}.values()
        warm_ids = [operator.request("POST", "/api/runs", {"scenario": str(path.relative_to(ROOT)),
                                                           "tag": "paper"})["id"] for path in first_of_kind]
        operator.wait(warm_ids, 600, poll_s=0.25)
        warm_up_s = time.monotonic() - t_warm
        print(f"  service ready {ready_s:.1f} s after its start (run processes: "
              f"{viewer.request('GET', '/api/health').get('run_processes')}); warm-up: {len(warm_ids)} run(s), one per "
              f"bench config (its drill), {warm_up_s:.1f} s")
        poller.start()
        t0 = time.monotonic()
        ids = []
        for _ in range(repeat):
            for path in scenarios:
                ids.append(operator.request("POST", "/api/runs", {"scenario": str(path.relative_to(ROOT)),
                                                                  "tag": "paper"})["id"])
        submitted = time.monotonic() - t0
        timeout = 600 + 120 * len(ids)
        runs = {}
        while time.monotonic() - t0 < timeout:
            listed = watcher.request("GET", "/api/runs?limit=1000")
            runs = {r["id"]: r for r in listed if r["id"] in ids}
            if len(runs) == len(ids) and all(r["state"] in FINAL for r in runs.values()):
                break
            time.sleep(0.25)
        makespan = time.monotonic() - t0
        poller.stop.set()
        poller.join(timeout=10)
    finally:
        stop_service(server)
    lost = len(set(ids) - set(runs))
    stuck = sum(r["state"] not in FINAL for r in runs.values())
    states: dict[str, int] = {}
    for r in runs.values():
        states[r["state"]] = states.get(r["state"], 0) + 1
    runs_per_min = (len(runs) - stuck) / (makespan / 60)
    api_p99 = p99(poller.latencies_ms)
    kind = "cold (--run-start cold)" if run_start == "cold" else "warm (forked from the fork server)"
    print(f"{kind}: submitted {len(ids)} runs in {submitted:.2f} s; all final after {makespan:.1f} s: {states}; "
          f"{runs_per_min:.2f} runs/min (load {load_average()})")
    print("  slowest: " + ", ".join(f"{ms:.0f} ms {path} at +{at - t0:.1f} s" for ms, path, at in poller.slowest))
    print(f"  API under load: {len(poller.latencies_ms)} requests, median "
          f"{statistics.median(poller.latencies_ms):.1f} ms, p99 {api_p99:.1f} ms, {poller.errors} errors")
    return {"runs": len(ids), "lost": lost, "stuck": stuck, "runs_per_min": runs_per_min, "api_p99": api_p99,
            "makespan": makespan, "ready_s": ready_s, "warm_up_s": warm_up_s}


def campaign_figure(scenario: str | None) -> float:
    """runs/min of benchmarks/campaign.py (two local workers), run here as a separate process."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "campaign.py"), "--no-ray",
                           *(["--scenario", scenario] if scenario else [])], cwd=ROOT,
                          capture_output=True, text=True, timeout=1800)
    line = next((l for l in done.stdout.splitlines() if l.startswith("RESULT ")), "")
    fields = dict(kv.split("=", 1) for kv in line.split()[1:])
    return float(fields.get("runs_per_min", "nan"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1, help="suite submissions (10 = 200 runs)")
    parser.add_argument("--full", action="store_true", help="--repeat 10")
    parser.add_argument("--parallel", type=int, default=os.cpu_count() or 2, help="run processes at once")
    parser.add_argument("--ttl", type=float, default=2.0, help="lease TTL of the service [s]")
    parser.add_argument("--port", type=int, default=8790)
    parser.add_argument("--no-cold", action="store_true", help="skip the cold-start service baseline")
    parser.add_argument("--no-campaign", action="store_true", help="skip benchmarks/campaign.py")
    parser.add_argument("--serial", action="store_true", help="also each scenario through drivebench run directly")
    parser.add_argument("--scenario", help="submit this one scenario --repeat times instead of the suite (the "
                                           "campaign benchmark's is scenarios/pmsm/fig08-20rads-rs-step.toml)")
    args = parser.parse_args()
    repeat = 10 if args.full else args.repeat
    scenarios = [(ROOT / args.scenario).resolve()] if args.scenario else suite()
    work = Path(tempfile.mkdtemp(prefix="drivebench-service-bench-"))
    print(f"{len(scenarios)} scenario(s) x {repeat} = {len(scenarios) * repeat} runs, {args.parallel} run "
          f"processes at once, four simulated rigs; work dir {work}; load {load_average()}")
    walls = baseline(scenarios, work / "baseline") if args.serial else {}
    campaign = float("nan") if args.no_campaign else campaign_figure(args.scenario)
    if not args.no_campaign:
        print(f"campaign: benchmarks/campaign.py --no-ray: {campaign:.1f} runs/min (load {load_average()})")
    cold = None if args.no_cold else throughput(work / "cold", args.port + 1, args.parallel, args.ttl, repeat,
                                                 scenarios, "cold")
    (work / "warm").mkdir(exist_ok=True)
    warm = throughput(work / "warm", args.port, args.parallel, args.ttl, repeat, scenarios, "forkserver")
    if cold:
        print(f"warm/cold: {warm['runs_per_min'] / cold['runs_per_min']:.2f}x runs/min; warm/campaign: "
              f"{warm['runs_per_min'] / campaign:.2f}")
    if walls:
        ideal = sum(walls.values()) * repeat / args.parallel
        print(f"serial: the suite through drivebench run directly, {sum(walls.values()):.1f} s; ideal makespan "
              f"{ideal:.1f} s on {args.parallel} processes; service/ideal = {warm['makespan'] / ideal:.2f}")
    lost, stuck, runs_per_min, api_p99 = warm["lost"], warm["stuck"], warm["runs_per_min"], warm["api_p99"]
    if cold:
        lost, stuck = lost + cold["lost"], stuck + cold["stuck"]

    server, tokens, _ = start_service(work / "warm", args.port, args.parallel, args.ttl)
    url = f"http://127.0.0.1:{args.port}"
    operator, viewer = Client(url, tokens["operator"]), Client(url, tokens["viewer"], timeout_s=5)
    try:
        # submit-to-start on an idle rig (server-side times: submitted_utc -> started_utc)
        import datetime as dt

        def ts(value):
            return dt.datetime.fromisoformat(value.replace("Z", "+00:00")).timestamp()

        starts = []
        for _ in range(3):
            run_id = operator.request("POST", "/api/runs", {"scenario": "scenarios/pmsm/fig08-20rads-rs-step.toml",
                                                            "rig": "pmsm-sim-1"})["id"]
            done = operator.wait([run_id], 120, poll_s=0.2)[run_id]
            starts.append((ts(done["started_utc"]) - ts(done["submitted_utc"])) * 1000)
        submit_to_start = max(starts)
        print(f"submit to start on an idle rig: {', '.join(f'{s:.0f}' for s in starts)} ms")

        # lease freed after its holder is SIGKILLed: a CI job holding the real rig, then a run process on it
        holder = subprocess.Popen([sys.executable, "-c", f"""
import time
from bench.service.client import Client
c = Client("{url}", "{tokens['operator']}")
lease = c.request("POST", "/api/rigs/real-rig/lease", {{"ttl_s": {args.ttl}, "reason": "ci job"}})
while True:
    time.sleep({args.ttl / 4})
    c.request("POST", f"/api/leases/{{lease['id']}}/extend", {{"ttl_s": {args.ttl}}})
"""], cwd=ROOT)
        while viewer.request("GET", "/api/rigs/real-rig")["state"] != "reserved":
            time.sleep(0.05)
        time.sleep(1.0)
        holder.kill()
        t_kill = time.monotonic()
        while viewer.request("GET", "/api/rigs/real-rig")["state"] != "free":
            time.sleep(0.02)
        free_ci = time.monotonic() - t_kill
        holder.wait(timeout=10)
        run_id = operator.request("POST", "/api/runs", {"scenario": "scenarios/pmsm/fig09-crane-lift-lower.toml",
                                                        "rig": "real-rig"})["id"]
        while (run := viewer.request("GET", f"/api/runs/{run_id}"))["state"] != "running" or not run["progress_s"]:
            time.sleep(0.05)
        os.kill(run["pid"], signal.SIGKILL)
        t_kill = time.monotonic()
        while viewer.request("GET", "/api/rigs/real-rig")["state"] != "free":
            time.sleep(0.02)
        free_run = time.monotonic() - t_kill
        print(f"rig free after its holder was SIGKILLed (TTL {args.ttl:g} s): CI job {free_ci:.2f} s, "
              f"run process {free_run:.2f} s")
        lease_free = max(free_ci, free_run)
    finally:
        stop_service(server)
    cold_rpm = cold["runs_per_min"] if cold else float("nan")
    print(f"RESULT runs={warm['runs'] + (cold['runs'] if cold else 0)} lost={lost} stuck={stuck} "
          f"runs_per_min={runs_per_min:.2f} cold_runs_per_min={cold_rpm:.2f} "
          f"warm_vs_cold={runs_per_min / cold_rpm:.2f} campaign_runs_per_min={campaign:.1f} "
          f"api_p99_ms={api_p99:.1f} submit_to_start_ms={submit_to_start:.0f} lease_free_s={lease_free:.2f} "
          f"ready_s={warm['ready_s']:.1f} warm_up_s={warm['warm_up_s']:.1f} load={load_average()}")
    ok = (lost == 0 and stuck == 0 and runs_per_min >= 100 and api_p99 <= 25 and submit_to_start <= 1000
          and lease_free <= args.ttl + 1)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
