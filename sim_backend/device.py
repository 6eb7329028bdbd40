"""Device-side logic every protocol front end of a simulated drive shares.

A SimulatedDevice wraps one DriveModel with what the drive's communication firmware does: the CiA 402
state machine, profile velocity mode, the trace recorder, fault detection and the load machine's
registers. The CANopen node, the serial server and the Modbus server all call into one instance; the
lock serialises them (each server runs in its own thread).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from drivers.contract import parameters
from drivers.contract.objects import EMCY_HEARTBEAT, EMCY_OVERCURRENT

EMCY_TEMPERATURE_WARNING = 0x4310     # CiA 301 device temperature: a warning a drive sends and runs on
from drivers.contract.cia402 import Command, Mode, State
from drivers.contract.parameters import ParamKind
from drivers.contract.signals import SIGNAL_NAMES
from sim_backend.cia402_device import Cia402Device
from sim_backend.comm_watchdog import Watchdog, WatchdogThread
from sim_backend.faults import ControlwordWritten, FaultState, LoadWritten, apply_fault
from sim_backend.drive_model import DriveModel
from sim_backend.trace import TraceRecorder


STANDSTILL_MECH_RAD_S = 0.5     # quick stop options 1-3: switch on disabled once the estimate is below this
QUICK_STOP_TO_DISABLED = (1, 2, 3)
QUICK_STOP_OPTIONS = (0, 1, 2, 3, 5, 6, 7)   # 0x605A codes this drive has (4 and 8: current/voltage limit, not)
HALT_BIT = 0x0100
VELOCITY_MODES = (Mode.PROFILE_VELOCITY, Mode.CYCLIC_SYNC_VELOCITY)   # the firmware follows the target in either


@dataclass
class LoadMachineRegisters:
    mode: int = 0
    value: float = 0.0
    enabled: bool = False
    fault: int = 0


@dataclass
class SimulatedDevice:
    model: DriveModel
    trace: TraceRecorder = field(default_factory=TraceRecorder)
    device: Cia402Device = field(default_factory=Cia402Device)
    mode_of_operation: int = Mode.PROFILE_VELOCITY
    target_speed_mech_rad_s: float = 0.0
    load: LoadMachineRegisters = field(default_factory=LoadMachineRegisters)
    step_count: int = 0
    lock: threading.RLock = field(default_factory=threading.RLock)
    pending_emcy: list[int] = field(default_factory=list)
    latest: np.ndarray = field(default_factory=lambda: np.zeros(len(SIGNAL_NAMES)))
    faults: FaultState = field(default_factory=FaultState)
    quick_stop_option: int = 2                 # 0x605A
    abort_connection_option: int = 3           # 0x6007
    cia402_comm_loss_reaction: bool = True     # False (a vendor quirk): a lost master gives EMCY + NMT change only
    master_watchdog: Watchdog = field(default_factory=lambda: Watchdog("drive"))
    load_watchdog: Watchdog = field(default_factory=lambda: Watchdog("load machine"))
    _watchdogs: WatchdogThread | None = None
    on_master_lost: list = field(default_factory=list)     # front ends' own reactions (CANopen: 0x1029)
    # vendor quirks (sim_backend.canopen.generic.DriveSpec): bit 9 (remote) drops after this much OPERATION ENABLED
    # drive time, or is 0 from power-on; a drive in local control ignores the controlword and keeps its target
    remote_drops_after_s: float | None = None
    local_control: bool = False
    warning_emcy_after_s: float | None = None   # EMCY 0x4310 + bit 7 after this much OPERATION ENABLED drive time
    comm_loss_delay_s: float = 0.0              # the comm-loss reaction this much after the consumer time
    velocity_filter_s: float = 0.0              # 0x606C's first-order filter (a drive's reported speed lags)
    speed_reported: float = 0.0                 # the estimate through that filter, rad/s
    _enabled_steps: int = 0

    @property
    def time_s(self) -> float:
        return self.step_count * self.model.control_period_s

    def restart(self, model: DriveModel) -> None:
        """A new bench session on a served rig: the drive as after power-up — a fresh model (the rig's seed: the same
        telemetry for the same scenario), power stage off, no injection or fault acting, an empty recorder, the load
        machine off, the comm-loss watchdogs off until the new bench configures them. The front ends' wiring stays."""
        with self.lock:
            self.model = model
            self.trace.clear()
            self.device = Cia402Device(remote=not self.local_control)
            self._enabled_steps = 0
            self.mode_of_operation = Mode.PROFILE_VELOCITY
            self.target_speed_mech_rad_s = 0.0
            self.load = LoadMachineRegisters()
            self.pending_emcy.clear()
            self.latest = np.zeros(len(SIGNAL_NAMES))
            self.faults.clear_injections()
            self.master_watchdog.arm(0.0)
            self.load_watchdog.arm(0.0)
            self._apply_outputs()

    def write_controlword(self, word: int) -> None:
        with self.lock:
            self.faults.log(ControlwordWritten(word))
            if not self.device.remote:
                return                       # local control: the bench's controlword is not obeyed
            self.device.write_controlword(word, fault_active=self._fault_code() != 0)
            self._apply_outputs()

    def set_target(self, speed_mech_rad_s: float) -> None:
        """0x60FF / the serial SPEED command: ignored in local control (the drive keeps its last target)."""
        with self.lock:
            if self.device.remote:
                self.target_speed_mech_rad_s = speed_mech_rad_s

    def _remote_drop(self, n_steps: int) -> None:
        if self.device.state is State.OPERATION_ENABLED:
            self._enabled_steps += n_steps
        enabled_s = self._enabled_steps * self.model.control_period_s
        if self.warning_emcy_after_s is not None and not self.device.warning and enabled_s >= self.warning_emcy_after_s:
            self.device.warning = True
            self.pending_emcy.append(EMCY_TEMPERATURE_WARNING)
        if self.remote_drops_after_s is None or not self.device.remote:
            return
        if self.device.state is State.OPERATION_ENABLED:
            if self._enabled_steps * self.model.control_period_s >= self.remote_drops_after_s:
                self.device.remote = False
                self.faults.self_stops.append(f"drive: statusword bit 9 (remote) dropped at t={self.time_s:.3f} s: "
                                              f"local control, target {self.target_speed_mech_rad_s:g} rad/s kept")

    def reset_fault(self) -> None:
        with self.lock:
            self.model.reset_fault()
            self.faults.overcurrent = False

    def set_load(self, mode: int | None = None, value: float | None = None, enabled: bool | None = None) -> None:
        with self.lock:
            self.faults.log(LoadWritten(mode, value, enabled))
            if mode is not None:
                self.load.mode = mode
            if value is not None:
                self.load.value = value
            if enabled is not None:
                self.load.enabled = enabled
            self.model.set_load(self.load.mode, self.load.value, self.load.enabled)

    def write_named(self, name: str, value: float) -> None:
        """A parameter of drivers.contract.parameters: test hook, firmware parameter, plant injection or fault."""
        kind = getattr(self.model, "kind", None)
        param = parameters.lookup(name, kind)
        if param is None:
            raise KeyError(f"unknown parameter {name!r} for a {kind} drive")
        with self.lock:
            if param.kind in (ParamKind.DEVICE_FAULT, ParamKind.WIRE_FAULT):
                apply_fault(self, param, value)
            elif param.kind is ParamKind.PLANT:
                self.model.set_plant_param(name, value)
            else:
                self.model.set_hook(name, value)

    def arm_watchdogs(self) -> None:
        """Start checking the drive's and the load machine's communication watchdogs (both off until armed)."""
        if self._watchdogs is None:
            self._watchdogs = WatchdogThread(self.lock, tick=self._free_run)
            self._watchdogs.add(self.master_watchdog, self._master_lost)
            self._watchdogs.add(self.load_watchdog, self._load_master_lost)

    def stop_watchdogs(self) -> None:
        if self._watchdogs is not None:
            self._watchdogs.stop()
            self._watchdogs = None

    def connection_aborted(self, what: str) -> None:
        """CiA 402 0x6007 on an NMT stop / reset communication / reset application while powered (CiA 402-2 0x6007:
        bus-off, heartbeat, NMT stopped, reset application, reset communication)."""
        with self.lock:
            if not self.device.power_enabled:
                return
            option = self.abort_connection_option
            self.faults.self_stops.append(f"drive: {what}, 0x6007 = {option}")
            if option == 1:
                self.device.fault(EMCY_HEARTBEAT)
            elif option == 2:
                self.device.write_controlword(Command.DISABLE_VOLTAGE)
            elif option == 3 and self.device.state is State.OPERATION_ENABLED:
                self.device.write_controlword(Command.QUICK_STOP)
                self._quick_stop_done_at_standstill()
            self._apply_outputs()

    def _master_lost(self, silent_s: float) -> None:
        """CiA 402 0x6007 abort connection option: the drive's own reaction to a lost master."""
        if self.comm_loss_delay_s > 0:
            timer = threading.Timer(self.comm_loss_delay_s, self._master_lost_late, (silent_s + self.comm_loss_delay_s,))
            timer.daemon = True
            timer.start()
            return
        self._react_to_master_lost(silent_s)

    def _master_lost_late(self, silent_s: float) -> None:
        with self.lock:
            if self.master_watchdog.tripped:
                self._react_to_master_lost(silent_s)

    def _react_to_master_lost(self, silent_s: float) -> None:
        option = self.abort_connection_option
        what = {1: "fault", 2: "disable voltage", 3: "quick stop"}.get(option, "no action")
        self.pending_emcy.append(EMCY_HEARTBEAT)
        if not self.cia402_comm_loss_reaction:
            self.faults.self_stops.append(f"drive: master silent for {silent_s:.2f} s, no CiA 402 reaction "
                                          f"(EMCY and NMT change only; state {self.device.state.name})")
            for react in self.on_master_lost:
                react()
            return
        self.faults.self_stops.append(f"drive: master silent for {silent_s:.2f} s, 0x6007 = {option} ({what})")
        if option == 1:
            self.device.fault(EMCY_HEARTBEAT)
        elif option == 2 and self.device.power_enabled:
            self.device.write_controlword(Command.DISABLE_VOLTAGE)
        elif option == 3 and self.device.state is State.OPERATION_ENABLED:
            self.device.write_controlword(Command.QUICK_STOP)
            self._quick_stop_done_at_standstill()
        self._apply_outputs()
        for react in self.on_master_lost:
            react()

    def _quick_stop_done_at_standstill(self) -> None:
        """A quick stop from standstill has no ramp to brake along: done at once (0x605A), so the drive's time does
        not run on for it (the bench's comm-loss drill, at zero speed, leaves the simulated run's start untouched)."""
        speed = self.latest[SIGNAL_NAMES.index("speed_est_mech_rad_s")]
        if (self.device.state is State.QUICK_STOP_ACTIVE and self.quick_stop_option in QUICK_STOP_TO_DISABLED
                and abs(speed) <= STANDSTILL_MECH_RAD_S):
            self.device.state = State.SWITCH_ON_DISABLED

    def _free_run(self, dt_s: float) -> None:
        """In lockstep the drive's time moves only with the bench's SYNCs; with the bench gone, a real drive's clock
        goes on and its reaction (braking on the quick-stop ramp) completes. So does this one's, in wall time."""
        chunk = max(1, round(0.01 / self.model.control_period_s))      # the drive's own checks every 10 ms
        steps = max(1, round(min(dt_s, 0.1) / self.model.control_period_s))
        while steps > 0 and self.master_watchdog.tripped and self.device.power_enabled:
            self.advance(min(chunk, steps))
            steps -= chunk

    def _load_master_lost(self, silent_s: float) -> None:
        """A dynamometer's Modbus watchdog: torque to zero, disabled."""
        self.faults.self_stops.append(f"load machine: no Modbus request for {silent_s:.2f} s, torque off, disabled")
        self.load.enabled = False
        self.load.value = 0.0
        self.model.set_load(self.load.mode, 0.0, False)

    def _apply_outputs(self) -> None:
        self.model.set_enabled(self.device.power_enabled)
        running = (self.device.state is State.OPERATION_ENABLED and self.mode_of_operation in VELOCITY_MODES
                   and not self.device.controlword & HALT_BIT)      # halt (bit 8): brake to zero, stay enabled
        self.model.set_speed_ref(self.target_speed_mech_rad_s if running else 0.0)

    def advance(self, n_steps: int) -> np.ndarray:
        """Run n control periods; feed the trace recorder; detect faults. Returns the telemetry block."""
        with self.lock:
            self._remote_drop(n_steps)
            self._apply_outputs()
            block = self.model.step(n_steps)
            self._filter_reported(block[:, SIGNAL_NAMES.index("speed_est_mech_rad_s")])
            self.trace.push(self.step_count + 1, block, self.device.power_enabled)
            self.step_count += n_steps
            self.latest = block[-1]
            code = self._fault_code()
            if code and self.device.state is not State.FAULT:
                self.device.fault(code)
                self.pending_emcy.append(code)
                self._apply_outputs()
            speed = self.latest[SIGNAL_NAMES.index("speed_est_mech_rad_s")]
            if (self.device.state is State.QUICK_STOP_ACTIVE and self.quick_stop_option in QUICK_STOP_TO_DISABLED
                    and abs(speed) <= STANDSTILL_MECH_RAD_S):
                self.device.state = State.SWITCH_ON_DISABLED      # stopped on the quick-stop ramp (0x605A)
                self._apply_outputs()
            self.device.target_reached = abs(speed - self.target_speed_mech_rad_s) <= 0.01 * max(
                1.0, abs(self.target_speed_mech_rad_s))
            return block

    def _filter_reported(self, speeds: np.ndarray) -> None:
        if self.velocity_filter_s <= 0:
            self.speed_reported = float(speeds[-1])
            return
        from scipy.signal import lfilter       # only a drive with the quirk pays for the import

        a = 1.0 - math.exp(-self.model.control_period_s / self.velocity_filter_s)
        y, _ = lfilter([a], [1.0, a - 1.0], speeds, zi=[(1.0 - a) * self.speed_reported])
        self.speed_reported = float(y[-1])

    def _fault_code(self) -> int:
        return self.model.fault_code() or (EMCY_OVERCURRENT if self.faults.overcurrent else 0)

    def take_emcy(self) -> list[int]:
        with self.lock:
            codes, self.pending_emcy = self.pending_emcy, []
            return codes
