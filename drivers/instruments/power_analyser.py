"""Yokogawa WT family power analyser (WT500/WT1800/WT5000 communication interface), the subset a drive test needs.

Channels of an `[[instruments]]` entry name WT functions, with the element number where the function has one:
U1 I1 P1 S1 Q1 LAMBDA1 FU1 FI1 (element 1..6), SIGMA elements as U_SIGMA... are not used, motor-option functions
SPEED TORQUE PM, efficiency ETA1..ETA4 (their formulas are set on the instrument), integration WP1 Q1.
Configuration: `:NUMeric:FORMat ASCii`, `:NUMeric:NORMal:NUMber n`, one `:NUMeric:NORMal:ITEM<k> <fn>,<el>` per
channel, `:INPut:VOLTage|CURRent:RANGe:ELEMent<el>` from each U/I channel's range, `:RATE` from poll_hz; then the
error queue (`:STATus:ERRor?`, the WT's own) must be empty. One poll is one `:NUMeric:NORMal:VALue?`.

Over-range: the WT answers 9.9E+37 for a value shown as OL (input past its range's peak) and 9.91E+37 for no data;
the driver also treats an rms U or I beyond its range as over-range. Either makes the value *not judged* (NaN in
the reading, its reason in `not_judged`), never a number.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

from drivers.contract.instruments import InstrumentConfig
from drivers.instruments.scpi import InstrumentError, ScpiSession

OVER_RANGE = 9.9e37              # WT: "OL"
NO_DATA = 9.91e37                # WT: "-----"
_CHANNEL = re.compile(r"^(U|I|P|S|Q|LAMBDA|FU|FI|WP|ETA[1-4]|SPEED|TORQUE|PM)([1-6]?)$")
_NO_ELEMENT = ("SPEED", "TORQUE", "PM", "ETA1", "ETA2", "ETA3", "ETA4")
_RATES_S = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


@dataclass(frozen=True)
class Reading:
    values: dict[str, float]                                  # signal -> value in its stated unit (NaN: not judged)
    not_judged: dict[str, str] = field(default_factory=dict)  # signal -> why


def parse_channel(channel: str) -> tuple[str, int | None]:
    m = _CHANNEL.match(channel.upper())
    if not m:
        raise InstrumentError(f"channel {channel!r}: not a WT function (U1, I1, P1, S1, Q1, LAMBDA1, FU1, FI1, WP1, "
                              "ETA1..4, SPEED, TORQUE, PM)")
    fn, el = m.group(1), m.group(2)
    if fn in _NO_ELEMENT:
        if el:
            raise InstrumentError(f"channel {channel!r}: {fn} has no element number")
        return fn, None
    if not el:
        raise InstrumentError(f"channel {channel!r}: {fn} needs an element number (1..6)")
    return fn, int(el)


def update_interval_s(poll_hz: float) -> float:
    """The WT's data update interval: the longest of its steps that still gives a new value each poll."""
    fitting = [r for r in _RATES_S if r <= 1.0 / poll_hz + 1e-12]
    return fitting[-1] if fitting else _RATES_S[0]


class WtPowerAnalyser:
    error_query = ":STATus:ERRor?"

    def __init__(self, cfg: InstrumentConfig, session: ScpiSession):
        self.cfg = cfg
        self.session = session
        self.items = [(c, *parse_channel(c.channel)) for c in cfg.channels]
        self.identity = ""

    @classmethod
    def open(cls, cfg: InstrumentConfig) -> "WtPowerAnalyser":
        try:
            items = [parse_channel(c.channel) for c in cfg.channels]
        except InstrumentError as exc:
            raise InstrumentError(f"instrument {cfg.name!r}: {exc}") from None
        session = ScpiSession(cfg.name, cfg.resource, cfg.timeout_s, cls.error_query)
        self = cls(cfg, session)
        try:
            self.identity = session.query("*IDN?")
            if not self.identity or "," not in self.identity:
                raise InstrumentError(f"instrument {cfg.name!r}: '*IDN?' answered garbage: {self.identity[:60]!r}")
            session.configure(self.setup_commands(items))
        except InstrumentError:
            session.close()
            raise
        return self

    def setup_commands(self, items: list[tuple[str, int | None]]) -> list[str]:
        interval = update_interval_s(self.cfg.poll_hz)
        out = ["*CLS", ":NUMeric:FORMat ASCii", f":RATE {round(interval * 1000)}MS",
               f":NUMeric:NORMal:NUMber {len(items)}"]
        for k, ((fn, el), c) in enumerate(zip(items, self.cfg.channels), start=1):
            out.append(f":NUMeric:NORMal:ITEM{k} {fn},{el}" if el is not None else f":NUMeric:NORMal:ITEM{k} {fn}")
            if fn in ("U", "I"):
                kind = "VOLTage" if fn == "U" else "CURRent"
                out.append(f":INPut:{kind}:RANGe:ELEMent{el} {c.range:g}")
        return out

    def poll(self) -> Reading:
        """One reading of every channel (signal -> value x scale); over-range values are NaN and not judged."""
        raw = self.session.query_floats(":NUMeric:NORMal:VALue?", len(self.items))
        values: dict[str, float] = {}
        why: dict[str, str] = {}
        for (channel, fn, _el), value in zip(self.items, raw):
            reason = None
            if abs(value) >= NO_DATA * 0.9995 and abs(value) <= NO_DATA * 1.0005:
                reason = f"{channel.channel}: no data"
            elif abs(value) >= OVER_RANGE * 0.999 or not math.isfinite(value):
                reason = f"{channel.channel}: over-range (OL) on the {channel_range(channel)} range"
            elif fn in ("U", "I") and abs(value) > channel.range:
                reason = f"{channel.channel}: {value:g} {channel.unit} beyond its {channel.range:g} {channel.unit} range"
            if reason:
                why[channel.signal] = reason
                values[channel.signal] = math.nan
            else:
                values[channel.signal] = value * channel.scale
        return Reading(values, why)

    def integration(self, command: str) -> None:
        """':INTEGrate:STARt' | ':INTEGrate:STOP' | ':INTEGrate:RESet', then the error queue must stay empty."""
        self.session.write(command)
        self.session.check_errors(command)

    def close(self) -> None:
        self.session.close()


def channel_range(channel) -> str:
    return f"{channel.range:g} {channel.unit}"
