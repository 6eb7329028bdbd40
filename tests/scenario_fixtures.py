"""Helpers for the scenario tests: a bench config in a temp dir whose EDS exists, scenario text builders."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


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
