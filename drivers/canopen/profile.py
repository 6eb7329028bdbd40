"""A drive profile: which object of a CANopen drive gives which bench signal, in which unit.

Two kinds:
- "cia402": standard CiA 402 objects only, in the drive's own units (any drive): velocity actual 0x606C ->
  speed_est_mech_rad_s, velocity demand 0x606B -> speed_ref_mech_rad_s, torque actual 0x6077 -> torque_est_nm
  (per mille of the rated torque 0x6076), current actual 0x6078 -> i_sy_a (per mille of the rated current 0x6075;
  CiA 402 leaves open which current, most drives report the torque-producing one), DC link 0x6079 -> vdc_v (mV);
  target velocity 0x60FF in the drive's velocity unit. Overridable per signal in the bench config.
- "drivebench": the drive carries drivebench's extension (drivers.contract.extension): its REAL32 signal objects, drive
  clock and trace recorder, plus the standard objects for the state machine and the velocity target.

Units come from the device at connect time (0x60A9 SI unit velocity, 0x608F encoder resolution, 0x6091 gear
ratio, 0x6075/0x6076 rated current/torque) or from the bench config where the drive has no such object; where
both exist they must agree, and an unknown velocity unit stops the run before anything moves. Which shaft the
velocity unit counts (motor or driving shaft) no CiA 402 object says: increments count the motor encoder (0x608F is
increments per motor revolution); for rev/rad/deg behind a gear ratio other than 1:1 the bench config must say
(`velocity_side`), or the run is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from drivers.contract import extension
from drivers.contract import objects as o
from drivers.contract.errors import ContentError
from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract.toml_file import known_entries
from drivers.contract.units import (MILLI, PER_MILLE, SIDES, VelocityScale, VelocityUnit, decode_velocity_unit,
                           parse_velocity_unit)

PROFILES = ("auto", "cia402", "drivebench")

# signal -> (object, what scales it): "velocity", "torque", "current", "millivolt"
STANDARD_SOURCES: dict[str, tuple[int, str]] = {
    "speed_est_mech_rad_s": (o.VELOCITY_ACTUAL, "velocity"),
    "speed_ref_mech_rad_s": (o.VELOCITY_DEMAND, "velocity"),
    "torque_est_nm": (o.TORQUE_ACTUAL, "torque"),
    "i_sy_a": (o.CURRENT_ACTUAL, "current"),
    "vdc_v": (o.DC_LINK_VOLTAGE, "millivolt"),
}
SCALES = ("velocity", "torque", "current", "millivolt", "factor")


@dataclass(frozen=True)
class SignalSource:
    signal: str
    index: int
    subindex: int
    factor: float               # physical value = drive value x factor
    unit_note: str              # how the factor was found, for the record

    def as_dict(self) -> dict[str, Any]:
        return {"signal": self.signal, "object": f"0x{self.index:04X}:{self.subindex:02X}", "factor": self.factor,
                "unit": self.unit_note}


@dataclass(frozen=True)
class DriveProfile:
    kind: str                                   # "cia402" | "drivebench"
    velocity: VelocityScale
    sources: tuple[SignalSource, ...]
    rated_torque_nm: float | None = None
    rated_current_a: float | None = None
    notes: dict[str, str] = field(default_factory=dict)     # where each unit came from
    unread: tuple[str, ...] = ()            # velocity factors the drive did not report: stated or CiA default
    units_confirmed: str | None = None      # the bench config's word on how the stated ones were checked

    @property
    def extension(self) -> bool:
        return self.kind == "drivebench"

    def source(self, signal: str) -> SignalSource | None:
        return next((s for s in self.sources if s.signal == signal), None)

    def as_record(self) -> dict[str, Any]:
        return {"kind": self.kind, "velocity_unit": self.velocity.describe(), "velocity_side": self.velocity.counts,
                "gear_ratio_motor_shaft": [self.velocity.gear_motor_revs, self.velocity.gear_shaft_revs],
                "rad_s_per_unit": self.velocity.rad_s_per_unit, "rated_torque_nm": self.rated_torque_nm,
                "rated_current_a": self.rated_current_a, "units_from": dict(self.notes),
                "velocity_factors_not_read": list(self.unread), "units_confirmed": self.units_confirmed,
                "signals": [s.as_dict() for s in self.sources]}


@dataclass(frozen=True)
class ProfileConfig:
    """What a bench config may state about a drive's profile ([drive] keys of a CANopen drive)."""

    profile: str = "auto"
    velocity_unit: str | None = None
    encoder_increments_per_rev: float | None = None
    gear_ratio: tuple[float, float] | None = None       # (motor revolutions, driving shaft revolutions)
    velocity_side: str | None = None                     # "motor" | "shaft": which shaft the velocity unit counts
    units_confirmed: str | None = None                   # free shaft: how the stated units were checked on the rig
    rated_torque_nm: float | None = None
    rated_current_a: float | None = None
    signals: dict[str, dict] = field(default_factory=dict)   # signal -> {"object": (index, sub), "scale": ..., "factor": ...}

    @classmethod
    def from_section(cls, section: dict) -> "ProfileConfig":
        gear = section.get("gear_ratio")
        return cls(profile=section.get("profile", "auto"), velocity_unit=section.get("velocity_unit"),
                   velocity_side=section.get("velocity_side"), units_confirmed=section.get("units_confirmed"),
                   encoder_increments_per_rev=section.get("encoder_increments_per_rev"),
                   gear_ratio=tuple(gear) if gear else None, rated_torque_nm=section.get("rated_torque_nm"),
                   rated_current_a=section.get("rated_current_a"), signals=dict(section.get("signals") or {}))


Reader = Callable[[int, int], "int | None"]   # SDO read of a standard object; None when the device has no such object


def _agree(what: str, read: float | None, stated: float | None, same: Callable[[float, float], bool],
           where_read: str, notes: dict[str, str]) -> float | None:
    if read is not None and stated is not None and not same(read, stated):
        raise ContentError(f"{what}: the drive reports {read} ({where_read}), the bench config states {stated}: "
                           "correct the bench config (or the drive) before running")
    if read is not None:
        notes[what] = f"read from the drive ({where_read})"
        return read
    if stated is not None:
        notes[what] = "stated in the bench config (the drive has no such object)"
    return stated


SIDE_HELP = ("[drive] velocity_side = \"motor\" (the drive's unit counts the motor, e.g. motor rpm: the gear ratio is "
             "applied) or \"shaft\" (it counts the driving shaft, CiA 402 user units: not applied)")


def _velocity_side(unit: VelocityUnit, gear: tuple[float, float] | None, stated: str | None, gear_from: str,
                   notes: dict[str, str]) -> str:
    """Which shaft the drive's velocity unit counts, and where that came from (notes); ContentError where a gear ratio
    other than 1:1 makes it matter and nothing says."""
    geared = gear is not None and gear[0] != gear[1]
    if stated is not None:
        notes["velocity_side"] = f"{stated}: stated in the bench config (velocity_side)"
        return stated
    if unit.needs_encoder:
        notes["velocity_side"] = "motor: increments of the motor encoder (CiA 402 0x608F: increments per motor rev)"
        return "motor"
    if geared:
        raise ContentError(f"velocity unit {unit.name} with a gear ratio of {gear[0]:g}:{gear[1]:g} ({gear_from}: "
                           f"motor revs : driving shaft revs): which shaft does the drive's {unit.name} count? No "
                           f"CiA 402 object says: state {SIDE_HELP}")
    notes["velocity_side"] = ("shaft: no gear (1:1), motor and driving shaft turn alike" if gear is not None else
                              "shaft: CiA 402 user unit, no gear ratio on the drive or in the bench config (checked "
                              "against the reference sensor at first motion; a free shaft needs units_confirmed)")
    return "shaft"


def resolve(cfg: ProfileConfig, vendor_id: int, product_code: int, read: Reader,
            has_object: Callable[[int], bool]) -> DriveProfile:
    """The profile of a connected drive. `read(index, sub)` reads the device (None when it has no such object);
    `has_object(index)` says whether the drive's EDS has the object."""
    if cfg.profile not in PROFILES:
        raise ContentError(f"profile {cfg.profile!r} is not one of {', '.join(PROFILES)}")
    kind = cfg.profile
    if kind == "auto":
        kind = "drivebench" if extension.carries_extension(vendor_id, product_code) else "cia402"
    notes: dict[str, str] = {}

    unit_code = read(o.SI_UNIT_VELOCITY, 0)
    try:
        read_unit = decode_velocity_unit(unit_code) if unit_code is not None else None
        stated_unit = parse_velocity_unit(cfg.velocity_unit) if cfg.velocity_unit else None
    except ContentError as exc:
        raise ContentError(f"velocity unit: {exc}") from None
    if read_unit is not None and stated_unit is not None and read_unit != stated_unit:
        raise ContentError(f"velocity unit: the drive reports {read_unit.name} (0x60A9 = 0x{unit_code:08X}), the bench "
                           f"config states {stated_unit.name}: correct the bench config (or the drive) before running")
    unit = read_unit or stated_unit
    if unit is None:
        raise ContentError("velocity unit unknown: the drive has no SI unit velocity (0x60A9); state it in the bench "
                           "config ([drive] velocity_unit, e.g. \"rpm\" or \"inc/s\") — the bench never assumes one")
    notes["velocity_unit"] = ("read from the drive (0x60A9)" if read_unit is not None
                              else "stated in the bench config (the drive has no 0x60A9)")

    increments = None
    if unit.needs_encoder:
        inc, revs = read(o.POSITION_ENCODER_RESOLUTION, 1), read(o.POSITION_ENCODER_RESOLUTION, 2)
        increments = _agree("encoder_increments_per_rev", inc / revs if inc and revs else None,
                            cfg.encoder_increments_per_rev, lambda a, b: abs(a - b) < 1e-9 * max(a, b),
                            "0x608F", notes)
        if not increments:
            raise ContentError(f"velocity unit {unit.name}: the encoder resolution is unknown (no 0x608F): state "
                               "[drive] encoder_increments_per_rev")
    motor_revs, shaft_revs = read(o.GEAR_RATIO, 1), read(o.GEAR_RATIO, 2)
    gear_read = (float(motor_revs), float(shaft_revs)) if motor_revs and shaft_revs else None
    gear = _agree("gear_ratio", gear_read, cfg.gear_ratio, lambda a, b: a[0] * b[1] == a[1] * b[0], "0x6091", notes)
    side = _velocity_side(unit, gear, cfg.velocity_side, "0x6091" if gear_read is not None else "[drive] gear_ratio",
                          notes)
    if gear is None:
        if side == "motor":
            what = ("counts motor encoder increments" if unit.needs_encoder and cfg.velocity_side is None
                    else "counts the motor (velocity_side)")
            raise ContentError(f"velocity unit {unit.name} {what} and the drive has no gear ratio (0x6091): state "
                               "[drive] gear_ratio = [motor_revs, shaft_revs] ([1, 1] without a gearbox)")
        gear = (1.0, 1.0)
        notes["gear_ratio"] = ("not applied: the velocity unit counts the driving shaft (no 0x6091 on the drive, "
                               "none stated)")
    velocity = VelocityScale(unit, increments, gear[0], gear[1], side)
    notes["velocity_factor"] = velocity.describe()

    torque_mnm = read(o.MOTOR_RATED_TORQUE, 0)
    current_ma = read(o.MOTOR_RATED_CURRENT, 0)
    rated_torque = _agree("rated_torque_nm", torque_mnm * MILLI if torque_mnm else None, cfg.rated_torque_nm,
                          lambda a, b: abs(a - b) <= 1e-6 * max(a, b), "0x6076", notes)
    rated_current = _agree("rated_current_a", current_ma * MILLI if current_ma else None, cfg.rated_current_a,
                           lambda a, b: abs(a - b) <= 1e-6 * max(a, b), "0x6075", notes)

    factors = {"velocity": (velocity.rad_s_per_unit, velocity.unit.name),
               "torque": (rated_torque * PER_MILLE if rated_torque else None, "per mille of the rated torque"),
               "current": (rated_current * PER_MILLE if rated_current else None, "per mille of the rated current"),
               "millivolt": (MILLI, "mV")}
    sources: list[SignalSource] = []
    if kind == "cia402":
        for signal, (index, scale) in STANDARD_SOURCES.items():
            if signal in cfg.signals or not has_object(index):
                continue
            factor, note = factors[scale]
            if factor is not None:
                sources.append(SignalSource(signal, index, 0, factor, note))
    for signal, spec in cfg.signals.items():
        index, subindex = spec["object"]
        if "factor" in spec:
            factor, note = float(spec["factor"]), f"factor {spec['factor']} stated in the bench config"
        else:
            factor, note = factors[spec["scale"]]
            if factor is None:
                raise ContentError(f"signals.{signal}: scale {spec['scale']!r} needs the motor's rated "
                                   f"{spec['scale']} (0x607{6 if spec['scale'] == 'torque' else 5} or "
                                   f"[drive] rated_{spec['scale']}_{'nm' if spec['scale'] == 'torque' else 'a'})")
        sources.append(SignalSource(signal, index, subindex, factor, note))
    unread = tuple(key for key in ("velocity_unit", "encoder_increments_per_rev", "gear_ratio", "velocity_side")
                   if key in notes and not notes[key].startswith(("read from the drive", "motor: increments",
                                                                   "shaft: no gear")))
    return DriveProfile(kind, velocity, tuple(sources), rated_torque, rated_current, notes, unread,
                        cfg.units_confirmed)


def check_section(section: dict, has_object: Callable[[int], bool], is_extension_eds: bool) -> list[tuple[str, str]]:
    """What validation can say from the EDS alone (no device): (field, reason) problems."""
    problems: list[tuple[str, str]] = []
    profile = section.get("profile", "auto")
    if profile == "drivebench" and not has_object(o.EXT_SIGNAL_BASE):
        problems.append(("drive.profile", "'drivebench' needs drivebench's extension objects, the EDS has none"))
    for index, name in ((o.CONTROLWORD, "controlword 0x6040"), (o.STATUSWORD, "statusword 0x6041"),
                        (o.TARGET_VELOCITY, "target velocity 0x60FF")):
        if not has_object(index):
            problems.append(("drive.eds", f"no {name}: the bench drives a CiA 402 drive in profile velocity mode"))
    if profile != "drivebench" and not is_extension_eds and not has_object(o.SI_UNIT_VELOCITY) \
            and not section.get("velocity_unit"):
        problems.append(("drive.velocity_unit", "the drive's EDS has no SI unit velocity (0x60A9): state the drive's "
                                                "velocity unit (e.g. \"rpm\", \"inc/s\"); the bench never assumes one"))
    unit = section.get("velocity_unit")
    if isinstance(unit, str) and unit:
        try:
            parsed = parse_velocity_unit(unit)
        except ContentError:
            pass                                # config_keys reports it
        else:
            if parsed.needs_encoder and not has_object(o.POSITION_ENCODER_RESOLUTION) \
                    and not section.get("encoder_increments_per_rev"):
                problems.append(("drive.encoder_increments_per_rev",
                                 f"{parsed.name} needs the encoder resolution and the EDS has no 0x608F"))
            gear = section.get("gear_ratio")
            if (not parsed.needs_encoder and isinstance(gear, list) and len(gear) == 2 and gear[0] != gear[1]
                    and not section.get("velocity_side")):
                problems.append(("drive.velocity_side", f"{parsed.name} with gear_ratio = {gear}: which shaft does the "
                                                        f"drive's unit count? state {SIDE_HELP}"))
            if section.get("velocity_side") == "motor" and not has_object(o.GEAR_RATIO) and not gear:
                problems.append(("drive.gear_ratio", "velocity_side = \"motor\" and the EDS has no gear ratio "
                                                     "(0x6091): state gear_ratio = [motor_revs, shaft_revs]"))
            if parsed.needs_encoder and not has_object(o.GEAR_RATIO) and not section.get("gear_ratio"):
                problems.append(("drive.gear_ratio", f"{parsed.name} counts motor increments and the EDS has no gear "
                                                     "ratio (0x6091): state gear_ratio = [motor_revs, shaft_revs]"))
    if not has_object(o.VELOCITY_ACTUAL) and "speed_est_mech_rad_s" not in (section.get("signals") or {}) \
            and not is_extension_eds:
        problems.append(("drive.eds", "no velocity actual value 0x606C: the bench cannot see the drive's speed"))
    return problems


def measurable(profile: DriveProfile) -> frozenset[str]:
    """Signals this drive gives (before the PDO mapping limits what arrives live)."""
    if profile.extension:
        return frozenset(SIGNAL_NAMES)
    return frozenset(s.signal for s in profile.sources)


# -- bench config keys ([drive] of a CANopen drive) -------------------------------------------------------------

PROFILE_KEYS = ("profile", "velocity_unit", "velocity_side", "units_confirmed", "encoder_increments_per_rev",
                "gear_ratio", "rated_torque_nm",
                "rated_current_a", "signals", "pdo", "comm_loss", "external_stop", "consumer_time_ms", "abort_option",
                "drill_margin_ms",
                "error_behaviour", "bench_node_id", "standstill_mech_rad_s", "stop_timeout_s", "can",
                "boot_timeout_s", "velocity_mode")
_POSITIVE = ("encoder_increments_per_rev", "rated_torque_nm", "rated_current_a")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value and abs(value) != float("inf")


def _object_ref(text: Any) -> tuple[int, int] | None:
    """"0x606C" or "0x2F01:02" -> (index, subindex)."""
    if not isinstance(text, str):
        return None
    head, _, sub = text.partition(":")
    try:
        index, subindex = int(head, 16), int(sub, 16) if sub else 0
    except ValueError:
        return None
    return (index, subindex) if 0x1000 <= index <= 0xFFFF and 0 <= subindex <= 0xFF else None


def config_keys(section: dict) -> tuple[dict[str, Any], list[tuple[str, str]]]:
    """The profile, PDO, comm-loss and python-can keys of a CANopen [drive] table, normalised, and (field, reason)
    problems. Units are checked here; whether the EDS has what they need, by check_section."""
    from drivers.contract import comm_loss
    from drivers.canopen.pdo import POLICIES

    out, problems = comm_loss.check_keys(section, comm_loss.STOP_KEYS + ("error_behaviour", "bench_node_id"))

    def bad(key: str, reason: str) -> None:
        problems.append((f"drive.{key}", reason))

    for key in PROFILE_KEYS:
        if key not in section or key in out or any(f == f"drive.{key}" for f, _ in problems):
            continue
        value = section[key]
        if key in ("profile", "pdo"):
            choices = {"profile": PROFILES, "pdo": POLICIES}[key]
            if value not in choices:
                bad(key, f"must be one of {', '.join(repr(c) for c in choices)}, got {value!r}")
                continue
        elif key == "velocity_unit":
            if not isinstance(value, str):
                bad(key, f"must be a string such as \"rpm\" or \"inc/s\", got {value!r}")
                continue
            try:
                parse_velocity_unit(value)
            except ContentError as exc:
                bad(key, str(exc))
                continue
        elif key == "units_confirmed":
            if not isinstance(value, str) or not value.strip():
                bad(key, "must say how the stated units were checked on the rig, e.g. \"hand tachometer: 20 rad/s "
                         "commanded read 191 rpm on the shaft, 2026-11-25\"")
                continue
        elif key == "velocity_side":
            if value not in SIDES:
                bad(key, f"must be \"motor\" or \"shaft\" (which shaft the drive's velocity unit counts), "
                         f"got {value!r}")
                continue
        elif key == "gear_ratio":
            if not (isinstance(value, list) and len(value) == 2 and all(_number(v) and v > 0 for v in value)):
                bad(key, f"must be [motor_revs, shaft_revs], two positive numbers, got {value!r}")
                continue
        elif key in _POSITIVE:
            if not _number(value) or value <= 0:
                bad(key, f"must be a number > 0, got {value!r}")
                continue
        elif key == "velocity_mode":
            if value not in ("auto", "pv", "csv"):
                bad(key, f"must be \"auto\" (profile velocity where 0x6502 has it, else cyclic synchronous velocity), "
                         f"\"pv\" or \"csv\", got {value!r}")
                continue
        elif key == "boot_timeout_s":
            if not _number(value) or not 0 <= value <= 600:
                bad(key, f"must be seconds, 0-600 (how long the drive may take to send its NMT boot-up), got {value!r}")
                continue
        elif key == "can":
            if not isinstance(value, dict):
                bad(key, "must be a table of python-can Bus() options (fd, data_bitrate, app_name, ...)")
                continue
        elif key == "signals":
            if not isinstance(value, dict):
                bad(key, "must be a table: signal = \"0x606C\" or { object = \"0x2F01:01\", factor = 0.001 }")
                continue
            value = _signals(value, problems)
        out[key] = value
    bench_id = section.get("bench_node_id", o.HEARTBEAT_BENCH_NODE_ID)
    if out.get("comm_loss", "heartbeat") == "heartbeat" and bench_id == section.get("node_id"):
        bad("bench_node_id", f"the bench's heartbeat node id ({bench_id}) must differ from the drive's node id")
    return out, problems


def _signals(table: dict, problems: list[tuple[str, str]]) -> dict[str, dict]:
    out = {}
    for signal, spec, where in known_entries(table, SIGNAL_NAMES, "drive.signals", "signal", problems):
        if isinstance(spec, str):
            spec = {"object": spec}
        if not isinstance(spec, dict) or set(spec) - {"object", "scale", "factor"}:
            problems.append((where, "must be \"0xINDEX[:SUB]\" or { object = \"0xINDEX[:SUB]\", scale = \"velocity\" "
                                    "| \"torque\" | \"current\" | \"millivolt\" } or { object, factor }"))
            continue
        ref = _object_ref(spec.get("object"))
        if ref is None:
            problems.append((where, f"object must be \"0xINDEX\" or \"0xINDEX:SUB\", got {spec.get('object')!r}"))
            continue
        standard = {index: scale for index, scale in STANDARD_SOURCES.values()}
        if "factor" in spec:
            if not _number(spec["factor"]) or spec["factor"] == 0:
                problems.append((where, f"factor must be a non-zero number, got {spec['factor']!r}"))
                continue
            out[signal] = {"object": ref, "factor": float(spec["factor"])}
        elif "scale" in spec or ref[0] in standard:
            scale = spec.get("scale", standard.get(ref[0]))
            if scale not in SCALES[:-1]:
                problems.append((where, f"scale must be one of velocity, torque, current, millivolt, got {scale!r}"))
                continue
            out[signal] = {"object": ref, "scale": scale}
        else:
            problems.append((where, f"0x{ref[0]:04X} is not a standard object: give its factor (physical = value x "
                                    "factor) or its scale"))
    return out


def static_measurable(section: dict, has_object: Callable[[int], bool], rated_in_eds: Callable[[int], bool],
                      is_extension_eds: bool) -> frozenset[str]:
    """What a CANopen drive will give, judged from its EDS and the bench config alone (before connecting): the
    extension's signals, or the standard objects the EDS has (torque and current only where the rated value is
    known) plus the signals the config maps."""
    if section.get("profile", "auto") == "drivebench" or (section.get("profile", "auto") == "auto" and is_extension_eds):
        return frozenset(SIGNAL_NAMES)
    rated = {"torque": bool(section.get("rated_torque_nm")) or rated_in_eds(o.MOTOR_RATED_TORQUE),
             "current": bool(section.get("rated_current_a")) or rated_in_eds(o.MOTOR_RATED_CURRENT),
             "velocity": True, "millivolt": True}
    signals = {signal for signal, (index, scale) in STANDARD_SOURCES.items() if has_object(index) and rated[scale]}
    return frozenset(signals | set(section.get("signals") or {}))
