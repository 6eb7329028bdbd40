"""[simulator]: the simulated rig a bench config describes, read by the bench (to refuse a bad config at validate
time, as `run` would) and by sim_backend (its rig is built from it: sim_backend.rig.rig_spec). Its [simulator.serve]
table is for `drivebench sim serve`. The instruments table is checked by sim_backend.instruments."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, replace
from pathlib import Path

from drivers.contract.checks import Problems, existing_path
from drivers.contract.sections import Section, key

TOY = "toy"           # sim_backend.toy.ToyDrive: protocol tests without physics


def _endpoint(value: object) -> str | None:
    host, sep, port = str(value).rpartition(":")
    if not isinstance(value, str) or not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        return f"expected 'host:port', got {value!r}"
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            return (f"{host} is not a loopback address: the simulator serves 127.0.0.1 only (no authentication: "
                    f"anyone who reaches the port drives the rig)")
    return None


def endpoint(value: str | None) -> tuple[str, int] | None:
    if value is None:
        return None
    host, _, port = value.rpartition(":")
    return host, int(port)


@dataclass(frozen=True)
class SimulatorServeConfig(Section):
    """[simulator.serve]: the endpoints of `drivebench sim serve` (each 'host:port' on the loopback)."""

    SECTION = "simulator.serve"
    canopen_socketcand: str | None = key(None, check=_endpoint)
    serial_tcp: str | None = key(None, check=_endpoint)
    modbus_tcp: str | None = key(None, check=_endpoint)
    one_bench: bool = key(True, kind="boolean")      # one bench at a time, each finding the drive restarted


def _gear(value: object) -> str | None:
    if not (isinstance(value, list) and len(value) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in value)):
        return f"must be [motor_revs, shaft_revs], two positive numbers, got {value!r}"
    return None


@dataclass(frozen=True)
class SimulatorConfig(Section):
    SECTION = "simulator"
    motor: str | None = key(None, kind="string", required=True)     # motor config file (resolved), or "toy"
    seed: int = key(0, kind="integer", min=0)                        # sim serve's seed (a run has its own)
    serial_line: str = key("tcp", kind="string", choices=("tcp", "pty"))
    drive: str = key("drivebench", kind="string", choices=("drivebench", "generic"))
    # drive = "generic": a third-party CiA 402 drive from the bench's EDS (sim_backend.canopen.generic.DriveSpec)
    velocity_unit: str | None = key(None, kind="string")
    velocity_side: str | None = key(None, kind="string", choices=("motor", "shaft"))
    encoder_increments_per_rev: float | None = key(None, kind="number", positive=True)
    gear_ratio: tuple[float, float] | None = key(None, check=_gear)
    rated_current_a: float | None = key(None, kind="number", positive=True)
    rated_torque_nm: float | None = key(None, kind="number", positive=True)
    fixed_pdo_mapping: bool | None = key(None, kind="boolean")
    # vendor quirks (docs/rig.md "Simulated quirks")
    comm_loss_reaction: bool | None = key(None, kind="boolean")
    found_running_mech_rad_s: float | None = key(None, kind="number")
    tpdo_stops_after_s: float | None = key(None, kind="number", min=0)
    tpdo_stops: int | None = key(None, kind="integer", min=0)
    csv_only: bool | None = key(None, kind="boolean")
    event_tpdos_only: bool | None = key(None, kind="boolean")
    boot_delay_s: float | None = key(None, kind="number", min=0)
    remote_drops_after_s: float | None = key(None, kind="number", min=0)
    local_control: bool | None = key(None, kind="boolean")
    mode_display_delay_s: float | None = key(None, kind="number", min=0)
    warning_emcy_after_s: float | None = key(None, kind="number", min=0)
    target_sdo_only_enabled: bool | None = key(None, kind="boolean")
    node_guarding: bool | None = key(None, kind="boolean")
    comm_loss_delay_s: float | None = key(None, kind="number", min=0)
    velocity_filter_s: float | None = key(None, kind="number", min=0)
    bus_drop_at_s: float | None = key(None, kind="number", min=0)
    bus_drop_s: float | None = key(None, kind="number", min=0)
    instruments: dict | None = key(None, kind="table")              # an instruments rig (sim_backend.instruments)
    lab_instruments: dict | None = key(None, kind="table")          # SCPI analyser and scope (sim_backend.lab_rig)
    serve: SimulatorServeConfig | None = key(None, kind="table")

    GENERIC = ("velocity_unit", "velocity_side", "encoder_increments_per_rev", "gear_ratio", "rated_current_a",
               "rated_torque_nm", "fixed_pdo_mapping", "comm_loss_reaction", "found_running_mech_rad_s",
               "tpdo_stops_after_s", "tpdo_stops", "csv_only", "event_tpdos_only", "boot_delay_s",
               "remote_drops_after_s", "local_control", "mode_display_delay_s", "warning_emcy_after_s",
               "target_sdo_only_enabled", "node_guarding", "comm_loss_delay_s", "velocity_filter_s",
               "bus_drop_at_s", "bus_drop_s")

    @classmethod
    def read(cls, table: dict, problems: Problems, where: str | None = None, root: Path | None = None,
             also: Path | None = None) -> "SimulatorConfig | None":
        sim = super().read(table, problems, where, root, also)
        serve = None
        if isinstance(table.get("serve"), dict):
            serve = SimulatorServeConfig.read(table["serve"], problems, f"{where or cls.SECTION}.serve")
        if sim is None:
            return None
        motor = sim.motor
        if motor != TOY:
            motor = existing_path(problems, f"{where or cls.SECTION}.motor", motor, root or Path.cwd(), also)
            if motor is None:
                return None
        return replace(sim, motor=motor, serve=serve,
                       gear_ratio=tuple(float(v) for v in sim.gear_ratio) if sim.gear_ratio else None)

    def generic(self) -> dict:
        """The third-party drive's options that are stated."""
        out = {k: getattr(self, k) for k in self.GENERIC if getattr(self, k) is not None}
        if "gear_ratio" in out:
            out["gear_ratio"] = tuple(float(v) for v in out["gear_ratio"])
        return out
