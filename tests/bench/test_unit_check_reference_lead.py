"""The first-motion unit check against a reference reading that is not stale yet still shows the shaft earlier than
the drive's sample (issue 32 item 5; the e35 false unit_mismatch of the strict benchmark under load): deterministic,
the way a real-time run feeds it, no load needed."""

from __future__ import annotations

import pytest

from bench.run.supervisor import UnitCheck

PERIOD_S = 0.01
READ_EVERY = 3          # a loaded bench: the dynamometer read once per batch of three SYNC answers (ages 0, 10, 20 ms)
REGISTER_LAG_S = 0.01   # the dynamometer's 100 Hz speed register: up to one period behind the shaft


def shaft(t: float) -> float:
    """At rest until 50 ms, then 100 rad/s^2 (a sensorless start breaking away) up to 20 rad/s."""
    return min(max(0.0, t - 0.05) * 100.0, 20.0)


def real_time_check() -> UnitCheck:
    # as bench.run.run_arming arms it in real time at a 10 ms SYNC period
    return UnitCheck(skew_s=2 * PERIOD_S, stale_s=0.03)


def run(check: UnitCheck, k: float = 1.0, samples: int = 400):
    """The drive reports k x the shaft at each SYNC (k != 1: a unit error); each sample gets the last reading taken at
    or before it, with its age, as bench.run.run_steps._reference_at gives it."""
    read_t = 0.0
    for n in range(1, samples):
        t = n * PERIOD_S
        if n % READ_EVERY == 0:
            read_t = t
        values = {"speed_est_mech_rad_s": k * shaft(t),
                  "speed_true_mech_rad_s": shaft(read_t - REGISTER_LAG_S),
                  "reference_age_s": t - read_t}
        trip = check.check(t, values)
        if trip is not None:
            return trip
    return None


def test_a_reading_20_ms_old_at_first_motion_is_no_unit_error():
    """The reading is younger than stale_s, so it is judged; at first motion it still shows the shaft at rest while
    the correct drive already reports 2-3 rad/s. Judging the drive's speed of that instant against it (the old gross
    test) tripped unit_mismatch at ~70 ms; the drive's speeds over the reading's span include the shaft's."""
    check = real_time_check()
    seen = []
    read_t = 0.0
    for n in range(1, 12):          # the condition itself: a fresh-enough reading of the shaft at rest, drive moving
        t = n * PERIOD_S
        read_t = t if n % READ_EVERY == 0 else read_t
        seen.append((shaft(t), shaft(read_t - REGISTER_LAG_S), t - read_t))
    assert any(est > 1.5 and true < 0.01 and age < check.stale_s for est, true, age in seen), seen
    assert run(check) is None
    assert check.done and check.skipped_stale == 0 and check.judged > 50


@pytest.mark.parametrize("k", [10.0, 0.1, 1.5, 1 / 1.5, 1.1, 1 / 1.1])
def test_a_wrong_unit_still_trips_with_the_reading_lagging(k):
    trip = run(real_time_check(), k=k)
    assert trip is not None and trip.reason == "unit_mismatch", trip
    assert "reference reading" in trip.message and "velocity_side" in trip.message
    if k in (10.0, 0.1):
        assert trip.t_s < 0.15, trip.message          # within a few SYNCs of first motion (t = 50 ms)
    else:
        assert trip.t_s < 2.5, trip.message           # 1.1: ~1.7 s, the check judging past 20 rad (the age)


def test_lockstep_judges_the_sample_alone():
    """No skew, a fresh reading: the span is the sample itself, so a 10x error trips on the second sample of first
    motion as before."""
    check = UnitCheck()
    trips = [check.check(n * PERIOD_S, {"speed_est_mech_rad_s": 10 * shaft(n * PERIOD_S),
                                        "speed_true_mech_rad_s": shaft(n * PERIOD_S), "reference_age_s": 0.0})
             for n in range(1, 10)]
    first = next(i for i, tr in enumerate(trips, 1) if tr is not None)
    assert trips[first - 1].reason == "unit_mismatch" and first * PERIOD_S <= 0.08
