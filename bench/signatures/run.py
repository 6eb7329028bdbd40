"""Run a drawn shaft signature (bench/signatures/draws.py) on its instruments rig: the scenario text drawn from the
seed is prepared like an uploaded file (named scenarios/<drive>-rig/sig-drawn-seed<N>.toml, hashed into the record),
the run directory keeps the drawn scenario (drawn.toml) and the record its points with their predictions
(record.json `signature_draws`, also drawn.json)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from bench.inputs.prepared import prepare_run
from bench.outputs.atomic_write import write_json_atomic
from bench.outputs.record_schema import RECORD
from bench.run.orchestrator import run_scenario
from bench.signatures.draws import draw
from drivers.contract.checks import find_repo_root

ROOT = find_repo_root(Path(__file__))


@dataclass
class DrawnResult:
    drive: str
    seed: int
    verdict: str
    failed: list[str]              # names of the failing criteria (and the abort reason, if any)
    criteria: list                 # the run's CriterionResults
    points: list[dict]
    run_dir: Path
    not_judged: list[str]          # criteria the rig could not judge (e.g. the DAQ gave no record): never a pass


def run_drawn(drive: str, seed: int, out_root: str | Path) -> DrawnResult:
    drawn, text = draw(drive, seed)
    name = ROOT / "scenarios" / f"{drive}-rig" / f"sig-drawn-seed{seed}.toml"
    prepared = prepare_run(name, text=text, seed=seed)
    result = run_scenario(prepared, out_root=out_root, rerun_mode="off")
    draws = {"drive": drive, "seed": seed, "generator": "bench/signatures/draws.py", "points": drawn.points}
    (result.run_dir / "drawn.toml").write_text(text)
    (result.run_dir / "drawn.json").write_text(json.dumps(draws, indent=1))
    record_path = result.run_dir / RECORD
    if record_path.is_file():
        record = json.loads(record_path.read_text())
        record["signature_draws"] = draws
        write_json_atomic(record_path, record)
    failed = [c.name for c in result.criteria if c.status == "fail"]
    if result.verdict in ("aborted", "error"):
        failed.insert(0, f"run {result.verdict}: {result.record.get('abort_reason') or result.error}")
    not_judged = [c.name for c in result.criteria if c.status == "not_judged"]
    return DrawnResult(drive, seed, result.verdict, failed, list(result.criteria), drawn.points, result.run_dir,
                       not_judged)
