"""Mutation testing of the acceptance suite: every firmware mutant (tests/mutants.py) run through its drive's paper
scenarios must be rejected by at least one criterion that the real firmware passes (a known gap does not count), or
by the run ending aborted or in error. A surviving mutant fails the suite.

Without --drivebench-out a mutant's scenarios run until one rejects it (that is the verdict); with --drivebench-out DIR
every scenario runs and the kill table (which scenarios reject it, and by what) is written to DIR/mutants/ (a file per mutant); `drivebench report DIR/* --suites
config/report/paper-suites.toml --out docs/validation.md` puts it in the validation page.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from bench.run.orchestrator import run_scenario
from bench.outputs.report import MUTANTS_DIR
from tests.mutants import ALL_MUTANTS, Mutant, _apply, build, compile_group, mutant_kernel

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow             # a numba compile per mutant and up to a run per paper scenario


def scenarios_of(drive: str) -> list[Path]:
    return sorted((ROOT / "scenarios" / drive).glob("*.toml"))


def kills(mutant: Mutant, out: Path, *, whole_table: bool = True) -> dict[str, list[str]]:
    """scenario stem -> what rejected the mutant there (failing criteria that are not known gaps, or the verdict).
    Without whole_table it stops at the first scenario that rejects the mutant (the verdict needs one)."""
    killed: dict[str, list[str]] = {}
    with mutant_kernel(mutant, build(mutant)):
        for path in scenarios_of(mutant.drive):
            result = run_scenario(path, out_root=out, rerun_mode="off")
            why = [c.name for c in result.criteria if c.status == "fail" and not c.known_gap]
            if result.verdict in ("aborted", "error"):
                why.insert(0, f"run {result.verdict}: {result.record.get('abort_reason') or result.error}")
            if why:
                killed[path.stem] = why
                if not whole_table:
                    break
    return killed


@pytest.mark.parametrize("mutant", [pytest.param(m, id=f"{m.drive}-{m.name}", marks=compile_group(m)) for m in ALL_MUTANTS])
def test_every_firmware_mutant_is_rejected(mutant, tmp_path, request):
    out = request.config.getoption("--drivebench-out")
    table = bool(out and out != "runs")   # the kill table for the validation page names every scenario that kills
    killed = kills(mutant, tmp_path, whole_table=table)
    assert killed, f"mutant {mutant.name} ({mutant.what}) survives every {mutant.drive} acceptance scenario"
    if table:                             # one file per mutant: the suite's workers write side by side
        path = Path(out) / MUTANTS_DIR / f"{mutant.drive}-{mutant.name}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        entry = {"drive": mutant.drive, "name": mutant.name, "what": mutant.what, "killed_by": killed}
        path.write_text(json.dumps(entry, indent=1, sort_keys=True))


# A cheat that passes a paper figure and fails only the designed signature, by the signature's whole prediction
# (value = |measured - expected| with the cheat's measurement ~0); the real firmware passes the signature.
SIGNATURE_CASES = [
    # an encoder-reading firmware passes the whole Fig. 8 scenario (zero position error is what fig08 asks for);
    # the eq. (15a) signature with i_sx* = 2 A is what tells it from the MRAS: |0 - (-0.0919)|
    ("encoder_cheat", "scenarios/pmsm/fig08-20rads-rs-step.toml", "scenarios/pmsm/sig-isx-rs-step-eq15a.toml",
     "position error after the R_s step = eq. (15a), i_sx = 2 A", (0.08, math.inf)),
    # a tachometer firmware passes Fig. 6; holding the slip estimator under load and then removing the load must
    # leave w^ - w at -(held - no-load slip) / n_p (eq. 33), which it cannot show: |0 - (-10.564)|
    ("true_speed_cheat", "scenarios/spim/fig06-1500rpm-load-step.toml", "scenarios/spim/sig-slip-hold-unload.toml",
     "slip held, load removed: w^ - w = -(held - no-load slip) / n_p of eq. (33)", (10.364, 10.764)),
]


@pytest.mark.parametrize("name, figure, signature, criterion, value_range", [
    pytest.param(*case, id=case[0], marks=compile_group(next(m for m in ALL_MUTANTS if m.name == case[0])))
    for case in SIGNATURE_CASES])
def test_the_sensor_cheat_is_caught_by_the_designed_signature_not_by_the_figure(tmp_path, name, figure, signature,
                                                                              criterion, value_range):
    mutant = next(m for m in ALL_MUTANTS if m.name == name)
    with mutant_kernel(mutant, build(mutant)):
        fig = run_scenario(ROOT / figure, out_root=tmp_path, rerun_mode="off")
        sig = run_scenario(ROOT / signature, out_root=tmp_path, rerun_mode="off")
    assert fig.verdict == "pass"
    failed = {c.name: c for c in sig.criteria if c.status == "fail"}
    assert list(failed) == [criterion]
    assert value_range[0] < failed[criterion].value < value_range[1]
    real = run_scenario(ROOT / signature, out_root=tmp_path, rerun_mode="off")
    assert real.verdict == "pass"


def test_a_mutant_edit_that_no_longer_matches_the_firmware_fails_loudly():
    with pytest.raises(AssertionError, match="found 0 times"):
        _apply("def firmware_step(): pass\n", [("s[S_THETA] = 0", "pass")], "stale mutant")
