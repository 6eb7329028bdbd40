"""PmsmDrive meets the DriveModel contract: shapes, enable/disable, loads, hooks, plant injections, faults."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest

from drivers.contract.signals import SIGNAL_INDEX as COL
from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract.errors import InputError
from sim_backend.drive import load_motor_config, make_drive
from drivers.contract.parameters import ParamKind, names_for
from sim_backend.mechanics import LOAD_BRAKE, LOAD_TORQUE, LOAD_VISCOUS
from sim_backend.drive_model import DriveModel
from sim_backend.pmsm.model import PmsmDrive

CONFIG = "config/motors/pmsm-paper.toml"


def test_meets_drive_model_protocol():
    drive = make_drive(CONFIG, seed=0)
    assert isinstance(drive, PmsmDrive)
    for name, member in inspect.getmembers(DriveModel):
        if not name.startswith("_") and callable(member):
            assert callable(getattr(drive, name)), name
    assert drive.control_period_s == 1e-4
    block = drive.step(25)
    assert block.shape == (25, len(SIGNAL_NAMES)) and block.dtype == np.float64
    assert drive.time_s == pytest.approx(25e-4)
    assert set(drive.hook_names()) | set(drive.plant_param_names()) == set(names_for("pmsm", ParamKind.TEST_HOOK, ParamKind.FIRMWARE, ParamKind.PLANT))


def test_disabled_drive_applies_no_voltage_and_keeps_flux_true():
    drive = make_drive(CONFIG, seed=0)
    block = drive.step(100)
    assert np.all(block[:, COL["u_sx_v"]] == 0) and np.all(block[:, COL["u_sy_v"]] == 0)
    assert np.all(block[:, COL["flux_true_wb"]] == pytest.approx(0.2592772))
    assert abs(block[:, COL["i_sy_a"]]).max() < 0.03  # ADC noise only
    assert block[:, COL["vdc_v"]].mean() == pytest.approx(540.0, abs=0.5)


def test_disable_stops_currents_and_load_feedback_reads_the_shaft():
    drive = make_drive(CONFIG, seed=0, noise=False)
    drive.set_enabled(True)
    drive.set_speed_ref(50.0)
    drive.step(5000)
    speed, torque = drive.load_feedback()
    assert speed == pytest.approx(50.0, rel=1e-3) and torque == 0.0
    drive.set_load(LOAD_VISCOUS, 0.02)
    drive.step(3000)
    speed, torque = drive.load_feedback()
    assert torque == pytest.approx(0.02 * speed)
    drive.set_enabled(False)
    block = drive.step(50)
    assert np.all(block[2:, COL["i_sy_a"]] == 0.0)
    assert block[-1, COL["speed_true_mech_rad_s"]] < speed  # coasting down against the load


def test_brake_load_holds_standstill_and_load_disable_means_zero_torque():
    drive = make_drive(CONFIG, seed=0, noise=False)
    drive.set_load(LOAD_BRAKE, 1.0)
    drive.set_enabled(True)
    drive.set_speed_ref(10.0)
    block = drive.step(10000)
    assert block[-1, COL["torque_load_nm"]] == pytest.approx(1.0)
    drive.set_load(LOAD_BRAKE, 1.0, enabled=False)
    assert drive.load_feedback()[1] == 0.0


def test_plant_injections_scale_nominal_values():
    drive = make_drive(CONFIG, seed=0, noise=False)
    drive.set_plant_param("plant_flux", 0.9)
    block = drive.step(2)
    assert block[-1, COL["flux_true_wb"]] == pytest.approx(0.9 * 0.2592772)
    drive.set_plant_param("plant_flux", 1.0)
    assert drive.step(1)[0, COL["flux_true_wb"]] == pytest.approx(0.2592772)
    with pytest.raises(KeyError):
        drive.set_plant_param("plant_rr", 1.0)
    with pytest.raises(ValueError):
        drive.set_plant_param("plant_rs", -1.0)
    with pytest.raises(KeyError):
        drive.set_hook("fw_rr_ohm", 1.0)


def test_inertia_injection_changes_acceleration():
    """Gates off (open winding), active 1 N m load: w(t) = -(T/B) (1 - exp(-B t / J))."""
    def speed_after_50ms(factor: float) -> float:
        drive = make_drive(CONFIG, seed=0, noise=False)
        drive.set_plant_param("plant_inertia", factor)
        drive.set_load(LOAD_TORQUE, 1.0)
        drive.step(500)
        return drive.load_feedback()[0]
    b = 2e-4
    for factor in (1.0, 3.0):
        expected = -(1.0 / b) * (1.0 - math.exp(-b * 0.05 / (factor * 1e-3)))
        assert speed_after_50ms(factor) == pytest.approx(expected, rel=1e-4)


def test_overcurrent_trips_0x2310_and_blocks_gates():
    drive = make_drive(CONFIG, seed=0, noise=False)
    drive.set_enabled(True)
    drive.set_speed_ref(50.0)
    drive.step(2000)
    drive.set_plant_param("plant_ls", 0.1)  # current-loop gain now 10x the plant's: it oscillates and grows
    block = drive.step(2000)
    assert drive.fault_code() == 0x2310
    tripped = np.argmax(np.abs(block[:, COL["u_sy_v"]]) == 0.0)
    assert tripped > 0
    assert np.all(block[tripped + 2:, COL["i_sx_a"]] == 0.0) and np.all(block[tripped + 2:, COL["i_sy_a"]] == 0.0)
    drive.reset_fault()
    assert drive.fault_code() == 0


def test_position_offset_hook_is_one_shot():
    drive = make_drive(CONFIG, seed=0, noise=False)
    drive.set_hook("pos_est_offset_rad", 1.0)
    block = drive.step(3)
    assert np.all(block[:, COL["pos_err_elec_rad"]] == pytest.approx(-1.0))
    assert block[0, COL["pos_est_elec_rad"]] == pytest.approx(1.0)


def test_make_drive_errors_name_file_and_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[motor]\nkind = "bldc"\n')
    with pytest.raises(InputError, match=r"bad\.toml: \[motor\] kind"):
        make_drive(bad)
    cfg = load_motor_config(CONFIG)
    del cfg["plant"]["rs_ohm"]
    with pytest.raises(InputError, match=r"\[plant\] rs_ohm: missing"):
        make_drive(cfg)
    cfg = load_motor_config(CONFIG)
    cfg["firmware"]["flux_est_kp"] = "fast"
    with pytest.raises(InputError, match=r"\[firmware\] flux_est_kp: expected a number"):
        make_drive(cfg)
    with pytest.raises(InputError, match=r"\(file\): not found"):
        make_drive(tmp_path / "missing.toml")


def test_every_config_value_has_a_source_comment():
    for line in open(CONFIG, encoding="utf-8"):
        line = line.strip()
        if "=" in line and not line.startswith("#"):
            comment = line.split("#", 1)[1] if "#" in line else ""
            assert "paper" in comment or "chosen" in comment, line
