"""Scenario files (TOML, schema_version = 1): profiles, injections, limits and acceptance criteria.

A scenario is data. load_scenario() validates the whole file and raises InputError listing every problem as
`<file>: <field>: <reason>`; the file's sha256 goes into the run record. The schema is documented in
docs/scenarios.md.
"""

from __future__ import annotations

import bisect
import hashlib
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from bench.inputs.benchconfig import BenchConfig, drive_description, load_bench_config
from bench.inputs.criteria import CriterionSpec, parse_criteria
import bench.inputs.capture_criteria  # noqa: F401  (registers the kinds judged on instruments' records)
from bench.inputs.drive_kind import check_drive_kind
from bench.inputs.requirements import parse_requirements
from drivers.contract.checks import Problems, find_repo_root, read_toml_with_bytes, resolve_path
from drivers.contract.errors import ContentError, InputError
from bench.run.load_emulation import EMULABLE, emulable
from drivers.contract import parameters
from drivers.contract.load_map import LoadMode, read_load_map
from drivers.contract.toml_file import parse_toml_bytes
from drivers.contract.parameters import Capability, Parameter

SCHEMA_VERSION = 1
GRAVITY_M_S2 = 9.80665
RPM = math.pi / 30.0   # mech rad/s per rpm


@dataclass(frozen=True)
class SpeedSegment:
    """Reference goes linearly from from_mech_rad_s at start_s to to_mech_rad_s at end_s."""
    kind: str                # "hold" | "step" | "ramp" | "reversal"
    start_s: float
    end_s: float
    from_mech_rad_s: float
    to_mech_rad_s: float


@dataclass(frozen=True)
class LoadSegment:
    kind: str                # "torque" | "viscous" | "brake" | "crane"
    start_s: float
    end_s: float
    mode: LoadMode
    value: float             # N*m (TORQUE, BRAKE) or N*m/(rad/s) (VISCOUS)


@dataclass(frozen=True)
class Injection:
    at_s: float
    name: str
    value: float


@dataclass(frozen=True)
class Limits:
    overspeed_mech_rad_s: float
    overcurrent_a: float
    max_duration_s: float            # wall-clock seconds the whole run may take
    pos_err_max_elec_rad: float | None = None
    vdc_max_v: float | None = None


@dataclass(frozen=True)
class Scenario:
    path: Path
    sha256: str
    schema_version: int
    name: str
    description: str
    bench: Path
    duration_s: float
    seed: int | None
    speed_segments: tuple[SpeedSegment, ...]
    load_segments: tuple[LoadSegment, ...]
    injections: tuple[Injection, ...]
    limits: Limits
    criteria: tuple[CriterionSpec, ...]
    drive_kind: str | None = None
    requirements: tuple[str, ...] = ()        # ids the run gives evidence for (bench/inputs/requirements.py)
    _speed_starts: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _load_starts: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_speed_starts", tuple(s.start_s for s in self.speed_segments))
        object.__setattr__(self, "_load_starts", tuple(s.start_s for s in self.load_segments))

    def speed_ref_at(self, t_s: float) -> float:
        """Mechanical rad/s. Before the first segment 0; between segments the last segment's end value."""
        i = bisect.bisect_right(self._speed_starts, t_s) - 1
        if i < 0:
            return 0.0
        seg = self.speed_segments[i]
        if t_s >= seg.end_s or seg.end_s == seg.start_s:
            return seg.to_mech_rad_s
        frac = (t_s - seg.start_s) / (seg.end_s - seg.start_s)
        return seg.from_mech_rad_s + frac * (seg.to_mech_rad_s - seg.from_mech_rad_s)

    def load_at(self, t_s: float) -> tuple[LoadMode, float]:
        """(mode, value) of the load machine at t_s; (TORQUE, 0.0) outside every load segment."""
        i = bisect.bisect_right(self._load_starts, t_s) - 1
        if i >= 0:
            seg = self.load_segments[i]
            if t_s < seg.end_s:
                return seg.mode, seg.value
        return LoadMode.TORQUE, 0.0

    def simulator_injections(self) -> tuple[Injection, ...]:
        """Injections only a simulator can honour (plant factors, device and wire faults)."""
        return tuple(inj for inj in self.injections if (p := parameters.lookup(inj.name)) and p.simulator_only)


_TOP_KEYS = ("schema_version", "name", "description", "bench", "duration_s", "seed", "requirements", "drive_kinds",
             "speed", "load", "injection", "limits", "criteria")
_SPEED_KEYS = {
    "hold": ("kind", "start_s", "end_s", "speed_mech_rad_s", "speed_rpm"),
    "step": ("kind", "at_s", "end_s", "speed_mech_rad_s", "speed_rpm"),
    "ramp": ("kind", "start_s", "end_s", "speed_mech_rad_s", "speed_rpm", "from_speed_mech_rad_s",
             "from_speed_rpm"),
    "reversal": ("kind", "start_s", "end_s", "from_speed_mech_rad_s", "from_speed_rpm"),
}
_LOAD_KEYS = {
    "torque": ("kind", "start_s", "end_s", "torque_nm"),
    "viscous": ("kind", "start_s", "end_s", "coeff_nm_per_rad_s"),
    "brake": ("kind", "start_s", "end_s", "torque_nm"),
    "crane": ("kind", "start_s", "end_s", "mass_kg", "drum_radius_m", "gravity_m_s2"),
}
_LIMIT_KEYS = ("overspeed_mech_rad_s", "overspeed_rpm", "overcurrent_a", "max_duration_s",
               "pos_err_max_elec_rad", "vdc_max_v")


MAX_DURATION_S = 86_400.0      # 24 h of drive time: beyond that a number is a typo, not a test


def default_max_duration_s(duration_s: float) -> float:
    """Wall-clock allowance when a scenario gives none: ten times the drive time plus 30 s of setup."""
    return 10.0 * duration_s + 30.0


def load_scenario(path: str | Path, bench: str | Path | None = None) -> Scenario:
    """Read and validate a scenario file. `bench` overrides the file's bench config (e.g. `--bench`)."""
    return parse_scenario(path, bench)[0]


def read_scenario_source(path: str | Path, text: str | bytes | None = None) -> tuple[dict, bytes]:
    """(parsed table, bytes) of a scenario: the file at `path`, or `text` given for it (an upload, named by path)."""
    if text is None:
        return read_toml_with_bytes(Path(path))
    data = text.encode() if isinstance(text, str) else bytes(text)
    try:
        return parse_toml_bytes(data), data
    except ContentError as exc:
        raise InputError([f"{path}: (file): {exc}"]) from None


def parse_scenario(path: str | Path, bench: str | Path | None = None,
                   source: tuple[dict, bytes] | None = None) -> tuple[Scenario, BenchConfig]:
    """The validated scenario and the bench config it was validated against, each file read once. `source`: the
    scenario's (table, bytes) when already read (read_scenario_source); `path` then names it and anchors its
    relative bench path."""
    path = Path(path)
    raw, data = source if source is not None else read_toml_with_bytes(path)
    sha256 = hashlib.sha256(data).hexdigest()
    p = Problems(path)
    p.unknown_keys(raw, _TOP_KEYS, "")

    version = p.integer(raw, "schema_version", "")
    if version is not None and version != SCHEMA_VERSION:
        p.add("schema_version", f"unsupported version {version} (this bench reads {SCHEMA_VERSION})")
    name = p.string(raw, "name", "", required=False, default=path.stem)
    if name is not None and not name.strip():
        p.add("name", "must not be empty")
    description = p.string(raw, "description", "", required=False, default="") or ""
    duration = p.number(raw, "duration_s", "", positive=True)
    if duration is not None and duration > MAX_DURATION_S:
        p.add("duration_s", f"{duration:g} s is longer than a bench run may be ({MAX_DURATION_S:g} s, 24 h)")
        duration = None
    seed = p.integer(raw, "seed", "", required=False, min_value=0, max_value=2**63 - 1)

    bench_path, bench_cfg = _bench(p, raw, path, bench)
    drive_desc = drive_description(bench_cfg) if bench_cfg else None
    kind = drive_desc.drivebench_kind if drive_desc else None
    dur = duration if duration is not None else math.inf   # keep checking the rest when duration is bad

    speed = _speed_segments(p, _array_of_tables(p, raw, "speed"), dur)
    load = _load_segments(p, _array_of_tables(p, raw, "load"), dur)
    _check_load_machine(p, load, bench_cfg, bench_path)
    offered = drive_desc.offered_parameters() if drive_desc else None
    injections = _injections(p, _array_of_tables(p, raw, "injection"), dur, kind, offered, bench_cfg, bench_path)
    limits = _limits(p, raw, duration, speed)
    criteria = parse_criteria(p, _array_of_tables(p, raw, "criteria"), dur)
    requirements = parse_requirements(p, raw)
    p.raise_if_any()

    return Scenario(path=path.resolve(), sha256=sha256, schema_version=version, name=name,
                    description=description, bench=bench_path, duration_s=duration, seed=seed,
                    speed_segments=speed, load_segments=load, injections=injections, limits=limits,
                    criteria=criteria, drive_kind=kind, requirements=requirements), bench_cfg


def with_injections(scenario: Scenario, bench_cfg: BenchConfig, added: tuple[tuple[str, float], ...],
                    where: str = "override") -> Scenario:
    """The scenario with each (parameter, value) injected at 0 s, checked as an `[[injection]]` table of the file
    would be (offered by the drive, honoured by the bench, value in range): a campaign point's axes. The result is
    what the file with those tables appended would give (injections ordered by time, the added ones last at 0 s)."""
    p = Problems(scenario.path)
    drive_desc = drive_description(bench_cfg)
    offered = drive_desc.offered_parameters() if drive_desc else None
    items = [(f"{where}[{i}]", {"at_s": 0.0, "name": name, "value": value}) for i, (name, value) in enumerate(added)]
    extra = _injections(p, items, scenario.duration_s, scenario.drive_kind, offered, bench_cfg, scenario.bench)
    p.raise_if_any()
    return replace(scenario, injections=tuple(sorted((*scenario.injections, *extra), key=lambda inj: inj.at_s)))


# --- sections ------------------------------------------------------------------------------------------

def _bench(p: Problems, raw: dict, path: Path, override: str | Path | None) -> tuple[Path | None, dict | None]:
    if override is not None:
        bench_path = Path(override)
        if not bench_path.exists():
            p.add("bench", f"bench config given on the command line not found: {override}")
            return None, None
    else:
        value = p.string(raw, "bench", "")
        if value is None:
            return None, None
        root = find_repo_root(path)
        bench_path = resolve_path(value, root, path.resolve().parent)
        if bench_path is None:
            p.add("bench", f"bench config not found: {value!r} (looked under the repo root {root} and "
                           f"next to the scenario)")
            return None, None
    try:
        cfg = load_bench_config(bench_path)
    except InputError as e:
        p.extend(e.problems)
        return bench_path.resolve(), None
    check_drive_kind(p, raw, path, cfg, bench_path)
    return bench_path.resolve(), cfg


def _array_of_tables(p: Problems, raw: dict, key: str) -> list[tuple[str, dict]]:
    value = raw.get(key, [])
    if not isinstance(value, list):
        p.add(key, f"must be an array of tables, written [[{key}]]")
        return []
    out = []
    for i, item in enumerate(value):
        where = f"{key}[{i}]"
        if not isinstance(item, dict):
            p.add(where, f"must be a table, written [[{key}]]")
        else:
            out.append((where, item))
    return out


def _time(p: Problems, table: dict, key: str, where: str, duration: float, *, required: bool = True,
          allow_end: bool = True) -> float | None:
    t = p.number(table, key, where, required=required, min_value=0.0)
    if t is not None and t > duration:
        p.add(f"{where}.{key}", f"{t:g} s is after the end of the run (duration_s = {duration:g})")
        return None
    if t is not None and not allow_end and t == duration:
        p.add(f"{where}.{key}", f"{t:g} s is the end of the run (duration_s): it would never take effect")
        return None
    return t


def _speed_value(p: Problems, table: dict, where: str, prefix: str, required: bool) -> float | None:
    """`<prefix>speed_mech_rad_s` or `<prefix>speed_rpm`, exactly one, in mech rad/s."""
    rad_key, rpm_key = f"{prefix}speed_mech_rad_s", f"{prefix}speed_rpm"
    if rad_key in table and rpm_key in table:
        p.add(f"{where}.{rpm_key}", f"give either {rad_key} or {rpm_key}, not both")
        return None
    if rpm_key in table:
        v = p.number(table, rpm_key, where)
        return None if v is None else v * RPM
    if rad_key in table:
        return p.number(table, rad_key, where)
    if required:
        p.add(f"{where}.{rad_key}", f"missing (give {rad_key} or {rpm_key})")
    return None


def _speed_segments(p: Problems, items: list[tuple[str, dict]], duration: float) -> tuple[SpeedSegment, ...]:
    parsed = []
    for where, item in items:
        kind = p.string(item, "kind", where, choices=tuple(_SPEED_KEYS))
        if kind is None:
            continue
        p.unknown_keys(item, _SPEED_KEYS[kind], where)
        start = _time(p, item, "at_s" if kind == "step" else "start_s", where, duration, allow_end=False)
        end = _time(p, item, "end_s", where, duration, required=kind in ("ramp", "reversal"))
        to = _speed_value(p, item, where, "", required=True) if kind != "reversal" else 0.0
        frm = _speed_value(p, item, where, "from_", required=False) if kind in ("ramp", "reversal") else None
        if kind == "reversal" and frm == 0:
            p.add(where, "a reversal from zero speed")
            continue
        if start is None or to is None:
            continue
        if end is not None and (end < start or (end == start and kind in ("ramp", "reversal"))):
            p.add(f"{where}.end_s", f"{end:g} s must be after the start {start:g} s")
            continue
        parsed.append((where, kind, start, end, frm, to))

    _check_order(p, [(w, s, e) for w, _, s, e, _, _ in parsed])
    segments: list[SpeedSegment] = []
    for n, (where, kind, start, end, frm, to) in enumerate(parsed):
        if end is None:
            end = parsed[n + 1][2] if n + 1 < len(parsed) else duration
        before = segments[-1].to_mech_rad_s if segments else 0.0
        if kind in ("hold", "step"):
            segments.append(SpeedSegment(kind, start, end, to, to))
        elif kind == "ramp":
            segments.append(SpeedSegment(kind, start, end, before if frm is None else frm, to))
        else:
            frm = before if frm is None else frm
            if frm == 0:
                p.add(where, "a reversal from zero speed: give from_speed_mech_rad_s or from_speed_rpm")
                continue
            segments.append(SpeedSegment(kind, start, end, frm, -frm))
    return tuple(segments)


def _check_order(p: Problems, spans: list[tuple[str, float, float | None]]) -> None:
    for (w0, s0, e0), (w1, s1, _) in zip(spans, spans[1:]):
        if s1 < s0:
            p.add(w1, f"starts at {s1:g} s, before {w0} ({s0:g} s): segments must be in time order")
        elif s1 == s0:
            p.add(w1, f"starts at {s1:g} s, the same time as {w0}")
        elif e0 is not None and s1 < e0:
            p.add(w1, f"starts at {s1:g} s, overlapping {w0} which ends at {e0:g} s")


def _load_segments(p: Problems, items: list[tuple[str, dict]], duration: float) -> tuple[LoadSegment, ...]:
    parsed = []
    for where, item in items:
        kind = p.string(item, "kind", where, choices=tuple(_LOAD_KEYS))
        if kind is None:
            continue
        p.unknown_keys(item, _LOAD_KEYS[kind], where)
        start = _time(p, item, "start_s", where, duration, allow_end=False)
        end = _time(p, item, "end_s", where, duration, required=False)
        if kind == "torque":
            mode, value = LoadMode.TORQUE, p.number(item, "torque_nm", where)
        elif kind == "brake":
            mode, value = LoadMode.BRAKE, p.number(item, "torque_nm", where, min_value=0.0)
        elif kind == "viscous":
            mode, value = LoadMode.VISCOUS, p.number(item, "coeff_nm_per_rad_s", where, min_value=0.0)
        else:
            mass = p.number(item, "mass_kg", where, positive=True)
            radius = p.number(item, "drum_radius_m", where, positive=True)
            g = p.number(item, "gravity_m_s2", where, required=False, default=GRAVITY_M_S2, positive=True)
            mode, value = LoadMode.TORQUE, (None if None in (mass, radius, g) else mass * g * radius)
        if value is None or start is None:
            continue
        if end is not None and end <= start:
            p.add(f"{where}.end_s", f"{end:g} s must be after the start {start:g} s")
            continue
        parsed.append((where, kind, start, end, mode, value))
    _check_order(p, [(w, s, e) for w, _, s, e, _, _ in parsed])
    segments = []
    for n, (where, kind, start, end, mode, value) in enumerate(parsed):
        if end is None:
            end = parsed[n + 1][2] if n + 1 < len(parsed) else duration
        segments.append(LoadSegment(kind, start, end, mode, value))
    return tuple(segments)


def _check_load_machine(p: Problems, segments: tuple[LoadSegment, ...], bench_cfg: BenchConfig | None,
                        bench_path: Path | None) -> None:
    """Load segments need a load machine, and one that has their mode (its register map says which)."""
    if not segments or bench_cfg is None:
        return
    load = bench_cfg.load
    if not load:
        p.add("load", f"the profile loads the shaft but bench config {bench_path} has no load machine ([load])")
        return
    if not load.get("map"):
        return
    modes = read_load_map(load["map"]).modes
    speed_measured = bench_cfg.reference_source == "load"
    for i, seg in enumerate(segments):
        if seg.mode not in modes and not emulable(seg.mode, modes, speed_measured):
            why = "" if seg.mode not in EMULABLE or LoadMode.TORQUE not in modes else (
                " and the bench cannot emulate it without measuring the shaft speed ([reference] source = \"load\")")
            p.add(f"load[{i}].kind", f"{seg.kind!r} needs {seg.mode.name.lower()} mode; the load machine of bench "
                                    f"config {bench_path} has {', '.join(m.name.lower() for m in modes)}{why}")


def _check_injection_name(p: Problems, field_: str, name: str, kind: str | None,
                          offered: tuple[Parameter, ...] | None, bench_cfg: BenchConfig | None,
                          bench_path: Path | None) -> Parameter | None:
    """The parameter record when the bench's drive offers `name` and the bench can honour its kind; else a problem.
    `offered` is None when the bench config could not be read (then any catalogue name is accepted here)."""
    param = next((q for q in offered if q.name == name), None) if offered is not None else parameters.lookup(name)
    if param is None:
        if offered is not None and name in parameters.ALL_NAMES:
            eds = Path(bench_cfg.drive["eds"]).name if bench_cfg and bench_cfg.drive.get("eds") else "none"
            what = f"a {kind} drive" if kind else f"the drive of bench config {bench_path} (EDS {eds})"
            p.add(field_, f"{name!r} is not a parameter of {what}")
        else:
            known = sorted(q.name for q in offered) if offered is not None else sorted(parameters.ALL_NAMES)
            p.add(field_, f"unknown hook {name!r} (known: {', '.join(known) or 'none: the drive offers no parameters'})")
        return None
    if bench_cfg is not None and param.capability is not Capability.NONE \
            and not getattr(bench_cfg.bench, param.capability.value):
        if param.capability is Capability.PLANT:
            p.add(field_, f"simulator-only injection {name!r} needs a simulator, but bench config {bench_path} has "
                          f"plant_injections = false")
        else:
            p.add(field_, f"wire fault {name!r} needs a simulated rig with frame-level fault wrappers, but bench "
                          f"config {bench_path} has wire_faults = false")
        return None
    return param


def _injections(p: Problems, items: list[tuple[str, dict]], duration: float, kind: str | None,
                offered: tuple[Parameter, ...] | None, bench_cfg: BenchConfig | None,
                bench_path: Path | None) -> tuple[Injection, ...]:
    out = []
    for where, item in items:
        p.unknown_keys(item, ("at_s", "name", "value"), where)
        at = _time(p, item, "at_s", where, duration, allow_end=False)
        name = p.string(item, "name", where)
        value = p.number(item, "value", where)
        param = None
        if name is not None:
            param = _check_injection_name(p, f"{where}.name", name, kind, offered, bench_cfg, bench_path)
            if param is None:
                continue
        if param is not None and value is not None:
            reason = param.problem(value)
            if reason:
                p.add(f"{where}.value", reason)
                continue
        if None not in (at, name, value):
            out.append(Injection(at, name, value))
    return tuple(sorted(out, key=lambda inj: inj.at_s))


def _limits(p: Problems, raw: dict, duration: float | None, speed: tuple[SpeedSegment, ...]) -> Limits | None:
    table = p.table(raw, "limits", "")
    if table is None:
        return None
    w = "limits"
    p.unknown_keys(table, _LIMIT_KEYS, w)
    if "overspeed_mech_rad_s" in table and "overspeed_rpm" in table:
        p.add("limits.overspeed_rpm", "give either overspeed_mech_rad_s or overspeed_rpm, not both")
        overspeed = None
    elif "overspeed_rpm" in table:
        rpm = p.number(table, "overspeed_rpm", w, positive=True)
        overspeed = None if rpm is None else rpm * RPM
    else:
        overspeed = p.number(table, "overspeed_mech_rad_s", w, positive=True)
    field_ = "limits.overspeed_rpm" if "overspeed_rpm" in table else "limits.overspeed_mech_rad_s"
    peak = max((max(abs(s.from_mech_rad_s), abs(s.to_mech_rad_s)) for s in speed), default=0.0)
    if overspeed is not None and overspeed <= peak:     # answered in the unit the file used
        unit, k = ("rpm", RPM) if field_.endswith("rpm") else ("mech rad/s", 1.0)
        p.add(field_, f"{overspeed / k:.6g} {unit} is not above the profile's peak reference {peak / k:.6g} {unit}")
    overcurrent = p.number(table, "overcurrent_a", w, positive=True)
    max_dur = p.number(table, "max_duration_s", w, required=False, positive=True)
    if duration is not None:
        if max_dur is None and "max_duration_s" not in table:
            max_dur = default_max_duration_s(duration)
        elif max_dur is not None and max_dur < duration:
            p.add("limits.max_duration_s", f"{max_dur:g} s (wall clock) is shorter than duration_s = {duration:g}")
    if max_dur is not None and max_dur > default_max_duration_s(MAX_DURATION_S):
        p.add("limits.max_duration_s", f"{max_dur:g} s: longer than any run may take "
                                       f"({default_max_duration_s(MAX_DURATION_S):g} s)")
    pos = p.number(table, "pos_err_max_elec_rad", w, required=False, positive=True)
    if pos is not None and pos > math.pi:
        p.add("limits.pos_err_max_elec_rad", f"{pos:g} rad can never trip: a wrapped angle error is at most pi")
    vdc = p.number(table, "vdc_max_v", w, required=False, positive=True)
    if None in (overspeed, overcurrent, max_dur):
        return None
    return Limits(overspeed, overcurrent, max_dur, pos, vdc)


