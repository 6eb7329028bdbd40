"""From a bench config to link objects: transport name -> class, and the optional [services] starter.

The transports and their config classes are registered in drivers.transports. Drive links are constructed as
`Class(config, base_dir, settings)` with the typed [drive] section and the bench's own LinkSettings ([bench] timing
and fault_reset); load links as `Class(config, base_dir)` with the typed [load] section.
A service is `module:function`, called as `function(bench_cfg.as_dict(), seed)`; it is a context manager that
yields endpoint overrides {"drive": {...}, "load": {...}} merged into the config before connecting.
"""

from __future__ import annotations

import contextlib
import importlib
from pathlib import Path
from typing import Any, ContextManager, Iterator, Mapping

from bench.inputs.benchconfig import BenchConfig, link_settings
from drivers.contract.errors import InputError
from bench.inputs.rig_services import registered_service
from drivers.transports import DRIVE_TRANSPORTS, LOAD_TRANSPORTS, Transport

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


def _transport(section: Mapping[str, Any], registry: dict[str, Transport], where: str, cfg_path: str) -> Transport:
    transport = section.get("transport")
    if transport not in registry:
        raise InputError([f"{cfg_path}: {where}.transport: unknown transport {transport!r} "
                          f"(known: {', '.join(registry)})"])
    return registry[transport]


def make_links(cfg: BenchConfig, base_dir: Path) -> tuple[Any, Any]:
    """(drive link, load link or None for a rig without a load machine), constructed but not opened: the one way
    `run`, `probe`, the drill, the service's runs and campaign points get their links."""
    transport = _transport(cfg.drive, DRIVE_TRANSPORTS, "drive", cfg.path)
    drive = transport.link_class()(transport.config.from_mapping(cfg.drive), base_dir, link_settings(cfg))
    if not cfg.load:
        return drive, None
    transport = _transport(cfg.load, LOAD_TRANSPORTS, "load", cfg.path)
    return drive, transport.link_class()(transport.config.from_mapping(cfg.load), base_dir)


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
