"""What the operator's rig page shows besides the rig's state and leases: the run on it now (drive-time progress,
an ETA from the wall time it has taken so far, the tail of its log), the last finished run's verdict, and the
scenarios this rig's bench config accepts (validated once per file version, so the picker never offers one that
`drivebench validate --bench` would refuse)."""

from __future__ import annotations

import functools
import time
from pathlib import Path

from drivers.contract.errors import InputError

MAX_SCENARIOS = 300
LOG_TAIL_LINES = 12


def current_run(service, rig: str) -> dict | None:
    running = service.list_runs(rig=rig, state="running", limit=1)
    if not running:
        return None
    run = running[0]
    view = {"id": run.id, "scenario": run.scenario_name or run.scenario, "owner": run.owner,
            "progress_s": run.progress_s, "duration_s": run.scenario_duration_s, "eta_s": None, "log": []}
    if run.started_ts and run.progress_s and run.scenario_duration_s and run.progress_s > 0:
        elapsed = time.time() - run.started_ts
        view["eta_s"] = max(0.0, elapsed / run.progress_s * (run.scenario_duration_s - run.progress_s))
    try:
        log = service.run_file(run.id, "service.log")
        view["log"] = log.read_text(encoding="utf-8", errors="replace").splitlines()[-LOG_TAIL_LINES:]
    except Exception:          # no log yet: the page shows none
        pass
    return view


def last_finished(service, rig: str) -> dict | None:
    from bench.service.db import FINAL_STATES

    for run in service.list_runs(rig=rig, limit=20):
        if run.state in FINAL_STATES:
            return {"id": run.id, "scenario": run.scenario_name or run.scenario, "verdict": run.verdict or run.state,
                    "reason": run.reason}
    return None


def drive_of_last_run(runs) -> dict | None:
    """The drive identity the newest run that reached the drive recorded (runs: newest first)."""
    from bench.service.probes import IDENTITY_FIELDS

    for run in runs:
        if run.drive:
            shown = [(label, str(run.drive[key])) for key, label in IDENTITY_FIELDS if run.drive.get(key) not in (None, "")]
            return {"run_id": run.id, "identity": shown}
    return None


def rig_scenarios(scenario_root: Path, bench: str) -> list[str]:
    """Scenario paths under the root (as the submit form takes them) that validate on this bench."""
    files = sorted(scenario_root.rglob("*.toml"))[:MAX_SCENARIOS]
    stamp = tuple((str(f), f.stat().st_mtime_ns) for f in files)
    bench_path = Path(bench)
    return list(_validated(str(scenario_root), bench, bench_path.stat().st_mtime_ns if bench_path.exists() else 0,
                           stamp))


@functools.lru_cache(maxsize=32)
def _validated(root: str, bench: str, bench_stamp: int, files: tuple[tuple[str, int], ...]) -> tuple[str, ...]:
    from bench.inputs.prepared import prepare_run

    ok = []
    for path, _ in files:
        try:
            prepare_run(path, bench)
        except (InputError, OSError, ValueError):
            continue
        ok.append(str(Path(path).relative_to(root)))
    return tuple(ok)
