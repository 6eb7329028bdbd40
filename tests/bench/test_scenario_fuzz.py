"""Whatever a user types into a scenario, load_scenario returns a Scenario or raises InputError: no traceback."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.contract.errors import InputError
from bench.inputs.scenario import load_scenario
from tests.scenario_fixtures import REPO, write_bench

EXAMPLES = []
for example in sorted((REPO / "scenarios" / "examples").glob("*.toml")):
    lines = example.read_text().replace('"config/benches/sim-pmsm.toml"', '"bench.toml"').replace(
        '"config/benches/sim-spim.toml"', '"bench.toml"').splitlines()
    EXAMPLES.append((lines, [i for i, line in enumerate(lines) if "=" in line and not line.lstrip().startswith("#")]))
TOKENS = ['""', '"x"', "0", "-1", "1e9", "-0.0", "nan", "inf", "-inf", "true", "[]", "[1]", "[1, 2]", "[2, 1]",
          "[-1, 3]", '["a", 1]', "{}", '{ a = 1 }', "1979-05-27", '"speed_est_mech_rad_s"', '"plant_rs"', "3.5"]


@st.composite
def mutations(draw):
    lines, value_lines = draw(st.sampled_from(EXAMPLES))
    lines = list(lines)
    for i, token in draw(st.lists(st.tuples(st.sampled_from(value_lines), st.sampled_from(TOKENS)), max_size=4)):
        lines[i] = f"{lines[i].split('=', 1)[0]}= {token}"
    for i in draw(st.lists(st.sampled_from(value_lines), max_size=2)):
        lines[i] = ""
    return lines


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lines=mutations())
def test_mutated_scenarios_never_crash(tmp_path: Path, lines):
    write_bench(tmp_path, kind=None)
    path = tmp_path / "fuzz.toml"
    path.write_text("\n".join(lines) + "\n")
    try:
        load_scenario(path)
    except InputError as e:
        files = (f"{path}: ", f"{tmp_path / 'bench.toml'}: ")
        assert e.problems and all(line.startswith(files) for line in e.problems), e.problems
