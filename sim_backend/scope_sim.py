"""A simulated scope/DAQ speaking the SCPI subset drivers/instruments/scope.py uses (see there).

Inputs (fixed wiring of the simulated rig, docs/instruments.md):
    CHAN1, CHAN2  winding voltages (PMSM u_a, u_b line-to-neutral; SPIM main, auxiliary), V
    CHAN3, CHAN4  winding currents (PMSM i_a, i_b; SPIM main, auxiliary), A
    CHAN5         the dynamometer encoder's index output (5 V for 20 us once a revolution), V
    CHAN6         the torque transducer's shaft torque, N*m: the dynamometer's torque plus what accelerates its rotor,
                  T_L + J_dyno dw/dt (as sim_backend/instruments.py; its fast analog output, no 100 Hz filter)
    CHAN7         DC-link voltage, V
    CHAN8         the dynamometer drive's analog speed monitor (from its own high-resolution encoder, no gate), rad/s
    CHAN9         a counter input on the dynamometer encoder (A, B, Z): the shaft angle since the last index, rad
                  (whole counts, 2 pi / counts_per_rev; a DAQ's angular-position counter with Z reset)
The plant gives one value per control period (100 us): the period's mean (the averaged inverter has no PWM pulses);
the scope samples at its own rate between them, each mean placed at its period's middle and linearly interpolated
(what an input's anti-aliasing filter makes of the pulses, without its delay). The scope's clock is the drive clock plus `clock_offset_s` (an instrument's clock is its own: the
tests shift it to prove the bench places captures by what it sees, not by trust).
Codes are int16, full scale +/-range per channel; beyond the range a sample is clipped at +/-32767.
"""

from __future__ import annotations

import math
import re
import threading

import numpy as np

from sim_backend.terminals import TerminalBlock

CHANNELS = 9
CODE_FULL = 32767
INDEX_WIDTH_S = 20e-6
_NUM = r"([0-9.eE+-]+)"


class SimScope:
    def __init__(self, encoder_offset_rad: float = 0.0, max_rate_hz: float = 1e6, history_s: float = 4.0,
                 counts_per_rev: int = 4096, dyno_inertia_kgm2: float = 0.0,
                 clock_offset_s: float = 0.0, identity: str = "KEYSIGHT TECHNOLOGIES,DSOX4034A,SIM0002,07.50"):
        self.identity = identity
        self.clock_offset_s = clock_offset_s
        self.encoder_offset_rad = encoder_offset_rad
        self.counts_per_rev = counts_per_rev
        self.dyno_inertia_kgm2 = dyno_inertia_kgm2
        self._last_speed = 0.0
        self.max_rate_hz = max_rate_hz
        self.history_s = history_s
        self.rate_hz = 50_000.0
        self.points = 1000
        self.pretrigger = 0.1
        self.ranges = [10.0] * CHANNELS
        self.source = None
        self.level = 0.0
        self.wave_source = 1
        self.errors: list[str] = []
        self._lock = threading.Lock()
        self._t = np.zeros(0)                  # per control period, drive clock
        self._x = np.zeros((0, CHANNELS))      # held / interpolated channel values at those instants
        self._chunks: list[tuple[np.ndarray, np.ndarray]] = []     # the memory, block by block
        self._last_t = 0.0
        self._angle = 0.0                      # shaft angle integrated from the plant's speed (the encoder's disc)
        self._index_t: list[float] = []        # drive times the encoder's index passed
        self._armed = False
        self._trigger_t: float | None = None   # scope clock
        self._record: tuple[np.ndarray, np.ndarray] | None = None

    # ---- fed by the plant ----
    def feed(self, b: TerminalBlock) -> None:
        n = b.t_s.size
        if n == 0:
            return
        dt = (b.t_s[-1] - b.t_s[0]) / (n - 1) if n > 1 else 1e-4
        angles = self._angle + self.encoder_offset_rad + np.concatenate(([0.0], np.cumsum(b.speed_mech_rad_s) * dt))
        turns = np.floor(angles / (2 * math.pi))
        for k in np.nonzero(np.diff(turns) != 0)[0]:        # the index passes within period k: interpolated
            edge = 2 * math.pi * max(turns[k], turns[k + 1])
            frac = (edge - angles[k]) / (angles[k + 1] - angles[k])
            # the plant's per-period speeds are at each period's start: their running sum is the shaft's angle half a
            # period earlier than the period's end (exact at constant speed)
            self._index_t.append(float(b.t_s[k] - 1.5 * dt + frac * dt))
        self._angle = float(angles[-1] - self.encoder_offset_rad)
        index = np.zeros(n)
        step = 2 * math.pi / self.counts_per_rev          # the counter at each period's end, since the index
        counter = np.floor(np.mod(angles[1:], 2 * math.pi) / step) * step
        shaft = b.torque_shaft_nm + self.dyno_inertia_kgm2 * np.diff(b.speed_mech_rad_s, prepend=self._last_speed) / dt
        self._last_speed = float(b.speed_mech_rad_s[-1])
        x = np.column_stack((b.u_v[:, 0], b.u_v[:, 1], b.i_a[:, 0], b.i_a[:, 1], index, shaft,
                             b.vdc_v, b.speed_mech_rad_s, counter))
        with self._lock:                 # memory as blocks: a DAQ's 30 s must not be copied every SYNC
            previous = self._chunks[-1] if self._chunks else None
            self._chunks.append((b.t_s.copy(), x))
            while self._chunks and self._chunks[0][0][-1] < b.t_s[-1] - self.history_s:
                self._chunks.pop(0)
            self._last_t = float(b.t_s[-1])
            self._index_t = [s for s in self._index_t if s >= self._chunks[0][0][0] - 1.0]
            self._check_trigger(dt, previous)

    def _check_trigger(self, dt: float, previous) -> None:
        if not self._armed:
            return
        if self._trigger_t is None and self.source is not None:
            t_new, x_new = self._chunks[-1]
            if previous is not None:
                t_new = np.concatenate((previous[0][-1:], t_new))
                x_new = np.concatenate((previous[1][-1:], x_new))
            y = x_new[:, self.source - 1] - self.level
            hit = np.nonzero((y[:-1] < 0) & (y[1:] >= 0))[0]
            if hit.size:
                k = hit[0]
                self._trigger_t = t_new[k] + dt * (-y[k] / (y[k + 1] - y[k])) + self.clock_offset_s
        if self._trigger_t is not None:
            post = self.points * (1.0 - self.pretrigger) / self.rate_hz
            if self._last_t + self.clock_offset_s >= self._trigger_t + post:
                self._t = np.concatenate([c[0] for c in self._chunks])
                self._x = np.concatenate([c[1] for c in self._chunks])
                self._record = self._sample()
                self._armed = False

    def _sample(self) -> tuple[np.ndarray, np.ndarray]:
        pre = round(self.points * self.pretrigger)
        t_scope = (np.arange(self.points) - pre) / self.rate_hz              # from the trigger
        t_drive = t_scope + self._trigger_t - self.clock_offset_s
        out = np.empty((self.points, CHANNELS))
        for c in range(CHANNELS):
            if c == 8:                   # the counter holds its count between edges (sum of speeds: see feed)
                dt = self._t[1] - self._t[0] if self._t.size > 1 else 1e-4
                k = np.searchsorted(self._t - 0.5 * dt, t_drive, side="right") - 1
                out[:, c] = self._x[np.clip(k, 0, self._t.size - 1), c]
            elif c == 4:                 # index pulse: INDEX_WIDTH_S from the instant the index passed
                on = np.zeros(self.points, dtype=bool)
                for s in self._index_t:
                    if t_drive[0] - INDEX_WIDTH_S <= s <= t_drive[-1]:
                        on |= (t_drive >= s) & (t_drive < s + INDEX_WIDTH_S)
                out[:, c] = np.where(on, 5.0, 0.0)
            else:                        # period means at the period's middle; speed and torque: at its start
                dt = self._t[1] - self._t[0] if self._t.size > 1 else 1e-4
                out[:, c] = np.interp(t_drive, self._t - (dt if c in (5, 7) else 0.5 * dt), self._x[:, c])
        return t_scope, out

    # ---- SCPI ----
    def answer(self, command: str) -> str | bytes | None:
        c = command.strip()
        up = c.upper()
        with self._lock:
            if up == "*IDN?":
                return self.identity
            if up == "*OPC?":
                return "0" if self._armed else "1"
            if up == "*CLS":
                self.errors.clear()
                return None
            if up in (":SYST:ERR?", ":SYSTEM:ERROR?"):
                return self.errors.pop(0) if self.errors else '+0,"No error"'
            if up in (":WAV:FORM WORD", ":WAVEFORM:FORMAT WORD", ":WAV:BYT LSBF", ":WAVEFORM:BYTEORDER LSBFIRST"):
                return None
            m = re.match(rf"^:ACQ(?:UIRE)?:SRAT(?:E)?\s+{_NUM}$", c, re.I)
            if m:
                rate = float(m.group(1))
                if not 0 < rate <= self.max_rate_hz:
                    self.errors.append(f'-222,"Data out of range: sample rate {rate:g}"')
                else:
                    self.rate_hz = rate
                return None
            m = re.match(rf"^:ACQ(?:UIRE)?:POIN(?:TS)?\s+{_NUM}$", c, re.I)
            if m:
                points = int(float(m.group(1)))
                if not 2 <= points <= self.history_s * self.rate_hz:
                    self.errors.append(f'-222,"Data out of range: points {points}"')
                else:
                    self.points = points
                return None
            m = re.match(rf"^:ACQ(?:UIRE)?:PRET(?:RIGGER)?\s+{_NUM}$", c, re.I)
            if m:
                self.pretrigger = min(max(float(m.group(1)), 0.0), 0.95)
                return None
            m = re.match(rf"^:CHAN(?:NEL)?(\d):RANG(?:E)?\s+{_NUM}$", c, re.I)
            if m and 1 <= int(m.group(1)) <= CHANNELS:
                self.ranges[int(m.group(1)) - 1] = float(m.group(2))
                return None
            m = re.match(r"^:TRIG(?:GER)?:EDGE:SOUR(?:CE)?\s+CHAN(\d)$", c, re.I)
            if m:
                self.source = int(m.group(1))
                return None
            m = re.match(rf"^:TRIG(?:GER)?:EDGE:LEV(?:EL)?\s+{_NUM}$", c, re.I)
            if m:
                self.level = float(m.group(1))
                return None
            if up in (":SING", ":SINGLE"):
                self._armed, self._trigger_t, self._record = True, None, None
                return None
            if up == ":STOP":              # end the acquisition: a triggered record keeps what it has so far
                if self._armed and self._trigger_t is not None and self._chunks:
                    self._t = np.concatenate([c[0] for c in self._chunks])
                    self._x = np.concatenate([c[1] for c in self._chunks])
                    have = int((self._last_t + self.clock_offset_s - self._trigger_t) * self.rate_hz)
                    self.points = max(2, min(self.points, round(self.points * self.pretrigger) + have))
                    self._record = self._sample()
                self._armed = False
                return None
            if up in (":TRIG:FORC", ":TRIGGER:FORCE"):
                if self._armed and self._trigger_t is None:     # now: the newest sample the scope has
                    self._trigger_t = self._last_t + self.clock_offset_s
                return None
            m = re.match(r"^:WAV(?:EFORM)?:SOUR(?:CE)?\s+CHAN(\d)$", c, re.I)
            if m and 1 <= int(m.group(1)) <= CHANNELS:
                self.wave_source = int(m.group(1))
                return None
            if up in (":WAV:PRE?", ":WAVEFORM:PREAMBLE?"):
                return self._preamble()
            if up in (":WAV:DATA?", ":WAVEFORM:DATA?"):
                return self._data()
            self.errors.append(f'-113,"Undefined header: {c[:40]}"')
            return "0" if c.endswith("?") else None

    def _yinc(self) -> float:
        return self.ranges[self.wave_source - 1] / CODE_FULL

    def _preamble(self) -> str:
        if self._record is None:
            self.errors.append('-230,"Data corrupt or stale: no record"')
            return "1,1,0,1,0,0,0,0,0,0"
        t, _ = self._record
        xinc = 1.0 / self.rate_hz
        return f"2,1,{t.size},1,{xinc:.9E},{t[0]:.9E},0,{self._yinc():.9E},0,0"

    def _data(self) -> bytes:
        if self._record is None:
            values = np.zeros(0)
        else:
            values = self._record[1][:, self.wave_source - 1]
        codes = np.clip(np.round(values / self._yinc()), -CODE_FULL, CODE_FULL).astype("<i2").tobytes()
        length = str(len(codes))
        return f"#{len(length)}{length}".encode("ascii") + codes
