"""From a bench config to link objects: transport name -> class, and the optional [services] starter.

Drive links are constructed as `Class(section, base_dir, settings)` with the config's [drive] table and the bench's
own LinkSettings ([bench] timing and fault_reset); load links as `Class(section, base_dir)` with [load].
A service is `module:function`, called as `function(bench_cfg.as_dict(), seed)`; it is a context manager that
yields endpoint overrides {"drive": {...}, "load": {...}} merged into the config before connecting.
"""

from __future__ import annotations

import contextlib
import importlib
from pathlib import Path
from typing import Any, Callable, ContextManager, Iterator, Mapping

from bench.benchconfig import BenchConfig, link_settings
from drivers.contract.errors import InputError
from bench.services import registered_service

DRIVE_TRANSPORTS: dict[str, str] = {
    "canopen": "drivers.canopen.link:CanopenDriveLink",
    "serial": "drivers.serial_link:SerialDriveLink",
}
LOAD_TRANSPORTS: dict[str, str] = {
    "modbus-tcp": "drivers.modbus_load:ModbusLoadLink",
    "modbus-rtu": "drivers.modbus_load:ModbusLoadLink",
}


def import_object(spec: str, what: str) -> Any:
    """`package.module:name` -> the object; InputError naming `what` if it cannot be imported."""
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise InputError([f"{what}: cannot import module {module_name!r} ({exc})"]) from None
    try:
        return getattr(module, attr)
    except AttributeError:
        raise InputError([f"{what}: module {module_name!r} has no {attr!r}"]) from None


def _link_class(section: Mapping[str, Any], table: dict[str, str], where: str, cfg_path: str) -> Callable:
    transport = section.get("transport")
    spec = table.get(transport)
    if spec is None:
        raise InputError([f"{cfg_path}: {where}.transport: unknown transport {transport!r} "
                          f"(known: {', '.join(table)})"])
    return import_object(spec, f"{cfg_path}: {where}.transport {transport!r}")


def make_links(cfg: BenchConfig, base_dir: Path) -> tuple[Any, Any]:
    """(drive link, load link or None for a rig without a load machine), constructed but not opened."""
    drive_cls = _link_class(cfg.drive, DRIVE_TRANSPORTS, "drive", cfg.path)
    drive = drive_cls(dict(cfg.drive), base_dir, link_settings(cfg))
    if not cfg.load:
        return drive, None
    load_cls = _link_class(cfg.load, LOAD_TRANSPORTS, "load", cfg.path)
    return drive, load_cls(dict(cfg.load), base_dir)


@contextlib.contextmanager
def started_services(cfg: BenchConfig, seed: int) -> Iterator[BenchConfig]:
    """Start [services] if the config names one; yield the config with its endpoint overrides merged."""
    if not cfg.services_start:
        yield cfg
        return
    where = f"{cfg.path}: services.start"
    start = import_object(registered_service(cfg.services_start, where), where)
    manager: ContextManager = start(cfg.as_dict(), seed)
    with manager as overrides:
        yield cfg.with_overrides(overrides or {})
