"""Drivers of a lab's instruments (power analyser, scope/DAQ) over SCPI through pyvisa with the pyvisa-py backend.

`open_instrument(cfg)` gives the driver of an `[[instruments]]` entry (drivers.contract.instruments.InstrumentConfig).
"""

from __future__ import annotations

from drivers.contract.instruments import InstrumentConfig
from drivers.instruments.scpi import InstrumentError, ScpiSession


def open_instrument(cfg: InstrumentConfig):
    """Connect, identify and configure the instrument; InstrumentError (one line) when it cannot be."""
    if cfg.driver == "yokogawa-wt":
        from drivers.instruments.power_analyser import WtPowerAnalyser
        return WtPowerAnalyser.open(cfg)
    if cfg.driver == "scpi-scope":
        from drivers.instruments.scope import ScpiScope
        return ScpiScope.open(cfg)
    raise InstrumentError(f"instrument {cfg.name!r}: no driver {cfg.driver!r}")


__all__ = ["InstrumentError", "ScpiSession", "open_instrument"]
