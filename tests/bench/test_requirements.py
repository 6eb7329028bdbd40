"""`requirements = [...]` in a scenario: validated (an array of distinct ids), and carried into record.json, the
run's junit.xml properties and the report."""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree as ET

import pytest

from bench.inputs.scenario import load_scenario
from drivers.contract.errors import InputError

REPO = Path(__file__).resolve().parents[2]
SHORT = (REPO / "tests/data/service/short.toml").read_text().replace(
    'bench = "config/benches/', f'bench = "{REPO}/config/benches/')


def _write(tmp_path: Path, line: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(SHORT.replace('seed = 1\n', f'seed = 1\n{line}\n'))
    return path


def test_requirements_reach_the_record_the_junit_properties_and_the_report(tmp_path):
    from bench.outputs.report import write_report
    from bench.run.orchestrator import run_scenario

    path = _write(tmp_path, 'requirements = ["REQ-12", "SYS-4.2"]')
    assert load_scenario(path).requirements == ("REQ-12", "SYS-4.2")
    result = run_scenario(path, None, out_root=tmp_path / "runs", rerun_mode="off")
    assert result.record["scenario"]["requirements"] == ["REQ-12", "SYS-4.2"]
    suite = ET.parse(result.run_dir / "junit.xml").getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    props = {p.get("name"): p.get("value") for p in suite.find("properties")}
    assert props["requirements"] == "REQ-12, SYS-4.2"
    report = write_report([result.run_dir], tmp_path / "report.md")
    assert "Requirements: REQ-12, SYS-4.2." in Path(report).read_text()


@pytest.mark.parametrize("line, problem", [
    ('requirements = "REQ-1"', "requirements: must be an array of requirement ids"),
    ('requirements = ["REQ-1", "REQ-1"]', "requirements[1]: 'REQ-1' is listed twice"),
    ('requirements = [""]', "requirements[0]: must be 1 to 200 characters")])
def test_bad_requirements_are_one_line_each(tmp_path, line, problem):
    path = _write(tmp_path, line)
    with pytest.raises(InputError) as err:
        load_scenario(path)
    assert len(err.value.problems) == 1 and err.value.problems[0].startswith(f"{path}: {problem}"), err.value.problems
