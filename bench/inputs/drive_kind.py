"""One check for "the right test on the right motor": a scenario run on a bench other than its own (`validate
--bench`, `run --bench`, a service rig, the rig page's picker, submit by tag) must be for the same drive kind
(PMSM, SPIM) as that bench's drive. The kind is known where the drive's EDS identifies it (drivebench's own
drives); where either side's kind is unknown (a third-party or serial drive) nothing is claimed."""

from __future__ import annotations

from pathlib import Path

from drivers.contract.checks import Problems, find_repo_root, resolve_path
from drivers.contract.errors import InputError

KIND_NAMES = {"pmsm": "PMSM", "spim": "SPIM"}


def bench_drive_kind(bench_cfg) -> str | None:
    """'pmsm' / 'spim' for a bench config whose drive's EDS says so, else None."""
    from bench.inputs.benchconfig import drive_description

    description = drive_description(bench_cfg) if bench_cfg is not None else None
    return description.drivebench_kind if description else None


def own_bench_kind(raw: dict, scenario_path: Path) -> tuple[str | None, str | None]:
    """The drive kind of the bench config the scenario file names itself, and that config's name as written;
    (None, None) when it names none or the file cannot be read (the text sent to a service with a relative path)."""
    from bench.inputs.benchconfig import load_bench_config

    value = raw.get("bench")
    if not isinstance(value, str) or not value.strip():
        return None, None
    try:
        found = resolve_path(value, find_repo_root(scenario_path), scenario_path.resolve().parent)
        if found is None:
            return None, value
        return bench_drive_kind(load_bench_config(found)), value
    except (InputError, OSError, ValueError):
        return None, value


def check_drive_kind(p: Problems, raw: dict, scenario_path: Path, bench_cfg, bench_path: Path) -> None:
    """Adds `bench: ...` when the scenario's own bench config is for another drive kind than `bench_cfg`."""
    own, own_name = own_bench_kind(raw, scenario_path)
    kind = bench_drive_kind(bench_cfg)
    if own and kind and own != kind:
        p.add("bench", f"the scenario is for a {KIND_NAMES.get(own, own)} drive (its bench {own_name}) and "
                       f"{bench_path.name}'s drive is {KIND_NAMES.get(kind, kind)}: refused, the wrong test on "
                       f"the wrong motor")
