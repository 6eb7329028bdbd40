"""make_drive: build the simulated drive a motor config describes (dispatch on [motor] kind)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from drivers.contract.errors import InputError
from drivers.contract.errors import ContentError
from drivers.contract.toml_file import read_toml_file
from sim_backend.drive_model import DriveModel


def load_motor_config(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        cfg, _ = read_toml_file(path)
    except ContentError as exc:
        raise InputError(f"{path}: (file): {exc}") from None
    kind = cfg.get("motor", {}).get("kind") if isinstance(cfg.get("motor"), dict) else None
    if kind not in ("pmsm", "spim"):
        raise InputError(f"{path}: [motor] kind: expected 'pmsm' or 'spim', got {kind!r}")
    return cfg


def make_drive(motor_config: str | Path | dict, seed: int = 0, **options: Any) -> DriveModel:
    """options go to the model's from_config (e.g. noise=False)."""
    if isinstance(motor_config, dict):
        cfg, where = motor_config, "<config dict>"
        kind = cfg.get("motor", {}).get("kind")
    else:
        cfg, where = load_motor_config(motor_config), str(motor_config)
        kind = cfg["motor"]["kind"]
    try:
        if kind == "pmsm":
            from sim_backend.pmsm.model import PmsmDrive
            return PmsmDrive.from_config(cfg, seed, **options)
        if kind == "spim":
            from sim_backend.spim.model import SpimDrive
            return SpimDrive.from_config(cfg, seed, **options)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None
    raise InputError(f"{where}: [motor] kind: expected 'pmsm' or 'spim', got {kind!r}")
