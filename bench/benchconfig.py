"""Bench config files (config/benches/*.toml): which drive and load machine, over which transport.

The bench reads [bench], [services], [drive] and [load]; [simulator] belongs to sim_backend and is only
checked for being a table (its `motor` path is resolved like every other path). Relative paths are resolved
against the repo root (the directory holding pyproject.toml) and rewritten as absolute strings.

load_bench_config() checks the whole file (every problem one `file: field: reason` line) and builds a BenchConfig
once: [bench] and [services] as typed sections; [drive] and [load] as the checked settings their link classes take
(the transport's module owns those keys), defaults filled in. A [services] starter receives `as_dict()`.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root, Problems
from bench.services import check_service
from drivers.contract.cia402 import FAULT_RESET_POLICIES
from drivers.api import LinkSettings, TIMINGS
from drivers.canopen.profile import check_section, config_keys, PROFILE_KEYS
from drivers.contract.comm_loss import EXTERNAL_HINT, STOP_KEYS, check_keys, external_stop_problem
from drivers.contract.errors import ContentError
from drivers.contract.toml_file import read_toml_file
from drivers.eds import DeviceDescription, read_eds
from drivers.contract.load_map import read_load_map
from drivers.reference import check_section as check_reference

_BENCH_KEYS = {"name", "description", "timing", "plant_injections", "wire_faults", "fault_reset", "drill_valid_s", "served_by"}
_SERVICES_KEYS = {"start"}
_LOAD_COMM_LOSS = ("watchdog", "external")
_DRIVE_COMMON = {"transport", "sync_period_s", "heartbeat_timeout_s", "trace_decimation", "trace_signals", "eds"}
_DRIVE_KEYS = {
    "canopen": _DRIVE_COMMON | {"interface", "channel", "bitrate", "node_id", "sdo_timeout_s"} | set(PROFILE_KEYS),
    "serial": _DRIVE_COMMON | {"port", "baudrate", "timeout_s"} | set(STOP_KEYS),
}
_LOAD_COMMON = {"transport", "map", "unit_id", "timeout_s", "comm_loss", "external_stop", "drill_margin_ms"}
_LOAD_KEYS = {
    "modbus-tcp": _LOAD_COMMON | {"host", "port"},
    "modbus-rtu": _LOAD_COMMON | {"port", "baudrate"},
}
_TOP_KEYS = {"bench", "services", "drive", "load", "reference", "simulator"}


@dataclass(frozen=True)
class BenchSection:
    """[bench]: what the bench itself decides, whatever the transport."""
    name: str
    description: str = ""
    timing: str = "lockstep"            # drivers.api.TIMINGS
    plant_injections: bool = False      # the rig may change the plant (a simulator)
    wire_faults: bool = False           # the rig may corrupt its own wire (a simulator)
    fault_reset: str = "once"           # drivers.api.FAULT_RESET_POLICIES
    drill_valid_s: float = 0.0          # a passed bench-death drill holds this long in one bench process (0: every run)


@dataclass(frozen=True)
class BenchConfig:
    path: str                                   # the config file, absolute
    bench: BenchSection
    drive: Mapping[str, Any]                    # [drive]: the drive link's settings
    load: Mapping[str, Any] = field(default_factory=dict)     # [load]: empty on a free shaft
    services_start: str | None = None           # [services] start: a simulated rig's starter; None on a real rig
    reference_source: str | None = None         # [reference] source
    simulator: Mapping[str, Any] | None = None  # [simulator], for sim_backend

    def as_dict(self) -> dict[str, Any]:
        """The plain layout a [services] starter receives (its contract: sections as tables, "_path")."""
        out: dict[str, Any] = {"_path": self.path, "bench": asdict(self.bench),
                               "services": {"start": self.services_start}, "drive": dict(self.drive),
                               "load": dict(self.load), "reference": {"source": self.reference_source}}
        if self.simulator is not None:
            out["simulator"] = dict(self.simulator)
        return out

    def with_overrides(self, overrides: Mapping[str, Mapping[str, Any]]) -> "BenchConfig":
        """The config with a starter's endpoint overrides ({"drive": {...}, "load": {...}}) merged in."""
        unknown = set(overrides) - {"drive", "load"}
        if unknown:
            raise ValueError(f"a [services] starter may override drive and load only, not {sorted(unknown)}")
        return replace(self, drive={**self.drive, **(overrides.get("drive") or {})},
                       load={**self.load, **(overrides.get("load") or {})})


# What `drivebench probe` finds out itself (a lab's first step, with only interface, channel and node id known): a
# config lacking these still probes; the probe's checklist says what to write.
PROBE_TELLS = ("drive.eds", "drive.velocity_unit", "drive.encoder_increments_per_rev", "drive.gear_ratio",
               "bench.timing", "load.map", "drive.external_stop", "load.external_stop")


def load_bench_config(path: str | Path, for_probe: bool = False) -> BenchConfig:
    """Read and validate a bench config; InputError lists every problem as `file: field: reason`. `for_probe`:
    problems the probe diagnoses itself (PROBE_TELLS) are let through."""
    path = Path(path)
    raw = read_toml(path)
    problems = Problems(path)
    root = find_repo_root(path)
    problems.unknown_keys(raw, _TOP_KEYS, "")

    bench = problems.table(raw, "bench", "") or {}
    problems.unknown_keys(bench, _BENCH_KEYS, "bench")
    section = BenchSection(
        name=problems.string(bench, "name", "bench"),
        description=problems.string(bench, "description", "bench", required=False, default=""),
        # a config without [services] drives a rig (or a served simulator, which says so): real time by default
        timing=problems.string(bench, "timing", "bench", required=False, choices=TIMINGS,
                               default="lockstep" if "services" in raw or bench.get("served_by") else "realtime"),
        plant_injections=problems.boolean(bench, "plant_injections", "bench", required=False, default=False),
        wire_faults=problems.boolean(bench, "wire_faults", "bench", required=False, default=False),
        fault_reset=problems.string(bench, "fault_reset", "bench", required=False, default="once",
                                    choices=FAULT_RESET_POLICIES),
        drill_valid_s=_drill_valid(problems, bench),
    )

    services = problems.table(raw, "services", "", required=False) or {}
    problems.unknown_keys(services, _SERVICES_KEYS, "services")
    start = problems.string(services, "start", "services", required=False)
    if start is not None:
        reason = check_service(start)
        if reason:
            problems.add("services.start", reason)
    served_by = problems.string(bench, "served_by", "bench", required=False)
    if section.timing == "lockstep" and start is None and not (served_by or "").strip():
        # the simulator advances only on the bench's SYNC: on a drive with its own clock the verdict would depend
        # on how fast the host happens to be
        problems.add("bench.timing", '"lockstep" is for simulators only (they advance on the bench\'s SYNC) and this '
                                     'config has no [services]: a real rig runs timing = "realtime" (a simulator '
                                     'served elsewhere says so: [bench] served_by = "drivebench sim serve ...")')

    drive = _drive(problems, problems.table(raw, "drive", ""), root)
    load = _load(problems, problems.table(raw, "load", "", required=False), root)
    reference, reference_problems = check_reference(raw.get("reference"), bool(load))
    for field_, reason in reference_problems:
        problems.add(field_, reason)

    simulator = problems.table(raw, "simulator", "", required=False)
    if simulator is not None:
        simulator = dict(simulator)
        if "motor" in simulator:
            motor = problems.string(simulator, "motor", "simulator")
            simulator["motor"] = _existing_path(problems, "simulator.motor", motor, root) if motor else None
    if for_probe:
        problems.lines = [line for line in problems.lines if not _probe_tells(line, problems.file)]
    problems.raise_if_any()
    return BenchConfig(path=str(path.resolve()), bench=section, drive=drive, load=load, services_start=start,
                       reference_source=reference.source if reference else None,
                       simulator=simulator)


def _probe_tells(line: str, file: str) -> bool:
    for key in PROBE_TELLS:
        if line.startswith(f"{file}: {key}:"):
            return key != "load.map" or "no communication watchdog" in line
    return False


def _drill_valid(problems: Problems, bench: dict) -> float:
    value = problems.number(bench, "drill_valid_s", "bench", required=False, default=0.0, min_value=0.0)
    if value is not None and not value <= 86400:
        problems.add("bench.drill_valid_s", f"must be at most 86400 s (a day), got {value!r}")
    return float(value or 0.0)


def link_settings(cfg: BenchConfig) -> LinkSettings:
    """The bench's own settings every drive link obeys, whatever the transport."""
    return LinkSettings(timing=cfg.bench.timing, fault_reset=cfg.bench.fault_reset)


def drive_description(cfg: BenchConfig) -> DeviceDescription | None:
    """The drive's EDS as the bench reads it before connecting (None when the config names none)."""
    eds = cfg.drive.get("eds")
    return _read_eds_cached(eds, *_stamp(eds)) if eds else None


def measurable_signals(cfg: BenchConfig) -> frozenset[str]:
    """The signals this bench can measure, judged from its files alone (the run records what it really measured):
    the drive's (from its EDS, profile and [drive] signals) and the reference sensor's."""
    from drivers.canopen.profile import static_measurable
    from drivers.reference import ReferenceConfig
    from drivers.contract.signals import SIGNAL_NAMES

    drive = cfg.drive
    description = drive_description(cfg)
    if drive.get("transport") != "canopen" or description is None:
        own = frozenset(SIGNAL_NAMES)                 # the serial protocol is drivebench's: every signal
    else:
        own = static_measurable(drive, description.has,
                                lambda index: description.has(index) and bool(description.od[index].default),
                                description.drivebench_kind is not None)
    reference = ReferenceConfig(cfg.reference_source)
    return (own - reference.not_from_drive()) | frozenset(reference.signals(bool(cfg.load)))


def _stamp(path: str) -> tuple[int, int]:
    st = Path(path).stat()
    return st.st_size, st.st_mtime_ns


@functools.lru_cache(maxsize=16)
def _read_eds_cached(path: str, size: int, mtime_ns: int) -> DeviceDescription:
    return read_eds(path)


def read_toml(path: Path) -> dict[str, Any]:
    return read_toml_with_bytes(path)[0]


def read_toml_with_bytes(path: Path) -> tuple[dict[str, Any], bytes]:
    try:
        return read_toml_file(path)
    except ContentError as exc:
        raise InputError([f"{path}: (file): {exc}"]) from None


def resolve_path(value: str, root: Path, also: Path | None = None) -> Path | None:
    """An existing file for `value`: absolute, else under the repo root, else under `also`."""
    if not value.strip():
        return None
    try:
        p = Path(value).expanduser()
        if p.is_absolute():
            return p if p.is_file() else None
        for base in (root, also):
            if base is not None and (base / p).is_file():
                return (base / p).resolve()
    except (OSError, ValueError, RuntimeError):   # a name too long for the file system, no such user (~x)
        return None
    return None


def _existing_path(problems: Problems, field: str, value: str, root: Path) -> str | None:
    found = resolve_path(value, root)
    if found is None:
        problems.add(field, f"file not found: {value!r} (relative paths are taken from the repo root {root})")
        return None
    return str(found)


def _drive(problems: Problems, drive: dict | None, root: Path) -> dict[str, Any]:
    if drive is None:
        return {}
    w = "drive"
    transport = problems.string(drive, "transport", w, choices=tuple(_DRIVE_KEYS))
    if transport is not None:
        problems.unknown_keys(drive, _DRIVE_KEYS[transport], w)
    out: dict[str, Any] = {
        "transport": transport,
        "sync_period_s": problems.number(drive, "sync_period_s", w, required=False, default=0.001, positive=True),
        "heartbeat_timeout_s": problems.number(drive, "heartbeat_timeout_s", w, required=False, default=0.5,
                                               positive=True),
        "trace_decimation": problems.integer(drive, "trace_decimation", w, required=False, default=1, min_value=1),
        "trace_signals": _signal_list(problems, drive, "trace_signals", w),
    }
    if transport == "canopen":
        out["interface"] = problems.string(drive, "interface", w)
        channel = drive.get("channel")
        if isinstance(channel, int) and not isinstance(channel, bool):
            out["channel"] = channel                  # python-can interfaces number their channels (pcan, kvaser)
        else:
            out["channel"] = problems.string(drive, "channel", w)
        out["bitrate"] = problems.integer(drive, "bitrate", w, required=False, default=1_000_000, min_value=1)
        out["node_id"] = problems.integer(drive, "node_id", w, min_value=1, max_value=127)
        out["sdo_timeout_s"] = problems.number(drive, "sdo_timeout_s", w, required=False, default=0.5, positive=True)
    if transport in _DRIVE_KEYS:
        # CANopen: the object dictionary the link loads. Serial: optional, the drive's description (which
        # parameters it offers), since the serial protocol has no file of its own.
        eds = problems.string(drive, "eds", w, required=transport == "canopen")
        out["eds"] = _existing_path(problems, "drive.eds", eds, root) if eds else None
        if out["eds"]:
            try:
                description = _read_eds_cached(out["eds"], *_stamp(out["eds"]))
            except (ContentError, OSError) as exc:
                problems.add("drive.eds", f"{eds}: {exc}")
                out["eds"] = None
            else:
                if transport == "canopen":
                    keys, key_problems = config_keys(drive)
                    out.update(keys)
                    for field_, reason in key_problems + check_section(
                            drive, description.has, description.drivebench_kind is not None):
                        problems.add(field_, reason)
    if transport == "serial":
        keys, key_problems = check_keys(drive)
        out.update(keys)
        for field_, reason in key_problems:
            problems.add(field_, reason)
        out["port"] = problems.string(drive, "port", w)
        out["baudrate"] = problems.integer(drive, "baudrate", w, required=False, default=115200, min_value=1)
        out["timeout_s"] = problems.number(drive, "timeout_s", w, required=False, default=0.5, positive=True)
    return out


def _signal_list(problems: Problems, table: dict, key: str, where: str) -> tuple[str, ...] | None:
    """An optional list of signal names from drivers.contract.signals; None when absent."""
    from drivers.contract.signals import SIGNAL_NAMES

    if key not in table:
        return None
    value = table[key]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        problems.add(f"{where}.{key}", "must be a non-empty list of signal names")
        return None
    unknown = [v for v in value if v not in SIGNAL_NAMES]
    if unknown:
        problems.add(f"{where}.{key}", f"unknown signal(s) {', '.join(unknown)}; known: {', '.join(SIGNAL_NAMES)}")
        return None
    return tuple(value)


def _load(problems: Problems, load: dict | None, root: Path) -> dict[str, Any]:
    """[load] is optional: a rig without a load machine (free shaft) has none."""
    if load is None:
        return {}
    w = "load"
    transport = problems.string(load, "transport", w, choices=tuple(_LOAD_KEYS))
    if transport is not None:
        problems.unknown_keys(load, _LOAD_KEYS[transport], w)
    map_name = problems.string(load, "map", w)
    map_path = _existing_path(problems, "load.map", map_name, root) if map_name else None
    if map_path:
        try:
            read_load_map(map_path)
        except ContentError as exc:
            for field_, reason in exc.problems:
                problems.add("load.map", f"{map_name}: {field_}: {reason}")
            map_path = None
    out: dict[str, Any] = {
        "transport": transport,
        "map": map_path,
        "unit_id": problems.integer(load, "unit_id", w, required=False, default=1, min_value=0, max_value=247),
        "timeout_s": problems.number(load, "timeout_s", w, required=False, default=0.5, positive=True),
        "comm_loss": problems.string(load, "comm_loss", w, required=False, default="watchdog",
                                     choices=_LOAD_COMM_LOSS),
    }
    problem = external_stop_problem(load, "load")
    if problem is not None:
        problems.add(*problem)
    elif out["comm_loss"] == "external":
        out["external_stop"] = load["external_stop"]
    if "drill_margin_ms" in load:
        out["drill_margin_ms"] = problems.integer(load, "drill_margin_ms", w, min_value=10, max_value=10000)
    if map_path and out["comm_loss"] == "watchdog" and not read_load_map(map_path).watchdog_timeout_ms:
        problems.add("load.map", f"{map_name}: no communication watchdog register: the machine keeps its torque when "
                                 f"the bench dies; add it to the map, or where the rig stops the machine by other "
                                 f"means write [load] {EXTERNAL_HINT}")
    if transport == "modbus-tcp":
        out["host"] = problems.string(load, "host", w)
        out["port"] = problems.integer(load, "port", w, min_value=0, max_value=65535)
    elif transport == "modbus-rtu":
        out["port"] = problems.string(load, "port", w)
        out["baudrate"] = problems.integer(load, "baudrate", w, required=False, default=19200, min_value=1)
    return out
