"""Safety supervisor: every limit trips with what/when/values; the safe stop runs once."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import pytest

from bench.run.supervisor import SafeStop, Supervisor, check_sample, check_status
from drivers.api import DriveStatus, LiveSample
from tests.fakes import SAFE_STOP, FakeRig


@dataclass
class Limits:
    overspeed_mech_rad_s: float = 100.0
    overcurrent_a: float = 10.0
    max_duration_s: float = 5.0
    pos_err_max_elec_rad: float | None = 0.5
    vdc_max_v: float | None = 700.0


OK = {"speed_true_mech_rad_s": 50.0, "speed_est_mech_rad_s": 50.0, "i_sx_a": 1.0, "i_sy_a": -2.0,
      "pos_err_elec_rad": 0.1, "vdc_v": 560.0}


@pytest.mark.parametrize(
    "change, reason",
    [
        ({"speed_true_mech_rad_s": -100.5}, "overspeed"),
        ({"speed_est_mech_rad_s": 101.0}, "overspeed"),     # estimated speed is judged too
        ({"i_sx_a": 10.5}, "overcurrent"),
        ({"i_sy_a": -11.0}, "overcurrent"),
        ({"pos_err_elec_rad": -0.6}, "position_error"),
        ({"vdc_v": 720.0}, "dc_link_overvoltage"),
    ],
)
def test_each_limit_trips_with_values(change, reason):
    values = {**OK, **change}
    trip = check_sample(Limits(), 1.25, values)
    assert trip is not None and trip.reason == reason
    assert trip.t_s == 1.25
    name, value = next(iter(change.items()))
    assert trip.values[name] == value
    assert "t=1.2500 s" in trip.message


def test_within_limits_and_optional_limits():
    assert check_sample(Limits(), 1.0, OK) is None
    relaxed = Limits(pos_err_max_elec_rad=None, vdc_max_v=None)
    assert check_sample(relaxed, 1.0, {**OK, "pos_err_elec_rad": 3.0, "vdc_v": 5000.0}) is None
    assert check_sample(Limits(), 1.0, {"speed_est_mech_rad_s": float("nan")}) is None  # NaN is not a value


def test_wall_clock_limit_trips_without_any_sample():
    sup = Supervisor(Limits(max_duration_s=0.1)).start()
    try:
        assert sup.tripped.wait(2.0)
        assert sup.trip.reason == "max_duration" and sup.trip.values["wall_s"] > 0.1
    finally:
        sup.stop()


def test_link_status_trips():
    assert check_status(0.1, DriveStatus("OPERATION ENABLED", False, True)) is None
    assert check_status(0.1, DriveStatus("OPERATION ENABLED", False, True, [(0x0000, "error reset")])) is None
    assert check_status(0.1, DriveStatus("FAULT", True, True, [(0x2310, "overcurrent")])).reason == "fault"
    emcy = check_status(0.2, DriveStatus("OPERATION ENABLED", False, True, [(0x3210, "DC-link overvoltage")]))
    assert emcy.reason == "emcy" and "0x3210" in emcy.message
    assert check_status(0.3, DriveStatus("OPERATION ENABLED", False, False)).reason == "heartbeat"


def test_supervisor_thread_trips_once_and_keeps_the_first_trip():
    seen = []
    sup = Supervisor(Limits(), on_trip=seen.append).start()
    try:
        sup.feed([LiveSample(0.001 * k, OK) for k in range(100)])
        sup.feed([LiveSample(0.2, {**OK, "i_sx_a": 12.0})])
        sup.feed([LiveSample(0.3, {**OK, "speed_true_mech_rad_s": 500.0})])
        sup.feed_status(0.4, DriveStatus("FAULT", True, False))
        assert sup.drain()
        assert sup.tripped.is_set()
        assert sup.trip.reason == "overcurrent" and sup.trip.t_s == 0.2
        assert seen == [sup.trip]
    finally:
        sup.stop()
    assert not sup._thread.is_alive()


def test_supervisor_runs_in_its_own_thread():
    threads = []
    sup = Supervisor(Limits(), on_trip=lambda trip: threads.append(threading.current_thread().name)).start()
    try:
        sup.feed([LiveSample(0.1, {**OK, "vdc_v": 800.0})])
        assert sup.tripped.wait(2.0)
        assert threads == ["drivebench-supervisor"]
    finally:
        sup.stop()


def test_safe_stop_runs_once_in_order_even_when_requested_twice():
    rig = FakeRig()
    stop = SafeStop(rig.drive, rig.load)
    assert stop.run() == []
    assert stop.run() == []
    assert rig.names() == SAFE_STOP


def test_safe_stop_requested_from_two_threads_runs_once():
    rig = FakeRig()
    stop = SafeStop(rig.drive, rig.load)
    threads = [threading.Thread(target=stop.run) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert rig.names() == SAFE_STOP


def test_safe_stop_continues_after_a_failing_step():
    rig = FakeRig()

    def broken():
        rig.calls.append(("load.zero_and_disable", ()))
        raise TimeoutError("modbus timeout")

    rig.load.zero_and_disable = broken
    stop = SafeStop(rig.drive, rig.load)
    errors = stop.run()
    assert rig.names() == SAFE_STOP  # the drive is still stopped and disabled
    assert len(errors) == 1 and "modbus timeout" in errors[0]


def test_inline_supervisor_judges_in_the_feeding_thread_at_once_and_the_thread_keeps_the_wall_clock():
    threads = []
    sup = Supervisor(Limits(max_duration_s=0.3), judge_inline=True,
                     on_trip=lambda trip: threads.append(threading.current_thread().name)).start()
    try:
        sup.feed([LiveSample(0.01 * k, OK) for k in range(10)])
        assert not sup.tripped.is_set()
        sup.feed([LiveSample(0.11, {**OK, "i_sy_a": -12.0})])
        assert sup.tripped.is_set()                       # before feed returned: the loop sees it at this SYNC
        assert sup.trip.reason == "overcurrent" and sup.trip.t_s == 0.11
        assert threads == [threading.current_thread().name]
        sup.feed([LiveSample(0.12, {**OK, "vdc_v": 900.0})])
        assert sup.trip.reason == "overcurrent" and len(threads) == 1      # the first trip stays the run's
        assert sup.drain(0.1)
    finally:
        sup.stop()
    wall = Supervisor(Limits(max_duration_s=0.1), judge_inline=True).start()
    try:
        assert wall.tripped.wait(2.0) and wall.trip.reason == "max_duration"
    finally:
        wall.stop()
