"""A run process of the service: `python -m bench.service.worker --parent PID [--nice N]`.

Two ways to start one (docs/service.md, "Warm run processes"): forked from the service's fork server, which paid
the imports of `drivebench run` and of the run services the installed packages register once (`forked`, the
default), or cold, as its own interpreter that pays them itself (`python -m bench.service.worker --parent PID`,
`serve --run-start cold`). Either way it lowers its CPU priority if told, takes one `RunRequest`
(bench/service/run_protocol.py), runs it exactly as `drivebench run` would, reports on its protocol pipe (nothing
else writes there: the run's own stdout goes to its log, the run's service.log) and exits. One run per process: a
crashing run takes only its own process with it.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
import threading
from multiprocessing.connection import Connection
from typing import Callable

from bench.service import child
from bench.service.run_protocol import MAX_LINE_BYTES, Failed, Message, ProtocolError, RunRequest, decode, encode


def _channel() -> Callable[[Message], None]:
    """The protocol pipe (the original stdout), and stdout pointed at stderr for everything else."""
    events = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)
    lock = threading.Lock()

    def send(message: Message) -> None:
        with lock:
            try:
                events.write(encode(message))
            except OSError:      # the service is gone: PDEATHSIG's SIGTERM is on its way, the run stops safely
                pass

    return send


def warm() -> None:
    """What a cold `drivebench run` would import before its first sample: the CLI, the run machinery, and the run
    services (e.g. a simulator) the installed packages register under drivebench.services."""
    import bench.faces.cli  # noqa: F401
    import bench.run.orchestrator  # noqa: F401
    from importlib.metadata import entry_points

    for entry in entry_points(group="drivebench.services"):
        try:
            entry.load()
        except Exception as exc:      # reported by the run that needs it, as a cold start would
            print(f"warm worker: run service {entry.name!r} ({entry.value}) not imported: {exc}", file=sys.stderr)


def run_args(request: RunRequest) -> list[str]:
    args = ["run", request.scenario_file, "--bench", request.bench, "--out", request.out_dir]
    if request.seed is not None:
        args += ["--seed", str(request.seed)]
    return args


def serve(line: bytes, send: Callable[[Message], None]) -> int:
    """Run the request `line` carries, reporting through `send`; the exit code of `drivebench run`."""
    try:
        request = decode(line)
        if not isinstance(request, RunRequest):
            raise ProtocolError(f"run protocol: expected a run_request, got {type(request).__name__}")
    except ProtocolError as exc:
        send(Failed(reason=str(exc), exit_code=2))
        return 2
    for name, value in (("DRIVEBENCH_RECORDING_ID", request.recording_id),
                        ("DRIVEBENCH_RECORDING_NAME", request.recording_name),
                        ("DRIVEBENCH_RERUN_INTERVAL_S", request.rerun_interval_s)):
        if value is not None:                 # read by bench.outputs.rerun_view in this process
            os.environ[name] = str(value)
    from bench.faces.cli import main as drivebench
    from bench.run.drill import adopt_proofs

    adopt_proofs(request.drill_proofs)
    child.attach(send)
    code = drivebench(run_args(request))
    if not child.finished:
        send(Failed(reason=f"drivebench run made no record (exit {code})", exit_code=code))
    return code


def main(argv: list[str] | None = None) -> int:
    """A cold run process (`serve --run-start cold`): started for its run, pays its imports, then runs it."""
    parser = argparse.ArgumentParser(prog="python -m bench.service.worker")
    parser.add_argument("--parent", type=int, required=True, help="the service's pid: die with it")
    parser.add_argument("--nice", type=int, default=0, help="added to this process's CPU niceness first")
    opts = parser.parse_args(argv)
    if opts.nice:             # its process group or session: the runner's Popen, as detach() below says why
        os.nice(opts.nice)
    child.die_with(opts.parent)
    send = _channel()
    warm()
    line = sys.stdin.buffer.readline(MAX_LINE_BYTES + 1)
    if not line:
        return 0
    return serve(line, send)


def _follow(service_pid: int) -> None:
    """SIGTERM (the run's safe stop) to this process when the service ends, however it ends, and only then: the
    fork server is this process's parent, and a parent-death signal would follow it (a fork server SIGKILLed, by the
    OOM killer say, took its runs with it), so the service's pidfd is watched instead."""
    from multiprocessing import forkserver

    server = forkserver._forkserver     # every forked child holds the server's "alive" pipe: let it go, so that the
    if server._forkserver_alive_fd is not None:     # fork server leaves with the service, not with the last run
        os.close(server._forkserver_alive_fd)
        server._forkserver_alive_fd = None
    try:
        watched = os.pidfd_open(service_pid)
    except ProcessLookupError:
        os.kill(os.getpid(), signal.SIGTERM)
        return

    def wait() -> None:
        select.select([watched], [], [])
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=wait, daemon=True, name="drivebench-follow-service").start()


def detach(nice: int) -> None:
    """Out of the service's process group, so that a Ctrl-C at its terminal is the service's to handle. A niced
    (simulated) run stays in the service's session: with Linux autogroups a session of its own would take an equal
    share of the CPU with the whole service whatever its niceness, and the API waited behind the runs
    (benchmarks/service.py). A run on a real rig gets a session of its own: its share of the CPU, and with it the
    heartbeat and SYNC it owes the drive, holds however busy the service is."""
    if nice:
        os.setpgid(0, 0)
        os.nice(nice)
    else:
        os.setsid()


def forked(line: bytes, events: Connection, log: Connection, nice: int, service_pid: int) -> None:
    """A warm run process: forked by the service's fork server (multiprocessing, preloaded with `preload_modules`),
    with the protocol pipe `events` and the log pipe `log` handed over by descriptor."""
    detach(nice)
    _follow(service_pid)
    os.dup2(log.fileno(), 1)
    os.dup2(log.fileno(), 2)
    log.close()
    stream = os.fdopen(os.dup(events.fileno()), "wb", buffering=0)
    events.close()
    lock = threading.Lock()

    def send(message: Message) -> None:
        with lock:
            try:
                stream.write(encode(message))
            except OSError:
                pass

    sys.exit(serve(line, send))


WARM_BENCHES_ENV = "DRIVEBENCH_WARM_BENCHES"     # the bench configs bench.service.fork_warm warms (a JSON list)


def ready() -> None:
    """Forked once at the service's start: returns when the fork server has imported everything."""


# What a run imports lazily, on its way (the summary plot, the telemetry file, the Rerun stream, the links):
# imported once by the fork server, not in every run (1.2 s of a 2.4 s first run in a process, measured).
LAZY_IMPORTS = ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg", "matplotlib.pyplot", "PIL.Image",
                "PIL.PngImagePlugin", "pyarrow", "pyarrow.parquet", "pyarrow.pandas_compat", "rerun", "numba", "can",
                "can.interfaces.virtual", "pymodbus.client", "pymodbus.server", "serial", "psutil", "rich.table",
                "rich.progress", "rich._emoji_codes", "encodings.idna")


def preload_modules() -> list[str]:
    """What the fork server imports once for every run it forks: the CLI, the run machinery and the drivers, what a
    run imports lazily, every module of the packages whose run services the installed packages register (a
    simulator), and last bench.service.fork_warm, which warms the rigs' runs (DRIVEBENCH_WARM_BENCHES)."""
    import pkgutil
    from importlib import import_module
    from importlib.metadata import entry_points

    bench_modules = [m.name for m in pkgutil.walk_packages(import_module("bench").__path__, "bench.")
                     if not m.name.startswith("bench.service.") or m.name == "bench.service.child"]
    driver_modules = [m.name for m in pkgutil.walk_packages(import_module("drivers").__path__, "drivers.")]
    services = []
    for package in sorted({entry.module.split(".")[0] for entry in entry_points(group="drivebench.services")}):
        try:
            found = import_module(package)
        except Exception:
            continue
        services += [package, *(m.name for m in pkgutil.walk_packages(getattr(found, "__path__", []), package + "."))]
    return [name for name in ("bench.faces.cli", "bench.run.orchestrator", "bench.service.worker", *LAZY_IMPORTS,
                              *bench_modules, *driver_modules, *services) if not name.endswith("__main__")] + [
        "bench.service.fork_warm"]      # last: warms the rigs' runs and freezes what all of the above left alive


if __name__ == "__main__":
    sys.exit(main())
