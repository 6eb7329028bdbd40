"""`twin --fit --write-motor`: a parameter the fit reports NOT IDENTIFIED is not written; the motor file keeps the
source's value and says why beside it, and the written file still builds a drive."""

from __future__ import annotations

import tomllib
from pathlib import Path

from sim_backend.twin_fit import FitResult, FittedParam, write_motor

REPO = Path(__file__).resolve().parents[2]
MOTOR = REPO / "config/motors/pmsm-paper.toml"


def test_a_parameter_not_identified_keeps_the_source_value(tmp_path):
    source = tomllib.loads(MOTOR.read_text())
    rs, j = source["plant"]["rs_ohm"], source["mechanics"]["inertia_kgm2"]
    params = [FittedParam("plant.rs_ohm", rs, rs * 1.1, rs * 1.05, rs * 1.15, True),
              FittedParam("mechanics.inertia_kgm2", j, j * 7.0, 0.0, j * 50, False, "interval spans zero")]
    result = FitResult("pmsm", params, ["speed_est_mech_rad_s"], 100, 100, 1.0, 0.5, 3, 4, 0.1, 0.0, [1.0], "ok")
    out = tmp_path / "fitted.toml"
    write_motor(MOTOR, result, "run-1", out)
    written = tomllib.loads(out.read_text())
    assert abs(written["plant"]["rs_ohm"] - rs * 1.1) < 1e-5 * rs                   # identified: written
    assert written["mechanics"]["inertia_kgm2"] == j                               # not identified: the source's
    line = next(x for x in out.read_text().splitlines() if x.startswith("inertia_kgm2"))
    assert "NOT IDENTIFIED (interval spans zero)" in line and "kept the source's value" in line
    assert written["firmware"] == source["firmware"]


def test_a_plot_or_motor_file_it_cannot_write_is_one_line_before_the_replay(tmp_path):
    import subprocess
    import sys

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    for option in ("--plot", "--write-motor"):
        extra = ["--fit-mechanics"] if option == "--write-motor" else []
        out = subprocess.run([sys.executable, "-m", "bench", "twin", str(tmp_path), option, str(blocker / "x"), *extra],
                             capture_output=True, text=True, cwd=REPO, timeout=120)
        lines = [line for line in out.stderr.splitlines() if line.strip()]
        assert out.returncode == 2 and lines == [f"{blocker / 'x'}: {option}: {blocker} is not a directory"], out.stderr
