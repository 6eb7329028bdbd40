"""The PMSM paper's quantitative statements, reproduced on the simulator (speeds in mech rad/s)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.contract.signals import SIGNAL_INDEX as COL
from sim_backend.drive import make_drive
from sim_backend.mechanics import LOAD_TORQUE, LOAD_VISCOUS

CONFIG = "config/motors/pmsm-paper.toml"
PSI = 0.2592772
RS, LS, P = 3.58356, 0.02, 3
STEPS_PER_S = 10000


def mean(block: np.ndarray, name: str) -> float:
    return float(block[:, COL[name]].mean())


@pytest.mark.parametrize("noise", [False, True])
def test_rs_drop_fig8_flux_offset_matches_eq15b(noise):
    """Fig. 8: 20 rad/s, 2 N m, Rs drops 20 % at t = 2 s. Position error returns to zero, psi^ settles at
    psi - psi^ = -(i_sy / (a2 w_e)) * delta_a1 (eq. 15b), delta_a1 = (0.8 - 1) Rs/Ls."""
    drive = make_drive(CONFIG, seed=11, noise=noise)
    drive.set_load(LOAD_TORQUE, 2.0)
    drive.set_enabled(True)
    drive.set_speed_ref(20.0)
    before = drive.step(2 * STEPS_PER_S)
    assert abs(mean(before[-5000:], "pos_err_elec_rad")) < 2e-3
    drive.set_plant_param("plant_rs", 0.8)
    after = drive.step(4 * STEPS_PER_S)
    transient = np.abs(after[:5000, COL["pos_err_elec_rad"]]).max()
    assert transient > 0.02  # the step really disturbed the estimator
    tail = after[-10000:]
    assert abs(mean(tail, "pos_err_elec_rad")) < 2e-3
    assert mean(tail, "speed_true_mech_rad_s") == pytest.approx(20.0, abs=0.05)
    assert mean(tail, "speed_est_mech_rad_s") == pytest.approx(mean(tail, "speed_true_mech_rad_s"), abs=0.05)
    w_e = P * mean(tail, "speed_est_mech_rad_s")
    delta_a1 = (0.8 - 1.0) * RS / LS
    predicted = -(mean(tail, "i_sy_a") * LS / w_e) * delta_a1   # psi - psi^, eq. (15b)
    measured = PSI - mean(tail, "flux_est_wb")
    assert predicted == pytest.approx(0.0205, abs=0.001)
    assert measured == pytest.approx(predicted, rel=0.05)


@pytest.mark.parametrize("speed", [2.0, -2.0])
def test_flux_estimate_step_recovers_fig7(speed):
    """Fig. 7: at +-2 rad/s with 2 N m, psi^ <- 1.1 psi^ inside the controller; the estimator recovers."""
    drive = make_drive(CONFIG, seed=7, noise=True)
    drive.set_load(LOAD_TORQUE, 2.0)
    drive.set_enabled(True)
    drive.set_speed_ref(speed)
    settled = drive.step(2 * STEPS_PER_S)[-5000:]
    assert mean(settled, "flux_est_wb") == pytest.approx(PSI, rel=0.02)
    drive.set_hook("flux_est_scale", 1.1)
    first = drive.step(50)
    assert mean(first, "flux_est_wb") > 1.06 * PSI
    block = drive.step(int(1.5 * STEPS_PER_S))
    tail = block[-5000:]
    assert mean(tail, "flux_est_wb") == pytest.approx(PSI, rel=0.02)
    assert abs(mean(tail, "pos_err_elec_rad")) < 0.01
    assert mean(tail, "speed_true_mech_rad_s") == pytest.approx(speed, abs=0.05)
    assert drive.fault_code() == 0


def test_speed_reversal_fig7_with_load():
    """Fig. 7 sequence: 2 rad/s, flux perturbation, reversal to -2 rad/s under a 2 N m active load."""
    drive = make_drive(CONFIG, seed=3, noise=True)
    drive.set_load(LOAD_TORQUE, 2.0)
    drive.set_enabled(True)
    drive.step(5000)
    drive.set_speed_ref(2.0)
    drive.step(15000)
    drive.set_hook("flux_est_scale", 1.1)
    drive.step(30000)
    drive.set_speed_ref(-2.0)
    tail = drive.step(30000)[-10000:]
    assert mean(tail, "speed_true_mech_rad_s") == pytest.approx(-2.0, abs=0.05)
    assert abs(mean(tail, "pos_err_elec_rad")) < 0.01
    assert mean(tail, "flux_est_wb") == pytest.approx(PSI, rel=0.02)
    assert mean(tail, "i_sy_a") == pytest.approx(2.0 / (1.5 * P * PSI), rel=0.02)


@pytest.mark.parametrize("speed, pos_err0", [(10.0, -1.2), (-10.0, 1.2)])
def test_initial_position_error_converges_fig10(speed, pos_err0):
    """Fig. 10: start at 10 rad/s into a DC generator on a resistor (viscous) with 1.2 rad initial error.

    Converges when the error and the rotation have opposite signs (20/20 seeds). With equal signs the
    estimated frame can lag into the 90 deg standstill trap (14/20 at +10 rad/s, +1.2 rad): below
    w_e ~ a1 the MRAS gives w^ ~ w cos(delta), so d delta/dt ~ w (1 - cos delta). See docs/firmware-pmsm.md.
    """
    drive = make_drive(CONFIG, seed=5, noise=True)
    drive.set_load(LOAD_VISCOUS, 0.1)
    drive.set_hook("pos_est_offset_rad", -pos_err0)  # pos_err = true - estimated
    first = drive.step(1)
    assert first[0, COL["pos_err_elec_rad"]] == pytest.approx(pos_err0, abs=1e-3)
    drive.set_enabled(True)
    drive.set_speed_ref(speed)
    block = drive.step(STEPS_PER_S)
    tail = block[-2000:]
    assert abs(mean(tail, "pos_err_elec_rad")) < 0.01
    assert mean(tail, "speed_true_mech_rad_s") == pytest.approx(speed, abs=0.1)
    settle = np.argmax(np.abs(block[:, COL["pos_err_elec_rad"]]) < 0.05) / STEPS_PER_S
    assert 0.0 < settle < 0.3


def test_speed_estimate_tracks_over_the_range():
    """Estimated speed equals true speed in steady state from 5 to 300 mech rad/s with 3 N m."""
    drive = make_drive(CONFIG, seed=2, noise=True)
    drive.set_load(LOAD_TORQUE, 3.0)
    drive.set_enabled(True)
    for ref in (5.0, 50.0, 300.0):
        drive.set_speed_ref(ref)
        tail = drive.step(STEPS_PER_S)[-3000:]
        assert mean(tail, "speed_true_mech_rad_s") == pytest.approx(ref, rel=0.01)
        assert mean(tail, "speed_est_mech_rad_s") == pytest.approx(mean(tail, "speed_true_mech_rad_s"), rel=0.005)
        assert abs(mean(tail, "pos_err_elec_rad")) < 0.02
    assert drive.fault_code() == 0


def test_freeze_hooks_hold_estimates():
    drive = make_drive(CONFIG, seed=2, noise=False)
    drive.set_enabled(True)
    drive.set_speed_ref(20.0)
    drive.step(5000)
    drive.set_hook("freeze_flux_est", 1)
    drive.set_hook("freeze_speed_est", 1)
    held = drive.step(1)[0]
    drive.set_speed_ref(40.0)
    block = drive.step(2000)
    assert np.all(block[:, COL["speed_est_mech_rad_s"]] == held[COL["speed_est_mech_rad_s"]])
    assert np.all(block[:, COL["flux_est_wb"]] == held[COL["flux_est_wb"]])
    drive.set_hook("freeze_speed_est", 0)
    drive.set_hook("freeze_flux_est", 0)
    tail = drive.step(20000)[-2000:]
    assert mean(tail, "speed_est_mech_rad_s") == pytest.approx(40.0, abs=0.1)


def test_firmware_resistance_override_acts_like_plant_mismatch():
    """fw_rs_ohm = 1.25 Rs against the nominal plant gives the same a1 mismatch as plant_rs = 0.8."""
    drive = make_drive(CONFIG, seed=1, noise=False)
    drive.set_load(LOAD_TORQUE, 2.0)
    drive.set_enabled(True)
    drive.set_speed_ref(20.0)
    drive.step(20000)
    drive.set_hook("fw_rs_ohm", 1.25 * RS)
    tail = drive.step(40000)[-10000:]
    w_e = P * mean(tail, "speed_est_mech_rad_s")
    delta_a1 = (1.0 - 1.25) * RS / LS
    predicted = -(mean(tail, "i_sy_a") * LS / w_e) * delta_a1
    assert PSI - mean(tail, "flux_est_wb") == pytest.approx(predicted, rel=0.05)
    assert abs(mean(tail, "pos_err_elec_rad")) < 2e-3


def test_flux_estimate_relaxes_to_nominal_at_standstill():
    """Enabling at zero speed into a 2 N m active load: the rotor is pushed back, psi^ is disturbed during
    that transient, then relaxes to the nominal flux once the shaft is held (no flux information there)."""
    drive = make_drive(CONFIG, seed=4, noise=True)
    drive.set_load(LOAD_TORQUE, 2.0)
    drive.set_enabled(True)
    block = drive.step(2000)
    assert abs(block[:, COL["flux_est_wb"]] - PSI).max() > 0.02
    tail = drive.step(40000)[-5000:]
    assert abs(mean(tail, "speed_true_mech_rad_s")) < 0.05
    assert mean(tail, "flux_est_wb") == pytest.approx(PSI, rel=0.03)
