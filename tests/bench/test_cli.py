"""drivebench CLI: exit codes 0/1/2, one line per bad-input problem without traceback, --json on stdout."""

from __future__ import annotations

import json
import re
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

import bench.run.orchestrator
from bench.faces.cli import cli
from tests.fakes import FakeRig, write_case

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def fake_rig(monkeypatch):
    """Every link the bench config names is replaced by an in-memory fake rig."""
    rigs: list[FakeRig] = []

    def make_links(cfg, base_dir):
        rigs.append(FakeRig())
        return rigs[-1].links()

    monkeypatch.setattr(bench.run.orchestrator, "make_links", make_links)
    return rigs


def invoke(*args):
    return CliRunner().invoke(cli, list(map(str, args)), catch_exceptions=False, env={"COLUMNS": "200"})


def drivebench(*args, cwd=REPO):
    """The real command in a subprocess: what a user sees, tracebacks included."""
    return subprocess.run([sys.executable, "-m", "bench", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=120, env={**os.environ, "DRIVEBENCH_DEBUG": ""})


@pytest.mark.slow
def test_run_pass_exit_0_and_json_parses(tmp_path, fake_rig):
    scenario = write_case(tmp_path)
    result = invoke("run", scenario, "--out", tmp_path / "runs", "--rerun", "off", "--json")
    assert result.exit_code == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1
    record = json.loads(lines[0])
    assert record["verdict"] == "pass"
    assert record["scenario"]["sha256"] and record["drive"]["firmware_version"] == "toy-1.0"
    # the verdict table goes to stderr with --json (its name cell may wrap on a narrow console: a word a line)
    assert re.search(r"speed(?: |[^\n]*\n[^\n]*)steady", result.stderr), result.stderr


@pytest.mark.slow
def test_run_two_scenarios_json_one_document_each(tmp_path, fake_rig):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = write_case(tmp_path / "a")
    b = write_case(tmp_path / "b", limit=0.0, duration=0.75)
    result = invoke("run", a, b, "--out", tmp_path / "runs", "--rerun", "off", "--json")
    assert result.exit_code == 1
    verdicts = [json.loads(line)["verdict"] for line in result.stdout.strip().splitlines()]
    assert verdicts == ["pass", "fail"]


def test_run_fail_exit_1_with_table(tmp_path, fake_rig):
    scenario = write_case(tmp_path, limit=0.0, duration=0.75)
    result = invoke("run", scenario, "--out", tmp_path / "runs", "--rerun", "off")
    assert result.exit_code == 1
    assert "FAIL" in result.stdout and "speed steady" in result.stdout


@pytest.mark.slow
def test_run_saves_rrd_by_default(tmp_path, fake_rig):
    scenario = write_case(tmp_path)
    result = invoke("run", scenario, "--out", tmp_path / "runs")
    assert result.exit_code == 0
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert (run_dir / "run.rrd").stat().st_size > 0
    assert {"record.json", "telemetry.parquet", "summary.png", "junit.xml"} <= {p.name for p in run_dir.iterdir()}


@pytest.mark.slow
def test_spawn_without_display_falls_back_to_saving(tmp_path, fake_rig, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    scenario = write_case(tmp_path)
    result = invoke("run", scenario, "--out", tmp_path / "runs", "--rerun", "spawn")
    assert result.exit_code == 0
    assert "no display" in result.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert (run_dir / "run.rrd").stat().st_size > 0


def test_show_and_evaluate_a_run(tmp_path, fake_rig):
    scenario = write_case(tmp_path)
    assert invoke("run", scenario, "--out", tmp_path / "runs", "--rerun", "off").exit_code == 0
    (run_dir,) = (tmp_path / "runs").iterdir()
    shown = invoke("show", run_dir)
    assert shown.exit_code == 0 and "speed steady" in shown.stdout
    # re-judge offline against a stricter copy of the scenario
    strict = tmp_path / "strict.toml"
    strict.write_text(scenario.read_text().replace("limit = 1.0", "limit = 0.0"))
    judged = invoke("evaluate", run_dir, "--scenario", strict)
    assert judged.exit_code == 1 and "fail" in judged.stdout
    assert invoke("evaluate", run_dir).exit_code == 0


@pytest.mark.slow
def test_show_incomplete_run(tmp_path, fake_rig):
    scenario = write_case(tmp_path)
    assert invoke("run", scenario, "--out", tmp_path / "runs", "--rerun", "off").exit_code == 0
    (run_dir,) = (tmp_path / "runs").iterdir()
    record = json.loads((run_dir / "record.json").read_text())
    record.update(verdict="running", complete=False)  # as a SIGKILLed run leaves it
    (run_dir / "record.json").write_text(json.dumps(record))
    shown = invoke("show", run_dir)
    assert shown.exit_code == 1
    assert "incomplete" in shown.stdout and "samples recovered" in shown.stdout


@pytest.mark.slow
def test_bad_scenario_one_line_per_problem_exit_2_no_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('schema_version = 1\nbench = "config/benches/sim-pmsm.toml"\nduration_s = -1\n')
    for command in ("run", "validate"):
        proc = drivebench(command, bad)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert lines and all(line.startswith(str(bad)) for line in lines), lines
        assert any("duration_s" in line for line in lines)
        assert proc.stdout == ""


@pytest.mark.slow
@pytest.mark.parametrize("content, needle", [
    (None, "not found"),
    ("this is = = not toml", "not valid TOML"),
])
def test_missing_or_broken_file_exit_2(tmp_path, content, needle):
    path = tmp_path / "x.toml"
    if content is not None:
        path.write_text(content)
    proc = drivebench("run", path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and needle in proc.stderr


@pytest.mark.slow
def test_validate_good_files_exit_0():
    files = [REPO / "config/benches/sim-pmsm.toml"] + sorted((REPO / "scenarios").rglob("*.toml"))[:2]
    proc = drivebench("validate", *files)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count(": ok") == len(files)


@pytest.mark.slow
def test_validate_knows_a_campaign_file_and_checks_its_scenarios(tmp_path):
    proc = drivebench("validate", REPO / "campaigns/inverter-pmsm.toml")
    assert proc.returncode == 0, proc.stderr
    assert "ok (campaign 'inverter-pmsm', 3 scenarios, 3 seeds, 45 runs)" in proc.stdout
    bad_scenario = tmp_path / "bad.toml"
    bad_scenario.write_text((REPO / "scenarios/examples/pmsm-rs-step.toml").read_text().replace(
        "duration_s = ", "duration_s = -", 1).replace('bench = "', f'bench = "{REPO}/', 1))
    camp = tmp_path / "camp.toml"
    camp.write_text(f'schema_version = 1\nname = "c"\nscenarios = ["{bad_scenario}"]\nseeds = [1]\n')
    proc = drivebench("validate", camp)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith(f"{bad_scenario}: duration_s:"), proc.stderr


def test_show_not_a_run_dir_exit_2(tmp_path):
    proc = drivebench("show", tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "record.json" in proc.stderr


@pytest.mark.slow
def test_report_of_a_run_and_of_a_bad_dir(tmp_path, fake_rig):
    scenario = write_case(tmp_path)
    assert invoke("run", scenario, "--out", tmp_path / "runs", "--rerun", "off").exit_code == 0
    (run_dir,) = (tmp_path / "runs").iterdir()
    out = tmp_path / "report" / "validation.md"
    result = invoke("report", run_dir, "--out", out)
    assert result.exit_code == 0, result.stderr
    assert out.exists() and "speed steady" in out.read_text()
    proc = drivebench("report", tmp_path / "nope", "--out", tmp_path / "r.md")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_list_shows_scenarios():
    proc = drivebench("list")
    assert proc.returncode == 0
    assert "scenarios" in proc.stdout


def test_usage_error_exit_2():
    proc = drivebench("run", "--rerun", "bogus", "x.toml")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr


SIGTERM_CHILD = """
import sys
import bench.run.orchestrator
from bench.faces.cli import main
from tests.fakes import FakeRig

rig = FakeRig()
bench.run.orchestrator.make_links = lambda cfg, base: rig.links()
code = main(sys.argv[1:])
print("CALLS", ",".join(rig.names()), file=sys.stderr)
sys.exit(code)
"""


@pytest.mark.slow
def test_sigterm_ends_with_safe_stop_and_an_aborted_record(tmp_path):
    import signal
    import time

    scenario = write_case(tmp_path, duration=60.0)
    out = tmp_path / "runs"
    child = subprocess.Popen(
        [sys.executable, "-c", SIGTERM_CHILD, "run", str(scenario), "--out", str(out), "--rerun", "off", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not list(out.glob("*/telemetry.arrows")):
        time.sleep(0.05)   # the journal appears with the first telemetry block: the drive is running
    child.send_signal(signal.SIGTERM)
    stdout, stderr = child.communicate(timeout=60)
    assert child.returncode == 1, stderr
    assert "Traceback" not in stderr
    record = json.loads(stdout)
    assert record["verdict"] == "aborted" and "SIGTERM" in record["abort_reason"]
    calls = stderr.split("CALLS ", 1)[1].strip().split(",")
    assert [c for c in calls if c in ("load.zero_and_disable", "drive.quick_stop", "drive.disable")] == [
        "load.zero_and_disable", "drive.quick_stop", "drive.disable"]


@pytest.mark.slow
def test_connect_url_after_connect_and_unreachable_viewer_falls_back(tmp_path, fake_rig):
    scenario = write_case(tmp_path)
    result = invoke("run", "--rerun", "connect", "rerun+http://127.0.0.1:9/proxy", scenario, "--out", tmp_path / "runs")
    assert result.exit_code == 0, result.stderr
    assert "no viewer answers at rerun+http://127.0.0.1:9/proxy" in result.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    record = json.loads((run_dir / "record.json").read_text())
    assert record["rerun"] == {"mode": "connect", "url": "rerun+http://127.0.0.1:9/proxy", "sinks": ["file"],
                               "rate_hz": 2000.0}
    assert (run_dir / "run.rrd").stat().st_size > 0


@pytest.mark.slow
def test_show_a_sigkilled_run_recovers_its_samples(tmp_path):
    import signal
    import time

    scenario = write_case(tmp_path, duration=60.0)
    out = tmp_path / "runs"
    child = subprocess.Popen(
        [sys.executable, "-c", SIGTERM_CHILD, "run", str(scenario), "--out", str(out), "--rerun", "off"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    deadline = time.monotonic() + 60
    journal, sizes = [], set()
    while time.monotonic() < deadline and len(sizes) < 3:  # 3 sizes seen: at least one batch written whole
        time.sleep(0.05)
        journal = list(out.glob("*/telemetry.arrows"))
        if journal and journal[0].stat().st_size:
            sizes.add(journal[0].stat().st_size)
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=30)
    proc = drivebench("show", journal[0].parent)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "incomplete run" in proc.stdout
    recovered = int(proc.stdout.split("; ")[1].split()[0])
    assert recovered > 1000
