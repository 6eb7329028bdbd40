"""`drivebench submit --junit`: each run's suite carries its wall time and what ran on what (properties), each
criterion's testcase the drive time it judges and its kind, signal, unit, value, limit and status — as `drivebench
run`'s junit.xml does."""

from __future__ import annotations

from xml.etree import ElementTree as ET

from bench.service.client import write_junit

RUN = {"id": 7, "state": "pass", "verdict": "pass", "rig": "sim-a", "scenario": "short.toml",
       "scenario_name": "service-short", "scenario_sha256": "ab" * 32, "seed": 3, "owner": "olga",
       "started_utc": "2026-11-28T10:00:00.000Z", "ended_utc": "2026-11-28T10:00:04.250Z", "duration_s": 4.25,
       "drive": {"device_name": "drivebench PMSM"}, "firmware_version": "1.2.0", "revision": "abc1234",
       "software": {"version": "0.9"},
       "criteria": [{"name": "stable", "kind": "pos_error_max", "signal": "pos_err_elec_rad", "unit": "rad",
                     "window_s": [0.5, 1.0], "value": 0.1, "limit": 0.785, "passed": True, "status": "pass"}]}


def test_submit_junit_has_times_and_properties(tmp_path):
    path = tmp_path / "results.xml"
    write_junit(path, [RUN], "http://127.0.0.1:8750")
    suite = ET.parse(path).getroot().find("testsuite")
    assert suite.get("time") == "4.250"
    props = {p.get("name"): p.get("value") for p in suite.find("properties")}
    assert props["run_id"] == "7" and props["url"] == "http://127.0.0.1:8750/runs/7"
    assert (props["seed"], props["git_revision"], props["drive"], props["firmware_version"]) == (
        "3", "abc1234", "drivebench PMSM", "1.2.0")
    assert props["scenario_sha256"] == "ab" * 32 and props["rig"] == "sim-a"
    case = suite.find("testcase")
    assert case.get("time") == "0.5"
    case_props = {p.get("name"): p.get("value") for p in case.find("properties")}
    assert case_props == {"kind": "pos_error_max", "signal": "pos_err_elec_rad", "unit": "rad", "value": "0.1",
                          "limit": "0.785", "status": "pass"}
