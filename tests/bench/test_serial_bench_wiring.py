"""Bench config -> links -> in-process serial + Modbus services, with the PMSM paper drive behind them."""

from pathlib import Path

import pytest

from bench.inputs.benchconfig import load_bench_config
from bench.run.links import make_links, started_services
from drivers.contract.load_map import LoadMode

ROOT = Path(__file__).resolve().parents[2]


def test_serial_bench_config_is_valid():
    cfg = load_bench_config(ROOT / "config/benches/sim-pmsm-serial.toml")
    assert cfg.drive["transport"] == "serial" and cfg.drive["port"].startswith("socket://127.0.0.1:")
    assert cfg.load["transport"] == "modbus-tcp"


def test_pmsm_drive_over_serial_and_modbus_services(tmp_path):
    text = (ROOT / "config/benches/sim-pmsm-serial.toml").read_text()
    text = text.replace("[drive]", '[services]\nstart = "sim_backend.rig:start"\n\n[drive]', 1)
    path = tmp_path / "bench.toml"
    text = text.replace('motor = "config/motors/', f'motor = "{ROOT}/config/motors/')
    path.write_text(text.replace("sync_period_s = 0.01 ", "sync_period_s = 0.001"))  # 1 ms SYNC: 300 -> 0.3 s
    cfg = load_bench_config(path)
    with started_services(cfg, seed=3) as live:
        drive, load = make_links(live, ROOT)
        identity = drive.open()
        assert identity.product_code == 0x04020001 and identity.has_trace_recorder   # same identity as over CAN
        assert load.open() == "drivebench-sim load machine"
        drive.configure(["speed_est_mech_rad_s", "speed_true_mech_rad_s"], ["speed_true_mech_rad_s"], 1)
        load.set_load(LoadMode.TORQUE, 0.5)
        load.enable(True)
        drive.set_speed_ref(2.0)
        drive.enable_velocity_mode()
        samples = [s for _ in range(300) for s in drive.sync()]
        fb = load.feedback()
        trace = drive.fetch_trace()
        load.zero_and_disable()
        drive.disable()
        drive.close()
        load.close()
    assert samples[-1].t_s == pytest.approx(300 * cfg.drive["sync_period_s"])
    assert fb.torque_nm == pytest.approx(0.5) and fb.enabled
    assert fb.speed_mech_rad_s == pytest.approx(samples[-1].values["speed_true_mech_rad_s"], abs=1e-4)
    assert len(trace["t_s"]) == 3000
    assert trace["speed_true_mech_rad_s"][-1] == pytest.approx(samples[-1].values["speed_true_mech_rad_s"],
                                                               rel=1e-6, abs=1e-6)
