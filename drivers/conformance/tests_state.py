"""Connection, identity, modes and the CiA 402 power drive state machine: what a drive must do and must refuse.

Clauses: CiA 301 v4.2 (7.2.8.3.2.1 boot-up, 7.5.2.1 device type 0x1000, 7.5.2.22 identity 0x1018); CiA 402-2 v4
(state machine: states, transitions 2-16 and the controlword commands of 0x6040; 0x6502/0x6060/0x6061 modes).
"""

from __future__ import annotations

import time

from drivers.conformance.motion import Context
from drivers.conformance.port import ObjectAbort
from drivers.conformance.result import TestResult, Timer
from drivers.contract import objects as o
from drivers.contract.cia402 import POWERED_STATES, Mode, State, state_name, supported_modes

S = State
SLOW_BOOT_S = 0.5


def found_state(ctx: Context, r: TestResult) -> None:
    word = ctx.statusword()
    state = ctx.state()
    speed = ctx.speed()
    r.measured.update(state=state_name(word), speed_mech_rad_s=speed)
    turning = speed is not None and abs(speed) > ctx.settings.standstill_mech_rad_s
    if state in POWERED_STATES or turning:
        if state is State.OPERATION_ENABLED:
            ctx.command(0x02, {S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED})
        r.measured["stop"] = ctx.measure_stop()
        r.note(f"drive found {state_name(word)} with the shaft at {speed if speed is not None else float('nan'):.1f} "
               f"rad/s: stopped (quick stop) before any test")
    r.check("state when the suite connected", "a state of the state machine", state_name(word), state is not None)


def boot(ctx: Context, r: TestResult) -> None:
    b = ctx.boot
    r.measured.update(b)
    if b.get("answered_after_s", 0) <= SLOW_BOOT_S:
        r.check("drive up when the suite connected", "SDO answered", f"answered after {b['answered_after_s']} s", True)
        return
    if not b.get("boot_up_seen"):
        r.fail(f"the drive answered only {b['answered_after_s']} s after the suite connected and sent no boot-up "
               f"message (0x700 + node id, data 00): a master cannot tell when it is ready")
        return
    r.note(f"the drive was booting: silent for {b['answered_after_s']} s, then its boot-up message; a bench needs "
           f"boot_timeout_s >= {b['answered_after_s'] * 2:.1f} in [drive]")


def identity(ctx: Context, r: TestResult) -> None:
    device_type = ctx.port.read(o.DEVICE_TYPE)
    r.measured["device_type"] = f"0x{device_type:08X}"
    r.measured.update(ctx.identity)
    r.check("0x1000 device type, profile (low word)", "402", str(device_type & 0xFFFF), device_type & 0xFFFF == 402)
    vendor = ctx.optional(o.IDENTITY, 1)
    r.check("0x1018:01 vendor id", "present, non-zero", "absent" if vendor is None else f"0x{vendor:08X}", bool(vendor))


def modes(ctx: Context, r: TestResult) -> None:
    bits = ctx.optional(o.SUPPORTED_DRIVE_MODES)
    r.measured["supported_modes_0x6502"] = None if bits is None else f"0x{bits:08X}"
    if bits is None:
        r.note("no 0x6502 (supported drive modes): what the drive supports is found by trying 0x6060")
    have = supported_modes(bits) if bits is not None else ()
    original = ctx.optional(o.MODES_OF_OPERATION, signed=True)
    try:
        for mode in (Mode.PROFILE_VELOCITY, Mode.CYCLIC_SYNC_VELOCITY):
            try:
                ctx.port.write(o.MODES_OF_OPERATION, 0, int(mode), 1, signed=True)
                display = ctx.optional(o.MODES_DISPLAY, signed=True)
                answer = f"accepted, 0x6061 = {display}"
                accepted = display == int(mode)
            except ObjectAbort as exc:
                answer, accepted = f"aborted 0x{exc.code:08X}", False
            if bits is None:
                r.check(f"0x6060 = {int(mode)} ({mode.name.lower()})", "observed", answer, None)
                continue
            expected = "accepted and shown in 0x6061" if mode in have else "aborted (not in 0x6502)"
            r.check(f"0x6060 = {int(mode)} ({mode.name.lower()})", expected, answer, accepted == (mode in have))
        if bits is not None and Mode.PROFILE_VELOCITY not in have:
            r.note("no profile velocity (3): only cyclic synchronous velocity, a target with every SYNC (a bench must "
                   "stream it: velocity_mode = \"csv\")")
    finally:
        if original is not None:
            try:
                ctx.port.write(o.MODES_OF_OPERATION, 0, original, 1, signed=True)
            except ObjectAbort as exc:
                r.note(f"0x6060 reads {original} at power-on but refuses it as a write (0x{exc.code:08X})")


# (name, from-sequence, controlword, expected state): CiA 402-2 transitions; the from-sequence starts at SWITCH ON
# DISABLED and is made of transitions already checked
TRANSITIONS = (
    ("T2 shutdown", (), 0x06, S.READY_TO_SWITCH_ON),
    ("T3 switch on", (0x06,), 0x07, S.SWITCHED_ON),
    ("T4 enable operation", (0x06, 0x07), 0x0F, S.OPERATION_ENABLED),
    ("T5 disable operation", (0x06, 0x07, 0x0F), 0x07, S.SWITCHED_ON),
    ("T6 shutdown from SWITCHED ON", (0x06, 0x07), 0x06, S.READY_TO_SWITCH_ON),
    ("T7 disable voltage from READY TO SWITCH ON", (0x06,), 0x00, S.SWITCH_ON_DISABLED),
    ("T8 shutdown from OPERATION ENABLED", (0x06, 0x07, 0x0F), 0x06, S.READY_TO_SWITCH_ON),
    ("T9 disable voltage from OPERATION ENABLED", (0x06, 0x07, 0x0F), 0x00, S.SWITCH_ON_DISABLED),
    ("T10 disable voltage from SWITCHED ON", (0x06, 0x07), 0x00, S.SWITCH_ON_DISABLED),
    ("T11 quick stop from OPERATION ENABLED", (0x06, 0x07, 0x0F), 0x02, None),   # QSA, or SOD at standstill (0x605A)
    ("T12 disable voltage from QUICK STOP ACTIVE", (0x06, 0x07, 0x0F, 0x02), 0x00, S.SWITCH_ON_DISABLED),
)
STEP = {0x06: S.READY_TO_SWITCH_ON, 0x07: S.SWITCHED_ON, 0x0F: S.OPERATION_ENABLED,
        0x02: (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED)}


def _from_disabled(ctx: Context, sequence: tuple[int, ...]) -> bool:
    state, _ = ctx.command(0x00, {S.SWITCH_ON_DISABLED})
    if state is not S.SWITCH_ON_DISABLED:
        return False
    for word in sequence:
        wanted = STEP[word]
        state, _ = ctx.command(word, set(wanted) if isinstance(wanted, tuple) else {wanted})
    return True


def transitions(ctx: Context, r: TestResult) -> None:
    ctx.select_mode()
    option = ctx.optional(o.QUICK_STOP_OPTION, signed=True)
    try:
        if option is not None:                  # 6: the drive stays in QUICK STOP ACTIVE, so T12 and T16 are reachable
            ctx.port.write(o.QUICK_STOP_OPTION, 0, 6, 2, signed=True)
    except ObjectAbort:
        pass
    try:
        _transitions(ctx, r)
        if _from_disabled(ctx, (0x06, 0x07, 0x0F, 0x02)) and ctx.state() is S.QUICK_STOP_ACTIVE:
            state, ms = ctx.command(0x0F, {S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE})
            r.check("T16 enable operation from QUICK STOP ACTIVE (0x605A 5-8; optional)", "observed",
                    state.label if state else "?", None, ms)
        ctx.command(0x00, {S.SWITCH_ON_DISABLED})
    finally:
        if option is not None:
            ctx.port.write(o.QUICK_STOP_OPTION, 0, option, 2, signed=True)


def _transitions(ctx: Context, r: TestResult) -> None:
    for name, sequence, word, expected in TRANSITIONS:
        if not _from_disabled(ctx, sequence):
            r.check(name, "reached its start state", state_name(ctx.statusword()), False)
            continue
        before = ctx.state()
        if word == 0x00 and before is S.SWITCH_ON_DISABLED:     # T12 needs QUICK STOP ACTIVE: 0x605A ended it
            r.check(name, "from QUICK STOP ACTIVE", "the drive ended the quick stop itself (0x605A 1-3)", None)
            continue
        wanted = {expected} if expected else {S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED}
        state, ms = ctx.command(word, wanted)
        r.check(f"{name} (0x6040 = 0x{word:04X})", " or ".join(s.label for s in wanted),
                state.label if state else state_name(ctx.statusword()), state in wanted, ms)


REFUSED = (
    ("enable operation from SWITCH ON DISABLED", (), 0x0F),
    ("switch on from SWITCH ON DISABLED", (), 0x07),
    ("enable operation from SWITCH ON DISABLED, fault-reset bit set", (), 0x8F),
)


def refused_transitions(ctx: Context, r: TestResult) -> None:
    for name, sequence, word in REFUSED:
        _from_disabled(ctx, sequence)
        ctx.port.set_command(controlword=word)
        for _ in range(3):
            ctx.cycle()
        state = ctx.state()
        r.check(f"{name} (0x6040 = 0x{word:04X})", "stays SWITCH ON DISABLED",
                state.label if state else state_name(ctx.statusword()), state is S.SWITCH_ON_DISABLED)
    ctx.command(0x00, {S.SWITCH_ON_DISABLED})


def fault_reset_edge(ctx: Context, r: TestResult) -> None:
    """A fault provoked the standard way (0x6007 = 1 and an NMT stop while enabled); then: enable refused in FAULT,
    fault-reset bit held high (no edge) refused, its rising edge accepted (transition 15)."""
    if ctx.optional(o.ABORT_CONNECTION_OPTION, signed=True) is None:
        r.not_run("needs 0x6007 (abort connection option) to provoke a fault the standard way; the drive has none "
                  "(see comm_loss_reaction)")
        return
    original = ctx.optional(o.ABORT_CONNECTION_OPTION, signed=True)
    ctx.port.write(o.ABORT_CONNECTION_OPTION, 0, 1, 2, signed=True)
    try:
        _fault_and_reset(ctx, r)
    finally:
        ctx.port.write(o.ABORT_CONNECTION_OPTION, 0, original, 2, signed=True)


def _fault_and_reset(ctx: Context, r: TestResult) -> None:
    if ctx.enable() is not S.OPERATION_ENABLED:
        r.check("enable before the fault", "OPERATION ENABLED", state_name(ctx.statusword()), False)
        return
    ctx.port.take_emcy()
    ctx.port.set_command(controlword=0x8F)      # bit 7 high before the fault: its level must not reset it later
    with Timer() as t:
        ctx.port.network_stop()                 # no SDO in NMT STOPPED: the state is read once operational again
        time.sleep(0.05)
        ctx.port.network_operational()
        state, _ = ctx.command(None, {S.FAULT})
    ms = t.ms
    if not r.check("0x6007 = 1 and NMT stop while enabled", "FAULT", state_name(ctx.statusword()), state is S.FAULT,
                   ms):
        return
    r.measured["error_code_0x603F"] = ctx.optional(o.ERROR_CODE)
    r.measured["emcy_with_the_fault"] = [f"0x{c:04X}" for c, _ in ctx.port.take_emcy()]
    for name, word in (("fault-reset bit held high (no rising edge)", 0x8F), ("enable operation in FAULT", 0x0F)):
        ctx.port.set_command(controlword=word)
        ctx.cycle()
        state = ctx.state()
        r.check(f"{name} (0x6040 = 0x{word:04X})", "stays FAULT", state.label if state else "?", state is S.FAULT)
    ctx.port.set_command(controlword=0x00)
    state, ms = ctx.command(0x80, {S.SWITCH_ON_DISABLED})
    r.check("T15 fault reset, rising edge of bit 7 (0x0000 -> 0x0080)", "SWITCH ON DISABLED",
            state.label if state else "?", state is S.SWITCH_ON_DISABLED, ms)
    ctx.cycle()
    r.measured["emcy_after_the_reset"] = [f"0x{c:04X}" for c, _ in ctx.port.take_emcy()]   # CiA 301: 0x0000 expected
    ctx.port.set_command(controlword=0x00)

