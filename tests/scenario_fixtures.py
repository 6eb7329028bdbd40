"""Helpers for the scenario tests: a bench config in a temp dir whose EDS exists, scenario text builders."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def write_bench(tmp: Path, *, plant_injections: bool = True, kind: str | None = "pmsm", name: str = "bench.toml") -> Path:
    eds = tmp / "drive.eds"
    eds.write_text("[FileInfo]\n")
    kind_line = f'kind = "{kind}"\n' if kind else ""
    path = tmp / name
    path.write_text(f"""
[bench]
name = "test-bench"
plant_injections = {str(plant_injections).lower()}

[drive]
transport = "canopen"
{kind_line}interface = "virtual"
channel = "test"
node_id = 1
eds = "{eds}"

[load]
transport = "modbus-tcp"
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
