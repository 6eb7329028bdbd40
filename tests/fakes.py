"""In-memory DriveLink / LoadLink over sim_backend.toy.ToyDrive, for bench unit tests only.

No protocol: the links call the toy model directly. Every link call is appended to `calls`, so tests can
check the order of the safe-stop sequence. Knobs make the drive misbehave on purpose.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from bench.run.orchestrator import run_scenario
from drivers.api import DriveIdentity, DriveLink, DriveStatus, LiveSample, LoadFeedback, LoadLink
from drivers.contract.signals import SIGNAL_INDEX, TIME_COLUMN
from drivers.contract.errors import LinkError
from drivers.contract.load_map import LoadMode
from sim_backend.toy import ToyDrive


@dataclass
class FakeRig:
    """A toy drive and its load machine sharing one model; `calls` is the log of every link call."""

    sync_period_s: float = 0.001
    has_trace_recorder: bool = True
    fault_at_s: float | None = None          # the drive reports FAULT + EMCY 0x2310 from this drive time on
    heartbeat_lost_at_s: float | None = None
    sync_error_at_s: float | None = None     # sync() raises LinkError from this drive time on
    open_error: str | None = None            # open() raises LinkError(open_error)
    interrupt_at_s: float | None = None      # sync() raises KeyboardInterrupt once at this drive time
    hang_at_s: float | None = None           # sync() blocks (a stuck call) from this drive time until `release` is set
    overspeed_offset: float = 0.0            # added to the true speed reported live (to trip the supervisor)
    drill_result: str = "passed"             # what the fake drive's comm-loss drill reports (passed/failed/unverified)
    calls: list[tuple[str, tuple]] = field(default_factory=list)
    model: object = None                     # any sim_backend DriveModel; default a ToyDrive

    def __post_init__(self):
        import threading
        self.release = threading.Event()
        if self.model is None:
            self.model = ToyDrive()
        self.drive = FakeDriveLink(self)
        self.load = FakeLoadLink(self)

    def links(self):
        return self.drive, self.load

    def names(self) -> list[str]:
        return [name for name, _ in self.calls]


class FakeDriveLink(DriveLink):
    def __init__(self, rig: FakeRig):
        self.rig = rig
        self.report: dict = {}
        self.live: tuple[str, ...] = ()
        self.trace: tuple[str, ...] = ()
        self.decimation = 1
        self._trace_rows: list[np.ndarray] = []
        self._trace_t: list[np.ndarray] = []
        self._interrupted = False

    def _log(self, name: str, *args) -> None:
        self.rig.calls.append((name, args))

    def open(self) -> DriveIdentity:
        self._log("drive.open")
        if self.rig.open_error:
            raise LinkError(self.rig.open_error)
        return DriveIdentity(0x1234, 0x402, 1, 42, "toy drive", "toy-1.0", self.rig.has_trace_recorder)

    def configure(self, live_signals: Sequence[str], trace_signals: Sequence[str], trace_decimation: int) -> None:
        self._log("drive.configure", tuple(live_signals), tuple(trace_signals), trace_decimation)
        self.live = tuple(live_signals)
        self.trace = tuple(trace_signals)
        self.decimation = trace_decimation

    def drill(self, before_withhold=None) -> dict:
        """No protocol, no watchdog: the fake says what the rig asks it to (the orchestrator's handling is tested)."""
        self._log("drive.drill")
        if before_withhold is not None:
            before_withhold()
        result = {"what": "drive", "result": self.rig.drill_result, "left_operation_enabled_ms": 0.0,
                  "consumer_ms": 0, "margin_ms": 0}
        if self.rig.drill_result == "failed":
            result["refusal"] = "fake drive: comm-loss drill failed (the rig says so)"
        if self.rig.drill_result == "unverified":
            result["external_stop"] = "fake STO relay"
        return result

    def enable_velocity_mode(self) -> None:
        self._log("drive.enable_velocity_mode")
        self.rig.model.set_enabled(True)

    def set_speed_ref(self, speed_mech_rad_s: float) -> None:
        if self.rig.hang_at_s is not None:
            self._log("drive.set_speed_ref", speed_mech_rad_s)
        self.rig.model.set_speed_ref(speed_mech_rad_s)

    def write_parameter(self, name: str, value: float) -> None:
        self._log("drive.write_parameter", name, value)
        model = self.rig.model
        if name in model.plant_param_names():  # a real drive link writes a named OD object instead
            model.set_plant_param(name, value)
        else:
            model.set_hook(name, value)

    def sync(self) -> list[LiveSample]:
        model = self.rig.model
        t = model.time_s
        if self.rig.sync_error_at_s is not None and t >= self.rig.sync_error_at_s:
            raise LinkError("SYNC not answered (fake)")
        if self.rig.hang_at_s is not None and t >= self.rig.hang_at_s and not self.rig.release.is_set():
            self._log("drive.sync_hangs")
            self.rig.release.wait(120.0)
        if self.rig.interrupt_at_s is not None and t >= self.rig.interrupt_at_s and not self._interrupted:
            self._interrupted = True
            raise KeyboardInterrupt
        n = max(1, round(self.rig.sync_period_s / model.control_period_s))
        steps = round(model.time_s / model.control_period_s)
        block = model.step(n)
        times = (steps + 1 + np.arange(n)) * model.control_period_s
        keep = slice(None, None, self.decimation)
        self._trace_rows.append(block[keep])
        self._trace_t.append(times[keep])
        last = block[-1]
        values = {name: float(last[SIGNAL_INDEX[name]]) for name in self.live}
        if "speed_true_mech_rad_s" in values:
            values["speed_true_mech_rad_s"] += self.rig.overspeed_offset
        return [LiveSample(float(times[-1]), values)]

    def fetch_trace(self) -> dict[str, np.ndarray] | None:
        self._log("drive.fetch_trace")
        if not self.rig.has_trace_recorder:
            return None
        if not self._trace_rows:
            return {TIME_COLUMN: np.zeros(0), **{n: np.zeros(0) for n in self.trace}}
        rows = np.concatenate(self._trace_rows)
        t = np.concatenate(self._trace_t)
        self._trace_rows, self._trace_t = [], []
        return {TIME_COLUMN: t, **{n: rows[:, SIGNAL_INDEX[n]].copy() for n in self.trace}}

    def status(self) -> DriveStatus:
        t = self.rig.model.time_s
        fault = self.rig.fault_at_s is not None and t >= self.rig.fault_at_s
        hb_lost = self.rig.heartbeat_lost_at_s is not None and t >= self.rig.heartbeat_lost_at_s
        return DriveStatus(
            state="FAULT" if fault else "OPERATION ENABLED",
            fault=fault,
            heartbeat_ok=not hb_lost,
            emcy=[(0x2310, "overcurrent (fake)")] if fault else [],
        )

    def begin_quick_stop(self) -> None:
        self._log("drive.begin_quick_stop")
        self.rig.model.set_speed_ref(0.0)

    def quick_stop(self) -> None:
        self._log("drive.quick_stop")
        self.rig.model.set_speed_ref(0.0)

    def disable(self) -> None:
        self._log("drive.disable")
        self.rig.model.set_enabled(False)

    def close(self) -> None:
        self._log("drive.close")


class FakeLoadLink(LoadLink):
    def __init__(self, rig: FakeRig):
        self.rig = rig
        self.report: dict = {}
        self.mode = LoadMode.TORQUE
        self.value = 0.0
        self.enabled = False

    def _log(self, name: str, *args) -> None:
        self.rig.calls.append((name, args))

    def open(self) -> str:
        self._log("load.open")
        return "toy load machine"

    def set_load(self, mode: LoadMode, value: float) -> None:
        self._log("load.set_load", int(mode), value)
        self.mode, self.value = LoadMode(mode), float(value)
        self.rig.model.set_load(int(self.mode), self.value, self.enabled)

    def enable(self, on: bool) -> None:
        self._log("load.enable", on)
        self.enabled = bool(on)
        self.rig.model.set_load(int(self.mode), self.value, self.enabled)

    def drill(self) -> dict:
        self._log("load.drill")
        return {"what": "load machine", "result": "passed", "disabled_within_ms": 0.0, "timeout_ms": 0}

    def feedback(self) -> LoadFeedback:
        speed, torque = self.rig.model.load_feedback()
        return LoadFeedback(speed, torque, self.enabled, False)

    def zero_and_disable(self) -> None:
        self._log("load.zero_and_disable")
        self.value = 0.0
        self.enabled = False
        self.rig.model.set_load(int(LoadMode.TORQUE), 0.0, False)

    def close(self) -> None:
        self._log("load.close")


SAFE_STOP = ["drive.begin_quick_stop", "load.zero_and_disable", "drive.quick_stop", "drive.disable"]


# A bench config and a toy-ramp scenario whose run goes over FakeRig's links (the orchestrator's tests and the
# CLI, plugin, supervisor and not-judged tests that build on them).
FAKE_BENCH = """
[bench]
name = "fake"
plant_injections = {plant}

[drive]
transport = "serial"
port = "fake"
sync_period_s = 0.001

[load]
transport = "modbus-tcp"
map = "config/load-machines/drivebench-sim.toml"
host = "127.0.0.1"
port = 1
"""

FAKE_SCENARIO = """
schema_version = 1
name = "toy-ramp"
bench = "{bench}"
duration_s = {duration}

[[speed]]
kind = "ramp"
start_s = 0.0
end_s = 0.2
speed_mech_rad_s = 20.0

[[load]]
kind = "torque"
start_s = 0.5
torque_nm = 2.0

{extra}

[limits]
overspeed_mech_rad_s = 40.0
overcurrent_a = 10.0

[[criteria]]
name = "speed steady"
kind = "steady_state_error"
signal = "speed_true_mech_rad_s"
window_s = [0.7, {duration}]
reference = "speed_ref_mech_rad_s"
percent = true
limit = {limit}
"""


def write_case(tmp_path: Path, *, plant: bool = True, duration: float = 1.0, limit: float = 1.0,
               extra: str = "") -> Path:
    bench = tmp_path / "bench.toml"
    bench.write_text(textwrap.dedent(FAKE_BENCH.format(plant=str(plant).lower())))
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(FAKE_SCENARIO.format(bench=bench, duration=duration, limit=limit, extra=extra))
    return scenario


def run_fake(tmp_path, rig, **kwargs):
    """Run write_case's scenario (or `scenario=`) over the fake rig's links; kwargs go to run_scenario."""
    scenario = kwargs.pop("scenario", None) or write_case(tmp_path, **kwargs.pop("case", {}))
    return run_scenario(scenario, out_root=tmp_path / "runs", rerun_mode=kwargs.pop("rerun_mode", "off"),
                        links=rig.links(), **kwargs)
