"""Stopping: quick stop with each option code the drive takes (0x605A), halt (controlword bit 8, 0x605D), and the
drive's own reaction to losing the bench (CiA 301 heartbeat consumer 0x1016 + CiA 402 0x6007), each measured.

Stop time and distance are measured on the reference sensor (the shaft, not the drive's report of itself).
"""

from __future__ import annotations

import time

from drivers.conformance.motion import HALT_BIT, Context
from drivers.conformance.port import ObjectAbort
from drivers.conformance.result import TestResult
from drivers.contract import objects as o
from drivers.contract.cia402 import State, decode, state_name

S = State
QUICK_STOP_CODES = (1, 2, 3, 5, 6, 7)          # 0: coast (power off at once), 4/8: current/voltage limit
TO_DISABLED = (1, 2, 3)                          # then SWITCH ON DISABLED; 5-7: stay in QUICK STOP ACTIVE
LATE_WATCH_S = 1.0
MARGIN_MS = 100
SETTLE_S = 0.5               # after standstill on the reference sensor, the drive's own standstill judgement


def _at_speed(ctx: Context, r: TestResult, what: str) -> bool:
    if ctx.enable() is not S.OPERATION_ENABLED:
        r.check(f"{what}: enable", "OPERATION ENABLED", state_name(ctx.statusword()), False)
        return False
    reached, speed = ctx.run_to(ctx.settings.test_speed_mech_rad_s)
    if not reached:
        r.check(f"{what}: reach {ctx.settings.test_speed_mech_rad_s:g} rad/s on the reference sensor", "reached",
                f"{speed} rad/s", False)
    return reached


def quick_stop_options(ctx: Context, r: TestResult) -> None:
    original = ctx.optional(o.QUICK_STOP_OPTION, signed=True)
    if original is None:
        r.note("no 0x605A (quick stop option code): the drive's quick stop is its own; tested as it is")
    codes = QUICK_STOP_CODES if original is not None else (None,)
    refused = []
    try:
        for code in codes:
            if code is not None:
                try:
                    ctx.port.write(o.QUICK_STOP_OPTION, 0, code, 2, signed=True)
                except ObjectAbort as exc:
                    refused.append(f"{code} (0x{exc.code:08X})")
                    continue
            if not _at_speed(ctx, r, f"0x605A = {code}"):
                ctx.safe_end()
                continue
            ctx.port.set_command(controlword=0x02)
            stop = ctx.measure_stop(done=lambda: decode(ctx.statusword()) is not State.OPERATION_ENABLED)
            end = ctx.state()
            for _ in range(round(SETTLE_S / ctx.period_s)):     # options 1-3: SWITCH ON DISABLED once it sees rest
                if end is not S.QUICK_STOP_ACTIVE or code not in TO_DISABLED:
                    break
                ctx.cycle()
                end = ctx.state()
            r.measured[f"0x605A={code}"] = stop
            expected = (S.SWITCH_ON_DISABLED if code in TO_DISABLED else S.QUICK_STOP_ACTIVE) if code else None
            r.check(f"quick stop, 0x605A = {code}: standstill on {ctx.reference_name}",
                    f"within {ctx.settings.stop_timeout_s:g} s",
                    f"{stop['stop_time_s']} s, {stop['stop_distance_rad']} rad",
                    stop["standstill"], None if stop["stop_time_s"] is None else stop["stop_time_s"] * 1e3)
            r.check(f"quick stop, 0x605A = {code}: state at standstill",
                    expected.label if expected else "QUICK STOP ACTIVE or SWITCH ON DISABLED",
                    end.label if end else "?", end is expected if expected else end in (S.QUICK_STOP_ACTIVE,
                                                                                      S.SWITCH_ON_DISABLED))
            ctx.wait_rest()                  # 5-7: the drive holds zero; the power goes off at rest, not coasting
            ctx.command(0x00, {S.SWITCH_ON_DISABLED})
    finally:
        if original is not None:
            ctx.port.write(o.QUICK_STOP_OPTION, 0, original, 2, signed=True)
    if refused:
        r.measured["refused_codes"] = refused
        r.check("0x605A codes refused (a drive need not have them all)", "observed", ", ".join(refused), None)


def halt(ctx: Context, r: TestResult) -> None:
    option = ctx.optional(0x605D, signed=True)
    r.measured["halt_option_0x605D"] = option if option is not None else "not on this drive"
    if not _at_speed(ctx, r, "halt"):
        return
    ctx.port.set_command(controlword=0x0F | HALT_BIT)
    stop = ctx.measure_stop()
    state = ctx.state()
    r.measured["stop"] = stop
    r.check("halt (0x6040 bit 8): standstill on the reference sensor", f"within {ctx.settings.stop_timeout_s:g} s",
            f"{stop['stop_time_s']} s, {stop['stop_distance_rad']} rad", stop["standstill"],
            None if stop["stop_time_s"] is None else stop["stop_time_s"] * 1e3)
    r.check("halt: state", "stays OPERATION ENABLED", state.label if state else "?", state is S.OPERATION_ENABLED)
    ctx.port.set_command(target=0)
    ctx.port.set_command(controlword=0x0F)       # halt released at target 0: the shaft stays at rest
    for _ in range(10):
        ctx.cycle()
    speed = ctx.speed()
    r.check("halt released with target 0", "shaft stays at rest", f"{speed} rad/s",
            speed is not None and abs(speed) <= ctx.settings.standstill_mech_rad_s)


def comm_loss_reaction(ctx: Context, r: TestResult) -> None:
    """Enabled at zero speed; the bench's liveness withheld; the drive must leave OPERATION ENABLED within its
    consumer time + margin (0x6007 reaction)."""
    consumer = ctx.settings.consumer_time_ms
    option = ctx.optional(o.ABORT_CONNECTION_OPTION, signed=True)
    r.measured["abort_connection_0x6007"] = option if option is not None else "not on this drive"
    if option is None:
        r.fail("no 0x6007 (abort connection option code): the drive's reaction to a lost master is not defined")
    else:
        ctx.port.write(o.ABORT_CONNECTION_OPTION, 0, ctx.settings.abort_option, 2, signed=True)
    try:
        r.measured.update(ctx.port.arm_liveness(consumer))
    except ObjectAbort as exc:
        r.fail(f"the drive refuses a consumer heartbeat time ({exc}): it cannot watch the bench")
        return
    if ctx.enable() is not S.OPERATION_ENABLED:
        r.check("enable at zero speed", "OPERATION ENABLED", state_name(ctx.statusword()), False)
        return
    ctx.port.take_emcy()
    nmt_before, _ = ctx.port.drive_liveness()
    withheld = time.monotonic()
    ctx.port.withhold_liveness()
    left_s = None
    deadline = withheld + (consumer + MARGIN_MS) / 1000.0 + LATE_WATCH_S
    while time.monotonic() < deadline:
        if ctx.state() is not S.OPERATION_ENABLED:
            left_s = time.monotonic() - withheld
            break
        time.sleep(0.005)
    time.sleep(0.05)
    emcy = ctx.port.take_emcy()
    nmt_after, heard = ctx.port.drive_liveness()
    ctx.port.resume_liveness()
    time.sleep(0.02)
    ctx.port.network_operational()
    r.measured.update(consumer_time_ms=consumer, left_operation_enabled_ms=None if left_s is None else
                      round(left_s * 1e3, 1), emcy=[f"0x{c:04X}" for c, _ in emcy], state_after=state_name(
                          ctx.statusword()), nmt_before=nmt_before, nmt_after=nmt_after if heard > withheld else None)
    r.check("0x1016 heartbeat lost: leaves OPERATION ENABLED", f"within {consumer} + {MARGIN_MS} ms",
            "stayed OPERATION ENABLED" if left_s is None else f"after {left_s * 1e3:.0f} ms",
            left_s is not None and left_s * 1e3 <= consumer + MARGIN_MS, None if left_s is None else left_s * 1e3)
    r.check("EMCY 0x8130 (heartbeat error)", "sent", ", ".join(r.measured["emcy"]) or "none",
            any(c == o.EMCY_HEARTBEAT for c, _ in emcy) or None)
    if ctx.state() in (S.FAULT, S.FAULT_REACTION_ACTIVE):
        ctx.command(0x00, {S.FAULT})
        ctx.command(0x80, {S.SWITCH_ON_DISABLED})
        ctx.port.set_command(controlword=0x00)
