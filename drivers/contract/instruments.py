"""A lab's instruments as a bench config names them: `[[instruments]]`, one typed frozen object each.

    [[instruments]]
    name = "analyser"                      # unique on the bench
    kind = "power_analyser"                # power_analyser | scope | daq
    resource = "TCPIP::192.168.1.20::10001::SOCKET"   # a VISA resource string (TCPIP SOCKET/INSTR, USB, ASRL)
    driver = "yokogawa-wt"                 # the family's driver (drivers/instruments)
    timeout_s = 2.0                        # every query
    poll_hz = 10.0                         # a power analyser: how often the bench reads it
    sample_rate_hz = 50000.0               # a scope/DAQ: the capture's rate
    [instruments.channels]                 # instrument channel -> signal, its unit, range and scaling
    U1 = { signal = "u_motor_v", unit = "V", range = 300.0 }
    I1 = { signal = "i_motor_a", unit = "A", range = 10.0, scale = 1.0 }

A signal's unit is stated here (a lab writes what its probes and shunts give), never assumed; `scale` multiplies the
instrument's reading (a probe's 10:1, a current clamp's A/V) and `range` is the instrument range the bench sets, so a
reading past it is over-range: not judged. This module holds data only: the drivers that speak SCPI (pyvisa) live in
drivers/instruments, and the contract imports none of them.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

from drivers.contract.checks import Problems

KINDS = ("power_analyser", "scope", "daq")
DRIVERS = {"power_analyser": ("yokogawa-wt",), "scope": ("scpi-scope",), "daq": ("scpi-scope",)}
UNITS = ("V", "A", "W", "VA", "var", "Hz", "N*m", "rad/s", "rad", "1", "%")
_RESOURCE = re.compile(r"^(TCPIP\d*::[^:]+::(\d+::SOCKET|[^:]+::INSTR|INSTR)|USB\d*::.+::INSTR|ASRL[^:]+::INSTR|GPIB\d*::\d+::INSTR)$",
                       re.IGNORECASE)
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_KEYS = ("name", "kind", "resource", "driver", "timeout_s", "poll_hz", "sample_rate_hz", "channels",
         "accuracy_reading_pct", "accuracy_range_pct")
_CHANNEL_KEYS = ("signal", "unit", "range", "scale")


@dataclass(frozen=True)
class Channel:
    channel: str          # the instrument's own name: "U1", "I2", "P3", "CHAN1"
    signal: str           # the bench's signal name, unit in the name where a reader could doubt it
    unit: str
    range: float          # in the instrument's units, before scaling
    scale: float = 1.0    # signal = scale * reading


@dataclass(frozen=True)
class InstrumentConfig:
    name: str
    kind: str
    resource: str
    driver: str
    channels: tuple[Channel, ...]
    timeout_s: float = 2.0
    poll_hz: float = 10.0
    sample_rate_hz: float = 50_000.0
    accuracy_reading_pct: float | None = None   # the instrument's stated accuracy: +/-(% of reading + % of range)
    accuracy_range_pct: float | None = None     # (its data sheet, for the readings' uncertainty budget)

    def channel(self, signal: str) -> Channel | None:
        return next((c for c in self.channels if c.signal == signal), None)

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "resource": self.resource, "driver": self.driver,
                "timeout_s": self.timeout_s, "poll_hz": self.poll_hz, "sample_rate_hz": self.sample_rate_hz,
                "accuracy_reading_pct": self.accuracy_reading_pct, "accuracy_range_pct": self.accuracy_range_pct,
                "channels": {c.channel: {"signal": c.signal, "unit": c.unit, "range": c.range, "scale": c.scale}
                             for c in self.channels}}


def read_instruments(value: Any, problems: Problems) -> tuple[InstrumentConfig, ...]:
    """`[[instruments]]` of a bench config; each problem one `file: instruments[i].field: reason` line."""
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(t, dict) for t in value):
        problems.add("instruments", "must be an array of tables ([[instruments]])")
        return ()
    out: list[InstrumentConfig] = []
    names: set[str] = set()
    for i, table in enumerate(value):
        where = f"instruments[{i}]"
        before = len(problems.lines)
        problems.unknown_keys(table, _KEYS, where)
        name = problems.string(table, "name", where)
        if name is not None and not _NAME.match(name):
            problems.add(f"{where}.name", f"{name!r}: lower-case letters, digits and _ only")
        elif name in names:
            problems.add(f"{where}.name", f"{name!r} is named twice")
        kind = problems.string(table, "kind", where, choices=KINDS)
        resource = problems.string(table, "resource", where)
        if resource is not None and not _RESOURCE.match(resource):
            problems.add(f"{where}.resource", f"{resource!r} is not a VISA resource string "
                                              "(e.g. TCPIP::10.0.0.5::5025::SOCKET, USB0::0x0B21::0x0025::SN::INSTR)")
        driver = problems.string(table, "driver", where)
        if kind is not None and driver is not None and driver not in DRIVERS[kind]:
            problems.add(f"{where}.driver", f"{driver!r} cannot drive a {kind}; known: {', '.join(DRIVERS[kind])}")
        timeout = problems.number(table, "timeout_s", where, required=False, default=2.0, positive=True)
        poll = problems.number(table, "poll_hz", where, required=False, default=10.0, positive=True)
        rate = problems.number(table, "sample_rate_hz", where, required=False, default=50_000.0, positive=True)
        channels = _channels(problems, table.get("channels"), f"{where}.channels")
        accuracy = [problems.number(table, key, where, required=False, min_value=0.0)
                    for key in ("accuracy_reading_pct", "accuracy_range_pct")]
        if (accuracy[0] is None) != (accuracy[1] is None):
            problems.add(where, "give both accuracy_reading_pct and accuracy_range_pct, or neither")
        if len(problems.lines) > before:
            continue
        names.add(name)
        out.append(InstrumentConfig(name, kind, resource, driver, channels, float(timeout), float(poll), float(rate),
                                    *accuracy))
    return tuple(out)


def _channels(problems: Problems, table: Any, where: str) -> tuple[Channel, ...]:
    if not isinstance(table, dict) or not table:
        problems.add(where, "missing: a table of channel = { signal, unit, range[, scale] }")
        return ()
    out = []
    signals: set[str] = set()
    for channel, spec in table.items():
        at = f"{where}.{channel}"
        if not isinstance(spec, dict):
            problems.add(at, "must be a table { signal = ..., unit = ..., range = ... }")
            continue
        problems.unknown_keys(spec, _CHANNEL_KEYS, at)
        signal = problems.string(spec, "signal", at)
        unit = problems.string(spec, "unit", at, choices=UNITS)
        rng = problems.number(spec, "range", at, positive=True)
        scale = problems.number(spec, "scale", at, required=False, default=1.0)
        if scale is not None and (scale == 0 or not math.isfinite(scale)):
            problems.add(f"{at}.scale", "must be a finite number other than 0")
            continue
        if signal in signals:
            problems.add(f"{at}.signal", f"{signal!r} is given by two channels")
            continue
        if None in (signal, unit, rng, scale):
            continue
        signals.add(signal)
        out.append(Channel(str(channel), signal, unit, float(rng), float(scale)))
    return tuple(out)


TRUTH_METHODS = ("encoder", "stator_flux")
_TRUTH_KEYS = {"method": "string", "daq": "string", "pole_pairs": "integer", "encoder_index_elec_rad": "number",
               "encoder_index_uncertainty_rad": "number", "aligned_utc": "string", "rs_main_ohm": "number",
               "rs_aux_ohm": "number", "lsd_h": "number", "lsq_h": "number", "msrd_h": "number", "msrq_h": "number"}
_NEEDS = {"encoder": ("pole_pairs", "encoder_index_elec_rad"),
          "stator_flux": ("rs_main_ohm", "rs_aux_ohm", "lsd_h", "lsq_h", "msrd_h", "msrq_h")}
DAQ_SIGNALS = {"encoder": ("encoder_angle_mech_rad",), "stator_flux": ("u_main_v", "u_aux_v", "i_main_a", "i_aux_a")}


@dataclass(frozen=True)
class RigTruthsConfig:
    """[rig_truths]: how the bench measures the field angle (pos_err_elec_rad) and the flux on this rig, from a DAQ
    that records the whole run (docs/instruments.md).

    method = "encoder"      PMSM: the dynamometer encoder's angle since its index (DAQ signal encoder_angle_mech_rad)
                            plus encoder_index_elec_rad, the rotor's electrical angle at the index, recorded by the
                            alignment step (bench.run.rig_truths.align) with its uncertainty and date
    method = "stator_flux"  SPIM: the stator flux integral(v - R_s i) dt of each winding (DAQ signals u_main_v,
                            u_aux_v, i_main_a, i_aux_a), symmetrised with the stated inductances (paper eqs. (15)-(16))
    """

    method: str
    daq: str
    values: tuple[tuple[str, Any], ...]

    def get(self, name: str, default: Any = None) -> Any:
        return dict(self.values).get(name, default)

    def signals(self) -> tuple[str, ...]:
        return ("pos_err_elec_rad",) if self.method == "encoder" else ("pos_err_elec_rad", "flux_true_wb")


def read_rig_truths(table: Any, instruments: tuple[InstrumentConfig, ...], problems: Problems) -> RigTruthsConfig | None:
    if table is None:
        return None
    if not isinstance(table, dict):
        problems.add("rig_truths", "must be a table")
        return None
    before = len(problems.lines)
    problems.unknown_keys(table, tuple(_TRUTH_KEYS), "rig_truths")
    method = problems.string(table, "method", "rig_truths", choices=TRUTH_METHODS)
    daq = problems.string(table, "daq", "rig_truths")
    for key, kind in _TRUTH_KEYS.items():
        if key in table and kind in ("number", "integer"):
            getattr(problems, kind)(table, key, "rig_truths")
    if method is not None:
        for key in _NEEDS[method]:
            if key not in table:
                problems.add(f"rig_truths.{key}", f"missing: method {method!r} needs it")
    entry = next((i for i in instruments if i.name == daq), None)
    if daq is not None and (entry is None or entry.kind not in ("daq", "scope")):
        problems.add("rig_truths.daq", f"{daq!r} is not a scope or DAQ of this bench's [[instruments]]")
    elif entry is not None and method is not None:
        missing = [s for s in DAQ_SIGNALS[method] if entry.channel(s) is None]
        if missing:
            problems.add("rig_truths.daq", f"{daq!r} records no {', '.join(missing)} (method {method!r} needs them)")
    if len(problems.lines) > before:
        return None
    return RigTruthsConfig(method, daq, tuple(sorted((k, v) for k, v in table.items() if k not in ("method", "daq"))))
