"""A run prepared once: one CLI run, one validate and one campaign read each input file once, and every face (the
run, the progress display, validate, campaign points, an upload) works on the same prepared scenario."""

from __future__ import annotations

import collections
import json
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

import drivers.contract.toml_file
from bench.faces.campaign import load_campaign, points
from bench.faces.campaign_run import _as_dict, run_point
from bench.faces.cli import cli
from drivers.contract.errors import InputError
from bench.inputs.prepared import PreparedRun, prepare_run

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "scenarios/pmsm/fig10-startup-position-error.toml"      # 2 s of drive time
BENCH = REPO / "config/benches/sim-pmsm.toml"
LONG = REPO / "scenarios/pmsm/fig08-20rads-rs-step.toml"                  # long enough for the progress bar


@pytest.fixture
def parses(monkeypatch) -> collections.Counter:
    """How often each file is read and parsed as TOML (the one TOML reader, wherever it was imported), by resolved
    path; TOML parsed from memory counts under "<text>"."""
    counts: collections.Counter = collections.Counter()
    read, parse = drivers.contract.toml_file.read_toml_file, drivers.contract.toml_file.parse_toml_bytes

    def counted_read(path, *args, **kwargs):
        counts[Path(path).resolve()] += 1
        return read(path, *args, **kwargs)

    def counted_parse(data, *args, **kwargs):
        counts["<text>"] += 1
        return parse(data, *args, **kwargs)

    for module in list(sys.modules.values()):
        if getattr(module, "read_toml_file", None) is read:
            monkeypatch.setattr(module, "read_toml_file", counted_read)
        if getattr(module, "parse_toml_bytes", None) is parse and module is not drivers.contract.toml_file:
            monkeypatch.setattr(module, "parse_toml_bytes", counted_parse)
    return counts


@pytest.mark.slow
def test_one_cli_run_reads_the_scenario_and_its_bench_config_once(tmp_path, parses):
    result = CliRunner().invoke(cli, ["run", str(SCENARIO), "--rerun", "off", "--out", str(tmp_path), "--json"])
    assert result.exit_code in (0, 1), result.output
    record = json.loads(result.stdout.splitlines()[0])
    assert record["scenario"]["path"] == str(SCENARIO) and record["verdict"] in ("pass", "fail")
    assert parses[SCENARIO] == 1 and parses[BENCH] == 1, dict(parses)
    assert parses["<text>"] == 0


def test_validate_reads_the_scenario_and_its_bench_config_once(parses):
    result = CliRunner().invoke(cli, ["validate", str(SCENARIO)])
    assert result.exit_code == 0 and ": ok (scenario" in result.output, result.output
    assert parses[SCENARIO] == 1 and parses[BENCH] == 1, dict(parses)


@pytest.mark.slow
def test_a_campaign_reads_its_file_and_each_scenario_once_for_all_its_points(tmp_path, parses):
    path = tmp_path / "campaign.toml"
    path.write_text(f'schema_version = 1\nname = "counted"\nscenarios = ["{SCENARIO.relative_to(REPO)}"]\n'
                    'seeds = [1, 2]\n[[axis]]\nparameter = "plant_rs"\nvalues = [0.9, 1.1]\n')
    camp = load_campaign(path)
    todo = points(camp)
    assert len(todo) == 4 and all(isinstance(p.prepared, PreparedRun) for p in todo)
    assert {(p.prepared.overrides, p.prepared.seed) for p in todo} == {
        ((("plant_rs", v),), s) for v in (0.9, 1.1) for s in (1, 2)}
    for point in todo[:2]:                          # what a worker does with a point: no file read again
        row = run_point(_as_dict(point), str(tmp_path / "runs"))
        assert row["verdict"] in ("pass", "fail") and row["criteria"], row
        record = json.loads((Path(row["run_dir"]) / "record.json").read_text())
        assert record["overrides"] == {"injections_at_0_s": [list(a) for a in point.axes]}
        assert record["seed"] == point.seed and record["scenario"]["path"] == str(SCENARIO)
    assert parses[path.resolve()] == 1 and parses[SCENARIO] == 1 and parses[BENCH] == 1, dict(parses)


def test_the_progress_display_shows_the_scenario_the_run_runs(tmp_path, monkeypatch):
    """--bench replaces the scenario's own bench config: the progress bar used to read the scenario again without
    it, so a scenario whose own bench is missing validated and then failed to run."""
    import bench.faces.cli

    copy = tmp_path / "elsewhere.toml"
    copy.write_text(SCENARIO.read_text().replace('bench = "config/benches/sim-pmsm.toml"',
                                                 'bench = "config/benches/not-here.toml"'))
    assert "not-here" in copy.read_text()
    totals: list[float] = []
    monkeypatch.setattr(bench.faces.cli, "PROGRESS_MIN_DURATION_S", 0.0)
    monkeypatch.setattr(type(bench.faces.cli.err_console), "is_terminal", property(lambda self: True))
    real = bench.faces.cli._progress.__enter__

    def enter(self):
        update = real(self)
        totals.append(self.bar.tasks[0].total)
        return update
    monkeypatch.setattr(bench.faces.cli._progress, "__enter__", enter)
    result = CliRunner().invoke(cli, ["run", str(copy), "--bench", str(BENCH), "--rerun", "off",
                                      "--out", str(tmp_path / "runs"), "--json"])
    assert result.exit_code in (0, 1), result.output
    record = json.loads(result.stdout.splitlines()[0])
    assert record["bench"]["path"] == str(BENCH) and totals == [2.0]


def test_an_upload_is_prepared_from_its_text_like_the_file(tmp_path):
    text = LONG.read_text()
    from_file = prepare_run(LONG, BENCH, seed=3)
    from_text = prepare_run(LONG, BENCH, text=text, seed=3)
    assert from_text == from_file and from_text.scenario.sha256 == from_file.scenario.sha256
    # named by a path of its own (the service's upload folder): its bench path is resolved from the repository
    named = tmp_path / "upload.toml"
    assert prepare_run(named, text=text).bench.path == str(BENCH)
    with pytest.raises(InputError) as bad:
        prepare_run(named, text=text.replace("duration_s = ", "duration_s = -"))
    assert bad.value.problems[0].startswith(f"{named}: duration_s: ")
    with pytest.raises(InputError) as bad:
        prepare_run(named, text=b"\xff\xfe")
    assert bad.value.problems == [f"{named}: (file): not valid TOML: not UTF-8 text"]


def test_overrides_are_checked_like_the_files_own_injections():
    prepared = prepare_run(LONG)
    assert prepared.with_injections(()) is prepared
    with pytest.raises(InputError) as bad:
        prepared.with_injections((("plant_bogus", 1.0),))
    assert bad.value.problems[0].startswith(f"{LONG}: override[0].name: unknown hook 'plant_bogus'")
    instruments = prepare_run(REPO / "scenarios/pmsm-rig/fig08-20rads-fw-rs-step.toml")
    with pytest.raises(InputError) as bad:
        instruments.with_injections((("plant_rs", 1.1),))
    assert "plant_injections = false" in bad.value.problems[0]
    with pytest.raises(InputError, match="--seed: must be an integer"):
        prepared.with_seed(-1)
    assert prepared.with_seed(5).seed == 5 and prepared.seed == prepare_run(LONG).seed
