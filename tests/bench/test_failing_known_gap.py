""""Failing now" lists criteria whose latest judged run fails; a documented known gap (a criterion that fails by
design, its run passing) is not such a failure and is not listed."""

from __future__ import annotations

from pathlib import Path

from tests.service_fixtures import client_for, make_settings


def test_a_known_gap_whose_runs_pass_is_not_failing_now(tmp_path):
    from bench.service.db import Run
    from bench.service.runner import index_record

    with client_for(make_settings(tmp_path)) as api:
        with api.service.db.session() as s:
            for k in (1, 2):
                run = Run(id=k, state="pass", verdict="pass", rig="sim-a", scenario="short.toml", scenario_file="x",
                          scenario_name="svc", owner="olga", submitted_ts=1000.0 + k, started_ts=1000.5 + k,
                          ended_ts=1001.0 + k)
                s.add(run)
                s.flush()
                record = {"verdict": "pass", "scenario": {"name": "svc"}, "criteria": [
                    {"name": "gap", "signal": "pos_err_elec_rad", "value": 0.9, "limit": 0.5, "passed": False,
                     "status": "fail", "known_gap": "the paper's Fig. 10 start-up: documented"},
                    {"name": "real", "signal": "speed_est_mech_rad_s", "value": 1.0, "limit": 0.5, "passed": k == 1,
                     "status": "pass" if k == 1 else "fail"}]}
                index_record(s, run, record, Path(tmp_path))
        failing = api.get("/api/failing", headers={"Authorization": f"Bearer {api.tokens.viewer}"}).json()
        assert [(f["criterion"], f["runs_failing"]) for f in failing] == [("real", 1)], failing
