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


def own_bench_kind(raw: dict, scenario_path: Path, known: tuple[Path, object] | None = None
                   ) -> tuple[str | None, str | None]:
    """The drive kind of the bench config the scenario file names itself, and that config's name as written;
    (None, None) when it names none or the file cannot be read (the text sent to a service with a relative path).
    `known`: a bench config already loaded (its resolved path and the config), used instead of reading it again."""
    from bench.inputs.benchconfig import load_bench_config

    value = raw.get("bench")
    if not isinstance(value, str) or not value.strip():
        return None, None
    try:
        found = resolve_path(value, find_repo_root(scenario_path), scenario_path.resolve().parent)
        if found is None:
            return None, value
        if known is not None and found.resolve() == known[0]:
            return bench_drive_kind(known[1]), value
        return bench_drive_kind(load_bench_config(found)), value
    except (InputError, OSError, ValueError):
        return None, value


def scenario_kinds(p: Problems, raw: dict, scenario_path: Path, known: tuple[Path, object] | None = None
                   ) -> tuple[set[str] | None, str]:
    """The drive kinds the scenario is written for and what says so: `drive_kinds = ["pmsm", "spim"]` in the file
    (a scenario that judges only what every drive has), else its own bench config's kind; (None, "") unknown."""
    if "drive_kinds" in raw:
        value = raw["drive_kinds"]
        if (not isinstance(value, list) or not value
                or any(not isinstance(v, str) or v not in KIND_NAMES for v in value)):
            p.add("drive_kinds", f"must be a non-empty array of {', '.join(map(repr, KIND_NAMES))}, got {value!r}")
            return None, ""
        return set(value), f"drive_kinds = {value}"
    own, own_name = own_bench_kind(raw, scenario_path, known)
    return ({own}, f"its bench {own_name}") if own else (None, "")


def check_drive_kind(p: Problems, raw: dict, scenario_path: Path, bench_cfg, bench_path: Path) -> None:
    """Adds `bench: ...` when the bench's drive is of a kind the scenario is not written for."""
    kinds, said = scenario_kinds(p, raw, scenario_path, (bench_path.resolve(), bench_cfg))
    kind = bench_drive_kind(bench_cfg)
    if kinds and kind and kind not in kinds:
        wanted = " or ".join(KIND_NAMES[k] for k in sorted(kinds))
        p.add("bench", f"the scenario is for a {wanted} drive ({said}) and {bench_path.name}'s drive is "
                       f"{KIND_NAMES.get(kind, kind)}: refused, the wrong test on the wrong motor")
