"""A drive's own units and the bench's physical ones.

The bench decides in shaft units: mechanical rad/s, rad, N*m, A, V (drivers.contract.signals). A CiA 402 drive reports and
accepts its own: velocity in the unit its SI unit velocity object says (0x60A9, e.g. rev/min or increments/s),
torque and current in per mille of the motor's rated values (0x6076, 0x6075), DC-link voltage in mV. This module
turns those into a factor per object: physical value = drive value x factor, drive value = physical / factor.

SI unit objects (CiA 402 0x60A8/0x60A9, codes of CiA 303-2): UNSIGNED32, bits 31-24 the decimal exponent (a signed
byte: 0xFD = 10^-3), bits 23-16 the numerator unit, bits 15-8 the denominator unit, bits 7-0 zero.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from drivers.contract.errors import ContentError

TWO_PI = 2.0 * math.pi

# CiA 303-2 unit codes a rotary drive uses, as (name, value in SI: rad for angles, s for times). Increments depend
# on the encoder and are resolved with the encoder resolution.
ANGLE_UNITS = {0x10: ("rad", 1.0), 0x41: ("deg", math.pi / 180.0), 0xB4: ("rev", TWO_PI), 0xB5: ("inc", None)}
TIME_UNITS = {0x03: ("s", 1.0), 0x47: ("min", 60.0), 0x48: ("h", 3600.0)}
PREFIXES = {-6: "u", -3: "m", -2: "c", -1: "d", 0: "", 3: "k"}


@dataclass(frozen=True)
class VelocityUnit:
    """A velocity unit: 10^exponent x angle unit per time unit. `code` is its 0x60A9 value."""

    exponent: int
    angle: int        # CiA 303-2 code: 0x10 rad, 0x41 deg, 0xB4 rev, 0xB5 inc
    time: int         # 0x03 s, 0x47 min, 0x48 h

    @property
    def code(self) -> int:
        return (self.exponent & 0xFF) << 24 | self.angle << 16 | self.time << 8

    @property
    def name(self) -> str:
        prefix = PREFIXES.get(self.exponent, f"1e{self.exponent} ")
        return f"{prefix}{ANGLE_UNITS[self.angle][0]}/{TIME_UNITS[self.time][0]}"

    @property
    def needs_encoder(self) -> bool:
        return self.angle == 0xB5

    def rad_s_per_unit(self, increments_per_rev: float | None = None) -> float:
        """Mechanical rad/s of one unit (of the shaft the unit refers to)."""
        angle = ANGLE_UNITS[self.angle][1]
        if angle is None:
            if not increments_per_rev or increments_per_rev <= 0:
                raise ContentError(f"{self.name}: the encoder resolution (increments per revolution) is not known")
            angle = TWO_PI / increments_per_rev
        return 10.0 ** self.exponent * angle / TIME_UNITS[self.time][1]


def decode_velocity_unit(code: int) -> VelocityUnit:
    """A 0x60A9 value -> VelocityUnit; ContentError for anything that is not a rotary velocity."""
    if not 0 <= code <= 0xFFFFFFFF:
        raise ContentError(f"0x{code:X} is not an UNSIGNED32 SI unit")
    exponent = (code >> 24) & 0xFF
    exponent = exponent - 0x100 if exponent >= 0x80 else exponent
    angle, time_unit, reserved = (code >> 16) & 0xFF, (code >> 8) & 0xFF, code & 0xFF
    if reserved:
        raise ContentError(f"0x{code:08X}: bits 7-0 of an SI unit must be 0")
    if angle not in ANGLE_UNITS:
        raise ContentError(f"0x{code:08X}: numerator unit 0x{angle:02X} is not an angle (rad, deg, rev, inc); "
                        "the bench drives rotary shafts")
    if time_unit not in TIME_UNITS:
        raise ContentError(f"0x{code:08X}: denominator unit 0x{time_unit:02X} is not a time (s, min, h)")
    if not -9 <= exponent <= 9:
        raise ContentError(f"0x{code:08X}: exponent {exponent} is not a plausible velocity prefix")
    return VelocityUnit(exponent, angle, time_unit)


_NAME_RE = re.compile(r"^(?P<scale>\d+(\.\d+)?\s*)?(?P<prefix>[umcdk]?)(?P<angle>rad|deg|rev|inc)/(?P<time>s|min|h)$")
ALIASES = {"rpm": "rev/min", "mrad/s": "mrad/s", "rad/s": "rad/s", "rps": "rev/s"}


def parse_velocity_unit(text: str) -> VelocityUnit:
    """A unit as a bench config writes it: "rpm", "rev/min", "0.1 rpm" is not SI (write "drev/min"), "inc/s",
    "mrad/s", "rad/s", "deg/s", or a 0x60A9 code "0x00B44700"."""
    t = text.strip()
    if re.fullmatch(r"0[xX][0-9a-fA-F]{1,8}", t):
        return decode_velocity_unit(int(t, 16))
    t = ALIASES.get(t, t)
    if t.endswith("rpm"):
        t = t[:-3] + "rev/min"
    m = _NAME_RE.match(t)
    if not m or m.group("scale"):
        raise ContentError(f"{text!r} is not a velocity unit (examples: rpm, rev/min, drev/min, inc/s, rad/s, "
                        "mrad/s, deg/s, or a 0x60A9 code such as 0x00B44700)")
    exponent = {p: e for e, p in PREFIXES.items()}[m.group("prefix")]
    angle = next(code for code, (name, _) in ANGLE_UNITS.items() if name == m.group("angle"))
    time_unit = next(code for code, (name, _) in TIME_UNITS.items() if name == m.group("time"))
    return VelocityUnit(exponent, angle, time_unit)


RPM = parse_velocity_unit("rpm")
INC_PER_S = parse_velocity_unit("inc/s")
MRAD_PER_S = parse_velocity_unit("mrad/s")


SIDES = ("motor", "shaft")


@dataclass(frozen=True)
class VelocityScale:
    """Drive velocity value <-> mechanical rad/s of the bench's shaft (the driving shaft, where the load machine and
    the reference sensor sit).

    CiA 402's factor group: 0x608F position encoder resolution = encoder increments per MOTOR revolution, 0x6091 gear
    ratio = motor shaft revolutions (sub 1) per driving shaft revolutions (sub 2). `side` says which shaft the unit
    counts: "motor" goes through the gear ratio (speed of the driving shaft = motor speed x shaft_revs / motor_revs),
    "shaft" does not. Increments count the motor encoder (0x608F) unless stated otherwise; angle units (rev, rad, deg)
    are CiA 402 user units of the driving shaft unless the drive or the bench config says they count the motor (many
    drives report motor rpm). None: that default."""

    unit: VelocityUnit
    increments_per_rev: float | None = None
    gear_motor_revs: float = 1.0            # 0x6091 sub 1
    gear_shaft_revs: float = 1.0            # 0x6091 sub 2
    side: str | None = None                 # "motor" | "shaft"; None: increments motor, angle units shaft

    @property
    def counts(self) -> str:
        return self.side or ("motor" if self.unit.needs_encoder else "shaft")

    @property
    def geared(self) -> bool:
        return self.gear_motor_revs != self.gear_shaft_revs

    @property
    def rad_s_per_unit(self) -> float:
        factor = self.unit.rad_s_per_unit(self.increments_per_rev)
        if self.counts == "motor":
            factor *= self.gear_shaft_revs / self.gear_motor_revs
        return factor

    def to_rad_s(self, value: float) -> float:
        return value * self.rad_s_per_unit

    def to_drive(self, speed_mech_rad_s: float) -> int:
        return round(speed_mech_rad_s / self.rad_s_per_unit)

    def describe(self) -> str:
        text = f"{self.unit.name} (0x{self.unit.code:08X}) of the {self.counts} = {self.rad_s_per_unit:.9g} rad/s " \
               "(driving shaft) per unit"
        if self.unit.needs_encoder:
            text += f", {self.increments_per_rev:g} increments/rev"
        if self.geared or self.counts == "motor":
            text += f", gear {self.gear_motor_revs:g}:{self.gear_shaft_revs:g} (motor:shaft revs)"
        return text


PER_MILLE = 1e-3
MILLI = 1e-3
