import numpy as np
import pytest

from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract.trace_format import decode_rows, mask_for
from drivers.contract.cia402 import State
from sim_backend.cia402_device import Cia402Device
from sim_backend.trace import TRIGGER_ON_ENABLE, TraceRecorder


def test_enable_sequence_statuswords():
    dev = Cia402Device()
    assert dev.statusword & 0x6F == 0x40
    for cw, state, sw in [(0x06, State.READY_TO_SWITCH_ON, 0x21), (0x07, State.SWITCHED_ON, 0x23),
                          (0x0F, State.OPERATION_ENABLED, 0x27)]:
        dev.write_controlword(cw)
        assert dev.state is state
        assert dev.statusword & 0x6F == sw
    assert dev.power_enabled


def test_quick_stop_then_disable_voltage():
    dev = Cia402Device(state=State.OPERATION_ENABLED)
    dev.write_controlword(0x02)
    assert dev.state is State.QUICK_STOP_ACTIVE and dev.statusword & 0x6F == 0x07
    dev.write_controlword(0x00)
    assert dev.state is State.SWITCH_ON_DISABLED and not dev.power_enabled


def test_fault_needs_rising_edge_reset_and_cleared_cause():
    dev = Cia402Device(state=State.OPERATION_ENABLED)
    dev.fault(0x2310)
    assert dev.statusword & 0x4F == 0x08 and not dev.power_enabled
    dev.write_controlword(0x80, fault_active=True)
    assert dev.state is State.FAULT
    dev.write_controlword(0x00)
    dev.write_controlword(0x80, fault_active=False)
    assert dev.state is State.SWITCH_ON_DISABLED and dev.error_code == 0


def test_trace_decimation_ring_and_roundtrip():
    rec = TraceRecorder(capacity_rows=8)
    names = ["speed_est_mech_rad_s", "i_sy_a"]
    mask = mask_for(names)
    rec.configure(mask, decimation=2)
    rec.start()
    block = np.arange(20 * len(SIGNAL_NAMES), dtype=float).reshape(20, len(SIGNAL_NAMES))
    rec.push(first_step=100, block=block, enabled=True)
    assert rec.rows_available == 8 and rec.lost_rows == 2          # 10 decimated rows, ring of 8
    cols = decode_rows(rec.read(5), mask, control_period_s=1e-4)
    np.testing.assert_allclose(cols["t_s"], np.array([104, 106, 108, 110, 112]) * 1e-4)
    np.testing.assert_array_equal(cols["i_sy_a"], block[[4, 6, 8, 10, 12], SIGNAL_NAMES.index("i_sy_a")])
    assert rec.rows_available == 3
    with pytest.raises(ValueError):
        decode_rows(b"\x00" * 5, mask, 1e-4)


def test_trace_waits_for_enable_trigger():
    rec = TraceRecorder(capacity_rows=100)
    rec.configure(mask_for(["speed_est_mech_rad_s"]), decimation=1, trigger=TRIGGER_ON_ENABLE)
    rec.start()
    rec.push(0, np.zeros((5, len(SIGNAL_NAMES))), enabled=False)
    assert rec.rows_available == 0
    rec.push(5, np.zeros((5, len(SIGNAL_NAMES))), enabled=True)
    assert rec.rows_available == 5


def test_standstill_wait_is_bounded_in_drive_time_too():
    """A frozen speed estimate never reaches standstill: in lockstep the wait ends after stop_timeout_s of drive time
    (max_advances SYNCs), long before the wall-clock bound, so the drive's trace recorder cannot overrun."""
    from drivers.contract import cia402

    advances = []
    report = cia402.wait_standstill(lambda: advances.append(1), lambda: 12.0, 0.5, timeout_s=30.0, max_advances=500)
    assert len(advances) == 500 and report["standstill"] is False and report["wait_s"] < 5.0
    speeds = iter([8.0, 3.0, 0.2, 0.1])
    advances.clear()
    report = cia402.wait_standstill(lambda: advances.append(1), lambda: next(speeds), 0.5, timeout_s=30.0, max_advances=500)
    assert len(advances) == 3 and report["standstill"] is True and report["speed_at_disable_mech_rad_s"] == 0.2


def test_standstill_wait_ends_when_the_drive_ends_its_quick_stop_itself():
    """After a unit trip the drive's speed, through the bench's wrong factor, may never read below 0.5 rad/s (here a
    frozen 12): the drive's own SWITCH ON DISABLED (0x605A 1-3: stopped by its judgement) ends the wait; a link error
    while asking ends it too, without a standstill claimed."""
    from drivers.contract import cia402
    from drivers.contract.errors import LinkError

    advances = []
    report = cia402.wait_standstill(lambda: advances.append(1), lambda: 12.0, 0.5, timeout_s=30.0, max_advances=500,
                                    stopped=lambda: len(advances) >= 3)
    assert len(advances) == 3 and report["standstill"] is True and "SWITCH ON DISABLED" in report["by"]

    def dead() -> bool:
        raise LinkError("node 1: SDO timeout")

    advances.clear()
    report = cia402.wait_standstill(lambda: advances.append(1), lambda: 12.0, 0.5, timeout_s=30.0, max_advances=500,
                                    stopped=dead)
    assert len(advances) == 1 and report["standstill"] is False and "by" not in report
