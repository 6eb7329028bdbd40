"""A limit written in rpm is answered in rpm (an overspeed_rpm below the profile's peak was answered in rad/s)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.inputs.scenario import load_scenario
from drivers.contract.errors import InputError

REPO = Path(__file__).resolve().parents[2]
TEXT = f"""schema_version = 1
bench = "{REPO}/config/benches/sim-pmsm.toml"
duration_s = 1.0

[[speed]]
kind = "step"
at_s = 0.0
speed_rpm = 300

[limits]
overcurrent_a = 10.0
"""


@pytest.mark.parametrize("limit, expected", [
    ("overspeed_rpm = 250", "limits.overspeed_rpm: 250 rpm is not above the profile's peak reference 300 rpm"),
    ("overspeed_mech_rad_s = 20.0",
     "limits.overspeed_mech_rad_s: 20 mech rad/s is not above the profile's peak reference 31.4159 mech rad/s")])
def test_the_overspeed_limit_is_answered_in_its_own_unit(tmp_path, limit, expected):
    path = tmp_path / "s.toml"
    path.write_text(TEXT + limit + "\n")
    with pytest.raises(InputError) as err:
        load_scenario(path)
    assert err.value.problems == [f"{path}: {expected}"]
