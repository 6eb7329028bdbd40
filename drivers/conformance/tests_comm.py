"""Communication robustness: process data every cycle, SYNC / command frames lost for N periods, PDO remap with read
back and restore, SDO abort codes, NMT reset mid-operation, bus-off.

Clauses: CiA 301 v4.2 7.2.2 (PDO; transmission types of 0x18xx sub 2), 7.2.5 (SYNC), 7.2.4.3.17 (SDO abort codes),
7.2.8.3.1 (NMT), 7.5.2.35/36 (PDO mapping procedure); CiA 402-2 0x6007 (abort connection option).
"""

from __future__ import annotations

import time

from drivers.conformance.motion import Context
from drivers.conformance.port import ObjectAbort
from drivers.conformance.result import TestResult
from drivers.contract import objects as o
from drivers.contract.cia402 import State, state_name

S = State
BOOT_UP_TIMEOUT_S = 5.0
AFTER_GAP_CYCLES = 3
IN_FLIGHT = 1               # real time: the answer to the last SYNC of a window may not have arrived yet


def _alive(ctx: Context, n: int) -> dict[int, int]:
    """Cycles in which each PDO came, over n cycles."""
    seen: dict[int, int] = {p.number: 0 for p in ctx.pdos}
    for _ in range(n):
        for number in ctx.cycle().frames:
            seen[number] = seen.get(number, 0) + 1
    return seen


def process_data(ctx: Context, r: TestResult) -> None:
    """At speed, every synchronous TPDO answers every SYNC (event-driven ones with their event timer at the cycle);
    the statusword they carry agrees with the one read by SDO."""
    if not ctx.pdos:
        r.fail("no TPDO of the drive's mapping carries the statusword or the velocity actual value")
        return
    if ctx.enable() is not S.OPERATION_ENABLED:
        r.check("enable", "OPERATION ENABLED", state_name(ctx.statusword()), False)
        return
    ctx.port.set_command(target=ctx.port.to_drive_velocity(ctx.settings.test_speed_mech_rad_s / 2))
    n = ctx.settings.continuity_periods
    first_missing: dict[int, int] = {}
    counts = {p.number: 0 for p in ctx.pdos}
    syncs = 0
    for k in range(n):
        answer = ctx.cycle()
        syncs += answer.syncs
        for p in ctx.pdos:
            counts[p.number] += answer.counts.get(p.number, 0)
            if syncs - counts[p.number] > IN_FLIGHT:
                first_missing.setdefault(p.number, k)
    r.measured.update(cycles=n, syncs=syncs, received={f"TPDO{k}": v for k, v in counts.items()})
    for p in ctx.pdos:
        how = "every SYNC" if p.sync else f"event-driven, event timer {p.event_timer_ms} ms"
        r.check(f"TPDO{p.number} ({how}) for {syncs} SYNCs", f"{syncs} frames (the last {IN_FLIGHT} may be in flight)",
                f"{counts[p.number]}" + (f", missing from cycle {first_missing[p.number]} "
                                         f"({first_missing[p.number] * ctx.period_s:.2f} s)"
                                         if p.number in first_missing else ""),
                syncs - IN_FLIGHT <= counts[p.number] <= syncs + IN_FLIGHT)
    sdo_state = ctx.state()
    pdo_word = ctx.last.statusword if ctx.last else None
    if pdo_word is not None:
        r.check("statusword by TPDO and by SDO", "the same state", f"{state_name(pdo_word)} / "
                f"{sdo_state.label if sdo_state else '?'}", state_name(pdo_word) == (sdo_state.label if sdo_state
                                                                                      else None))


def tpdo_sync_transmission(ctx: Context, r: TestResult) -> None:
    for p in ctx.pdos:
        r.check(f"TPDO{p.number}: 0x{0x1800 + p.number - 1:04X} sub 2 = 1 (every SYNC)", "accepted",
                "accepted" if p.sync else f"refused: event-driven (255) with event timer {p.event_timer_ms} ms", None)
    event = [p.number for p in ctx.pdos if not p.sync]
    if event:
        r.note(f"TPDO {', '.join(map(str, event))} refuse SYNC transmission (types 0-240): samples are not tied to a "
               f"SYNC; a bench stamps them on receipt and states the jitter")


def _gap(ctx: Context, r: TestResult, what: str, sync: bool, command: bool) -> None:
    if ctx.enable() is not S.OPERATION_ENABLED:
        r.check("enable", "OPERATION ENABLED", state_name(ctx.statusword()), False)
        return
    reached, _ = ctx.run_to(ctx.settings.test_speed_mech_rad_s / 2)
    before = {number for number, count in _alive(ctx, 3).items() if count == 3}
    speed_before = ctx.speed()
    n = ctx.settings.gap_periods
    started = time.monotonic()
    for _ in range(n):
        ctx.cycle(sync=sync, command=command)
    back: set[int] = set()
    for k in range(1, AFTER_GAP_CYCLES + 1):        # lockstep: the first; real time: an answer may cross a window
        back |= before & set(ctx.cycle().frames)
        if back == before:
            break
    state = ctx.state()
    speed_after = ctx.speed()
    r.measured.update(gap_periods=n, gap_s=round(time.monotonic() - started, 4), state_after=state_name(
        ctx.statusword()), speed_before_mech_rad_s=speed_before, speed_after_mech_rad_s=speed_after)
    r.measured["answered_again_after_cycles"] = k
    r.check(f"TPDOs that answered before the {what} gap answer again at once", ", ".join(
        f"TPDO{k}" for k in sorted(before)) or "none", (", ".join(f"TPDO{k}" for k in sorted(back)) or "none") +
        f" within {k} cycle(s)", back == before and k <= (1 if ctx.port.timing == "lockstep" else AFTER_GAP_CYCLES))
    r.check(f"state after {n} periods without {what}", "a defined state (kept, or the drive's stated reaction)",
            state.label if state else state_name(ctx.statusword()), state is not None)
    if state is S.OPERATION_ENABLED:
        r.check("behaviour", "observed", "kept running at its last target", None)


def sync_loss(ctx: Context, r: TestResult) -> None:
    _gap(ctx, r, "SYNC", sync=False, command=False)


def rpdo_loss(ctx: Context, r: TestResult) -> None:
    if not ctx.port.has_command_frame():
        r.not_run("no RPDO of the drive's mapping carries the target velocity: the target goes by SDO, there is no "
                  "command frame to lose")
        return
    _gap(ctx, r, "command frames (RPDO)", sync=True, command=False)


def pdo_remap(ctx: Context, r: TestResult) -> None:
    if not ctx.pdos:
        r.not_run("no TPDO in use")
        return
    number = ctx.pdos[0].number
    original = ctx.port.pdo_mapping(number)
    wanted = [(o.STATUSWORD, 0, 16), (o.VELOCITY_ACTUAL, 0, 32)]
    if [tuple(e) for e in original] == wanted:
        wanted = [(o.VELOCITY_ACTUAL, 0, 32), (o.STATUSWORD, 0, 16)]
    r.measured["original"] = [f"0x{i:04X}:{s:02X}/{b}" for i, s, b in original]
    alive = number in ctx.cycle().frames            # a TPDO already silent is process_data's finding, not this one's
    try:
        ctx.port.remap(number, wanted)
    except ObjectAbort as exc:
        now = ctx.port.pdo_mapping(number)
        r.check(f"TPDO{number} mapping unchanged after the refused remap", "the original", str(now == original),
                now == original)
        r.note(f"TPDO{number} mapping is fixed: remap refused with 0x{exc.code:08X}; a bench uses the drive's own")
        return
    back = ctx.port.pdo_mapping(number)
    r.check(f"TPDO{number} remapped (CiA 301 order), read back", str(wanted), str(back), back == wanted)
    frame = ctx.cycle().frames.get(number)
    r.check(f"TPDO{number} on SYNC with the new mapping", "6 bytes", "no frame" if frame is None else
            f"{len(frame)} bytes", (frame is not None and len(frame) == 6) if alive else None)
    errors = ctx.port.restore_process_data()
    ctx.pdos = ctx.port.start_process_data()
    restored = ctx.port.pdo_mapping(number)
    r.check(f"TPDO{number} original mapping restored, read back", str(original), str(restored) + (
        f" ({'; '.join(errors)})" if errors else ""), restored == original)


def sdo_aborts(ctx: Context, r: TestResult) -> None:
    probes = (
        ("write to a read-only object (0x6041 statusword)", o.STATUSWORD, 0, 0, 2, (o.ABORT_READ_ONLY,)),
        ("write to a non-existent object (0x5FFE)", 0x5FFE, 0, 0, 4, (o.ABORT_NOT_IN_OD,)),
        ("write to a non-existent subindex (0x1018:7F)", o.IDENTITY, 0x7F, 0, 4, (0x06090011, o.ABORT_READ_ONLY)),
        ("write of a reserved value (0x605A = 0x7FFF)", o.QUICK_STOP_OPTION, 0, 0x7FFF, 2,
         (o.ABORT_INVALID_VALUE, 0x06090031)),
    )
    for what, index, sub, value, size, codes in probes:
        if index == o.QUICK_STOP_OPTION and ctx.optional(index) is None:
            r.check(what, "abort 0x06090030/31", "no 0x605A on this drive", None)
            continue
        try:
            ctx.port.write(index, sub, value, size)
            answer, ok = "accepted", False
        except ObjectAbort as exc:
            answer, ok = f"abort 0x{exc.code:08X}", exc.code in codes
        r.check(what, " or ".join(f"abort 0x{c:08X}" for c in codes), answer, ok)


def nmt_reset(ctx: Context, r: TestResult, what: str) -> None:
    """Mid-operation (enabled at zero speed, process data running): the boot-up message, the drive out of OPERATION
    ENABLED (0x6007 reaction: reset communication / reset application), and what became of the bench's 0x1016."""
    if ctx.enable() is not S.OPERATION_ENABLED:
        r.check("enable", "OPERATION ENABLED", state_name(ctx.statusword()), False)
        return
    for _ in range(3):
        ctx.cycle()
    option = ctx.optional(o.ABORT_CONNECTION_OPTION, signed=True)
    boot_s = ctx.port.network_reset(what, BOOT_UP_TIMEOUT_S)
    r.check(f"NMT reset {what}: boot-up message (0x700 + id, data 00)", f"within {BOOT_UP_TIMEOUT_S:g} s",
            "none" if boot_s is None else f"after {boot_s * 1e3:.1f} ms", boot_s is not None,
            None if boot_s is None else boot_s * 1e3)
    if boot_s is None:
        time.sleep(0.2)
    state = ctx.state()
    reaction = {0: "no action", 1: "fault", 2: "disable voltage", 3: "quick stop"}.get(option, "vendor")
    r.measured.update(state_after=state.label if state else "?", abort_connection_0x6007=option)
    if option in (None, 0) and what == "communication":
        r.check("state after", "observed (0x6007 absent or 0: no reaction required)", state.label if state else "?",
                None)
    else:
        r.check("state after", f"not OPERATION ENABLED (0x6007 = {option}: {reaction})" if what == "communication"
                else "not OPERATION ENABLED (the application restarts)", state.label if state else "?",
                state is not S.OPERATION_ENABLED)
    consumer = ctx.optional(o.CONSUMER_HEARTBEAT, 1)
    r.measured["consumer_heartbeat_after"] = None if consumer is None else f"0x{consumer:08X}"
    r.check("0x1016 after the reset", "its power-on value (the bench must arm it again)",
            "none" if consumer is None else f"0x{consumer:08X}", None)


def nmt_reset_communication(ctx: Context, r: TestResult) -> None:
    nmt_reset(ctx, r, "communication")


def nmt_reset_node(ctx: Context, r: TestResult) -> None:
    nmt_reset(ctx, r, "node")


def bus_off(ctx: Context, r: TestResult) -> None:
    reason = ctx.port.bus_off_recovery()
    if reason is None:
        r.not_run(f"bus-off and recovery not simulated: {ctx.port.bus_off_reason}")
