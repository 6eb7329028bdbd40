"""The CiA 402 conformance-and-robustness suite over a port: the tests in order, each ending with the drive disabled
(a turning shaft stopped first), the drive's parameters and process-data mapping read before and restored after, and
a last test that reads them back and lists what could not be restored.

Safety between tests: the bench's liveness is armed in the drive (consumer heartbeat) for the whole suite, so a
bench that dies mid-test leaves a drive that stops itself; every test ends through Context.safe_end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable

from drivers.conformance import tests_comm as comm, tests_state as state, tests_stop as stop
from drivers.conformance.motion import Context
from drivers.conformance.port import ObjectAbort, PortError
from drivers.conformance.result import TestResult
from drivers.contract import objects as o
from drivers.contract.cia402 import State

CIA301, CIA402 = "CiA 301", "CiA 402-2"

# (name, clause, title, function)
TESTS: tuple[tuple[str, str, str, Callable[[Context, TestResult], None]], ...] = (
    ("found_state", f"{CIA402} state machine (a drive found powered)", "state and shaft when the suite connects",
     state.found_state),
    ("boot", f"{CIA301} 7.2.8.3.2.1 boot-up protocol", "boot: answering at once, or a boot-up message when ready",
     state.boot),
    ("identity", f"{CIA301} 7.5.2.1 (0x1000), 7.5.2.22 (0x1018)", "device type 402 and identity", state.identity),
    ("modes", f"{CIA402} 0x6502 / 0x6060 / 0x6061", "supported velocity modes agree with what 0x6060 accepts",
     state.modes),
    ("transitions", f"{CIA402} state machine, transitions 2-12 (16 observed)", "transitions the drive must take",
     state.transitions),
    ("refused_transitions", f"{CIA402} state machine (undefined commands)", "commands the drive must refuse",
     state.refused_transitions),
    ("fault_reset_edge", f"{CIA402} state machine, transition 15 (0x6040 bit 7)",
     "fault reset acts on the rising edge only", state.fault_reset_edge),
    ("quick_stop_options", f"{CIA402} 0x605A quick stop option code, transition 11",
     "quick stop per option code: stop time and distance on the reference sensor", stop.quick_stop_options),
    ("halt", f"{CIA402} 0x6040 bit 8 (halt), 0x605D", "halt: stop time and distance, stays enabled", stop.halt),
    ("comm_loss_reaction", f"{CIA301} 7.2.8.3.2.2 heartbeat consumer 0x1016; {CIA402} 0x6007",
     "the drive stops itself when the bench goes silent", stop.comm_loss_reaction),
    ("process_data", f"{CIA301} 7.2.2 PDO, 0x18xx transmission type", "every TPDO answers every cycle at speed",
     comm.process_data),
    ("tpdo_sync_transmission", f"{CIA301} 7.2.2 PDO transmission types 0-240 (0x18xx sub 2)",
     "TPDOs take SYNC transmission", comm.tpdo_sync_transmission),
    ("sync_loss", f"{CIA301} 7.2.5 SYNC", "SYNC lost for N periods: the drive's state and its answers after",
     comm.sync_loss),
    ("rpdo_loss", f"{CIA301} 7.2.2 PDO (RPDO)", "command frames lost for N periods", comm.rpdo_loss),
    ("pdo_remap", f"{CIA301} 7.5.2.35/36 PDO mapping procedure", "TPDO remap, read back, restore",
     comm.pdo_remap),
    ("sdo_aborts", f"{CIA301} 7.2.4.3.17 SDO abort codes", "abort codes for refused writes", comm.sdo_aborts),
    ("nmt_reset_communication", f"{CIA301} 7.2.8.3.1 NMT; {CIA402} 0x6007",
     "NMT reset communication mid-operation", comm.nmt_reset_communication),
    ("nmt_reset_node", f"{CIA301} 7.2.8.3.1 NMT", "NMT reset node mid-operation", comm.nmt_reset_node),
    ("bus_off", f"{CIA301} / ISO 11898-1 bus-off; {CIA402} 0x6007",
     "bus-off and recovery without a stale setpoint", comm.bus_off),
)
NAMES = tuple(t[0] for t in TESTS)

# the drive's parameters the suite may change: read before, written back after, read again to check. Not the target
# velocity (0x60FF): it is left at 0, never restored — a setpoint put back is a stale setpoint the next enable obeys
PARAMETERS = ((o.QUICK_STOP_OPTION, 0, 2, True), (0x605D, 0, 2, True), (o.ABORT_CONNECTION_OPTION, 0, 2, True),
              (o.MODES_OF_OPERATION, 0, 1, True), (o.COMM_CYCLE_PERIOD, 0, 4, False),
              (o.ERROR_BEHAVIOUR, 1, 1, False)) + tuple((o.CONSUMER_HEARTBEAT, k, 4, False) for k in range(1, 5))
AFTER_RESET = ("nmt_reset_communication", "nmt_reset_node")


@dataclass
class SuiteRun:
    identity: dict[str, Any]
    results: list[TestResult] = field(default_factory=list)
    restore: list[str] = field(default_factory=list)
    started_utc: str = ""
    duration_s: float = 0.0
    safe_end: str = ""
    drive_time_s: float = 0.0           # process-data cycles x period (lockstep: the drive's own time)
    liveness: str = ""                  # the bench's heartbeat in the drive for the whole suite, or why not


def snapshot(ctx: Context) -> dict[tuple[int, int], tuple[int, int, bool]]:
    out = {}
    for index, sub, size, signed in PARAMETERS:
        value = ctx.optional(index, sub, signed)
        if value is not None:
            out[(index, sub)] = (value, size, signed)
    return out


def _rearm(ctx: Context, consumer_ms: int) -> None:
    """After a reset: process data and the bench's liveness in the drive again."""
    ctx.port.restore_process_data()
    ctx.pdos = ctx.port.start_process_data()
    ctx.port.arm_liveness(consumer_ms)


def _fault_left(ctx: Context, r: TestResult) -> str | None:
    """A test that left the drive in FAULT (not one it provoked and reset itself): with [bench] fault_reset = "once" the
    fault is reset (said in the test's line); with "never" the suite stops there: a person looks at the drive first.
    Returns why the suite stops, or None."""
    if not r.safe_end.startswith("FAULT"):
        return None
    code = ctx.optional(o.ERROR_CODE)
    what = f"the drive is in FAULT after {r.name} (0x603F = {'?' if code is None else f'0x{code:04X}'})"
    if ctx.settings.fault_reset != "once":
        r.fail(f"{what}; [bench] fault_reset = \"never\": the suite stops, a person looks at the drive first")
        return f"{what} and [bench] fault_reset is \"never\": a person looks at the drive first"
    ctx.command(0x00, {State.FAULT})
    state, _ = ctx.command(0x80, {State.SWITCH_ON_DISABLED})
    ctx.port.set_command(controlword=0x00)
    r.safe_end += f"; {what}, reset ({state.label if state else '?'})"
    return None


def restore_and_check(ctx: Context, saved: dict) -> TestResult:
    r = TestResult("restored", "drivebench (destructive-safe suite)", "parameters and mapping restored, read back")
    for error in ctx.port.restore_process_data() + ctx.port.disarm_liveness():
        r.fail(f"could not restore: {error}")
    for (index, sub), (value, size, signed) in saved.items():
        try:
            ctx.port.write(index, sub, value, size, signed)
        except (ObjectAbort, PortError) as exc:
            if ctx.optional(index, sub, signed) != value:
                r.fail(f"0x{index:04X}:{sub:02X} not restored to {value}: {exc}")
    for (index, sub), (value, _, signed) in saved.items():
        now = ctx.optional(index, sub, signed)
        r.check(f"0x{index:04X}:{sub:02X}", str(value), str(now), now == value)
    before = getattr(ctx.port, "process_data_snapshot", dict)()
    for (index, sub), raw in sorted(before.items()):
        try:
            now = ctx.port.read_bytes(index, sub)
        except (ObjectAbort, PortError) as exc:
            now = str(exc).encode()
        if now != raw:
            r.check(f"0x{index:04X}:{sub:02X} (process data)", raw.hex(), now.hex(), False)
    r.measured["process_data_objects_checked"] = len(before)
    target = ctx.optional(o.TARGET_VELOCITY, signed=True)
    r.check("0x60FF target velocity", "0 (left at 0, never restored)", str(target), target in (0, None))
    return r


def run_suite(ctx: Context, only: tuple[str, ...] = (), progress: Callable[[TestResult], None] | None = None
              ) -> SuiteRun:
    started = time.monotonic()
    run = SuiteRun(ctx.identity, started_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    saved = snapshot(ctx)
    consumer = ctx.settings.consumer_time_ms
    try:
        ctx.pdos = ctx.port.start_process_data()
        try:
            ctx.port.arm_liveness(consumer)
            run.liveness = f"armed: the drive watches the bench ({consumer} ms)"
        except ObjectAbort as exc:
            run.liveness = (f"NOT ARMED ({exc}): if the bench dies mid-test, nothing in the drive stops the motor; "
                            f"comm_loss_reaction says why")
        for name, clause, title, test in TESTS:
            if only and name not in only and name != "found_state":
                continue
            r = TestResult(name, clause, title)
            t0 = time.monotonic()
            try:
                test(ctx, r)
            except (ObjectAbort, PortError) as exc:
                r.fail(f"the test could not finish: {exc}")
            except Exception as exc:            # a bug of the test must not cost the lab its report or its restore
                r.fail(f"the test raised {type(exc).__name__}: {exc}")
            finally:
                if name in AFTER_RESET:
                    try:
                        _rearm(ctx, consumer)
                    except (ObjectAbort, PortError) as exc:
                        r.fail(f"re-arming after the reset: {exc}")
                r.safe_end = ctx.safe_end()
                r.duration_s = round(time.monotonic() - t0, 3)
            if "may still turn" in r.safe_end:
                r.fail(r.safe_end)
            stop = _fault_left(ctx, r)
            run.results.append(r)
            if progress is not None:
                progress(r)
            if stop:
                for later in [t for t in TESTS if t[0] not in {x.name for x in run.results}]:
                    if not only or later[0] in only:
                        skipped = TestResult(later[0], later[1], later[2])
                        skipped.not_run(stop)
                        run.results.append(skipped)
                break
    finally:
        run.safe_end = ctx.safe_end()
        restored = restore_and_check(ctx, saved)
        run.results.append(restored)
        run.restore = [f for f in restored.findings]
        run.duration_s = round(time.monotonic() - started, 2)
        run.drive_time_s = round(ctx.cycles * ctx.period_s, 3)
    return run
