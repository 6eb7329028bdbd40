"""The bench's CANopen link against the simulated node, in process on a private virtual channel."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from drivers.contract.errors import LinkError
from drivers.contract.extension import FIRMWARE_VERSION
from drivers.contract.extension import PRODUCT_CODES, VENDOR_ID
from tests.canopen_helpers import EDS, rig

LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a"]
TRACE = ["speed_est_mech_rad_s", "torque_load_nm"]


def test_identity_and_software_version_come_from_the_drive():
    with rig() as r:
        ident = r.link.identity
        assert (ident.vendor_id, ident.product_code) == (VENDOR_ID, PRODUCT_CODES["pmsm"])
        assert ident.firmware_version == FIRMWARE_VERSION
        assert ident.device_name == "drivebench simulated PMSM drive"
        assert ident.has_trace_recorder


def test_enable_lockstep_sync_and_speed_follows_reference():
    with rig() as r:
        r.link.configure(LIVE, TRACE, 1)
        r.link.enable_velocity_mode()
        assert r.link.status().state == "OPERATION ENABLED"
        r.link.set_speed_ref(100.0)
        times = []
        for _ in range(30):
            samples = r.link.sync()
            assert len(samples) == 1          # lockstep: exactly this SYNC's sample
            times.append(samples[0].t_s)
        # each SYNC advances the drive clock by exactly one sync period (100 control steps of 100 us)
        assert np.allclose(np.diff(times), 0.01)
        assert r.device.step_count == 3000
        expected = 100.0 * (1 - (1 - 1e-4 / 0.05) ** 3000)   # ToyDrive's first-order lag
        assert samples[-1].values["speed_est_mech_rad_s"] == pytest.approx(expected, rel=1e-5)
        assert samples[-1].values["speed_ref_mech_rad_s"] == 100.0
        assert r.toy._ref == 100.0


def test_trace_upload_is_full_rate_and_matches_the_live_stream():
    with rig() as r:
        r.link.configure(LIVE, TRACE, 1)
        r.link.enable_velocity_mode()
        r.link.set_speed_ref(50.0)
        r.device.set_load(0, 2.5, True)
        live = [s for _ in range(20) for s in r.link.sync()]
        first = r.link.fetch_trace()
        live += [s for _ in range(10) for s in r.link.sync()]
        second = r.link.fetch_trace()
        t = np.concatenate([first["t_s"], second["t_s"]])
        assert len(t) == 3000                              # every control period, nothing lost or repeated
        assert np.allclose(np.diff(t), 1e-4)
        speed = np.concatenate([first["speed_est_mech_rad_s"], second["speed_est_mech_rad_s"]])
        for sample in live:                                # the trace row at the live sample's drive time
            k = int(round(sample.t_s / 1e-4)) - int(round(t[0] / 1e-4))
            assert speed[k] == pytest.approx(sample.values["speed_est_mech_rad_s"], rel=1e-6)
        assert np.all(second["torque_load_nm"] == pytest.approx(2.5))
        assert r.link.fetch_trace()["t_s"].size == 0       # nothing new since


def test_trace_decimation_is_configured_on_the_drive():
    with rig() as r:
        r.link.configure(LIVE, TRACE, 10)
        for _ in range(10):
            r.link.sync()
        trace = r.link.fetch_trace()
        assert len(trace["t_s"]) == 100
        assert np.allclose(np.diff(trace["t_s"]), 1e-3)


def test_write_parameter_reaches_the_model_by_eds_name():
    with rig() as r:
        r.link.write_parameter("flux_est_scale", 0.5)
        r.link.write_parameter("plant_rs", 1.25)
        assert r.toy.hooks["flux_est_scale"] == 0.5
        assert r.toy.plant_factors["plant_rs"] == 1.25
        with pytest.raises(LinkError, match="no parameter named 'no_such_thing'"):
            r.link.write_parameter("no_such_thing", 1.0)
        with pytest.raises(LinkError, match="not a manufacturer object"):
            r.link.write_parameter("Controlword", 15)
        with pytest.raises(LinkError, match="read-only"):
            r.link.write_parameter("speed_est_mech_rad_s", 1.0)


def test_fault_gives_emcy_and_fault_state_then_reset_once_reenables():
    with rig() as r:
        r.link.configure(LIVE, TRACE, 1)
        r.link.enable_velocity_mode()
        r.link.sync()
        r.toy.raise_fault(0x2310)
        r.link.sync()
        status = r.link.status()
        assert status.state == "FAULT" and status.fault
        assert [code for code, _ in status.emcy] == [0x2310]
        assert "Current" in status.emcy[0][1]
        assert r.link.status().emcy == []                  # drained
        r.toy.reset_fault()
        r.link.enable_velocity_mode()                      # fault_reset policy "once"
        assert r.link.status().state == "OPERATION ENABLED"


def test_fault_reset_policy_never_refuses_to_enable_a_faulted_drive():
    with rig(fault_reset="never") as r:
        r.link.configure(LIVE, TRACE, 1)
        r.toy.raise_fault(0x3210)
        r.link.sync()
        with pytest.raises(LinkError, match="FAULT"):
            r.link.enable_velocity_mode()


def test_quick_stop_waits_for_standstill_before_the_power_stage_goes_off():
    """The safe stop brakes to standstill first (quick stop option 0x605A = 2: the drive stops on its ramp, then
    switches itself off); the power stage is never cut at speed, and disable leaves the drive disabled."""
    with rig() as r:
        r.link.configure(LIVE, TRACE, 1)
        r.link.enable_velocity_mode()
        r.link.set_speed_ref(30.0)
        for _ in range(60):
            r.link.sync()
        assert abs(r.toy.load_feedback()[0]) > 10.0
        r.link.quick_stop()
        stop = r.link.report["stop"]
        assert stop["standstill"] and stop["speed_at_disable_mech_rad_s"] <= 0.5 and stop["wait_s"] > 0
        assert r.device.device.state.name == "SWITCH_ON_DISABLED"       # 0x605A = 2: off by itself at standstill
        assert abs(r.toy.load_feedback()[0]) <= 0.5
        r.link.disable()
        assert r.link.status().state == "SWITCH ON DISABLED"
        assert not r.device.device.power_enabled


def test_quick_stop_option_that_holds_quick_stop_active():
    """With 0x605A = 6 the drive stays in QUICK STOP ACTIVE after stopping; the bench's disable ends it."""
    with rig() as r:
        r.link.sdo.write(0x605A, 0, 6)
        r.link.configure(LIVE, TRACE, 1)
        r.link.enable_velocity_mode()
        r.link.quick_stop()
        assert r.link.status().state == "QUICK STOP ACTIVE" and r.device.device.power_enabled
        r.link.disable()
        assert r.link.status().state == "SWITCH ON DISABLED" and not r.device.device.power_enabled


def test_lost_heartbeat_is_detected_within_the_timeout():
    with rig(heartbeat_timeout_s=0.3) as r:          # producer heartbeat set to 75 ms by the link
        r.link.configure(LIVE, TRACE, 1)
        assert r.link.status().heartbeat_ok
        r.node.stop_heartbeat()
        stopped = time.monotonic()
        while r.link.status().heartbeat_ok:
            assert time.monotonic() - stopped < 0.3 + 0.5, "lost heartbeat not noticed"
            time.sleep(0.01)
        assert time.monotonic() - stopped >= 0.3 - 0.08   # not before the last heartbeat's timeout
        with pytest.raises(LinkError, match="no heartbeat for more than 0.3 s"):
            r.link.sync()


def test_unknown_sdo_index_is_a_clear_link_error():
    with rig() as r:
        with pytest.raises(LinkError, match=r"0x5FFF:00 aborted with 0x06020000"):
            r.link.sdo_upload(0x5FFF)


@pytest.mark.slow
def test_sync_without_answer_times_out():
    with rig(sdo_timeout_s=0.3, heartbeat_timeout_s=30.0) as r:
        r.link.configure(LIVE, TRACE, 1)
        r.node.stop()
        started = time.monotonic()
        with pytest.raises(LinkError, match="no TPDOs for SYNC within 2 s"):
            r.link.sync()
        assert 2.0 <= time.monotonic() - started < 4.0


@pytest.mark.slow
def test_sdo_timeout_names_the_object():
    with rig(sdo_timeout_s=0.2, heartbeat_timeout_s=30.0) as r:
        r.node.stop()
        with pytest.raises(LinkError, match=r"0x6041:00 \(Statusword\).*No SDO response"):
            r.link.enable_velocity_mode()


def _eds_without_recorder(tmp_path):
    text = EDS.read_text()
    out, skip = [], False
    for line in text.splitlines():
        if line.startswith("["):
            skip = line[1:5] in ("2100", "2101")
        if not skip and not (line.split("=")[-1] in ("0x2100", "0x2101") and line[0].isdigit()):
            out.append(line)
    path = tmp_path / "third-party.eds"
    path.write_text("\n".join(out))
    return path


def test_drive_without_trace_recorder_is_detected_by_sdo_abort(tmp_path):
    # the bench's EDS lists the recorder, the drive does not have it: the probe's SDO abort decides
    with rig(node_eds=_eds_without_recorder(tmp_path)) as r:
        assert r.link.identity.has_trace_recorder is False
        r.link.configure(LIVE, TRACE, 1)
        r.link.sync()
        assert r.link.fetch_trace() is None


def test_drive_without_trace_recorder_in_its_eds(tmp_path):
    eds = _eds_without_recorder(tmp_path)
    with rig(node_eds=eds, eds=str(eds)) as r:
        assert r.link.identity.has_trace_recorder is False
        assert r.link.fetch_trace() is None


def test_realtime_mode_samples_are_continuous_on_the_drive_clock():
    with rig(timing="realtime", sync_period_s=0.002) as r:
        r.link.configure(LIVE, TRACE, 1)
        r.link.enable_velocity_mode()
        r.link.set_speed_ref(10.0)
        samples = []
        deadline = time.monotonic() + 10.0
        while len(samples) < 100:
            assert time.monotonic() < deadline
            samples += r.link.sync()
            time.sleep(0.01)                  # the bench's pacing; SYNC runs on its own thread
        steps = np.round(np.array([s.t_s for s in samples]) / 1e-4).astype(int)
        assert np.all(np.diff(steps) == 20)   # one sample per SYNC, none lost, none repeated


def test_live_signals_fall_back_to_scaled_integers_when_real32_exceeds_the_bus():
    from drivers.contract.signals import SIGNAL_NAMES
    with rig(sync_period_s=0.001) as r:
        r.link.configure(list(SIGNAL_NAMES), TRACE, 1)   # 16 x REAL32 at 1 kHz would need >100 %
        assert r.link.live_encoding == "scaled"
        assert r.link.live_bus_load_pct <= 80.0
        r.link.enable_velocity_mode()
        r.link.set_speed_ref(100.0)
        for _ in range(50):
            samples = r.link.sync()
        values = samples[-1].values
        assert set(values) == set(SIGNAL_NAMES)
        assert values["speed_est_mech_rad_s"] == pytest.approx(r.device.latest[1], abs=0.025)
        assert values["vdc_v"] == pytest.approx(560.0, abs=0.05)
        assert math.isclose(values["flux_est_wb"], 0.26, abs_tol=1e-4)
    with rig(sync_period_s=0.0002) as r:
        with pytest.raises(LinkError, match="budget 80%"):
            r.link.configure(list(SIGNAL_NAMES), TRACE, 1)


def test_inprocess_service_opens_private_endpoints():
    from bench.inputs.benchconfig import link_settings, load_bench_config
    from drivers.canopen.link import CanopenDriveLink
    from sim_backend.rig import start
    from tests.canopen_helpers import REPO
    import socket

    cfg = load_bench_config(REPO / "config/benches/sim-pmsm.toml")
    with start(cfg.as_dict(), seed=3) as first, start(cfg.as_dict(), seed=3) as second:
        assert first["drive"]["channel"] != second["drive"]["channel"]      # parallel runs never cross-talk
        link = CanopenDriveLink(dict(cfg.drive, **first["drive"], sync_period_s=0.01), REPO, link_settings(cfg))
        try:
            assert link.open().product_code == 0x04020001
            link.configure(LIVE, TRACE, 10)
            assert link.sync()[0].t_s == pytest.approx(0.01)
        finally:
            link.close()
        socket.create_connection(("127.0.0.1", first["load"]["port"]), timeout=5).close()


@pytest.mark.slow
def test_block_upload_that_stalls_times_out_with_a_clear_error():
    with rig(sdo_timeout_s=0.3) as r:
        r.link.configure(LIVE, TRACE, 1)
        r.link.sync()
        r.node.node.sdo._send_block = lambda: None          # the server goes quiet after "start upload"
        started = time.monotonic()
        with pytest.raises(LinkError, match=r"block upload of 0x2101:00: block segments stopped arriving"):
            r.link.fetch_trace()
        assert time.monotonic() - started < 4.0
