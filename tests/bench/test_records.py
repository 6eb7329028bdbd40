"""Run records: record.json lifecycle, Parquet + JUnit at finish, and recovery of killed runs from the journal."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace
from xml.etree import ElementTree as ET

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.inputs.benchconfig import BenchConfig, BenchSection
from bench.inputs.criteria import CriterionResult
from drivers.contract.errors import InputError
from bench.outputs.record_schema import JOURNAL
from bench.outputs.recorder import RunRecorder
from bench.outputs.run_files import load_run
from drivers.contract.signals import SIGNAL_NAMES

SCENARIO = SimpleNamespace(name="demo/run 1", path=Path("/x/demo.toml"), sha256="ab" * 32, duration_s=1.0)
BENCH = BenchConfig(path="/x/bench.toml", bench=BenchSection(name="sim-test"), drive={})


def block(k: int, n: int = 100) -> dict[str, np.ndarray]:
    t = (np.arange(n) + k * n) * 1e-3
    return {"t_s": t, "speed_est_mech_rad_s": np.sin(t), "i_sx_a": np.cos(t)}


def result(name, value, limit, passed, gap=None):
    return CriterionResult(name, "peak_abs", "i_sx_a", (0.0, 1.0), value, limit, passed, gap, f"detail of {name}",
                           unit="A")


def test_record_lifecycle_parquet_and_junit(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 42, BENCH, flush_interval_s=0.05)
    assert rec.run_dir.parent == tmp_path and rec.run_dir.name.endswith("-demo-run-1")
    started = json.loads((rec.run_dir / "record.json").read_text())
    assert started["verdict"] == "running" and started["complete"] is False
    assert started["scenario"] == {"path": "/x/demo.toml", "sha256": "ab" * 32, "name": "demo/run 1", "duration_s": 1.0}
    assert started["seed"] == 42 and started["bench"] == {"name": "sim-test", "path": "/x/bench.toml"}
    assert set(started["software"]) >= {"version", "git_revision"} and started["started_utc"].endswith("Z")

    rec.set_drive({"vendor_id": 1, "device_name": "sim", "firmware_version": "1.2.3"})
    rec.note("data_source", "trace")
    for k in range(10):
        rec.append(block(k))
    rec.append({"t_s": np.array([1.0]), "vdc_v": np.array([540.0])})      # other columns NaN
    criteria = [result("ok", 0.5, 1.0, True), result("bad", 2.0, 1.0, False),
                result("gap", math.inf, 1.0, False, "eq. 15b offset")]
    returned = rec.finish("fail", criteria, None)
    run_dir = rec.run_dir

    record, cols, complete = load_run(run_dir)
    assert returned == record                      # finish() returns exactly what record.json holds
    assert complete and record["verdict"] == "fail" and record["complete"] is True
    assert record["drive"]["firmware_version"] == "1.2.3" and record["drive"]["identity"]["device_name"] == "sim"
    assert record["data_source"] == "trace" and record["ended_utc"] >= record["started_utc"]
    assert record["abort_reason"] is None
    by_name = {c["name"]: c for c in record["criteria"]}
    assert by_name["bad"] == {"name": "bad", "kind": "peak_abs", "signal": "i_sx_a", "window_s": [0.0, 1.0],
                              "value": 2.0, "limit": 1.0, "passed": False, "known_gap": None,
                              "detail": "detail of bad", "status": "fail", "unit": "A"}
    assert by_name["gap"]["value"] is None and by_name["gap"]["known_gap"] == "eq. 15b offset"   # inf -> null
    assert record["telemetry"]["rows"] == 1001

    assert list(pq.read_schema(run_dir / "telemetry.parquet").names) == ["t_s", *SIGNAL_NAMES]
    assert cols["t_s"].size == 1001 and np.array_equal(cols["t_s"][:1000], np.arange(1000) * 1e-3)
    assert np.array_equal(cols["speed_est_mech_rad_s"][:1000], np.sin(np.arange(1000) * 1e-3))
    assert np.isnan(cols["vdc_v"][:1000]).all() and cols["vdc_v"][1000] == 540.0
    assert np.isnan(cols["flux_est_wb"]).all()
    assert not (run_dir / JOURNAL).exists() and not list(run_dir.glob("*.tmp"))

    suite = ET.parse(run_dir / "junit.xml").getroot().find("testsuite")
    assert suite.get("tests") == "3" and suite.get("failures") == "1" and suite.get("skipped") == "1"
    cases = {c.get("name"): c for c in suite.findall("testcase")}
    failure = cases["bad"].find("failure")
    assert "value 2 A" in failure.get("message") and "limit 1 A" in failure.get("message")
    assert all(c.get("time") == "1" for c in cases.values())           # the window's drive seconds
    assert {p.get("name"): p.get("value") for p in cases["bad"].iter("property")} == {
        "kind": "peak_abs", "signal": "i_sx_a", "unit": "A", "value": "2", "limit": "1", "status": "fail"}
    props = {p.get("name"): p.get("value") for p in suite.find("properties").iter("property")}
    assert props["seed"] == "42" and props["scenario.sha256"] == "ab" * 32 and props["verdict"] == "fail"
    assert props["drive.firmware_version"] == "1.2.3" and "software.git_revision" in props
    assert float(suite.get("time")) >= 0.0
    assert cases["gap"].find("skipped").get("message") == "known gap: eq. 15b offset"
    assert cases["ok"].find("failure") is None and cases["ok"].find("skipped") is None


def test_aborted_run_gets_an_error_testcase(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH)
    rec.append(block(0))
    rec.finish("aborted", [result("ok", 0.5, 1.0, True)], "overcurrent at t=0.1 s")
    record, cols, complete = load_run(rec.run_dir)
    assert complete and record["abort_reason"] == "overcurrent at t=0.1 s" and cols["t_s"].size == 100
    suite = ET.parse(rec.run_dir / "junit.xml").getroot().find("testsuite")
    assert suite.get("errors") == "1"
    assert "overcurrent" in suite.find("testcase[@name='run']/error").get("message")


def test_run_without_telemetry(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH)
    rec.finish("error", [], "cannot connect")
    record, cols, complete = load_run(rec.run_dir)
    assert record["verdict"] == "error" and cols["t_s"].size == 0 and "i_sx_a" in cols


def test_bad_appends_and_verdicts_are_refused(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH)
    with pytest.raises(ValueError, match="t_s"):
        rec.append({"i_sx_a": np.zeros(3)})
    with pytest.raises(ValueError, match="rows"):
        rec.append({"t_s": np.zeros(3), "i_sx_a": np.zeros(2)})
    rec.append({"t_s": np.zeros(3), "extra_probe": np.zeros(3)})
    with pytest.raises(ValueError, match="first block"):
        rec.append({"t_s": np.zeros(3), "another": np.zeros(3)})
    with pytest.raises(ValueError, match="verdict"):
        rec.finish("running", [], None)
    rec.finish("pass", [], None)
    _, cols, _ = load_run(rec.run_dir)
    assert "extra_probe" in cols


def test_journal_is_flushed_by_drive_time_too(tmp_path):
    """A simulator in lockstep runs many times faster than the wall clock: with a wall interval far away, rows are
    still on disk once they span flush_drive_s of drive time (what a SIGKILL can lose is bounded in drive time)."""
    from bench.outputs.run_files import read_journal

    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH, flush_interval_s=3600, flush_drive_s=0.25)

    def on_disk() -> int:
        journal = rec.run_dir / "telemetry.arrows"
        return sum(b.num_rows for b in read_journal(journal)[1]) if journal.exists() else 0

    rec.append(block(0))                      # t = 0 .. 0.099 s: the first block is written at once
    first = on_disk()
    rec.append(block(1))                      # up to 0.199 s: less than 0.25 s since the last flush
    assert on_disk() == first
    rec.append(block(2))
    rec.append(block(3))                      # up to 0.399 s: 0.3 s of drive time since the last flush
    assert on_disk() == 400
    rec.finish("pass", [], None)


def test_read_back_while_running(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH, flush_interval_s=3600)
    assert rec.read_back()["t_s"].size == 0
    for k in range(3):
        rec.append(block(k))
    cols = rec.read_back()
    assert np.array_equal(cols["t_s"], np.arange(300) * 1e-3) and np.isnan(cols["vdc_v"]).all()
    rec.note("trips", [{"t_s": np.float64(0.5), "value": np.inf}])
    rec.append(block(3))
    assert rec.read_back()["t_s"].size == 400
    rec.finish("pass", [], None)
    record, cols, _ = load_run(rec.run_dir)
    assert record["trips"] == [{"t_s": 0.5, "value": None}] and cols["t_s"].size == 400


def test_memory_is_bounded_by_the_flush_interval(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH, flush_interval_s=0.0)
    for k in range(20):
        rec.append(block(k))
        assert rec._pending_sizes == [] and not any(rec._pending.values())   # every block went to the journal
    rec.finish("pass", [], None)


def test_unique_run_dirs_and_missing_run(tmp_path):
    dirs = {RunRecorder(tmp_path, SCENARIO, 1, BENCH).run_dir for _ in range(3)}
    assert len(dirs) == 3
    with pytest.raises(InputError, match="record.json: not found"):
        load_run(tmp_path / "nope")


CHILD = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from types import SimpleNamespace
    import numpy as np
    from bench.inputs.benchconfig import BenchConfig, BenchSection
    from bench.outputs.recorder import RunRecorder
    sc = SimpleNamespace(name="killed", path=Path("/x.toml"), sha256="00", duration_s=100.0)
    bench = BenchConfig(path="/b.toml", bench=BenchSection(name="b"), drive={})
    rec = RunRecorder(Path(sys.argv[1]), sc, 5, bench, flush_interval_s=0.1)
    print(rec.run_dir, flush=True)
    k = 0
    while True:
        t = (np.arange(100) + 100 * k) * 1e-3
        rec.append({"t_s": t, "i_sx_a": t * 2})
        k += 1
        time.sleep(0.5)                     # > flush interval: the journal must hold these rows now
        print(100 * k, flush=True)
""")


@pytest.mark.slow
def test_sigkilled_run_is_recovered_from_the_journal(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                             cwd=Path(__file__).resolve().parents[2])
    try:
        run_dir = Path(child.stdout.readline().strip())
        rows = 0
        while rows < 400:
            line = child.stdout.readline()
            assert line, "child died"
            rows = int(line)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
    record, cols, complete = load_run(run_dir)
    assert complete is False and record["verdict"] == "running"
    n = cols["t_s"].size
    assert rows <= n <= rows + 100, (rows, n)
    assert np.array_equal(cols["t_s"], np.arange(n) * 1e-3)
    assert np.array_equal(cols["i_sx_a"], cols["t_s"] * 2)
    assert not (run_dir / "telemetry.parquet").exists()


def test_truncated_last_batch_is_dropped(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH, flush_interval_s=3600)
    sizes = []
    for k in range(5):
        rec.append(block(k))
        rec.flush()
        sizes.append((rec.run_dir / JOURNAL).stat().st_size)
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copy(rec.run_dir / "record.json", copy / "record.json")
    data = (rec.run_dir / JOURNAL).read_bytes()
    assert len(data) == sizes[-1]
    for cut, expected_rows in [(sizes[-1] - 1, 400), ((sizes[3] + sizes[4]) // 2, 400), (sizes[3], 400),
                               (sizes[0] - 10, 0), (10, 0), (0, 0)]:
        (copy / JOURNAL).write_bytes(data[:cut])
        record, cols, complete = load_run(copy)
        assert not complete and cols["t_s"].size == expected_rows, (cut, cols["t_s"].size)
        assert np.array_equal(cols["t_s"], np.arange(expected_rows) * 1e-3)
    rec.finish("pass", [], None)


def test_a_note_outside_the_record_schema_is_refused(tmp_path):
    rec = RunRecorder(tmp_path, SCENARIO, 1, BENCH)
    rec.note("safe_stop", {"steps": [], "errors": []})
    with pytest.raises(ValueError, match="not a field of RunRecord"):
        rec.note("safe_stpo", {})
    rec.finish("pass", [], None)


def test_the_heap_is_frozen_once_per_process_not_before_every_run():
    """freeze_long_lived freezes at a process's second run only: freezing before every run would keep each earlier
    run's cyclic garbage for good."""
    import gc
    code = ("import gc, json, bench.outputs.memory as r\n"
            "counts, keep = [], []\n"
            "for k in range(4):\n"
            "    r.freeze_long_lived()\n"
            "    keep.append([{}])                        # survivors of each run: a second freeze would take them\n"
            "    junk = [[] for _ in range(1000)]\n"
            "    for a, b in zip(junk, junk[1:]): a.append(b); b.append(a)   # cyclic garbage of this 'run'\n"
            "    del junk, a, b\n"
            "    counts.append(gc.get_freeze_count())\n"
            "print(json.dumps(counts))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[2])
    counts = json.loads(out.stdout)
    assert counts[0] == 0 and counts[1] > 0 and counts[1] == counts[2] == counts[3], (counts, out.stderr)
    assert gc.isenabled()
