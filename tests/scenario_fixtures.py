"""Helpers for the scenario tests: a bench config in a temp dir whose EDS exists, scenario text builders, and the
paper suite's known gaps (tests/known_gaps.toml) with their measured bands."""

from __future__ import annotations

import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


KNOWN_GAPS_FILE = REPO / "tests" / "known_gaps.toml"
THIRD_PARTY_EDS = REPO / "config" / "od" / "third-party" / "cia402_slave.eds"


def write_bench(tmp: Path, *, plant_injections: bool = True, kind: str | None = "pmsm", name: str = "bench.toml") -> Path:
    """kind: the drivebench drive whose EDS the bench names; None: a third-party CiA 402 drive (no drivebench
    objects, so no parameters)."""
    eds = tmp / "drive.eds"
    source = REPO / "config" / "od" / f"drivebench-{kind}.eds" if kind else THIRD_PARTY_EDS
    eds.write_text(source.read_text())
    unit = "" if kind else 'velocity_unit = "rpm"\n'        # a third-party EDS without 0x60A9: the config says
    path = tmp / name
    path.write_text(f"""
[bench]
name = "test-bench"
plant_injections = {str(plant_injections).lower()}

[drive]
transport = "canopen"
{unit}interface = "virtual"
channel = "test"
node_id = 1
eds = "{eds}"

[load]
transport = "modbus-tcp"
map = "config/load-machines/drivebench-sim.toml"
host = "127.0.0.1"
port = 0
""")
    return path


BASE = """
schema_version = 1
name = "t"
bench = "bench.toml"
duration_s = 10.0
limits = { overspeed_mech_rad_s = 100.0, overcurrent_a = 10.0 }
"""


def write_scenario(tmp: Path, body: str, *, base: str = BASE, name: str = "s.toml") -> Path:
    path = tmp / name
    path.write_text(base + body)
    return path


# The known gaps of the paper suite (tests/known_gaps.toml): which criteria must fail with a seed, and their bands.
def gap_entries() -> list[dict]:
    return tomllib.loads(KNOWN_GAPS_FILE.read_text(encoding="utf-8")).get("gap", [])


def known_gaps() -> dict[str, set[str]]:
    gaps: dict[str, set[str]] = {}
    for entry in gap_entries():
        gaps.setdefault(entry["scenario"], set()).add(entry["criterion"])
    return gaps


def expected_failures(scenario: str, seed: int) -> set[str]:
    """The gaps that must fail with this seed: every plain gap, a seed-dependent one only for its failing seeds."""
    return {e["criterion"] for e in gap_entries() if e["scenario"] == scenario
            and ("failing_seeds" not in e or seed in e["failing_seeds"])}


def band_violations(scenario: str, seed: int, criteria) -> list[str]:
    """Gaps of this scenario whose value is outside their measured band: `band` when the gap fails with this seed,
    `pass_band` when a seed-dependent gap passes with it."""
    values = {c.name: c.value for c in criteria}
    out = []
    for e in gap_entries():
        if e["scenario"] != scenario or e["criterion"] not in values:
            continue
        failing = "failing_seeds" not in e or seed in e["failing_seeds"]
        key = "band" if failing else "pass_band"
        lo, hi = e[key]
        value = values[e["criterion"]]
        if not lo <= value <= hi:
            out.append(f"{e['criterion']}: value {value:.6g} outside its {key} [{lo:g}, {hi:g}] (seeds 1-20)")
    return out
