"""Three-phase VSI and ADC helpers, and what dead time does to the sensorless drive."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.contract.signals import SIGNAL_INDEX as COL
from sim_backend.drive import load_motor_config, make_drive
from sim_backend.three_phase_inverter import (adc_lsb, adc_sample, clarke, inverse_clarke, limit_to_linear_range,
                                  switching_error_voltage)
from sim_backend.mechanics import LOAD_TORQUE


def test_clarke_round_trip_and_zero_sum():
    a, b, c = inverse_clarke(1.3, -0.4)
    assert a + b + c == pytest.approx(0.0, abs=1e-12)
    assert clarke(a, b) == pytest.approx((1.3, -0.4))


def test_voltage_limited_to_the_linear_svpwm_circle():
    u = limit_to_linear_range(400.0, 300.0, 540.0)
    assert math.hypot(*u) == pytest.approx(540.0 / math.sqrt(3.0))
    assert u[1] / u[0] == pytest.approx(0.75)            # direction kept
    assert limit_to_linear_range(100.0, -50.0, 540.0) == (100.0, -50.0)


def test_dead_time_error_opposes_the_current():
    """Current along phase a (i_b = i_c = -i_a/2): phase a loses V, b and c gain V; amplitude-invariant
    Clarke of (-V, V, V): alpha = (2/3)(-V - V/2 - V/2) = -(4/3) V, beta = 0."""
    v = 540.0 * 2e-6 / 1e-4 + 1.5
    e = switching_error_voltage(2.0, 0.0, 540.0, 2e-6, 1e-4, 1.5, 0.05)
    assert e[0] == pytest.approx(-4.0 / 3.0 * v) and e[1] == pytest.approx(0.0, abs=1e-12)
    assert switching_error_voltage(2.0, 1.0, 540.0, 0.0, 1e-4, 0.0, 0.05) == (0.0, 0.0)
    small = switching_error_voltage(0.01, 0.0, 540.0, 2e-6, 1e-4, 0.0, 0.05)
    assert abs(small[0]) < 0.3 * 4.0 / 3.0 * 10.8      # fades through zero current


def test_adc_rounds_to_lsb_and_clips():
    lsb = adc_lsb(12, 12.5, True)
    assert lsb == pytest.approx(25.0 / 4096)
    x = adc_sample(1.0, 0.0, 0.0, lsb, 12.5, True)
    assert x / lsb == pytest.approx(round(x / lsb)) and abs(x - 1.0) <= lsb / 2
    assert adc_sample(50.0, 0.0, 0.0, lsb, 12.5, True) == pytest.approx(12.5 - lsb)
    assert adc_sample(-50.0, 0.0, 0.0, lsb, 12.5, True) == pytest.approx(-12.5)
    assert adc_sample(1.0, 0.1, 2.0, 0.0, 12.5, True) == pytest.approx(1.2)   # ideal converter
    assert adc_lsb(0, 12.5, True) == 0.0


def test_measured_current_noise_matches_config():
    drive = make_drive("config/motors/pmsm-paper.toml", seed=3, noise=True)
    block = drive.step(20000)                       # gates off: true currents are zero
    noise = np.hypot(block[:, COL["i_sx_a"]], block[:, COL["i_sy_a"]])
    # two sensors, 5 mA noise + quantisation (6.1 mA LSB) each: i_alpha = i_a, i_beta = (i_a + 2 i_b)/sqrt(3),
    # so E|i|^2 = s^2 + 5 s^2 / 3 = 8/3 s^2
    per_phase = math.sqrt(0.005 ** 2 + (25.0 / 4096) ** 2 / 12)
    assert math.sqrt((noise ** 2).mean()) == pytest.approx(per_phase * math.sqrt(8.0 / 3.0), rel=0.05)
    assert block[:, COL["vdc_v"]].std() == pytest.approx(math.sqrt(0.5 ** 2 + (1000 / 4096) ** 2 / 12), rel=0.1)


@pytest.mark.parametrize("speed", [20.0, 2.0])
def test_uncompensated_dead_time_loses_the_sensorless_drive_compensation_restores_it(speed):
    """2 us dead time + 1.5 V drop = 12.3 V per phase, more than the back-EMF at these speeds (the paper's
    DSP compensates inverter non-linearities [11])."""
    def run(comp: float) -> np.ndarray:
        cfg = load_motor_config("config/motors/pmsm-paper.toml")
        cfg["inverter"]["dead_time_s"] = 2e-6
        cfg["inverter"]["device_drop_v"] = 1.5
        cfg["firmware"]["deadtime_comp_v"] = comp
        drive = make_drive(cfg, seed=1, noise=True)
        drive.set_load(LOAD_TORQUE, 2.0)
        drive.set_enabled(True)
        drive.set_speed_ref(speed)
        return drive.step(30000)[-10000:]
    lost = run(0.0)
    assert abs(lost[:, COL["speed_true_mech_rad_s"]].mean() - speed) > 5.0
    kept = run(540.0 * 2e-6 / 1e-4 + 1.5)
    assert kept[:, COL["speed_true_mech_rad_s"]].mean() == pytest.approx(speed, abs=0.05)
    assert abs(kept[:, COL["pos_err_elec_rad"]].mean()) < 0.02
