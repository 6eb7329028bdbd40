"""Bench config files (config/benches/*.toml): which drive and load machine, over which transport.

Each section is one typed, frozen object defined once with its defaults: [bench] BenchSection and [services]
ServicesSection here (the bench's own), [drive] and [load] the config class of their transport
(drivers.transports: CanopenDriveConfig, SerialDriveConfig, ModbusTcpConfig, ModbusRtuConfig, registered beside their
link classes), [reference] drivers.reference.ReferenceConfig, [simulator] drivers.contract.simulator.SimulatorConfig
(read here too, so `validate` refuses what the simulator would). Relative paths are resolved against the repo root
(the directory holding pyproject.toml) and kept as absolute strings.

load_bench_config() checks the whole file (every problem one `file: field: reason` line, an unknown key refused with
the allowed ones) and builds a BenchConfig once. A [services] starter receives `as_dict()`, the sections as plain
tables.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

from bench.inputs.rig_services import check_service
from drivers.api import LinkSettings, TIMINGS
from drivers.canopen.profile import check_section, config_keys
from drivers.contract.checks import Problems, find_repo_root, read_toml
from drivers.contract.cia402 import FAULT_RESET_POLICIES
from drivers.contract.comm_loss import EXTERNAL_HINT, check_keys, external_stop_problem
from drivers.contract.errors import ContentError
from drivers.contract.load_map import read_load_map
from drivers.contract.sections import Section, key
from drivers.contract.simulator import SimulatorConfig
from drivers.contract.eds import DeviceDescription, read_eds
from drivers.contract.instruments import InstrumentConfig, RigTruthsConfig, read_instruments, read_rig_truths
from drivers.reference import ReferenceConfig
from drivers.sections import DriveSection, LoadSection
from drivers.transports import DRIVE_TRANSPORTS, LOAD_TRANSPORTS

_TOP_KEYS = ("bench", "services", "drive", "load", "reference", "simulator", "instruments", "rig_truths")


@dataclass(frozen=True)
class BenchSection(Section):
    """[bench]: what the bench itself decides, whatever the transport."""

    SECTION = "bench"
    name: str = key(None, kind="string", required=True)
    description: str = key("", kind="string")
    timing: str = key("lockstep", kind="string", choices=TIMINGS)   # default on a file: see load_bench_config
    plant_injections: bool = key(False, kind="boolean")     # the rig may change the plant (a simulator)
    wire_faults: bool = key(False, kind="boolean")          # the rig may corrupt its own wire (a simulator)
    fault_reset: str = key("once", kind="string", choices=FAULT_RESET_POLICIES)
    # a passed bench-death drill holds this long in one bench process (0: every run)
    drill_valid_s: float = key(0.0, kind="number", min=0.0, max=86400.0)
    served_by: str | None = key(None, kind="string")        # a simulator served out of process says how


@dataclass(frozen=True)
class ServicesSection(Section):
    """[services]: what starts a simulated rig with the run (a registered starter); a real rig has none."""

    SECTION = "services"
    start: str | None = key(None, kind="string", check=check_service)


@dataclass(frozen=True)
class BenchConfig:
    path: str                                   # the config file, absolute
    bench: BenchSection
    drive: Mapping[str, Any]                    # [drive]: a DriveSection of its transport
    load: Mapping[str, Any] = field(default_factory=dict)     # [load]: a LoadSection; empty on a free shaft
    services: ServicesSection = field(default_factory=ServicesSection)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    simulator: SimulatorConfig | None = None
    instruments: tuple[InstrumentConfig, ...] = ()           # [[instruments]]: a lab's analyser, scope, DAQ
    rig_truths: RigTruthsConfig | None = None                 # [rig_truths]: measured field angle and flux

    @property
    def services_start(self) -> str | None:
        return self.services.start

    @property
    def reference_source(self) -> str | None:
        return self.reference.source

    def as_dict(self) -> dict[str, Any]:
        """The plain layout a [services] starter receives (its contract: sections as tables, "_path")."""
        out: dict[str, Any] = {"_path": self.path, "bench": dict(self.bench.items()),
                               "services": {"start": self.services_start}, "drive": dict(self.drive),
                               "load": dict(self.load), "reference": {"source": self.reference_source}}
        if self.simulator is not None:
            out["simulator"] = dict(self.simulator)
        if self.instruments:
            out["instruments"] = [i.as_dict() for i in self.instruments]
        return out

    def with_overrides(self, overrides: Mapping[str, Mapping[str, Any]]) -> "BenchConfig":
        """The config with a starter's endpoint overrides ({"drive": {...}, "load": {...}}) merged in."""
        unknown = set(overrides) - {"drive", "load", "instruments"}
        if unknown:
            raise ValueError(f"a [services] starter may override drive, load and instruments only, not {sorted(unknown)}")
        resources = dict(overrides.get("instruments") or {})     # instrument name -> the resource it serves at
        instruments = tuple(replace(i, resource=resources.get(i.name, i.resource)) for i in self.instruments)
        return replace(self, drive=_overridden(self.drive, overrides.get("drive")),
                       load=_overridden(self.load, overrides.get("load")), instruments=instruments)


def _overridden(section: Mapping[str, Any], values: Mapping[str, Any] | None) -> Mapping[str, Any]:
    if not values:
        return section
    if isinstance(section, Section):
        return replace(section, **values)
    return {**section, **values}


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

    table = problems.table(raw, "bench", "") or {}
    # a config without [services] drives a rig (or a served simulator, which says so): real time by default
    simulated = "services" in raw or bool(table.get("served_by"))
    section = BenchSection.read(table, problems)
    if section is not None and "timing" not in table:
        section = replace(section, timing="lockstep" if simulated else "realtime")

    services = ServicesSection.read(problems.table(raw, "services", "", required=False) or {}, problems)
    start = services.start if services else None
    if section is not None and section.timing == "lockstep" and start is None and \
            not (section.served_by or "").strip():
        # the simulator advances only on the bench's SYNC: on a drive with its own clock the verdict would depend
        # on how fast the host happens to be
        problems.add("bench.timing", '"lockstep" is for simulators only (they advance on the bench\'s SYNC) and this '
                                     'config has no [services]: a real rig runs timing = "realtime" (a simulator '
                                     'served elsewhere says so: [bench] served_by = "drivebench sim serve ...")')

    drive = _drive(problems, problems.table(raw, "drive", ""), root)
    load = _load(problems, problems.table(raw, "load", "", required=False), root)
    reference = _reference(problems, raw.get("reference"), bool(load))

    simulator = None
    sim_table = problems.table(raw, "simulator", "", required=False)
    if sim_table is not None:
        simulator = SimulatorConfig.read(sim_table, problems, root=root)
    instruments = read_instruments(raw.get("instruments"), problems)
    rig_truths = read_rig_truths(raw.get("rig_truths"), instruments, problems)
    if for_probe:
        problems.lines = [line for line in problems.lines if not _probe_tells(line, problems.file)]
    problems.raise_if_any()
    return BenchConfig(path=str(path.resolve()), bench=section, drive=drive, load=load,
                       services=services or ServicesSection(), reference=reference or ReferenceConfig(),
                       simulator=simulator, instruments=instruments,
                       rig_truths=rig_truths)


def _probe_tells(line: str, file: str) -> bool:
    for told in PROBE_TELLS:
        if line.startswith(f"{file}: {told}:"):
            return told != "load.map" or "no communication watchdog" in line
    return False


def link_settings(cfg: BenchConfig) -> LinkSettings:
    """The bench's own settings every drive link obeys, whatever the transport."""
    return LinkSettings(timing=cfg.bench.timing, fault_reset=cfg.bench.fault_reset)


def drive_description(cfg: BenchConfig) -> DeviceDescription | None:
    """The drive's EDS as the bench reads it before connecting (None when the config names none)."""
    eds = cfg.drive.get("eds")
    return _read_eds_cached(eds, *_stamp(eds)) if eds else None


def measurable_signals(cfg: BenchConfig) -> frozenset[str]:
    """The signals this bench can measure, judged from its files alone (the run records what it really measured):
    the drive's (from its EDS, profile and [drive] signals), the reference sensor's, and its instruments' records
    (`<instrument>:<signal>`)."""
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
    truths = frozenset(cfg.rig_truths.signals()) if cfg.rig_truths is not None else frozenset()
    from bench.inputs.capture_criteria import capture_signals_of
    return ((own - reference.not_from_drive()) | frozenset(reference.signals(bool(cfg.load))) | truths
            | capture_signals_of(cfg.instruments))


def _stamp(path: str) -> tuple[int, int]:
    st = Path(path).stat()
    return st.st_size, st.st_mtime_ns


@functools.lru_cache(maxsize=16)
def _read_eds_cached(path: str, size: int, mtime_ns: int) -> DeviceDescription:
    return read_eds(path)


def _reference(problems: Problems, table: Any, has_load: bool) -> ReferenceConfig | None:
    if table is None:
        return ReferenceConfig()
    if not isinstance(table, dict):
        problems.add("reference", "must be a table: [reference] source = \"load\" | \"drive\" | \"none\"")
        return None
    reference = ReferenceConfig.read(table, problems)
    if reference is not None and reference.source == "load" and not has_load:
        problems.add("reference.source", "'load' needs a load machine ([load]) and this bench has none")
        return None
    return reference


def _transport(problems: Problems, table: dict, where: str, registry: dict) -> Any:
    name = problems.string(table, "transport", where, choices=tuple(registry))
    return registry[name].config if name is not None else None


def _drive(problems: Problems, drive: dict | None, root: Path) -> DriveSection | dict:
    if drive is None:
        return {}
    cls = _transport(problems, drive, "drive", DRIVE_TRANSPORTS)
    if cls is None:
        return {}
    section = cls.read(drive, problems, root=root)
    keys: dict[str, Any] = {}
    description = None
    if section is not None and section.eds:
        try:
            description = _read_eds_cached(section.eds, *_stamp(section.eds))
        except (ContentError, OSError) as exc:
            problems.add("drive.eds", f"{drive.get('eds')}: {exc}")
    if drive["transport"] == "canopen":
        keys, key_problems = config_keys(drive)
        if description is not None:
            key_problems += check_section(drive, description.has, description.drivebench_kind is not None)
    else:
        keys, key_problems = check_keys(drive)
    for field_, reason in key_problems:
        problems.add(field_, reason)
    if section is None:
        return {}
    if keys.get("gear_ratio"):
        keys["gear_ratio"] = tuple(keys["gear_ratio"])
    if section.trace_signals is not None:
        keys["trace_signals"] = tuple(section.trace_signals)
    return replace(section, **keys)


def _load(problems: Problems, load: dict | None, root: Path) -> LoadSection | dict:
    """[load] is optional: a rig without a load machine (free shaft) has none."""
    if load is None:
        return {}
    cls = _transport(problems, load, "load", LOAD_TRANSPORTS)
    if cls is None:
        return {}
    section = cls.read(load, problems, root=root)
    map_name = load.get("map")
    load_map = None
    if section is not None:
        try:
            load_map = read_load_map(section.map)
        except ContentError as exc:
            for field_, reason in exc.problems:
                problems.add("load.map", f"{map_name}: {field_}: {reason}")
            section = None
    problem = external_stop_problem(load, "load")
    if problem is not None:
        problems.add(*problem)
    if load_map is not None and section.comm_loss == "watchdog" and not load_map.watchdog_timeout_ms:
        problems.add("load.map", f"{map_name}: no communication watchdog register: the machine keeps its torque when "
                                 f"the bench dies; add it to the map, or where the rig stops the machine by other "
                                 f"means write [load] {EXTERNAL_HINT}")
    return section if section is not None else {}
