"""The bench service under the abuse of issue 23, beside two running runs (`drivebench serve` with the usual
1,024-descriptor limit, two run processes at once, the rigs of benchmarks/service.py):

1. baseline: one client, 100 API requests one after the other (the ratio's denominator);
2. 50 client processes x 20 requests, released at once (rigs, runs, one run, leases, health): p99, errors, the
   service's RSS;
3. 100 concurrent GET /trend.png of 100 different plots while /api/health is timed;
4. four 100 MB request bodies at once from a viewer token and four from an operator: refused before they are read,
   the service's RSS before and after;
5. 1,100 idle TCP connections (no token, no bytes): /api/health timed while they are held.

Last line: `RESULT api_p99_ms=... api_p99_ratio=... api_errors=... rss_mb=... health_under_plots_max_ms=...
body_rss_growth_mb=... idle_health_ms=... idle_ok=...`.
Usage: python benchmarks/service_abuse.py [--port 8791]
"""

from __future__ import annotations

import argparse
import http.client
import os
import resource
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench.service.client import Client  # noqa: E402
from service import p99, rigs_toml  # noqa: E402

CLIENTS, REQUESTS = 50, 20
PATHS = ["/api/rigs", "/api/runs?limit=20", "/api/runs/1", "/api/leases", "/api/health"]
LONG_SCENARIO = "scenarios/pmsm/fig09-crane-lift-lower.toml"


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def cpu_s(pid: int) -> float:
    """User + system CPU time of the process and its threads [s] (its run processes are not counted)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def load_average() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def timed(client: Client, path: str) -> float:
    t0 = time.perf_counter()
    client.request("GET", path)
    return (time.perf_counter() - t0) * 1000


def start(work: Path, port: int) -> tuple[subprocess.Popen, dict[str, str]]:
    (work / "rigs.toml").write_text(rigs_toml())
    tokens = {}
    for role in ("operator", "viewer"):
        tokens[role] = subprocess.run([sys.executable, "-m", "bench", "token", "create", "--role", role, "--name",
                                       f"abuse-{role}", "--data", str(work / "data")], cwd=ROOT, capture_output=True,
                                      text=True, timeout=60, check=True).stdout.strip()

    def usual_limit():
        resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))
    log = open(work / "serve.log", "ab")
    proc = subprocess.Popen([sys.executable, "-m", "bench", "serve", "--data", str(work / "data"), "--port", str(port),
                             "--rigs", str(work / "rigs.toml"), "--max-parallel", "2"], cwd=ROOT, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True, preexec_fn=usual_limit)
    viewer = Client(f"http://127.0.0.1:{port}", tokens["viewer"], timeout_s=5)
    deadline = time.monotonic() + 60
    while True:
        try:
            viewer.request("GET", "/api/health")
            return proc, tokens
        except Exception:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit(f"drivebench serve did not start; see {work / 'serve.log'}")
            time.sleep(0.2)


def _client_process(url: str, token: str, k: int, gate, out, nice: int) -> None:
    if nice:
        os.nice(nice)      # --client-nice: the clients stand back as remote ones would (they share the 2 cores here)
    c = Client(url, token, timeout_s=10)
    latencies, errors = [], 0
    gate.wait()
    for i in range(REQUESTS):
        try:
            latencies.append(timed(c, PATHS[(k + i) % len(PATHS)]))
        except Exception:
            errors += 1
    out.put((latencies, errors))


def load(url: str, token: str, nice: int = 0) -> tuple[list[float], int]:
    """CLIENTS client processes (a lab's browsers and CI jobs are not threads of one Python process: 50 threads
    sharing one interpreter lock measured the client as much as the service), all released at once."""
    import multiprocessing as mp

    gate, out = mp.Barrier(CLIENTS), mp.Queue()
    procs = [mp.Process(target=_client_process, args=(url, token, k, gate, out, nice)) for k in range(CLIENTS)]
    for p in procs:
        p.start()
    latencies: list[float] = []
    errors = 0
    for _ in procs:
        got, bad = out.get(timeout=300)
        latencies += got
        errors += bad
    for p in procs:
        p.join(30)
    return latencies, errors


async def _one_connection(port: int, token: str, k: int, gate: "asyncio.Event") -> tuple[list[float], int]:
    """One client on one keep-alive connection: REQUESTS requests one after the other, raw HTTP/1.1."""
    import asyncio

    latencies, errors = [], 0
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    await gate.wait()
    for i in range(REQUESTS):
        request = (f"GET {PATHS[(k + i) % len(PATHS)]} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                   f"Authorization: Bearer {token}\r\n\r\n").encode()
        t0 = time.perf_counter()
        try:
            writer.write(request)
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
            length = next((int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                           if line.lower().startswith(b"content-length:")), 0)
            await asyncio.wait_for(reader.readexactly(length), 10)
            if not head.startswith(b"HTTP/1.1 200"):
                raise OSError(head.split(b"\r\n", 1)[0].decode())
            latencies.append((time.perf_counter() - t0) * 1000)
        except (OSError, asyncio.TimeoutError, asyncio.IncompleteReadError, ValueError):
            errors += 1
            writer.close()
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.close()
    return latencies, errors


def load_async(port: int, token: str) -> tuple[list[float], int]:
    """CLIENTS clients as keep-alive connections of one asyncio process, released at once. A lab's browsers and CI
    jobs run on other machines; here they share the service's 2 cores, and 50 Python client processes spend more
    CPU per request than the service does (their own scheduling then shows in their timings). Raw HTTP on asyncio
    costs the client a few tens of microseconds a request, so the figure is the service's."""
    import asyncio

    async def main() -> list[tuple[list[float], int]]:
        gate = asyncio.Event()
        tasks = [asyncio.create_task(_one_connection(port, token, k, gate)) for k in range(CLIENTS)]
        await asyncio.sleep(0.5)               # every connection open before the first request
        gate.set()
        return await asyncio.gather(*tasks)

    results = asyncio.run(main())
    return [x for got, _ in results for x in got], sum(bad for _, bad in results)


def plots_and_health(port: int, url: str, token: str) -> tuple[float, dict[int, int]]:
    statuses: dict[int, int] = {}
    done = threading.Event()

    def plot(k: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
        try:
            conn.request("GET", f"/trend.png?criterion=c{k}&scenario=s{k}", headers={"Authorization": f"Bearer {token}"})
            status = conn.getresponse().status
        except OSError:
            status = 0
        statuses[status] = statuses.get(status, 0) + 1
        conn.close()
    threads = [threading.Thread(target=plot, args=(k,)) for k in range(100)]
    health: list[float] = []
    c = Client(url, token, timeout_s=30)

    def poll() -> None:
        while not done.is_set():
            health.append(timed(c, "/api/health"))
            time.sleep(0.02)
    poller = threading.Thread(target=poll)
    poller.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    done.set()
    poller.join(30)
    return max(health, default=float("nan")), statuses


def big_body(port: int, token: str, size: int = 100 * 1024 * 1024) -> int:
    """Send headers announcing `size` bytes, then up to all of them; the status the server answered (0: none)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    head = (f"POST /api/runs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\nContent-Type: application/json"
            f"\r\nContent-Length: {size}\r\n\r\n").encode()
    try:
        sock.sendall(head)
        chunk = b"x" * (1 << 20)
        for _ in range(size // len(chunk)):
            sock.sendall(chunk)
    except OSError:
        pass
    try:
        answer = sock.recv(200)
        return int(answer.split()[1]) if answer.startswith(b"HTTP/1.1") else 0
    except (OSError, ValueError, IndexError):
        return 0
    finally:
        sock.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=8791)
    parser.add_argument("--clients", choices=("asyncio", "processes", "both"), default="asyncio",
                        help="the 50 clients as connections of one asyncio process (default: the service's figure) or "
                             "as 50 processes (their own CPU competes with the service's on this host); both: "
                             "processes first, the RESULT from asyncio")
    parser.add_argument("--client-nice", type=int, default=0,
                        help="the 50 client processes' niceness (19: as if they ran elsewhere; default 0: as before)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="drivebench-service-abuse-"))
    url = f"http://127.0.0.1:{args.port}"
    proc, tokens = start(work, args.port)
    operator, viewer = Client(url, tokens["operator"]), Client(url, tokens["viewer"], timeout_s=10)
    try:
        ids = [operator.request("POST", "/api/runs", {"scenario": LONG_SCENARIO, "rig": rig})["id"]
               for rig in ("pmsm-sim-1", "pmsm-sim-2") * 6]
        deadline = time.monotonic() + 60
        while sum(r["state"] == "running" for r in viewer.request("GET", "/api/runs?state=running")) < 2:
            if time.monotonic() > deadline:
                raise SystemExit("two runs did not start within 60 s")
            time.sleep(0.2)
        base = [timed(viewer, PATHS[i % len(PATHS)]) for i in range(100)]
        base_p99 = p99(base)
        print(f"baseline (one client, two runs running): median {statistics.median(base):.1f} ms, "
              f"p99 {base_p99:.1f} ms")

        for kind in (("processes", "asyncio") if args.clients == "both" else (args.clients,)):
            cpu0 = cpu_s(proc.pid)
            if kind == "processes":
                latencies, errors = load(url, tokens["viewer"], args.client_nice)
            else:
                latencies, errors = load_async(args.port, tokens["viewer"])
            cpu_ms = (cpu_s(proc.pid) - cpu0) * 1000 / max(1, len(latencies))
            api_p99 = p99(latencies)
            rss = rss_mb(proc.pid)
            running = sum(r["state"] == "running" for r in viewer.request("GET", "/api/runs?state=running"))
            print(f"{CLIENTS} clients ({kind}, nice {args.client_nice if kind == 'processes' else 0}) x {REQUESTS} "
                  f"requests: {len(latencies)} answered, {errors} errors, median {statistics.median(latencies):.1f} ms, "
                  f"p99 {api_p99:.1f} ms (x{api_p99 / base_p99:.2f} baseline), max {max(latencies):.0f} ms; service "
                  f"RSS {rss:.0f} MB; service CPU {cpu_ms:.2f} ms per request (its runner and readers included); "
                  f"runs running at the end: {running}; load {load_average()}")

        health_max, statuses = plots_and_health(args.port, url, tokens["viewer"])
        print(f"100 concurrent trend.png (100 different plots): statuses {statuses}; /api/health slowest "
              f"{health_max:.0f} ms meanwhile")

        rss_before = rss_mb(proc.pid)
        results: list[int] = []
        threads = [threading.Thread(target=lambda t=t: results.append(big_body(args.port, t)))
                   for t in [tokens["viewer"]] * 4 + [tokens["operator"]] * 4]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
        rss_after = rss_mb(proc.pid)
        print(f"four 100 MB bodies from a viewer and four from an operator: answered {sorted(results)}; service RSS "
              f"{rss_before:.0f} -> {rss_after:.0f} MB")

        idle = []
        for _ in range(1100):
            try:
                idle.append(socket.create_connection(("127.0.0.1", args.port), timeout=5))
            except OSError:
                break
        time.sleep(1.0)
        try:
            idle_ms = timed(Client(url, tokens["viewer"], timeout_s=10), "/api/health")
            idle_ok = 1
        except Exception as exc:
            idle_ms, idle_ok = float("nan"), 0
            print(f"  /api/health with the idle connections held: {exc}")
        for s in idle:
            s.close()
        print(f"{len(idle)} idle connections held (service at 1,024 descriptors): /api/health in {idle_ms:.0f} ms")
        for run_id in ids:
            try:
                operator.request("POST", f"/api/runs/{run_id}/abort")
            except Exception:
                pass
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
    log_lines = (work / "serve.log").read_text(errors="replace").count("\n")
    print(f"service log: {log_lines} lines ({work / 'serve.log'})")
    print(f"RESULT api_p99_ms={api_p99:.1f} api_p99_ratio={api_p99 / base_p99:.2f} api_errors={errors} "
          f"rss_mb={rss:.0f} clients={args.clients} client_nice={args.client_nice} cpu_ms_per_request={cpu_ms:.2f} load={load_average()} health_under_plots_max_ms={health_max:.0f} "
          f"body_rss_growth_mb={rss_after - rss_before:.1f} idle_health_ms={idle_ms:.0f} idle_ok={idle_ok} "
          f"log_lines={log_lines}")
    return 0 if errors == 0 and api_p99 <= 50 and idle_ok and rss_after - rss_before < 20 else 1


if __name__ == "__main__":
    sys.exit(main())
