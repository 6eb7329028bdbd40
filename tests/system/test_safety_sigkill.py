"""A real `drivebench run` (in-process simulator: CANopen on a virtual bus + Modbus TCP) SIGKILLed mid-run:
`drivebench show` recovers every sample flushed before the kill, with a continuous drive clock, marked incomplete."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.outputs.run_files import load_run

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from benchmarks.fault_campaign import write_bench, write_scenario  # noqa: E402


def test_sigkilled_simulator_run_is_recovered_up_to_the_last_flush(tmp_path):
    bench = write_bench(tmp_path, "canopen")
    bench.write_text(bench.read_text().replace("wire_faults = true", "wire_faults = false"))
    scenario = write_scenario(tmp_path, bench, "killed", [], duration_s=60.0)
    out = tmp_path / "runs"
    child = subprocess.Popen([sys.executable, "-m", "bench", "run", str(scenario), "--out", str(out), "--rerun", "off"],
                             cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "DRIVEBENCH_DEBUG": ""})
    try:
        deadline = time.monotonic() + 120
        before = 0
        while before < 3 * 5000:            # at least three 0.5 s trace uploads (10 kHz) journaled
            assert child.poll() is None, child.communicate()[1]
            assert time.monotonic() < deadline, "the run never journaled three uploads"
            time.sleep(0.05)
            journals = list(out.glob("*/telemetry.arrows"))
            if journals:
                before = len(load_run(journals[0].parent)[1]["t_s"])    # what a reader sees right now
        run_dir = journals[0].parent
        child.send_signal(signal.SIGKILL)
        killed = time.time()
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
    last_flush_age = killed - (run_dir / "telemetry.arrows").stat().st_mtime
    proc = subprocess.run([sys.executable, "-m", "bench", "show", str(run_dir)], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "DRIVEBENCH_DEBUG": ""})
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "incomplete run" in proc.stdout
    record, columns, complete = load_run(run_dir)
    assert not complete and record["verdict"] == "running"
    t = columns["t_s"]
    assert len(t) >= before                                        # nothing flushed before the kill is lost
    assert np.allclose(np.diff(t), 1e-4)                           # drive clock continuous, 10 kHz trace
    assert abs(t[0] - 1e-4) < 1e-9
    # the journal gets a batch per trace upload (0.5 s of drive time) and is flushed within 0.5 s of wall time;
    # lockstep runs near real time here, so the last write is recent (generous for a loaded 2-core machine)
    assert last_flush_age < 3.0, last_flush_age
