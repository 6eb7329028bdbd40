"""`drivebench export`: the run's telemetry read back by the tools a lab opens it with — asammdf for MDF4 (master
channel t_s on the drive clock, units, the record attached) and a CSV reader — equal to telemetry.parquet."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.csv as pacsv
import pytest

from bench.inputs.benchconfig import BenchConfig, BenchSection
from bench.inputs.criteria import evaluate, verdict
from bench.outputs.recorder import RunRecorder
from bench.outputs.run_files import load_run
from bench.inputs.scenario import load_scenario
from drivers.contract.signals import SIGNAL_NAMES

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    scenario = load_scenario(REPO / "scenarios/examples/pmsm-rs-step.toml")
    rec = RunRecorder(tmp_path / "runs", scenario, 5, BenchConfig(path="x", bench=BenchSection(name="sim-x"), drive={}))
    t = (np.arange(1, 3001) * 1e-3).astype(np.float64)
    cols = {name: np.full_like(t, np.nan) for name in SIGNAL_NAMES}   # not measured unless set below
    cols.update(t_s=t, speed_est_mech_rad_s=np.sin(t), speed_true_mech_rad_s=np.cos(t), torque_load_nm=t * 2.0)
    cols["i_sy_a"] = np.where(t > 1.0, 3.0, np.nan)                   # measured, with missing samples early on
    rec.append(cols)
    results = evaluate(scenario.criteria, t, cols)
    rec.finish(verdict(results, aborted=False), results, None)
    return rec.run_dir


def drivebench(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bench", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.slow
def test_mf4_reads_back_in_asammdf_with_the_drive_clock_as_master(run_dir: Path, tmp_path: Path):
    from asammdf import MDF

    out = tmp_path / "run.mf4"
    proc = drivebench("export", run_dir, "--format", "mf4", "--out", out)
    assert proc.returncode == 0 and proc.stdout.strip() == f"wrote {out}", proc.stderr
    record, cols, _ = load_run(run_dir)
    mdf = MDF(out)
    names = [c.name for c in mdf.groups[0].channels]
    assert names == ["t_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s", "i_sy_a", "torque_load_nm"]
    assert mdf.groups[0].channels[0].unit == "s"
    speed = mdf.get("speed_est_mech_rad_s")
    assert speed.unit == "rad/s" and np.array_equal(speed.timestamps, cols["t_s"])
    assert np.array_equal(speed.samples, cols["speed_est_mech_rad_s"])
    assert mdf.get("torque_load_nm").unit == "N·m"
    i_sy = mdf.get("i_sy_a").samples
    assert np.array_equal(np.isnan(i_sy), np.isnan(cols["i_sy_a"])) and (i_sy[1000:] == 3.0).all()
    assert "not measured on this bench" in mdf.header.comment and "flux_true_wb" in mdf.header.comment
    data, name = mdf.extract_attachment(0)[:2]
    assert Path(name).name == "record.json" and json.loads(bytes(data)) == record
    mdf.close()


@pytest.mark.slow
def test_csv_has_the_same_rows_and_empty_cells_where_samples_are_missing(run_dir: Path):
    proc = drivebench("export", run_dir, "--format", "csv")
    assert proc.returncode == 0, proc.stderr
    table = pacsv.read_csv(run_dir / "telemetry.csv")
    _, cols, _ = load_run(run_dir)
    assert table.column_names == ["t_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s", "i_sy_a", "torque_load_nm"]
    assert np.array_equal(table.column("t_s").to_numpy(), cols["t_s"])
    assert np.array_equal(table.column("speed_true_mech_rad_s").to_numpy(), cols["speed_true_mech_rad_s"])
    assert table.column("i_sy_a").null_count == int(np.isnan(cols["i_sy_a"]).sum()) == 1000


@pytest.mark.slow
def test_an_out_file_in_a_missing_directory_is_one_line(run_dir: Path):
    proc = drivebench("export", run_dir, "--format", "mf4", "--out", "/nonexistent-dir/x.mf4")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == "/nonexistent-dir/x.mf4: --out: the directory /nonexistent-dir does not exist"


def test_not_a_run_directory(tmp_path: Path):
    proc = drivebench("export", tmp_path, "--format", "csv")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "record.json" in proc.stderr
