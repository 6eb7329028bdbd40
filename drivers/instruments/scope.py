"""A SCPI scope/DAQ: the command subset of Keysight InfiniiVision/Infiniium-style scopes a capture needs.

    *IDN?                                      identity
    :CHANnel<n>:RANGe <v>                      input range, +/- v (in the instrument's units, before the probe scale)
    :ACQuire:SRATe <hz> ; :ACQuire:POINts <n>  sample rate and record length
    :ACQuire:PRETrigger <fraction>             part of the record before the trigger
    :TRIGger:EDGE:SOURce CHAN<n> ; :TRIGger:EDGE:LEVel <v> ; :TRIGger:EDGE:SLOPe POSitive|NEGative
    :SINGle ; :TRIGger:FORCe ; *OPC?           arm, trigger now, wait until the record is complete
    :STOP                                      end the acquisition: a triggered record keeps what it has
    :WAVeform:SOURce CHAN<n> ; :WAVeform:FORMat WORD ; :WAVeform:BYTeorder LSBFirst
    :WAVeform:PREamble?                        format,type,points,count,xinc,xorigin,xref,yinc,yorigin,yref
    :WAVeform:DATA?                            int16 samples as an IEEE 488.2 definite-length block
    :SYSTem:ERRor?                             the error queue, read after configuration

A sample at the code +/-32767 is clipped (the input beyond its range): the channel is over-range and not judged.
t = (i - xref) * xinc + xorigin is the time from the trigger on the instrument's clock.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field

import numpy as np

from drivers.contract.instruments import InstrumentConfig
from drivers.instruments.scpi import InstrumentError, ScpiSession

CLIP_CODE = 32767
_CHANNEL = re.compile(r"^CHAN([1-9]|1[0-6])$")


@dataclass
class Capture:
    t_s: np.ndarray                            # from the trigger, the instrument's clock
    signals: dict[str, np.ndarray]             # signal -> values in its stated unit (NaN where clipped)
    sample_rate_hz: float
    not_judged: dict[str, str] = field(default_factory=dict)


class ScpiScope:
    error_query = ":SYSTem:ERRor?"

    def __init__(self, cfg: InstrumentConfig, session: ScpiSession):
        self.cfg = cfg
        self.session = session
        self.identity = ""

    @classmethod
    def open(cls, cfg: InstrumentConfig) -> "ScpiScope":
        for c in cfg.channels:
            if not _CHANNEL.match(c.channel.upper()):
                raise InstrumentError(f"instrument {cfg.name!r}: channel {c.channel!r}: expected CHAN1..CHAN16")
        session = ScpiSession(cfg.name, cfg.resource, cfg.timeout_s, cls.error_query)
        self = cls(cfg, session)
        try:
            self.identity = session.query("*IDN?")
            if "," not in self.identity:
                raise InstrumentError(f"instrument {cfg.name!r}: '*IDN?' answered garbage: {self.identity[:60]!r}")
            session.configure(["*CLS", f":ACQuire:SRATe {cfg.sample_rate_hz:g}", ":WAVeform:FORMat WORD",
                               ":WAVeform:BYTeorder LSBFirst"]
                              + [f":{c.channel.upper()}:RANGe {c.range:g}".replace(":CHAN", ":CHANnel")
                                 for c in cfg.channels])
        except InstrumentError:
            session.close()
            raise
        return self

    def arm(self, duration_s: float, pretrigger: float = 0.1, source: str | None = None, level: float = 0.0) -> None:
        """Set the record (duration, pre-trigger fraction, edge trigger on `source` or forced) and arm a single
        acquisition; the error queue must stay empty."""
        points = max(2, round(duration_s * self.cfg.sample_rate_hz))
        commands = [f":ACQuire:POINts {points}", f":ACQuire:PRETrigger {pretrigger:g}"]
        if source is not None:
            commands += [f":TRIGger:EDGE:SOURce {source}", f":TRIGger:EDGE:LEVel {level:g}"]
        commands.append(":SINGle")
        self.session.configure(commands)

    def force(self) -> None:
        """Trigger now; returns once the instrument has taken the command (a query behind it answered)."""
        self.session.configure([":TRIGger:FORCe"])

    def stop(self) -> None:
        """End the acquisition now (:STOP): a triggered record keeps the samples it has."""
        self.session.configure([":STOP"])

    def wait(self, timeout_s: float) -> None:
        """Until the record is complete (*OPC? answers 1), each query within the instrument's timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.session.query("*OPC?").strip() in ("1", "+1"):
                return
            if time.monotonic() > deadline:
                raise InstrumentError(f"instrument {self.cfg.name!r}: capture not complete within {timeout_s:g} s")
            time.sleep(0.01)

    def fetch(self) -> Capture:
        """Every configured channel's waveform, scaled to its signal's unit; clipped channels not judged."""
        signals: dict[str, np.ndarray] = {}
        why: dict[str, str] = {}
        t = None
        for c in self.cfg.channels:
            self.session.write(f":WAVeform:SOURce {c.channel.upper()}")
            pre = self.session.query_floats(":WAVeform:PREamble?", 10)
            codes = self.session.query_block(":WAVeform:DATA?", "h")
            points, xinc, xorigin, xref, yinc, yorigin, yref = (int(pre[2]), *pre[4:10])
            if codes.size != points:
                raise InstrumentError(f"instrument {self.cfg.name!r}: {c.channel}: {codes.size} samples, "
                                      f"the preamble says {points}")
            values = ((codes.astype(np.float64) - yref) * yinc + yorigin) * c.scale
            clipped = np.abs(codes) >= CLIP_CODE
            if clipped.any():
                why[c.signal] = (f"{c.channel}: {int(clipped.sum())} samples clipped (beyond +/-{c.range:g} "
                                 f"{c.unit}): over-range")
                values[clipped] = np.nan
            signals[c.signal] = values
            if t is None:
                t = (np.arange(points) - xref) * xinc + xorigin
        self.session.check_errors("the waveform transfer")
        rate = 1.0 / (t[1] - t[0]) if t is not None and t.size > 1 else self.cfg.sample_rate_hz
        return Capture(t if t is not None else np.zeros(0), signals, rate, why)

    def close(self) -> None:
        self.session.close()
