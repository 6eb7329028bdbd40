"""Queue order under a starving queue: how soon a run for a free rig starts when STARVING runs are queued ahead of
it for a rig that cannot take them (disabled), against the same with an empty queue (the baseline, same run).

One in-process service (the runner's own loop, real run processes of a one-second scenario on a simulated rig);
start latency is the service's own submitted -> started time, per run, median of --runs.
Last line: `RESULT starving=N start_ms_empty=... start_ms_starving=... ratio=...`.
Usage: python benchmarks/service_queue.py [--starving 150] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.service.auth import Principal  # noqa: E402
from bench.service.core import Service, ServiceSettings  # noqa: E402
from bench.service.db import Run  # noqa: E402
from bench.service.queue import Submission, submit  # noqa: E402

SCENARIO = "service-bench-short.toml"
SCENARIO_TOML = (ROOT / "tests" / "data" / "service" / "short.toml").read_text()
RIGS = f"""
[[rig]]
name = "free"
bench = "{ROOT}/config/benches/sim-pmsm.toml"
tags = ["pmsm"]

[[rig]]
name = "off"
bench = "{ROOT}/config/benches/sim-pmsm.toml"
tags = ["pmsm"]
"""


def start_latencies(service: Service, who: Principal, runs: int) -> list[float]:
    latencies = []
    for _ in range(runs):
        run = submit(service.db, who, Submission(scenario_toml=SCENARIO_TOML, filename=SCENARIO, rig="free"),
                     service.settings.scenario_root, service.settings.data_dir)
        service.runner.wake()
        deadline = time.monotonic() + 120
        while True:
            with service.db.session() as s:
                row = s.get(Run, run.id)
                if row.state not in ("queued", "running"):
                    break
            if time.monotonic() > deadline:
                raise SystemExit(f"run {run.id} did not end within 120 s")
            time.sleep(0.05)
        assert row.state == "pass", (row.state, row.reason)
        latencies.append(row.started_ts - row.submitted_ts)
    return latencies


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starving", type=int, default=150)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="drivebench-queue-") as tmp:
        rigs = Path(tmp) / "rigs.toml"
        rigs.write_text(RIGS)
        service = Service(ServiceSettings(data_dir=Path(tmp) / "data", rigs_path=rigs, lease_ttl_s=3.0,
                                          max_parallel=2))
        service.start()
        who = Principal(1, "bench", "operator")
        try:
            empty = start_latencies(service, who, args.runs)
            service.set_rig_enabled("off", False)
            with service.db.session() as s:
                s.add_all(Run(state="queued", rig="off", scenario=SCENARIO, scenario_file=SCENARIO, owner="other")
                          for _ in range(args.starving))
            starving = start_latencies(service, who, args.runs)
        finally:
            service.stop()
    e_ms, s_ms = statistics.median(empty) * 1000, statistics.median(starving) * 1000
    print(f"empty queue: submitted -> started {', '.join(f'{v * 1000:.1f}' for v in empty)} ms")
    print(f"{args.starving} runs queued ahead for a disabled rig: submitted -> started "
          f"{', '.join(f'{v * 1000:.1f}' for v in starving)} ms")
    print(f"RESULT starving={args.starving} start_ms_empty={e_ms:.1f} start_ms_starving={s_ms:.1f} "
          f"ratio={s_ms / e_ms:.2f}")


if __name__ == "__main__":
    main()
