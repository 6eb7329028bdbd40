"""Failing since: for every scenario and criterion whose latest judged run fails, the run (and software revision)
where the current streak of failures began, and the last run where it passed before that. A criterion not judged
counts as neither, nor does a documented known gap (its run passes); a run on a real rig and one on a simulator count alike (the rig is shown)."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from bench.service.db import CriterionValue, Run, iso


def failing_since(s: Session, scenario: str | None = None, limit_runs: int = 5000) -> list[dict]:
    q = (select(CriterionValue.name, CriterionValue.passed, CriterionValue.status, Run.id, Run.scenario_name,
                Run.revision, Run.rig, Run.ended_ts)
         .join(Run, Run.id == CriterionValue.run_id).where(Run.ended_ts.is_not(None)))
    if scenario:
        q = q.where(Run.scenario_name == scenario)
    rows = s.execute(q.order_by(Run.ended_ts.desc(), Run.id.desc()).limit(limit_runs * 50)).all()
    streaks: dict[tuple[str, str], dict] = {}
    closed: set[tuple[str, str]] = set()
    for name, passed, status, run_id, scen, revision, rig, ended in rows:     # newest first
        key = (scen or "", name)
        if key in closed or status in ("not_judged", "known_gap"):
            continue
        entry = streaks.get(key)
        if passed:
            if entry is not None:
                entry["last_pass"] = {"run_id": run_id, "revision": revision, "ended_utc": iso(ended)}
            closed.add(key)                     # the streak (if any) ends here, going back in time
            continue
        if entry is None:
            entry = streaks[key] = {"scenario": scen, "criterion": name, "runs_failing": 0, "latest_run_id": run_id,
                                    "last_pass": None}
        entry["runs_failing"] += 1
        entry["since"] = {"run_id": run_id, "revision": revision, "rig": rig, "ended_utc": iso(ended)}
    return sorted(streaks.values(), key=lambda e: (e["scenario"] or "", e["criterion"]))
