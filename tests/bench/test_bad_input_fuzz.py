"""Bad input through the CLI entry point: whatever is in a scenario or bench config file — wrong types, NaN/inf,
negative times, overlapping segments, unknown keys, huge values, missing files — `drivebench validate` / `run`
exit 2 with one `file: field: reason` line per problem, never a traceback, never a hang (hypothesis deadline)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, currently_in_test_context, event, given, settings
from hypothesis import strategies as st

from bench.faces.cli import cli

REPO = Path(__file__).resolve().parents[2]
TOKENS = ['""', '"x"', "0", "-1", "-0.5", "1e9", "1e308", "1e400", "-1e400", "nan", "inf", "-inf", "true", "[]",
          "[1, 2]", "[2, 1]", '["a", 1]', "{}", "{ a = 1 }", "1979-05-27", "12:30:00", '"../../nope.toml"',
          "99999999999999999999", '"\\u0000"', '"' + "x" * 300 + '"', "3.5"]
FUZZ = settings(max_examples=120, deadline=timedelta(seconds=10),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _absolute(text: str) -> str:
    return text.replace('"config/', f'"{REPO}/config/')


def _value_lines(lines: list[str]) -> list[int]:
    return [i for i, line in enumerate(lines) if "=" in line and not line.lstrip().startswith("#")]


BENCHES = [(p.name, _absolute(p.read_text()).splitlines()) for p in sorted((REPO / "config/benches").glob("*.toml"))]
SCENARIOS = [(p.name, _absolute(p.read_text()).splitlines()) for p in sorted((REPO / "scenarios/examples").glob("*.toml"))]


@st.composite
def mutated(draw, sources):
    name, lines = draw(st.sampled_from(sources))
    lines = list(lines)
    values = _value_lines(lines)
    for i, token in draw(st.lists(st.tuples(st.sampled_from(values), st.sampled_from(TOKENS)), max_size=4)):
        lines[i] = f"{lines[i].split('=', 1)[0].rstrip()} = {token}"
    for i in draw(st.lists(st.sampled_from(values), max_size=2)):
        lines[i] = ""                                            # a missing field
    tables = [i for i, line in enumerate(lines) if line.startswith("[")]
    if tables and draw(st.booleans()):
        at = draw(st.sampled_from(tables))
        lines.insert(at + 1, f"{draw(st.sampled_from(['bogus', 'Overspeed_rpm', 'start']))} = 1")   # unknown key
    return name, lines


def invoke(*args) -> object:
    return CliRunner().invoke(cli, [str(a) for a in args], env={"COLUMNS": "200", "DRIVEBENCH_DEBUG": ""})


def check_outcome(result, path: Path, others: tuple[str, ...] = ()) -> list[str]:
    assert result.exit_code in (0, 2), (result.exit_code, result.output, result.exception)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output and "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    if currently_in_test_context():
        event(f"exit {result.exit_code}")          # --hypothesis-show-statistics: both outcomes occur
    if result.exit_code == 2:
        assert lines, "exit 2 without saying why"
        for line in lines:                                       # one line per problem, naming the file
            assert line.startswith((f"{path}:", *others)), line
            assert "DRIVEBENCH_DEBUG" not in line                # not an internal error
    else:
        assert lines == []
    return lines


@pytest.mark.slow
@FUZZ
@given(case=mutated(BENCHES))
def test_fuzzed_bench_configs(tmp_path, case):
    name, lines = case
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    check_outcome(invoke("validate", path), path)


@pytest.mark.slow
@FUZZ
@given(case=mutated(SCENARIOS), bench=mutated(BENCHES))
def test_fuzzed_scenarios_with_fuzzed_benches_through_validate_and_run(tmp_path, case, bench):
    bench_name, bench_lines = bench
    bench_path = tmp_path / bench_name
    bench_path.write_text("\n".join(bench_lines) + "\n")
    name, lines = case
    lines = [re.sub(r'^bench = ".*"', f'bench = "{bench_path}"', line) for line in lines]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    problems = check_outcome(invoke("validate", path), path, (f"{bench_path}:",))
    if problems:            # run validates before connecting: the same lines, exit 2, nothing started
        result = invoke("run", path, "--out", tmp_path / "runs", "--rerun", "off")
        assert check_outcome(result, path, (f"{bench_path}:",)) == problems
        assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


SEGMENTS = st.lists(st.tuples(st.sampled_from(["hold", "step", "ramp", "reversal"]),
                              st.floats(allow_nan=True, allow_infinity=True, width=32),
                              st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True, width=32)),
                              st.floats(allow_nan=True, allow_infinity=True, width=32)), min_size=1, max_size=4)


def _toml_float(x: float) -> str:
    return {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(x), repr(x))


@pytest.mark.slow
@FUZZ
@given(segments=SEGMENTS, duration=st.floats(allow_nan=True, allow_infinity=True, width=32),
       seed=st.one_of(st.integers(-5, 2**70), st.floats(width=16)))
def test_fuzzed_profiles_times_and_seeds(tmp_path, segments, duration, seed):
    """Negative, unordered and overlapping times, NaN/inf anywhere, huge seeds."""
    body = [f'schema_version = 1\nbench = "{REPO}/config/benches/sim-pmsm.toml"',
            f"duration_s = {_toml_float(duration)}", f"seed = {_toml_float(seed) if isinstance(seed, float) else seed}"]
    for kind, start, end, speed in segments:
        at = "at_s" if kind == "step" else "start_s"
        body.append(f"[[speed]]\nkind = \"{kind}\"\n{at} = {_toml_float(start)}")
        if end is not None:
            body.append(f"end_s = {_toml_float(end)}")
        body.append(f"{'from_speed_mech_rad_s' if kind == 'reversal' else 'speed_mech_rad_s'} = {_toml_float(speed)}")
    body.append("[limits]\noverspeed_mech_rad_s = 1e9\novercurrent_a = 10.0")
    path = tmp_path / "profile.toml"
    path.write_text("\n".join(body) + "\n")
    check_outcome(invoke("validate", path), path)


@pytest.mark.parametrize("content", [None, "", "\x00\xff", "[[[", "schema_version = 1", "a = 1\na = 2"])
def test_missing_empty_and_broken_files(tmp_path, content):
    path = tmp_path / "case.toml"
    if content is not None:
        path.write_bytes(content.encode("latin-1"))
    for args in (("validate", path), ("run", path, "--out", tmp_path / "runs", "--rerun", "off")):
        result = invoke(*args)
        assert result.exit_code == 2
        check_outcome(result, path)


def test_scenario_naming_a_missing_bench_config(tmp_path):
    text = (REPO / "scenarios/examples/pmsm-rs-step.toml").read_text()
    path = tmp_path / "s.toml"
    path.write_text(re.sub(r'^bench = ".*"', 'bench = "no/such/bench.toml"', text, flags=re.M))
    result = invoke("run", path, "--out", tmp_path / "runs")
    (line,) = check_outcome(result, path)
    assert result.exit_code == 2 and "bench" in line and "no/such/bench.toml" in line


@pytest.mark.slow
def test_real_subprocess_one_line_per_problem(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('schema_version = 1\nbench = "config/benches/sim-pmsm.toml"\nduration_s = nan\nbogus = 1\n'
                   "[limits]\novercurrent_a = -inf\n")
    proc = subprocess.run([sys.executable, "-m", "bench", "validate", str(bad)], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "DRIVEBENCH_DEBUG": ""})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) >= 3 and all(line.startswith(f"{bad}: ") for line in lines), lines
    fields = " ".join(line.split(": ")[1] for line in lines)
    assert "duration_s" in fields and "bogus" in fields and "overcurrent_a" in fields
