"""A simulated power analyser speaking the Yokogawa WT subset drivers/instruments/power_analyser.py uses.

Elements: one per motor winding (PMSM phases a, b, c; SPIM main and auxiliary winding), then the DC link. Motor
option: SPEED (rpm... here rad/s, as the bench config states the unit), TORQUE (N*m), PM (shaft power, W).
Efficiencies: ETA1 = PM / sum(P motor elements) (motor), ETA2 = sum(P motor) / P(DC link) (inverter),
ETA3 = PM / P(DC link) (drive system), in %.
Each data update interval (`:RATE`, on the drive clock) the analyser computes, over that interval's samples
(the plant's per-control-period terminal values, sim_backend.terminals): U, I rms, P mean, S = U I, Q, lambda = P/S,
FU (from the voltage's rising zero crossings), WP (integrated since :INTEGrate:STARt). A query answers the last
completed update, like the real one.
Accuracy: every value carries a fixed error drawn once from the seed within +/-(reading_pct % of reading +
range_pct % of range) (a calibrated instrument's error is systematic within its spec, not noise).
Overload: an element whose rms exceeds 140 % of its range or whose peak exceeds crest_factor x range answers
9.9E+37 (OL) for that element's U/I/P/S/Q/LAMBDA; no completed update yet answers 9.91E+37.
"""

from __future__ import annotations

import math
import re
import threading
from dataclasses import dataclass, fields

import numpy as np

from sim_backend.terminals import TerminalBlock

OL, NO_DATA = 9.9e37, 9.91e37
_ITEM = re.compile(r"^:NUM(?:ERIC)?:NORM(?:AL)?:ITEM(\d+)\s+([A-Z0-9]+)(?:,(\d))?$", re.I)
_RANGE = re.compile(r"^:INP(?:UT)?:(VOLT|CURR)(?:AGE|ENT)?:RANG(?:E)?:ELEM(?:ENT)?(\d)\s+([0-9.eE+-]+)$", re.I)
_RATE = re.compile(r"^:RATE\s+(\d+)\s*MS$", re.I)


@dataclass(frozen=True)
class AnalyserSpec:
    reading_pct: float = 0.05
    range_pct: float = 0.05
    crest_factor: float = 3.0
    voltage_range_v: float = 600.0     # power-on ranges, until the bench sets them
    current_range_a: float = 20.0


class SimPowerAnalyser:
    def __init__(self, windings: int, seed: int, spec: AnalyserSpec = AnalyserSpec(), identity: str | None = None):
        self.windings = windings
        self.elements = windings + 1                  # + the DC link
        self.spec = spec
        self.identity = identity or "YOKOGAWA,WT5000,SIM0001,F1.01"
        rng = np.random.default_rng([int(seed), 0x3A7A])
        # per element and quantity: a gain error (fraction of reading) and an offset error (fraction of range)
        self._gain = rng.uniform(-1.0, 1.0, (self.elements + 1, 4)) * spec.reading_pct / 100.0
        self._offset = rng.uniform(-1.0, 1.0, (self.elements + 1, 4)) * spec.range_pct / 100.0
        self.ranges = {("U", e): spec.voltage_range_v for e in range(1, self.elements + 1)}
        self.ranges.update({("I", e): spec.current_range_a for e in range(1, self.elements + 1)})
        self.interval_s = 0.1
        self.items: dict[int, tuple[str, int | None]] = {}
        self.count = 0
        self.errors: list[str] = []
        self._lock = threading.Lock()
        self._buf: list[TerminalBlock] = []
        self._buffered = 0
        self._latest: dict[tuple[str, int | None], float] = {}
        self._integrating = False
        self._wp = np.zeros(self.elements + 1)

    # ---- fed by the plant, per stepped block (drive clock) ----
    def feed(self, block: TerminalBlock) -> None:
        n = block.t_s.size
        if n == 0:
            return
        dt = (block.t_s[-1] - block.t_s[0]) / (n - 1) if n > 1 else 1e-4
        with self._lock:
            start = 0
            while start < n:                      # update intervals of whole control periods, whatever the blocks
                need = max(1, round(self.interval_s / dt) - self._buffered)
                part = _slice(block, start, min(n, start + need))
                self._buf.append(part)
                self._buffered += part.t_s.size
                start += part.t_s.size
                if self._buffered >= round(self.interval_s / dt):
                    self._update(dt)
                    self._buf, self._buffered = [], 0

    def _update(self, dt: float) -> None:
        u = np.concatenate([b.u_v for b in self._buf])
        i = np.concatenate([b.i_a for b in self._buf])
        vdc = np.concatenate([b.vdc_v for b in self._buf])
        idc = np.concatenate([b.idc_a for b in self._buf])
        w = np.concatenate([b.speed_mech_rad_s for b in self._buf])
        tq = np.concatenate([b.torque_shaft_nm for b in self._buf])
        us = [u[:, k] for k in range(self.windings)] + [vdc]
        iis = [i[:, k] for k in range(self.windings)] + [idc]
        out: dict[tuple[str, int | None], float] = {}
        p_motor = 0.0
        for e, (ue, ie) in enumerate(zip(us, iis), start=1):
            urms, irms = math.sqrt(float(np.mean(ue * ue))), math.sqrt(float(np.mean(ie * ie)))
            p = float(np.mean(ue * ie))
            over = any(rms > 1.4 * self.ranges[(q, e)] or float(np.max(np.abs(x))) > self.spec.crest_factor *
                       self.ranges[(q, e)] for q, rms, x in (("U", urms, ue), ("I", irms, ie)))
            if self._integrating:
                self._wp[e] += p * ue.size * dt / 3600.0
            s = urms * irms
            vals = {"U": self._err(urms, e, 0, self.ranges[("U", e)]),
                    "I": self._err(irms, e, 1, self.ranges[("I", e)]),
                    "P": self._err(p, e, 2, self.ranges[("U", e)] * self.ranges[("I", e)])}
            vals["S"] = vals["U"] * vals["I"]
            vals["Q"] = math.sqrt(max(vals["S"] ** 2 - vals["P"] ** 2, 0.0))
            vals["LAMBDA"] = vals["P"] / vals["S"] if vals["S"] > 0 else 0.0
            for q, v in vals.items():
                out[(q, e)] = OL if over else v
            out[("FU", e)] = _frequency(ue, dt)
            out[("FI", e)] = _frequency(ie, dt)
            out[("WP", e)] = self._wp[e]
            if e <= self.windings:
                p_motor += vals["P"]
        p_dc = out[("P", self.elements)]
        speed = float(np.mean(w))
        torque = self._err(float(np.mean(tq)), 0, 3, 10.0)
        out[("SPEED", None)], out[("TORQUE", None)] = speed, torque
        pm = speed * torque
        out[("PM", None)] = pm
        ok = all(out[(q, e)] < OL for q in ("P",) for e in range(1, self.elements + 1))
        out[("ETA1", None)] = 100.0 * pm / p_motor if ok and p_motor > 0 else 0.0
        out[("ETA2", None)] = 100.0 * p_motor / p_dc if ok and p_dc > 0 else 0.0
        out[("ETA3", None)] = 100.0 * pm / p_dc if ok and p_dc > 0 else 0.0
        out[("ETA4", None)] = 0.0
        self._latest = out

    def _err(self, value: float, element: int, quantity: int, rng: float) -> float:
        return value * (1.0 + self._gain[element, quantity]) + self._offset[element, quantity] * rng

    # ---- SCPI ----
    def answer(self, command: str) -> str | None:
        c = command.strip()
        up = c.upper()
        with self._lock:
            if up == "*IDN?":
                return self.identity
            if up == "*OPC?":
                return "1"
            if up == "*CLS":
                self.errors.clear()
                return None
            if up in (":STAT:ERR?", ":STATUS:ERROR?"):
                return self.errors.pop(0) if self.errors else '0,"No error"'
            if up in (":NUM:FORM ASC", ":NUMERIC:FORMAT ASCII"):
                return None
            m = _RATE.match(c)
            if m:
                self.interval_s = int(m.group(1)) / 1000.0
                return None
            m = re.match(r"^:NUM(?:ERIC)?:NORM(?:AL)?:NUM(?:BER)?\s+(\d+)$", c, re.I)
            if m:
                self.count = int(m.group(1))
                return None
            m = _ITEM.match(c)
            if m:
                el = int(m.group(3)) if m.group(3) else None
                if el is not None and not 1 <= el <= self.elements:
                    self.errors.append(f'222,"Data out of range: element {el}"')
                    return None
                self.items[int(m.group(1))] = (m.group(2).upper(), el)
                return None
            m = _RANGE.match(c)
            if m:
                q, el = ("U" if m.group(1).upper() == "VOLT" else "I"), int(m.group(2))
                if not 1 <= el <= self.elements:
                    self.errors.append(f'222,"Data out of range: element {el}"')
                    return None
                self.ranges[(q, el)] = float(m.group(3))
                return None
            if up in (":INTEG:STAR", ":INTEGRATE:START"):
                self._integrating = True
                return None
            if up in (":INTEG:STOP", ":INTEGRATE:STOP"):
                self._integrating = False
                return None
            if up in (":INTEG:RES", ":INTEGRATE:RESET"):
                self._wp[:] = 0.0
                return None
            if up in (":NUM:NORM:VAL?", ":NUMERIC:NORMAL:VALUE?"):
                return ",".join(f"{self._value(k):.6E}" for k in range(1, self.count + 1))
            if c.endswith("?"):
                self.errors.append(f'113,"Undefined header: {c[:40]}"')
                return '0'
            self.errors.append(f'113,"Undefined header: {c[:40]}"')
            return None

    def _value(self, k: int) -> float:
        item = self.items.get(k)
        if item is None or not self._latest:
            return NO_DATA
        return self._latest.get(item, NO_DATA)


def _slice(b: TerminalBlock, i: int, j: int) -> TerminalBlock:
    return TerminalBlock(*(getattr(b, f.name)[i:j] for f in fields(TerminalBlock)))


def _frequency(x: np.ndarray, dt: float) -> float:
    """From the rising zero crossings (interpolated) of a signal with its mean removed, with a hysteresis of 20 % of
    its rms (as the analyser's frequency filter: PWM ripple near zero counts no extra cycle); 0 below two."""
    y = x - float(np.mean(x))
    h = 0.2 * math.sqrt(float(np.mean(y * y)))
    if h == 0.0:
        return 0.0
    state = np.where(y > h, 1, np.where(y < -h, -1, 0))
    at = np.nonzero(state)[0]
    rises = at[1:][(state[at][1:] == 1) & (state[at][:-1] == -1)]       # above +h after being below -h
    zeros = np.nonzero((y[:-1] < 0.0) & (y[1:] >= 0.0))[0]
    if rises.size < 2 or zeros.size == 0:
        return 0.0
    k = zeros[np.clip(np.searchsorted(zeros, rises) - 1, 0, zeros.size - 1)]   # the last upward zero before each
    crossings = k + y[k] / (y[k] - y[k + 1])
    return float((crossings.size - 1) / ((crossings[-1] - crossings[0]) * dt))
