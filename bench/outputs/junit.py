"""junit.xml of a run: one testcase per criterion, for CI."""

from __future__ import annotations

import datetime as dt
import math
import os
from pathlib import Path
from xml.etree import ElementTree as ET


def write_junit(path: Path, record: dict) -> None:
    """One testcase per criterion (time: the drive seconds of its window, the part of the run it judges), a "run"
    testcase for an aborted, failed-to-run or incomplete run; the suite's time is the run's wall time, its
    properties say what ran on what (seed, scenario hash, bench, drive, firmware, software revision)."""
    scenario = record.get("scenario", {}).get("name") or "scenario"
    criteria = record.get("criteria", [])
    suite = ET.Element("testsuite", name=scenario)
    properties = ET.SubElement(suite, "properties")
    for name, value in _junit_properties(record):
        ET.SubElement(properties, "property", name=name, value=value)
    failures = skipped = errors = 0
    for c in criteria:
        window = c["window_s"]
        case = ET.SubElement(suite, "testcase", classname=f"drivebench.{scenario}", name=str(c["name"]),
                             time=f"{max(0.0, float(window[1]) - float(window[0])):.6g}")
        unit = f" {c['unit']}" if c.get("unit") else ""
        case_props = ET.SubElement(case, "properties")
        for name, value in (("kind", c["kind"]), ("signal", c["signal"]), ("unit", c.get("unit") or ""),
                            ("value", _fmt(c["value"])), ("limit", _fmt(c["limit"])),
                            ("status", c.get("status") or "")):
            ET.SubElement(case_props, "property", name=name, value=str(value))
        text = (f"{c['kind']} of {c['signal']} in [{window[0]:g}, {window[1]:g}] s: "
                f"value {_fmt(c['value'])}{unit}, limit {_fmt(c['limit'])}{unit}")
        if c.get("status") == "not_judged":
            skipped += 1
            ET.SubElement(case, "skipped", message=f"not judged: {c.get('detail', '')}").text = text
        elif not c["passed"] and c.get("known_gap"):
            skipped += 1
            ET.SubElement(case, "skipped", message=f"known gap: {c['known_gap']}").text = f"{text}; {c['detail']}"
        elif not c["passed"]:
            failures += 1
            ET.SubElement(case, "failure", message=text).text = c.get("detail", "")
        else:
            ET.SubElement(case, "system-out").text = f"{text}; {c.get('detail', '')}"
    if record.get("verdict") in ("aborted", "error"):
        errors += 1
        case = ET.SubElement(suite, "testcase", classname=f"drivebench.{scenario}", name="run")
        ET.SubElement(case, "error", message=f"run {record['verdict']}: {record.get('abort_reason') or 'no reason given'}")
    elif record.get("verdict") == "incomplete":      # a run that could not judge everything is not a pass in CI
        failures += 1
        case = ET.SubElement(suite, "testcase", classname=f"drivebench.{scenario}", name="run")
        unjudged = [c["name"] for c in criteria if c.get("status") == "not_judged"]
        ET.SubElement(case, "failure", message=f"run incomplete: {len(unjudged)} criteria not judged").text = \
            "; ".join(unjudged)
    wall = _wall_s(record)
    if wall is not None:
        suite.set("time", f"{wall:.3f}")
    suite.set("tests", str(len(criteria) + errors))
    suite.set("failures", str(failures))
    suite.set("errors", str(errors))
    suite.set("skipped", str(skipped))
    suite.set("timestamp", str(record.get("started_utc") or ""))
    root = ET.Element("testsuites")
    root.append(suite)
    ET.indent(root)
    tmp = path.with_name(path.name + ".tmp")
    ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
    os.replace(tmp, path)


def _junit_properties(record: dict) -> list[tuple[str, str]]:
    scenario = record.get("scenario") or {}
    drive = record.get("drive") or {}
    identity = drive.get("identity") or {}
    software = record.get("software") or {}
    bench = record.get("bench") or {}
    pairs = [("verdict", record.get("verdict")), ("seed", record.get("seed")),
             ("scenario.path", scenario.get("path")), ("scenario.sha256", scenario.get("sha256")),
             ("bench.name", bench.get("name")), ("drive.device_name", identity.get("device_name")),
             ("drive.firmware_version", drive.get("firmware_version")),
             ("software.version", software.get("version")), ("software.git_revision", software.get("git_revision")),
             ("started_utc", record.get("started_utc")), ("ended_utc", record.get("ended_utc")),
             ("requirements", ", ".join(scenario.get("requirements") or []))]
    return [(k, str(v)) for k, v in pairs if v is not None and v != ""]


def _wall_s(record: dict) -> float | None:
    try:
        start, end = (dt.datetime.fromisoformat(str(record[k]).replace("Z", "+00:00"))
                      for k in ("started_utc", "ended_utc"))
    except (KeyError, TypeError, ValueError):
        return None
    return max(0.0, (end - start).total_seconds())


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:.6g}"


