"""Transport name -> (its config class, its link class): the one registry a bench config's [drive] and [load]
tables are read through and their links built from. Transports are plugins: each registers itself in the
entry-point group `drivebench.transports` (drive) or `drivebench.load_transports` (load machine) as
`name = "package.module:ConfigClass"`, and in `drivebench.transport_links` / `drivebench.load_transport_links` as
`name = "package.module:LinkClass"`. This module names none of them. Link classes are named, not imported, so
reading a config does not load python-can, pyserial, pymodbus or pysoem."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

from drivers.contract.sections import Section


@dataclass(frozen=True)
class Transport:
    config: type[Section]
    link: str                   # "module:Class", constructed as Class(config, base_dir[, settings])

    def link_class(self) -> Any:
        module, _, name = self.link.partition(":")
        return getattr(importlib.import_module(module), name)


def _registry(configs: str, links: str) -> dict[str, Transport]:
    link_of = {ep.name: ep.value for ep in entry_points(group=links)}
    found = {}
    for ep in entry_points(group=configs):
        if ep.name in link_of:
            found[ep.name] = Transport(ep.load(), link_of[ep.name])
    return dict(sorted(found.items()))


DRIVE_TRANSPORTS: dict[str, Transport] = _registry("drivebench.transports", "drivebench.transport_links")
LOAD_TRANSPORTS: dict[str, Transport] = _registry("drivebench.load_transports", "drivebench.load_transport_links")
if not DRIVE_TRANSPORTS:
    raise ImportError("no drive transport is registered (entry-point group drivebench.transports): install drivebench "
                      "(python3 dev.py setup, or pip install -e .) so its entry points are known")
