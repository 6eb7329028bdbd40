"""JSON Schema (draft 2020-12) of the scenario file, built from the same key lists and criterion kinds the scenario
parser checks (bench/inputs/scenario.py, bench/inputs/criteria.py), so the two cannot drift apart. Shipped as
`bench/inputs/schemas/scenario.schema.json` for editors (taplo / Even Better TOML: `#:schema` at the top of a file,
or the association in `.taplo.toml`); `python -m bench.inputs.scenario_schema` writes it again.

The schema checks shape (keys, types, kinds, signal names); what depends on the bench (an injection the drive
offers, a signal the bench measures, the drive kind) and on other values (times within duration_s, segments in
order) stays with `drivebench validate`, which says it in one line per problem."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from bench.inputs import scenario as sc
from bench.inputs.criteria import _CRITERION_KEYS, KINDS
import bench.inputs.capture_criteria  # noqa: F401  (registers the kinds judged on instruments' records)
from drivers.contract.signals import SIGNAL_NAMES
from bench.inputs.capture_names import _CAPTURE

SCHEMA_FILE = Path(__file__).with_name("schemas") / "scenario.schema.json"
NUMBER = {"type": "number"}
TIME = {"type": "number", "minimum": 0}


def _key_schema(key: str) -> dict[str, Any]:
    if key == "kind":
        return {"type": "string"}
    return TIME if key.endswith("_s") and not key.endswith("rad_s") else NUMBER     # times >= 0; values signed


def _tables_by_kind(keys_by_kind: dict[str, tuple[str, ...]]) -> dict[str, Any]:
    return {"type": "array", "items": {"oneOf": [
        {"type": "object", "required": ["kind"], "additionalProperties": False,
         "properties": {**{k: _key_schema(k) for k in keys if k != "kind"}, "kind": {"const": kind}}}
        for kind, keys in keys_by_kind.items()]}}


def _signal() -> dict[str, Any]:
    """A telemetry signal, or an instrument's `<instrument>:<signal>` (bench.inputs.capture_names)."""
    return {"anyOf": [{"enum": list(SIGNAL_NAMES)}, {"type": "string", "pattern": _CAPTURE.pattern}]}


def _criterion(kind_name: str) -> dict[str, Any]:
    kind = KINDS[kind_name]
    params = {}
    for key, spec in kind.params.items():
        params[key] = (_signal() if spec.type == "signal"
                       else {"type": "boolean"} if spec.type == "bool" else NUMBER)
        if spec.help:
            params[key] = {**params[key], "description": spec.help}
    required = ["name", "kind", "signal", "window_s", "limit"] + [k for k, s in kind.params.items() if s.required]
    common = {"name": {"type": "string", "minLength": 1}, "kind": {"const": kind_name},
              "signal": _signal(),
              "window_s": {"type": "array", "items": TIME, "minItems": 2, "maxItems": 2},
              "limit": {"type": "number", "minimum": 0}, "known_gap": {"type": "string", "minLength": 1}}
    assert set(common) == set(_CRITERION_KEYS), "criteria.py's common keys changed: update the schema"
    return {"type": "object", "description": kind.help, "required": required, "additionalProperties": False,
            "properties": {**common, **params}}


def scenario_schema() -> dict[str, Any]:
    top = {
        "schema_version": {"const": sc.SCHEMA_VERSION},
        "name": {"type": "string", "minLength": 1},
        "description": {"type": "string"},
        "bench": {"type": "string", "minLength": 1, "description": "bench config, from the repository root or beside "
                                                                   "this file"},
        "duration_s": {"type": "number", "exclusiveMinimum": 0, "maximum": sc.MAX_DURATION_S},
        "seed": {"type": "integer", "minimum": 0, "maximum": 2**63 - 1},
        "requirements": {"type": "array", "uniqueItems": True, "maxItems": 100,
                         "items": {"type": "string", "minLength": 1, "maxLength": 200, "pattern": "^[^,\\n\\r\\t]+$"}},
        "drive_kinds": {"type": "array", "minItems": 1, "uniqueItems": True, "items": {"enum": ["pmsm", "spim"]},
                        "description": "the drive kinds the scenario is for (default: its own bench's)"},
        "speed": _tables_by_kind(sc._SPEED_KEYS),
        "load": _tables_by_kind(sc._LOAD_KEYS),
        "injection": {"type": "array", "items": {
            "type": "object", "required": ["at_s", "name", "value"], "additionalProperties": False,
            "properties": {"at_s": TIME, "name": {"type": "string"}, "value": NUMBER}}},
        "limits": {"type": "object", "additionalProperties": False,
                   "properties": {k: {"type": "number", "exclusiveMinimum": 0} for k in sc._LIMIT_KEYS}},
        "criteria": {"type": "array", "items": {"oneOf": [_criterion(k) for k in KINDS]}},
    }
    assert set(top) == set(sc._TOP_KEYS), "scenario.py's top keys changed: update the schema"
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": "drivebench/scenario.schema.json",
            "title": "drivebench scenario (schema_version 1)",
            "description": "docs/scenarios.md; `drivebench validate FILE --bench CONFIG` checks what depends on the bench",
            "type": "object", "required": ["schema_version", "bench", "duration_s", "limits"],
            "additionalProperties": False, "properties": top}


def text() -> str:
    return json.dumps(scenario_schema(), indent=1, sort_keys=False) + "\n"


if __name__ == "__main__":
    SCHEMA_FILE.parent.mkdir(exist_ok=True)
    SCHEMA_FILE.write_text(text())
    sys.stdout.write(f"wrote {SCHEMA_FILE.name}\n")
