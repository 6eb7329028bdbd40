"""The child process of sim_backend.ethercat.rig_child: builds the simulated rig (the slave in its network namespace
and the Modbus load machine), answers the bench's pipe with the endpoint overrides, and serves until the pipe closes,
then waits out the drive's comm-loss reaction (GRACE_S)."""

from __future__ import annotations

import json
import sys
import time

from sim_backend.ethercat.rig_child import GRACE_S
from sim_backend.rig import build, spec_for_bench


def main() -> int:
    request = json.loads(sys.stdin.readline())
    spec = spec_for_bench(request["bench"], int(request["seed"]))
    try:
        with build(spec) as rig:
            print(json.dumps(rig.overrides), flush=True)
            sys.stdin.read()                 # until the bench closes the pipe or dies
            deadline = time.monotonic() + GRACE_S
            while time.monotonic() < deadline and rig.device.device.power_enabled:
                time.sleep(0.05)
    except Exception as exc:                 # one line to the bench, which names it
        print(f"error: {exc}", flush=True)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
