"""Each class of hostile input the adversarial pass found escaping the one-line rule (issue 11): devices and FIFOs
as files, TOML nested 1,000 deep, absurd durations and seeds, run-directory roots that cannot hold runs, records that
are not records, a [services] starter that is not registered, a simulator endpoint off the loopback. Every one:
exit 2, every stderr line `file-or-option: field: reason`, no traceback, no run directory left behind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from bench.faces.cli import cli

REPO = Path(__file__).resolve().parents[2]
FIG08 = REPO / "scenarios/pmsm/fig08-20rads-rs-step.toml"


def invoke(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args], env={"COLUMNS": "200", "DRIVEBENCH_DEBUG": ""})
    return result.exit_code, result.stderr if hasattr(result, "stderr") else result.output


def assert_one_line_errors(code: int, err: str, *needles: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err and "DRIVEBENCH_DEBUG" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and all(": " in line for line in lines), err
    for needle in needles:
        assert needle in err, err


def test_devices_and_fifos_are_not_read(tmp_path):
    fifo = tmp_path / "scenario.toml"
    os.mkfifo(fifo)
    assert_one_line_errors(*invoke("validate", fifo), "not a regular file")
    assert_one_line_errors(*invoke("validate", "/dev/zero"), "not a regular file")


def test_toml_nested_1000_deep_and_oversize_files(tmp_path):
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 1000 + "]" * 1000 + "\n")
    assert_one_line_errors(*invoke("validate", deep), "nested deeper")
    big = tmp_path / "big.toml"
    big.write_text("# x\n" * 300_000)
    assert_one_line_errors(*invoke("validate", big), "larger than")


def test_absurd_duration_and_seed_are_refused(tmp_path):
    scenario = tmp_path / "long.toml"
    scenario.write_text(FIG08.read_text().replace("duration_s = 5.0", "duration_s = 1e308")
                        .replace('bench = "', f'bench = "{REPO}/'.replace("//", "/"), 1))
    assert_one_line_errors(*invoke("validate", scenario), "duration_s: 1e+308 s is longer")
    for seed in ("-1", str(2**70)):
        assert_one_line_errors(*invoke("run", FIG08, "--seed", seed, "--out", tmp_path / "runs", "--rerun", "off"),
                               "--seed: must be an integer")
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_out_roots_that_cannot_hold_runs(tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
    for out in (a_file, a_file / "under", tmp_path / "loop1"):
        assert_one_line_errors(*invoke("run", FIG08, "--out", out, "--rerun", "off"), "--out: cannot hold")


def test_key_with_an_escaped_newline_stays_on_one_line(tmp_path):
    scenario = tmp_path / "esc.toml"
    scenario.write_text('"x\\ny" = 1\n' + FIG08.read_text())
    code, err = invoke("validate", scenario)
    assert_one_line_errors(code, err, "x\\ny: unknown key")
    assert all(line.startswith(str(scenario)) for line in err.splitlines() if line.strip())


def test_records_that_are_not_records(tmp_path):
    listed = tmp_path / "r1"
    listed.mkdir()
    (listed / "record.json").write_text("[1, 2]")
    for command in ("show", "evaluate"):
        assert_one_line_errors(*invoke(command, listed), "not a run record")
    broken = tmp_path / "r2"
    broken.mkdir()
    (broken / "record.json").write_text('{"verdict": "pass", "complete": true, "criteria": []}')
    (broken / "telemetry.parquet").write_bytes(b"garbage")
    assert_one_line_errors(*invoke("show", broken), "not a readable Parquet file")


def test_services_start_must_be_a_registered_starter(tmp_path):
    bench = tmp_path / "bench.toml"
    bench.write_text('[bench]\nname = "x"\n[services]\nstart = "os:system"\n[drive]\ntransport = "serial"\n'
                     'port = "x"\n')
    assert_one_line_errors(*invoke("validate", bench), "services.start: 'os:system' is not a registered")


@pytest.mark.slow
def test_simulator_endpoints_only_on_the_loopback(tmp_path):
    text = (REPO / "config/benches/sim-pmsm.toml").read_text().replace('"config/', f'"{REPO}/config/')
    config = tmp_path / "serve.toml"
    config.write_text(text.replace("127.0.0.1:29536", "0.0.0.0:29536"))
    proc = subprocess.run([sys.executable, "-m", "bench", "sim", "serve", "--config", str(config)],
                          capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode == 2 and "0.0.0.0 is not a loopback address" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_a_disk_that_fills_up_mid_run_is_one_line_after_the_safe_stop(tmp_path):
    """Files stop growing at 150 kB (RLIMIT_FSIZE, the way a full disk looks to the writer): the run goes on to its
    safe stop, the journal keeps what was written before, and the bench says so in one line (exit 2)."""
    code = (
        "import resource, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (150_000, resource.RLIM_INFINITY))\n"
        "from bench.faces.cli import main\n"
        f"sys.exit(main(['run', {str(FIG08)!r}, '--out', {str(tmp_path / 'runs')!r}, '--rerun', 'off']))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO,
                          env={**os.environ, "DRIVEBENCH_DEBUG": ""})
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert "--out: cannot write the run record" in lines[0] and "safe stop was done" in lines[0]
    run_dir = next((tmp_path / "runs").iterdir())
    from bench.outputs.run_files import load_run

    record, columns, complete = load_run(run_dir)
    assert not complete and 0 < len(columns["t_s"])           # what reached the disk is recoverable
    assert record["safe_stop"]["steps"] and not record["safe_stop"]["errors"]
