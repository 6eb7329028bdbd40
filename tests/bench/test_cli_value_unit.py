"""The CLI's verdict table gives the value with its unit, as the limit has it (a value column without a unit left a
reader to guess rad/s from rpm)."""

from __future__ import annotations

from rich.console import Console

from bench.faces.cli import criteria_table


def test_value_and_limit_both_carry_the_unit():
    table = criteria_table("criteria", [{"name": "held", "signal": "speed_est_mech_rad_s", "window_s": [0.5, 1.0],
                                         "value": 0.25, "limit": 1.0, "unit": "rad/s", "passed": True}])
    console = Console(width=200, record=True)
    console.print(table)
    row = next(line for line in console.export_text().splitlines() if "held" in line)
    assert "0.25 rad/s" in row and "1 rad/s" in row, row
