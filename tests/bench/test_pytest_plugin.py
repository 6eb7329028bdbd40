"""The `drivebench` pytest fixture, run in a child pytest over fake links: record attached to the report."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

CHILD_TEST = """
import bench.run.orchestrator
from tests.fakes import FakeRig, write_case


def test_uses_fixture(drivebench, tmp_path, monkeypatch):
    monkeypatch.setattr(bench.run.orchestrator, "make_links", lambda cfg, base: FakeRig().links())
    result = drivebench.run(write_case(tmp_path), rerun_mode="off")
    assert result.verdict == "pass"
    assert result.run_dir.parent == OUT


def test_failing_run_shows_table(drivebench, tmp_path, monkeypatch):
    monkeypatch.setattr(bench.run.orchestrator, "make_links", lambda cfg, base: FakeRig().links())
    result = drivebench.run(write_case(tmp_path, limit=0.0, duration=0.75), rerun_mode="off")
    assert result.verdict == "pass"
"""


@pytest.mark.slow
def test_fixture_attaches_record_to_report(tmp_path):
    out = tmp_path / "bench-runs"
    test_file = tmp_path / "test_child.py"
    test_file.write_text(f"from pathlib import Path\nOUT = Path({str(out)!r})\n" + textwrap.dedent(CHILD_TEST))
    junit = tmp_path / "junit.xml"
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", str(test_file), "-q", "-p", "no:cacheprovider", "--rootdir", str(tmp_path),
         f"--drivebench-out={out}", f"--junitxml={junit}", "-o", "junit_logging=all"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr   # one pass, one fail
    # the failing test's report carries the criteria table
    assert "drivebench run 1: toy-ramp" in proc.stdout
    assert "speed steady" in proc.stdout and "FAIL" in proc.stdout
    cases = {c.get("name"): c for c in ET.parse(junit).getroot().iter("testcase")}
    props = {p.get("name"): p.get("value") for p in cases["test_uses_fixture"].iter("property")}
    assert props["drivebench_verdict"] == "pass"
    assert Path(props["drivebench_run_dir"]).parent == out
    assert (Path(props["drivebench_run_dir"]) / "record.json").exists()
    criteria = json.loads(props["drivebench_criteria"])
    assert criteria[0]["name"] == "speed steady" and criteria[0]["passed"] is True
