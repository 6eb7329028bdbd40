"""config/rigs.toml: the lab's rigs. Each names a bench config and tags; a simulated rig runs several runs at once
(each its own simulator), a real rig one at a time.

    [[rig]]
    name = "pmsm-sim-1"
    bench = "config/benches/sim-pmsm.toml"
    tags = ["pmsm"]
    max_concurrent = 2          # simulated rigs only (default 2); a real rig is always 1
    # simulated = true          # default: the bench config starts its own services (a simulator)
    # allow_unverified_comm_loss = true   # an admin's mark: the bench config states an external stop chain
    #                                     # (comm_loss = "external") instead of the drill; its runs are unverified
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from bench.inputs.benchconfig import load_bench_config
from drivers.contract.checks import read_toml, resolve_path
from bench.run.drill import stated_external
from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root, Problems

NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
DEFAULT_SIM_CONCURRENCY = 2


@dataclass(frozen=True)
class RigConfig:
    name: str
    bench: str                  # absolute path of the bench config
    tags: tuple[str, ...]
    simulated: bool
    max_concurrent: int
    description: str = field(default="")
    comm_loss_unverified: str | None = None     # what the bench config states instead of the drill (bench.run.drill)


def load_rigs(path: str | Path) -> list[RigConfig]:
    path = Path(path)
    raw = read_toml(path)
    p = Problems(path)
    p.unknown_keys(raw, ("rig",), "")
    items = raw.get("rig")
    if not isinstance(items, list) or not items:
        p.add("rig", "missing: at least one [[rig]] table is needed")
        p.raise_if_any()
    root = find_repo_root(path)
    rigs: list[RigConfig] = []
    seen: set[str] = set()
    for i, item in enumerate(items):
        where = f"rig[{i}]"
        if not isinstance(item, dict):
            p.add(where, "must be a table")
            continue
        p.unknown_keys(item, ("name", "bench", "tags", "simulated", "max_concurrent", "description",
                              "allow_unverified_comm_loss"), where)
        name = p.string(item, "name", where)
        if name is not None and not NAME_RE.match(name):
            p.add(f"{where}.name", f"{name!r}: letters, digits, '.', '_' and '-' only (at most 64)")
            name = None
        if name in seen:
            p.add(f"{where}.name", f"{name!r} is used twice")
        seen.add(name)
        bench_value = p.string(item, "bench", where)
        bench = resolve_path(bench_value, root, path.parent) if bench_value else None
        cfg = None
        if bench_value and bench is None:
            p.add(f"{where}.bench", f"{bench_value}: not found")
        elif bench is not None:
            try:
                cfg = load_bench_config(bench)
            except InputError as exc:
                p.extend(exc.problems)
        tags = item.get("tags", [])
        if not isinstance(tags, list) or not all(isinstance(t, str) and t for t in tags):
            p.add(f"{where}.tags", "must be an array of non-empty strings")
            tags = []
        starts_services = bool(cfg and cfg.services_start)
        simulated = p.boolean(item, "simulated", where, required=False, default=starts_services)
        concurrent = p.integer(item, "max_concurrent", where, required=False,
                               default=DEFAULT_SIM_CONCURRENCY if simulated else 1, min_value=1, max_value=64)
        if not simulated and concurrent not in (None, 1):
            p.add(f"{where}.max_concurrent", "a real rig runs one run at a time (1)")
        description = p.string(item, "description", where, required=False, default="") or ""
        unverified = stated_external(cfg) if cfg is not None else None
        allowed = p.boolean(item, "allow_unverified_comm_loss", where, required=False, default=False)
        if unverified and not allowed:
            p.add(f"{where}.allow_unverified_comm_loss", f"its bench config states an external stop chain instead of "
                  f"the drill ({unverified}); the service runs it only when an admin sets "
                  f"allow_unverified_comm_loss = true on this rig")
        if name and bench and cfg is not None and simulated is not None and concurrent is not None:
            kind = "simulated" if simulated else "real"
            all_tags = tuple(dict.fromkeys([*tags, kind]))
            rigs.append(RigConfig(name, str(bench), all_tags, bool(simulated), concurrent if simulated else 1,
                                  description, unverified))
    p.raise_if_any()
    return rigs
