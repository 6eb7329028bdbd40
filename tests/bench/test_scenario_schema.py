"""The scenario JSON Schema shipped for editors (bench/inputs/schemas/scenario.schema.json): it is what the parser's
key lists and criterion kinds make (regenerated, byte for byte), every scenario of the repository validates
against it, and a typo of a key, a kind or a signal is refused."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

jsonschema = pytest.importorskip("jsonschema")

from bench.inputs.scenario_schema import SCHEMA_FILE, text

REPO = Path(__file__).resolve().parents[2]


def _validator():
    schema = json.loads(SCHEMA_FILE.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_the_shipped_schema_is_the_generated_one():
    assert SCHEMA_FILE.read_text() == text(), "run: python -m bench.inputs.scenario_schema"


def test_every_scenario_of_the_repository_validates():
    validator = _validator()
    files = sorted((REPO / "scenarios").rglob("*.toml"))
    assert len(files) > 30
    for path in files:
        errors = [e.message for e in validator.iter_errors(tomllib.loads(path.read_text()))]
        assert not errors, (path, errors[:3])


@pytest.mark.parametrize("change", [
    ("overcurrent_a = 10.0", "overcurent_a = 10.0"),               # a key's typo
    ('kind = "step"', 'kind = "stepp"'),                           # a kind's typo
    ('signal = "pos_err_elec_rad"', 'signal = "pos_error"'),        # a signal that does not exist
])
def test_a_typo_is_refused(change):
    text_ = (REPO / "tests/data/service/short.toml").read_text()
    assert change[0] in text_
    assert list(_validator().iter_errors(tomllib.loads(text_.replace(change[0], change[1], 1))))
