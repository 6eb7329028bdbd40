"""A run process of the service: `python -m bench.service.worker --parent PID [--nice N]`.

Started ahead of need (a warm worker, docs/service.md "Warm run processes"): it lowers its CPU priority, pays the
imports of `drivebench run` and of the run services the installed packages register, then waits for one
`RunRequest` on stdin (bench/service/run_protocol.py), runs it exactly as `drivebench run` would, reports on its
stdout (the protocol's pipe: the run's own stdout is pointed at stderr, the run's service.log) and exits. One run per
process: a crashing run takes only its own process with it. End of input before a request: exit 0 (pool shrunk).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading

from bench.service import child
from bench.service.run_protocol import MAX_LINE_BYTES, Failed, Message, ProtocolError, RunRequest, decode, encode


def _channel() -> "callable":
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
    import bench.cli  # noqa: F401
    import bench.orchestrator  # noqa: F401
    from importlib.metadata import entry_points

    for entry in entry_points(group="drivebench.services"):
        try:
            entry.load()
        except Exception as exc:      # reported by the run that needs it, as a cold start would
            print(f"warm worker: run service {entry.name!r} ({entry.value}) not imported: {exc}", file=sys.stderr)


def run_args(request: RunRequest) -> list[str]:
    args = ["run", request.scenario_file, "--bench", request.bench, "--out", request.out_dir]
    if request.rerun_url:
        args += ["--rerun", "connect", "--rerun-url", request.rerun_url]
    if request.seed is not None:
        args += ["--seed", str(request.seed)]
    return args


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.service.worker")
    parser.add_argument("--parent", type=int, required=True, help="the service's pid: die with it")
    parser.add_argument("--nice", type=int, default=0, help="added to this process's CPU niceness first")
    opts = parser.parse_args(argv)
    if opts.nice:
        os.nice(opts.nice)
    child.die_with(opts.parent)
    send = _channel()
    warm()
    line = sys.stdin.buffer.readline(MAX_LINE_BYTES + 1)
    if not line:
        return 0
    try:
        request = decode(line)
        if not isinstance(request, RunRequest):
            raise ProtocolError(f"run protocol: expected a run_request, got {type(request).__name__}")
    except ProtocolError as exc:
        send(Failed(reason=str(exc), exit_code=2))
        return 2
    if request.recording_id:
        os.environ["DRIVEBENCH_RECORDING_ID"] = request.recording_id    # read by bench.rerun_view in this process
    from bench.cli import main as drivebench
    from bench.drill import adopt_proofs

    adopt_proofs(request.drill_proofs)
    child.attach(send)
    code = drivebench(run_args(request))
    if not child.finished:
        send(Failed(reason=f"drivebench run made no record (exit {code})", exit_code=code))
    return code


if __name__ == "__main__":
    sys.exit(main())
