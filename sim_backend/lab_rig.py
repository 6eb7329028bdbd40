"""The simulated rig's SCPI instruments: a power analyser and a scope/DAQ on 127.0.0.1, fed by the plant's terminals.

A bench config's `[simulator.lab_instruments]` asks for them (checked here, `file: field: reason`):

    [simulator.lab_instruments]
    analyser = true                  # sim_backend.analyser_sim.SimPowerAnalyser (Yokogawa WT subset)
    scope = true                     # sim_backend.scope_sim.SimScope (9 inputs, see there), 4 s of memory
    daq = true                       # a second SimScope as a DAQ recording a whole run (30 s of memory)
    reading_pct = 0.05               # analyser accuracy: +/-(reading_pct % of reading + range_pct % of range)
    range_pct = 0.05
    scope_clock_offset_s = 0.0       # the scope's own clock against the drive's
    slow_s = 0.0                     # every answer this much later (a busy instrument)
    drop_after = 0                   # the analyser drops its connection after this many answers (0: never)

The rig builder starts one ScpiServer per instrument and hands the bench each `[[instruments]]` entry's resource
(`TCPIP::127.0.0.1::<port>::SOCKET`) by its kind, as it hands the CAN channel and the Modbus port.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

_BOOLS = ("analyser", "scope", "daq")


@dataclass(frozen=True)
class LabSpec:
    analyser: bool = True
    scope: bool = True
    daq: bool = False
    reading_pct: float = 0.05
    range_pct: float = 0.05
    scope_clock_offset_s: float = 0.0
    slow_s: float = 0.0
    drop_after: int = 0              # the analyser drops its connection after this many answers (0: never)

    @classmethod
    def from_table(cls, table: Any, where: str = "simulator.lab_instruments") -> "LabSpec":
        if not isinstance(table, dict):
            raise RuntimeError(f"{where}: must be a table")
        known = {f.name for f in fields(cls)}
        for k, v in table.items():
            if k not in known:
                raise RuntimeError(f"{where}.{k}: unknown key (known: {', '.join(sorted(known))})")
            if k in _BOOLS:
                if not isinstance(v, bool):
                    raise RuntimeError(f"{where}.{k}: must be true or false, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or \
                    (k != "scope_clock_offset_s" and v < 0):
                raise RuntimeError(f"{where}.{k}: must be a number{'' if k == 'scope_clock_offset_s' else ' >= 0'}, "
                                   f"got {v!r}")
        return cls(**table)


def start_lab(stack, model: Any, spec: LabSpec, seed: int, names: dict[str, list[str]]) -> tuple[list, dict]:
    """Serve the instruments of `spec` fed by `model` (a sim_backend.terminals.TappedModel, possibly wrapped);
    `names`: kind -> the bench's [[instruments]] names. Returns (servers, {name: resource})."""
    from sim_backend.analyser_sim import AnalyserSpec, SimPowerAnalyser
    from sim_backend.scope_sim import SimScope
    from sim_backend.scpi_server import ScpiServer

    servers, resources = [], {}
    windings = len(model.windings)
    if spec.analyser:
        analyser = SimPowerAnalyser(windings, seed, AnalyserSpec(spec.reading_pct, spec.range_pct))
        model.listeners.append(analyser.feed)
        servers.append(_serve(stack, ScpiServer(analyser), spec, names.get("power_analyser", []), resources))
        servers[-1].quirks.drop_after = spec.drop_after or None
    encoder = getattr(model, "instruments", None)
    common = dict(encoder_offset_rad=float(getattr(model, "offset_rad", 0.0)), clock_offset_s=spec.scope_clock_offset_s,
                  counts_per_rev=int(encoder.encoder_counts_per_rev) if encoder is not None else 4096,
                  dyno_inertia_kgm2=float(getattr(encoder, "dyno_inertia_kgm2", 0.0)) if encoder is not None else 0.0)
    for kind, wanted, memory_s in (("scope", spec.scope, 4.0), ("daq", spec.daq, 30.0)):
        if wanted:
            scope = SimScope(history_s=memory_s, **common)
            model.listeners.append(scope.feed)
            servers.append(_serve(stack, ScpiServer(scope), spec, names.get(kind, []), resources))
    return servers, resources


def _serve(stack, server, spec: LabSpec, names: list[str], resources: dict) -> Any:
    server.quirks.slow_s = spec.slow_s
    stack.callback(server.stop)
    for name in names:
        resources[name] = server.resource
    return server
