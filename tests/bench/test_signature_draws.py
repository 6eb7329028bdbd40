"""Drawn shaft signatures (bench/signatures, issue 36): deterministic draws from the seed, predictions from the papers'
equations, scenarios an instruments rig can run, a hook-free start, and every kick or mismatch hidden among no-op
writes of the same object. Fast: no simulation (tests/system/test_drawn_signatures.py runs them)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from bench.inputs.prepared import prepare_run
from bench.signatures.draws import PMSM_MOTOR, SPIM_MOTOR, draw
from bench.signatures.predict import PmsmData, SpimData

ROOT = Path(__file__).resolve().parents[2]
MEASURED_ON_A_RIG = {"speed_true_mech_rad_s", "speed_est_mech_rad_s"}   # dyno encoder, the drive's own report
# the PMSM rig's aligned encoder (DAQ) minus the drive's reported angle, derived after the run ([rig_truths])
MEASURED_AFTER_THE_RUN = {"pmsm": {"pos_err_elec_rad"}, "spim": set()}
HOOK_FREE_UNTIL = {"pmsm": 0.72, "spim": 1.0}


def test_the_same_seed_draws_the_same_signature_and_another_seed_another():
    for drive in ("pmsm", "spim"):
        assert draw(drive, 7)[1] == draw(drive, 7)[1]
        a, b = draw(drive, 7)[0], draw(drive, 8)[0]
        assert [i["at_s"] for i in a.injection] != [i["at_s"] for i in b.injection]
        assert a.points != b.points


def test_eq33_gives_the_documented_rr_offset_and_eq5c_the_kick_advance():
    spim = SpimData.from_motor(ROOT / SPIM_MOTOR)
    assert spim.slip(4.1912, spim.rr) == pytest.approx(22.203, abs=1e-3)          # docs/shaft-signatures.md
    assert spim.slip(4.1912, spim.rr * 1.2) == pytest.approx(26.644, abs=1e-3)
    assert spim.rr_offset(4.1912, 1.2) == pytest.approx(2.220, abs=1e-3)
    pmsm = PmsmData.from_motor(ROOT / PMSM_MOTOR)
    assert pmsm.shaft_angle(0.5, 0.0, 0.0) == pytest.approx(0.5 / 3)
    # a step D through the 1000 rad/s^2 ramp lags by D^2/2R; a load step moves the PI integrator by dT/(J w_c^2 z)
    assert pmsm.shaft_angle(0.0, 20.0, 0.0) == pytest.approx(-0.2 - 2e-4 * 20 / 2.5)
    assert pmsm.shaft_angle(0.0, 0.0, 2.5) == pytest.approx(-1.0)


@pytest.mark.parametrize("drive", ["pmsm", "spim"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_drawn_signature_is_a_valid_instruments_rig_scenario(drive, seed):
    drawn, text = draw(drive, seed)
    prepared = prepare_run(ROOT / "scenarios" / f"{drive}-rig" / f"sig-drawn-seed{seed}.toml", text=text, seed=seed)
    scenario = prepared.scenario
    assert prepared.bench.bench.plant_injections is False        # the instruments rig: no plant injections
    signals = {c.signal for c in scenario.criteria}
    assert signals <= MEASURED_ON_A_RIG | MEASURED_AFTER_THE_RUN[drive]
    assert MEASURED_AFTER_THE_RUN[drive] <= signals
    assert MEASURED_AFTER_THE_RUN[drive] <= set(prepared.bench.rig_truths.signals())   # measured there, not assumed
    assert {seg.kind for seg in scenario.load_segments} == {"torque"}    # the dynamometer's own mode
    for c in scenario.criteria:
        assert c.limit > 0 and "expected" in c.params and c.window_s[1] <= scenario.duration_s


@pytest.mark.parametrize("drive", ["pmsm", "spim"])
def test_the_start_is_hook_free_and_every_write_hides_among_no_op_writes(drive):
    for seed in range(1, 6):
        drawn, _ = draw(drive, seed)
        writes = drawn.injection
        assert min(w["at_s"] for w in writes) >= HOOK_FREE_UNTIL[drive]
        assert len({w["name"] for w in writes}) == 1
        resting = 0.0 if drive == "pmsm" else SpimData.from_motor(ROOT / SPIM_MOTOR).rr
        no_ops = [w for w in writes if w["value"] == resting]
        real = [w for w in writes if w["value"] != resting]
        assert len(no_ops) >= 10 and 3 <= len(real) <= 4
        pulses = [seg for seg in drawn.load if seg["start_s"] < HOOK_FREE_UNTIL[drive]]
        assert pulses and all(math.isclose(round(p["start_s"], 2), p["start_s"]) for p in pulses)   # SYNC grid


def test_the_kicks_cover_the_envelope():
    drawn, _ = draw("pmsm", 4)
    whats = " | ".join(p["what"] for p in drawn.points)
    for where in ("right after a step", "right after a reversal", "lowest speed", "N*m at"):
        assert where in whats
    kicks = [p for p in drawn.points if "kick_rad" in p]
    assert all(0.25 <= abs(k["kick_rad"]) <= 0.6 for k in kicks)
    assert math.isclose(abs(drawn.points[0]["low"]), 2.0)


def test_the_position_error_criteria_sit_on_the_kicks_sync_and_expect_the_kick_back():
    """The measured angle error must jump by -m in the rows right after the SYNC that applies a steady kick (the
    estimator's angle was written) and be back to zero, within the rig's stated uncertainty, at the window's end."""
    for seed in (1, 2, 3):
        drawn, _ = draw("pmsm", seed)
        pos = [c for c in drawn.criteria if c["signal"] == "pos_err_elec_rad"]
        steady = [p for p in drawn.points if "kick_rad" in p and "right after" not in p["what"]]
        assert len(pos) == 2 * len(steady) == 4
        for k in steady:
            jump = next(c for c in pos if c["name"].startswith(k["what"]) and "jumps" in c["name"])
            back = next(c for c in pos if c["name"].startswith(k["what"]) and "back to zero" in c["name"])
            sync = math.ceil(round(k["at_s"], 4) * 100 - 1e-9) / 100
            assert sync - 0.01 < k["at_s"] <= sync + 1e-9
            assert jump["window_s"] == [round(sync + 0.0005, 4), round(sync + 0.0045, 4)]
            assert jump["expected"] == -k["kick_rad"] and jump["limit"] < abs(k["kick_rad"]) / 3
            assert back["expected"] == 0.0 and back["window_s"][1] == k["window_s"][1]
            assert 0.005 < back["limit"] < 0.03
