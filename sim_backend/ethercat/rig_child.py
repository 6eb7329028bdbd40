"""A simulated rig with an EtherCAT drive, served from a child process. pysoem holds the interpreter lock while SOEM
waits for a frame (state checks, register access), so a slave answering from a thread of the bench's own process
would never be heard: the rig (the slave in its network namespace and the Modbus load machine, one simulated device)
runs in a process of its own, as the drive's hardware would. The child ends when the bench's pipe closes (the bench
exited or died), after a grace period in which the drive's own comm-loss reaction completes."""

from __future__ import annotations

import contextlib
import json
import select
import subprocess
import sys
from typing import Iterator

READY_TIMEOUT_S = 180.0          # the child builds the drive model (compiled kernels) before it answers
GRACE_S = 10.0                   # after the bench is gone: the SM watchdog and the drive's stop ramp run out


@contextlib.contextmanager
def serve_out_of_process(bench_cfg: dict, seed: int) -> Iterator[dict]:
    child = subprocess.Popen([sys.executable, "-m", "sim_backend.ethercat.child"], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        child.stdin.write(json.dumps({"bench": bench_cfg, "seed": seed}, default=str) + "\n")
        child.stdin.flush()
        ready, _, _ = select.select([child.stdout], [], [], READY_TIMEOUT_S)
        line = child.stdout.readline() if ready else ""
        if not line.startswith("{"):
            child.kill()
            raise RuntimeError(f"simulated EtherCAT rig did not start: {line.strip()} "
                               f"{child.stderr.read().strip().splitlines()[-1:] if child.poll() is not None else ''}")
        yield json.loads(line)
    finally:
        try:
            child.stdin.close()
        except OSError:
            pass
        try:
            child.wait(timeout=GRACE_S + 5)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait(timeout=5)
