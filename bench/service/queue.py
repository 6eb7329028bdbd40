"""Submitting runs: resolve the scenario (a path under the service's scenario root, or TOML text), validate it
against the rig's bench config with the CLI's own validation, and queue it."""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select

from drivers.contract.errors import InputError
from bench.service.auth import Principal
from bench.service.db import Database, Rig, Run, RunCandidate, iso
from bench.service.errors import ApiError, bad_input
from bench.service.leases import active_leases, blocking_holder
from bench.service.limits import MAX_SCENARIO_CHARS



@dataclass
class Submission:
    scenario: str | None = None
    scenario_toml: str | None = None
    filename: str | None = None        # how 422 lines name inline TOML (default "scenario_toml")
    rig: str | None = None
    tag: str | None = None
    seed: int | None = None


def resolve_scenario_path(value: str, root: Path) -> Path:
    """A scenario path as submitted ("scenarios/pmsm/x.toml" or "pmsm/x.toml") -> the file under `root`;
    anything that resolves outside the root (.., absolute paths elsewhere, symlinks out) is refused."""
    root = root.resolve()
    if not value.strip() or "\0" in value:
        raise bad_input(["request: scenario: must be a non-empty path"])
    given = Path(value)
    candidates = [given] if given.is_absolute() else [root.parent / given, root / given]
    inside = []
    for candidate in candidates:
        try:
            resolved = candidate.resolve()
        except (OSError, RuntimeError):
            continue
        if resolved.is_relative_to(root):
            inside.append(resolved)
    if not inside:
        raise bad_input([f"request: scenario: {value}: outside the scenario root (give a path under "
                         f"{root.name}/ or send scenario_toml)"])
    for path in inside:
        if path.is_file():
            return path
    raise bad_input([f"{value}: (file): not found under the scenario root"])


def store_inline(text: str, data_dir: Path) -> Path:
    raw = text.encode("utf-8")
    if len(raw) > MAX_SCENARIO_CHARS:
        raise bad_input([f"request: scenario_toml: larger than {MAX_SCENARIO_CHARS} bytes"])
    folder = data_dir / "scenarios"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"inline-{hashlib.sha256(raw).hexdigest()[:20]}.toml"
    if not path.exists():
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(raw)
        tmp.replace(path)
    return path


def _rename(lines: list[str], path: Path, shown: str) -> list[str]:
    prefix = str(path)
    return [shown + line[len(prefix):] if line.startswith(prefix) else line for line in lines]


def validate(path: Path, bench: str, shown: str):
    """The CLI's validation (`drivebench validate --bench`); lines name the file as the client named it."""
    from bench.inputs.prepared import prepare_run

    try:
        scenario = prepare_run(path, bench).scenario
    except InputError as exc:
        raise bad_input(_rename(exc.problems or [str(exc)], path, shown)) from None
    except tomllib.TOMLDecodeError as exc:
        raise bad_input([f"{shown}: (file): not valid TOML: {exc}"]) from None
    except OSError as exc:
        raise bad_input([f"{shown}: (file): cannot read: {exc.strerror or exc}"]) from None
    return scenario


def _fitting_rigs(path: Path, shown: str, rigs: list[Rig], by_tag: bool):
    """Validate against each distinct bench config of the rigs (which refuses a rig whose drive kind, PMSM or
    SPIM, is not the one of the scenario's own bench config: bench.inputs.drive_kind); by tag, keep the rigs the
    scenario validates on."""
    if not by_tag:
        return validate(path, rigs[0].bench, shown), None
    validated: dict[str, object] = {}
    first_error: ApiError | None = None
    fitting: list[str] = []
    scenario = None
    for rig in rigs:
        if rig.bench not in validated:
            try:
                validated[rig.bench] = validate(path, rig.bench, shown)
            except ApiError as exc:
                validated[rig.bench] = None
                first_error = first_error or exc
        if validated[rig.bench] is not None:
            scenario = scenario or validated[rig.bench]
            fitting.append(rig.name)
    if not fitting:
        raise first_error or bad_input(["request: tag: no rig with this tag"])
    return scenario, fitting


def submit(db: Database, who: Principal, body: Submission, scenario_root: Path, data_dir: Path) -> Run:
    problems = []
    if (body.scenario is None) == (body.scenario_toml is None):
        problems.append("request: scenario: give exactly one of scenario (a path under the scenario root) "
                        "or scenario_toml (the file's text)")
    if (body.rig is None) == (body.tag is None):
        problems.append("request: rig: give exactly one of rig (a rig's name) or tag")
    if body.seed is not None and not 0 <= body.seed <= 2**63 - 1:
        problems.append(f"request: seed: must be an integer >= 0, got {body.seed}")
    if problems:
        raise bad_input(problems)
    with db.session() as s:
        rigs = list(s.execute(select(Rig).order_by(Rig.name)).scalars())
    if body.rig is not None:
        chosen = [r for r in rigs if r.name == body.rig]
        if not chosen:
            raise bad_input([f"request: rig: no rig named {body.rig!r} (rigs: {', '.join(r.name for r in rigs)})"])
    else:
        chosen = [r for r in rigs if body.tag in r.tags]
        if not chosen:
            tags = sorted({t for r in rigs for t in r.tags})
            raise bad_input([f"request: tag: no rig has tag {body.tag!r} (tags: {', '.join(tags)})"])
    if body.scenario is not None:
        path = resolve_scenario_path(body.scenario, scenario_root)
        shown = body.scenario
    else:
        path = store_inline(body.scenario_toml, data_dir)
        shown = body.filename or "scenario_toml"
    scenario, fitting = _fitting_rigs(path, shown, chosen, by_tag=body.rig is None)
    with db.session() as s:
        if body.rig is not None:
            rig = chosen[0]
            other = blocking_holder(rig, [l for l in active_leases(s, rig.name) if l.kind == "manual"], who.name)
            if other is not None:
                raise ApiError(409, f"rig {rig.name}: reserved by {other.holder} until {iso(other.expires_ts)} "
                                    f"({other.reason or 'no reason given'}); submit by tag or wait")
        run = Run(state="queued", rig=body.rig, tag=body.tag, candidates=fitting, scenario=body.scenario or shown,
                  scenario_file=str(path), scenario_name=scenario.name, scenario_sha256=scenario.sha256,
                  scenario_duration_s=scenario.duration_s, seed=body.seed, owner=who.name,
                  owner_token_id=who.token_id)
        s.add(run)
        s.flush()
        s.add_all(RunCandidate(run_id=run.id, rig=name) for name in dict.fromkeys(fitting or []))
        return run
