"""Campaigns: files validated like scenarios, points run through the same bench path as `drivebench run` on a local
pool of reused workers, results resumable, pass rates judged with the Wilson interval."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from bench.faces.campaign import load_campaign, points, wilson_interval
from bench.faces.campaign_run import pass_rate_grid, run_campaign, write_results
from bench.faces.cli import cli
from drivers.contract.errors import InputError
from bench.run.orchestrator import run_scenario
from bench.inputs.scenario import Injection, load_scenario

REPO = Path(__file__).resolve().parents[2]
RS_STEP = "scenarios/examples/pmsm-rs-step.toml"
CRANE = "scenarios/examples/pmsm-crane.toml"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "campaign.toml"
    path.write_text(text)
    return path


def test_wilson_interval_known_values():
    low, high = wilson_interval(20, 20, 0.95)
    assert abs(low - 0.8389) < 1e-4 and high == 1.0
    low, high = wilson_interval(0, 10, 0.95)
    assert abs(low) < 1e-12 and abs(high - 0.2775) < 1e-4
    low, high = wilson_interval(5, 10, 0.95)
    assert abs(low - 0.2366) < 1e-4 and abs(high - 0.7634) < 1e-4


@pytest.mark.parametrize("body, field, words", [
    ('scenarios = ["nope.toml"]\nseeds = [1]', "scenarios[0]", "file not found"),
    (f'scenarios = ["{RS_STEP}"]\nseeds = [1, 1]', "seeds", "listed twice"),
    (f'scenarios = ["{RS_STEP}"]\nseeds = {{ from = -1, count = 3 }}', "seeds.from", ""),
    (f'scenarios = ["{RS_STEP}"]\nseeds = [1]\n[[axis]]\nparameter = "plant_bogus"\nvalues = [1.0]',
     "axis[0].parameter", "unknown parameter"),
    (f'scenarios = ["{RS_STEP}"]\nseeds = [1]\n[[axis]]\nparameter = "plant_rs"\nlow = 0.8\nhigh = 1.2',
     "sampling.points", "missing"),
    (f'scenarios = ["{RS_STEP}"]\nseeds = [1]\n[acceptance]\nmin_pass_rate = 1.5', "acceptance.min_pass_rate", ""),
])
def test_bad_campaign_files_are_one_line_each(tmp_path, body, field, words):
    path = write(tmp_path, "schema_version = 1\n" + body + "\n")
    with pytest.raises(InputError) as exc:
        load_campaign(path)
    assert any(line.startswith(f"{path}: {field}: ") and words in line for line in exc.value.problems), \
        exc.value.problems
    result = CliRunner().invoke(cli, ["campaign", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2 and "Traceback" not in result.output


def test_axes_grid_and_latin_hypercube_points(tmp_path):
    grid = load_campaign(write(tmp_path, f'schema_version = 1\nscenarios = ["{RS_STEP}"]\nseeds = [1, 2]\n'
                                         '[[axis]]\nparameter = "plant_rs"\nvalues = [0.9, 1.1]\n'))
    pts = points(grid, tmp_path / "out")
    assert len(pts) == 4 and {p.axes for p in pts} == {(("plant_rs", 0.9),), (("plant_rs", 1.1),)}
    # the axis is a typed override of the prepared scenario (no edited copy of the file): the same injections, in
    # the same order, as the file with `[[injection]] at_s = 0.0` appended gives
    assert pts[0].prepared.overrides == (("plant_rs", 0.9),) and pts[0].scenario == REPO / RS_STEP
    assert not (tmp_path / "out").exists()
    text = (REPO / RS_STEP).read_text().replace('bench = "', f'bench = "{REPO.as_posix()}/')
    appended = tmp_path / "appended.toml"
    appended.write_text(text + '\n[[injection]]\nat_s = 0.0\nname = "plant_rs"\nvalue = 0.9\n')
    assert pts[0].prepared.scenario.injections == load_scenario(appended).injections
    assert pts[0].prepared.scenario.injections[0] == Injection(0.0, "plant_rs", 0.9)
    assert [p.prepared.seed for p in pts] == [1, 2, 1, 2]
    lhs = load_campaign(write(tmp_path, f'schema_version = 1\nscenarios = ["{RS_STEP}"]\nseeds = [1]\n'
                                        '[[axis]]\nparameter = "plant_rs"\nlow = 0.8\nhigh = 1.2\n'
                                        '[[axis]]\nparameter = "plant_ls"\nlow = 0.9\nhigh = 1.1\n'
                                        '[sampling]\npoints = 5\nseed = 3\n'))
    a = [p.axes for p in points(lhs, tmp_path / "a")]
    b = [p.axes for p in points(lhs, tmp_path / "b")]
    assert a == b and len(a) == 5                                # the same draw every time (seeded)
    rs = sorted(v[0][1] for v in a)
    assert all(0.8 <= x <= 1.2 for x in rs)
    assert sorted(int((x - 0.8) / 0.4 * 5) for x in rs) == [0, 1, 2, 3, 4]   # one sample per stratum


def test_the_heatmap_counts_runs_per_cell_of_the_first_two_axes(tmp_path):
    grid_file = write(tmp_path, f'schema_version = 1\nscenarios = ["{RS_STEP}"]\nseeds = [1, 2]\n'
                                '[[axis]]\nparameter = "plant_rs"\nvalues = [0.9, 1.1]\n'
                                '[[axis]]\nparameter = "plant_ls"\nvalues = [0.8, 1.0, 1.2]\n')
    camp = load_campaign(grid_file)
    rows = []
    for p in points(camp, tmp_path / "out"):
        axes = dict(p.axes)
        failing = axes["plant_rs"] == 1.1 and axes["plant_ls"] == 1.2 or (axes["plant_ls"] == 0.8 and p.seed == 2)
        rows.append({"point_id": p.point_id, "axes": json.dumps([list(a) for a in p.axes]), "seed": p.seed,
                     "scenario": str(p.source), "verdict": "fail" if failing else "pass", "criteria": []})
    grid = pass_rate_grid(camp, rows)
    assert (grid.x_name, grid.y_name, grid.x_labels, grid.y_labels) == ("plant_rs", "plant_ls", ("0.9", "1.1"),
                                                                          ("0.8", "1", "1.2"))
    assert grid.runs.tolist() == [[2, 2], [2, 2], [2, 2]]
    assert grid.passes.tolist() == [[1, 1], [2, 2], [2, 0]]
    write_results(camp, tmp_path / "out", rows)
    assert (tmp_path / "out" / "heatmap.png").stat().st_size > 1000
    assert "heatmap.png" in (tmp_path / "out" / "report.md").read_text()
    sampled = load_campaign(write(tmp_path, f'schema_version = 1\nscenarios = ["{RS_STEP}"]\nseeds = [1]\n'
                                            '[[axis]]\nparameter = "plant_rs"\nlow = 0.8\nhigh = 1.2\n'
                                            '[[axis]]\nparameter = "plant_ls"\nlow = 0.9\nhigh = 1.1\n'
                                            '[sampling]\npoints = 10\nseed = 3\n'))
    rows = [{"axes": json.dumps([list(a) for a in p.axes]), "verdict": "pass"} for p in points(sampled, tmp_path / "s")]
    grid = pass_rate_grid(sampled, rows)
    assert grid.runs.shape == (5, 5) and grid.runs.sum() == 10
    assert grid.runs.sum(axis=0).tolist() == [2, 2, 2, 2, 2]       # Latin hypercube: two samples per bin of each axis
    no_axes = write(tmp_path, f'schema_version = 1\nscenarios = ["{RS_STEP}"]\nseeds = [1]\n')
    assert pass_rate_grid(load_campaign(no_axes), []) is None


@pytest.mark.slow
def test_a_campaign_runs_every_point_like_drivebench_run_and_resumes(tmp_path):
    path = write(tmp_path, f'schema_version = 1\nname = "ci"\nscenarios = ["{RS_STEP}", "{CRANE}"]\n'
                           'seeds = [1, 2, 3]\n[acceptance]\nrule = "every_run"\n')
    camp = load_campaign(path)
    out = tmp_path / "out"
    dry = CliRunner().invoke(cli, ["campaign", str(path), "--out", str(out), "--dry-run"])
    assert dry.exit_code == 0 and dry.output.count(" to run\n") == 6, dry.output
    assert "6 points, 6 to run, 0 done" in dry.output and not (out / "results.jsonl").exists()
    rows = run_campaign(camp, out, workers=2)
    summary = write_results(camp, out, rows)
    table = pq.read_table(out / "results.parquet")
    assert table.num_rows == 6 and sorted(table.column("seed").to_pylist()) == [1, 1, 2, 2, 3, 3]
    assert len({r["worker_pid"] for r in rows}) <= 2                      # two reused workers for six points
    # the same point through `drivebench run`'s path gives the same criterion values, bit for bit
    direct = run_scenario(REPO / RS_STEP, out_root=tmp_path / "direct", seed=2, rerun_mode="off")
    row = next(r for r in rows if r["scenario"].endswith("pmsm-rs-step.toml") and r["seed"] == 2)
    assert [c["value"] for c in row["criteria"]] == [c["value"] for c in direct.record["criteria"]]
    assert row["verdict"] == direct.verdict
    assert (out / "report.md").read_text().startswith("# Campaign ci") and (out / "pass_rates.png").stat().st_size
    assert summary["runs"] == 6
    # a second call finds every point done: nothing runs again
    lines = (out / "results.jsonl").read_text().splitlines()
    run_dirs = sorted((out / "runs").iterdir())
    rows_again = run_campaign(camp, out, workers=2)
    assert len(rows_again) == 6 and (out / "results.jsonl").read_text().splitlines() == lines
    assert sorted((out / "runs").iterdir()) == run_dirs
    assert json.loads(lines[0])["point_id"] in {r["point_id"] for r in rows_again}
    dry = CliRunner().invoke(cli, ["campaign", str(path), "--out", str(out), "--dry-run"])
    assert "6 points, 0 to run, 6 done" in dry.output and dry.output.count("a resume skips it") == 6
    resumed = CliRunner().invoke(cli, ["campaign", str(path), "--out", str(out)])
    assert resumed.exit_code == 0 and "6 runs (0 run now, 6 resumed from" in resumed.output, resumed.output


def _pool_workers() -> list[int]:
    """This process's children that are multiprocessing spawn workers."""
    me, out = os.getpid(), []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == me and b"spawn_main" in cmdline:
            out.append(int(stat.parent.name))
    return out


@pytest.mark.slow
def test_a_killed_worker_loses_only_its_points_and_they_run_again(tmp_path):
    camp = load_campaign(write(tmp_path, f'schema_version = 1\nname = "kill"\nscenarios = ["{RS_STEP}"]\n'
                                         'seeds = [1, 2, 3, 4, 5, 6]\n[acceptance]\nrule = "every_run"\n'))
    out = tmp_path / "out"
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(rows=run_campaign(camp, out, workers=2)), daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not (out / "results.jsonl").exists() or not (out / "results.jsonl").read_text().strip():
        assert time.monotonic() < deadline and thread.is_alive(), "no point finished"
        time.sleep(0.05)
    done_before = {json.loads(line)["point_id"] for line in (out / "results.jsonl").read_text().splitlines()}
    workers = _pool_workers()
    assert len(workers) == 2, workers
    killed_at = time.time()
    os.kill(workers[0], signal.SIGKILL)                      # mid-campaign: it holds a point (two queued per worker)
    thread.join(180)
    assert not thread.is_alive()
    rows = result["rows"]
    assert sorted(r["seed"] for r in rows) == [1, 2, 3, 4, 5, 6]          # no point lost
    assert [r["verdict"] for r in rows] == ["pass"] * 6, [(r["seed"], r["verdict"], r["error"]) for r in rows]
    # the killed worker may have finished a point between the snapshot and the kill; nothing it did ends after it
    assert all(r["ended_unix"] < killed_at for r in rows if r["worker_pid"] == workers[0])
    assert any(r["ended_unix"] > killed_at for r in rows)   # the points it held ran again elsewhere
    assert done_before <= {r["point_id"] for r in rows}
    lines = (out / "results.jsonl").read_text().splitlines()
    assert len(lines) == 6                                    # what had finished was not run again
