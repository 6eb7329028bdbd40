"""What the simulated node's objects mean: the standard CiA 402 objects and drivebench's extension objects, read from
and written to the SimulatedDevice. The node calls `read` / `write` from canopen's SDO server callbacks and PDOs;
None / False means "not mine": canopen's own object store answers."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

from canopen import objectdictionary
from canopen.sdo import SdoAbortedError

from drivers.contract import objects as o
from drivers.contract.cia402 import FAULT_RESET_BIT, State
from drivers.contract.signals import SIGNAL_INDEX, SIGNAL_NAMES
from drivers.contract.units import decode_velocity_unit, MRAD_PER_S, VelocityScale
from drivers.contract.errors import ContentError
from sim_backend.device import QUICK_STOP_OPTIONS, SimulatedDevice

log = logging.getLogger(__name__)

SPEED_EST = SIGNAL_INDEX["speed_est_mech_rad_s"]
SPEED_REF = SIGNAL_INDEX["speed_ref_mech_rad_s"]
TORQUE_EST = SIGNAL_INDEX["torque_est_nm"]
I_SY = SIGNAL_INDEX["i_sy_a"]
VDC = SIGNAL_INDEX["vdc_v"]
ABORT_DEVICE_STATE = 0x08000022     # CiA 301: data cannot be transferred because of the present device state


@dataclass
class DriveUnits:
    """The units a simulated drive reports and takes: its velocity unit (0x60A9) with encoder resolution and gear
    ratio, and the motor's rated current and torque that current/torque actual values are per mille of."""

    velocity: VelocityScale = VelocityScale(MRAD_PER_S)
    rated_current_a: float | None = None
    rated_torque_nm: float | None = None

    def to_drive(self, speed_mech_rad_s: float) -> int:
        return self.velocity.to_drive(speed_mech_rad_s) if math.isfinite(speed_mech_rad_s) else 0


def _per_mille(value: float, rated: float | None) -> int:
    if not rated or not math.isfinite(value):
        return 0
    return max(-32768, min(32767, round(1000.0 * value / rated)))


def error_register_for(code: int) -> int:
    """Bits of 0x1001 for an EMCY error code (bit 0 generic is set for any error)."""
    if code == 0:
        return 0
    reg = 0x01
    reg |= {0x2: 0x02, 0x3: 0x04, 0x4: 0x08}.get(code >> 12, 0)
    if code >> 8 in (0x81, 0x82):
        reg |= 0x10
    return reg


class Cia402Objects:
    """0x6040/0x6041 state machine, modes, velocity target/demand/actual in the drive's units, torque and current
    actual (per mille of rated), DC link (mV), position actual, the factor group, error code and register."""

    def __init__(self, device: SimulatedDevice, on_controlword: Callable[[], None], units: DriveUnits | None = None,
                 supported_modes: int | None = None):
        """`supported_modes`: 0x6502 as this drive has it (None: the EDS default, every mode accepted)."""
        self.device = device
        self.supported_modes = supported_modes
        self._on_controlword = on_controlword
        self.units = units or DriveUnits()
        self._position_rad = 0.0
        self._position_step = 0
        self.mode_display_delay_s = 0.0          # quirks (generic.DriveSpec)
        self.target_sdo_only_enabled = False
        self.from_rpdo: Callable[[], bool] = lambda: False
        self._mode_shown = (None, 0.0)           # (mode shown before the last 0x6060 write, when it was written)

    def read(self, index: int, subindex: int, od) -> object:
        dev = self.device
        if index == o.STATUSWORD:
            return dev.device.statusword
        if index == o.MODES_DISPLAY:
            before, written = self._mode_shown
            late = before is not None and time.monotonic() - written < self.mode_display_delay_s
            return before if late else dev.mode_of_operation
        if index == o.SUPPORTED_DRIVE_MODES and self.supported_modes is not None:
            return self.supported_modes
        if index == o.ERROR_CODE:
            return dev.device.error_code
        if index == o.ERROR_REGISTER:
            return error_register_for(dev.device.error_code) if dev.device.state is State.FAULT else 0
        if index == o.VELOCITY_ACTUAL:
            return self.units.to_drive(dev.speed_reported)
        if index == o.VELOCITY_DEMAND:
            return self.units.to_drive(float(dev.latest[SPEED_REF]))
        if index == o.TORQUE_ACTUAL:
            return _per_mille(float(dev.latest[TORQUE_EST]), self.units.rated_torque_nm)
        if index == o.CURRENT_ACTUAL:
            return _per_mille(float(dev.latest[I_SY]), self.units.rated_current_a)
        if index == o.DC_LINK_VOLTAGE:
            vdc = float(dev.latest[VDC])
            return max(0, round(vdc * 1000.0)) if math.isfinite(vdc) else 0
        if index == o.POSITION_ACTUAL:
            return self._position()
        if index == o.SI_UNIT_VELOCITY:
            return self.units.velocity.unit.code
        if index == o.POSITION_ENCODER_RESOLUTION and self.units.velocity.increments_per_rev:
            return {1: round(self.units.velocity.increments_per_rev), 2: 1}.get(subindex)
        if index == o.GEAR_RATIO:
            return {1: round(self.units.velocity.gear_motor_revs), 2: round(self.units.velocity.gear_shaft_revs)}.get(
                subindex)
        if index == o.MOTOR_RATED_CURRENT and self.units.rated_current_a:
            return round(self.units.rated_current_a * 1000.0)
        if index == o.MOTOR_RATED_TORQUE and self.units.rated_torque_nm:
            return round(self.units.rated_torque_nm * 1000.0)
        if index == o.QUICK_STOP_OPTION:
            return dev.quick_stop_option
        if index == o.ABORT_CONNECTION_OPTION:
            return dev.abort_connection_option
        return None

    def write(self, index: int, subindex: int, od, value) -> bool:
        dev = self.device
        if index == o.CONTROLWORD:
            with dev.lock:
                if value & FAULT_RESET_BIT and dev.device.state is State.FAULT:
                    dev.reset_fault()
                dev.write_controlword(value)
            self._on_controlword()
        elif index == o.MODES_OF_OPERATION:
            if self.supported_modes is not None and value and not (0 < value <= 32 and
                                                                   self.supported_modes >> (value - 1) & 1):
                raise SdoAbortedError(o.ABORT_INVALID_VALUE)
            with dev.lock:
                self._mode_shown = (dev.mode_of_operation, time.monotonic())
                dev.mode_of_operation = value
        elif index == o.TARGET_VELOCITY:
            if (self.target_sdo_only_enabled and not self.from_rpdo()
                    and dev.device.state is not State.OPERATION_ENABLED):
                raise SdoAbortedError(ABORT_DEVICE_STATE)
            dev.set_target(self.units.velocity.to_rad_s(value))
        elif index == o.SI_UNIT_VELOCITY:
            try:
                unit = decode_velocity_unit(value)
                scale = dataclasses.replace(self.units.velocity, unit=unit)
                scale.rad_s_per_unit
            except ContentError:
                raise SdoAbortedError(o.ABORT_INVALID_VALUE) from None
            self.units.velocity = scale
        elif index == o.QUICK_STOP_OPTION:
            if value not in QUICK_STOP_OPTIONS:
                raise SdoAbortedError(o.ABORT_INVALID_VALUE)
            with dev.lock:
                dev.quick_stop_option = value
        elif index == o.ABORT_CONNECTION_OPTION:
            if value not in o.ABORT_CONNECTION_CODES:
                raise SdoAbortedError(o.ABORT_INVALID_VALUE)
            with dev.lock:
                dev.abort_connection_option = value
        else:
            return False
        return True

    def _position(self) -> int:
        """Position actual value: the drive's own (estimated) shaft angle integrated, in increments where the unit
        counts them, else in mrad."""
        dev = self.device
        if dev.step_count != self._position_step:
            dt = (dev.step_count - self._position_step) * dev.model.control_period_s
            self._position_rad += float(dev.latest[SPEED_EST]) * dt
            self._position_step = dev.step_count
        per_rad = (self.units.velocity.increments_per_rev / (2 * math.pi)
                   if self.units.velocity.increments_per_rev else 1000.0)
        return max(-2**31, min(2**31 - 1, round(self._position_rad * per_rad)))

    def fast_getter(self, index: int, subindex: int) -> tuple[str, Callable[[], object]] | None:
        dev = self.device
        if subindex == 0 and index == o.STATUSWORD:
            return "H", lambda: dev.device.statusword
        if subindex == 0 and index == o.MODES_DISPLAY:
            return "b", lambda: dev.mode_of_operation
        return None


class ExtensionObjects:
    """drivebench's manufacturer objects: drive clock, live signals, trace recorder, parameters
    (drivers.contract.objects EXT_*). Present only in the drivebench EDS files."""

    def __init__(self, device: SimulatedDevice, od: objectdictionary.ObjectDictionary):
        self.device = device
        self.trace_pending = b""
        self.trace_max_rows = int(od[o.EXT_TRACE][o.TRACE_MAX_ROWS].default) if o.EXT_TRACE in od else 0
        self._trace_cfg = [device.trace.mask, device.trace.decimation, device.trace.trigger]

    def read(self, index: int, subindex: int, od) -> object:
        dev = self.device
        if index == o.EXT_STEP_COUNT:
            return dev.step_count & 0xFFFFFFFF
        if index == o.EXT_CONTROL_PERIOD_NS:
            return round(dev.model.control_period_s * 1e9)
        if o.EXT_SIGNAL_BASE <= index < o.EXT_SIGNAL_BASE + len(SIGNAL_NAMES):
            return float(dev.latest[index - o.EXT_SIGNAL_BASE])
        if o.EXT_SCALED_BASE <= index < o.EXT_SCALED_BASE + len(SIGNAL_NAMES):
            value = float(dev.latest[index - o.EXT_SCALED_BASE]) / od.factor
            return 0 if value != value else max(-32768, min(32767, round(value)))
        if index == o.EXT_TRACE:
            trace = dev.trace
            return {o.TRACE_MASK: trace.mask, o.TRACE_DECIMATION: trace.decimation, o.TRACE_TRIGGER: trace.trigger,
                    o.TRACE_CONTROL: int(trace.running),
                    o.TRACE_ROWS_AVAILABLE: trace.rows_available + len(self.trace_pending) // trace.row_size,
                    o.TRACE_ROW_SIZE: trace.row_size, o.TRACE_LOST_ROWS: trace.lost_rows,
                    o.TRACE_CAPACITY: trace.capacity_rows, o.TRACE_MAX_ROWS: self.trace_max_rows}.get(subindex)
        if index == o.EXT_TRACE_DATA:
            if not self.trace_pending:
                with dev.lock:
                    self.trace_pending = dev.trace.read(self.trace_max_rows)
            return self.trace_pending
        return None

    def write(self, index: int, subindex: int, od, value) -> bool:
        if index in o.EXT_PARAMETER_RANGE:
            try:
                self.device.write_named(od.name, float(value))
            except (KeyError, ValueError) as exc:
                log.warning("drive rejected %s = %r: %s", od.name, value, exc)
                raise SdoAbortedError(o.ABORT_INVALID_VALUE) from None
        elif index == o.EXT_TRACE:
            self._write_trace(subindex, value)
        else:
            return False
        return True

    def _write_trace(self, subindex: int, value: int) -> None:
        trace = self.device.trace
        with self.device.lock:
            if subindex in (o.TRACE_MASK, o.TRACE_DECIMATION, o.TRACE_TRIGGER):
                cfg = list(self._trace_cfg)
                cfg[subindex - 1] = value
                try:
                    trace.configure(*cfg)
                except ValueError:
                    raise SdoAbortedError(o.ABORT_INVALID_VALUE) from None
                self._trace_cfg = cfg
                self.trace_pending = b""
            elif subindex == o.TRACE_CONTROL:
                if value == o.TRACE_START:
                    trace.start()
                elif value == o.TRACE_STOP:
                    trace.stop()
                elif value == o.TRACE_CLEAR:
                    trace.clear()
                    self.trace_pending = b""
                else:
                    raise SdoAbortedError(o.ABORT_INVALID_VALUE)
            elif subindex == o.TRACE_MAX_ROWS:
                if value < 1:
                    raise SdoAbortedError(o.ABORT_INVALID_VALUE)
                self.trace_max_rows = value

    def upload_complete(self, index: int, subindex: int) -> None:
        if index == o.EXT_TRACE_DATA:
            self.trace_pending = b""

    def fast_getter(self, index: int, subindex: int) -> tuple[str, Callable[[], object]] | None:
        dev = self.device
        if subindex == 0 and index == o.EXT_STEP_COUNT:
            return "L", lambda: dev.step_count & 0xFFFFFFFF
        if o.EXT_SIGNAL_BASE <= index < o.EXT_SIGNAL_BASE + len(SIGNAL_NAMES):
            column = index - o.EXT_SIGNAL_BASE
            return "f", lambda: float(dev.latest[column])
        return None
