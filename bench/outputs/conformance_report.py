"""The conformance report: one JSON document (the source), Markdown for people, JUnit XML for CI; kept per drive
identity (conformance/<vendor>-<product>-<revision>-<software>/<UTC stamp>.{json,md,xml} and latest.*), and a
comparison of two reports (two drives, or two firmware versions of one) test by test."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

from bench.outputs.atomic_write import write_text_atomic

SCHEMA = "drivebench.conformance/1"


def document(run: Any, bench: str, settings: dict, reference: str, software: dict) -> dict[str, Any]:
    results = [r.as_dict() for r in run.results]
    counts = {k: sum(r["outcome"] == k for r in results) for k in ("pass", "note", "fail", "not_run")}
    return {"schema": SCHEMA, "bench": bench, "identity": run.identity, "started_utc": run.started_utc,
            "duration_s": run.duration_s, "drive_time_s": run.drive_time_s,
            "verdict": "fail" if counts["fail"] else "pass", "counts": counts,
            "reference_sensor": reference, "settings": settings, "software": software,
            "safe_end": run.safe_end, "liveness": run.liveness, "not_restored": run.restore, "tests": results}


def drive_key(doc: dict) -> str:
    ident = doc["identity"].get("identity", {})
    raw = "-".join(str(ident.get(k) or "x") for k in ("vendor_id", "product_code", "revision", "software_version"))
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", raw)


def markdown(doc: dict) -> str:
    ident = doc["identity"].get("identity", {})
    c = doc["counts"]
    lines = [f"# CiA 402 conformance: {ident.get('device_name') or '?'} ({doc['bench']})", "",
             f"vendor {ident.get('vendor_id')}, product {ident.get('product_code')}, revision {ident.get('revision')}, "
             f"software {ident.get('software_version') or '?'}; {doc['started_utc']}; {doc['duration_s']} s", "",
             f"**{doc['verdict'].upper()}**: {c['pass']} pass, {c['note']} note, {c['fail']} fail, "
             f"{c['not_run']} not run. Reference sensor: {doc['reference_sensor']}. Drive at the end: "
             f"{doc['safe_end']}; load machine: {doc.get('load_end', '?')}. Bench heartbeat in the drive during the "
             f"suite: {doc.get('liveness', '?')}.", ""]
    if doc["not_restored"]:
        lines += ["## Not restored", ""] + [f"- {line}" for line in doc["not_restored"]] + [""]
    findings = [(t["name"], f) for t in doc["tests"] for f in t["findings"]]
    if findings:
        lines += ["## Findings", ""] + [f"- `{name}`: {f}" for name, f in findings] + [""]
    lines += ["## Tests", "", "| test | CiA reference | outcome | time [s] | drive at the end |",
              "|---|---|---|---|---|"]
    for t in doc["tests"]:
        lines.append(f"| `{t['name']}` | {t['clause']} | {t['outcome']} | {t['duration_s']} | {t['safe_end']} |")
    for t in doc["tests"]:
        lines += ["", f"### {t['name']}: {t['title']}", "", f"{t['clause']}. Outcome: **{t['outcome']}**"
                  + (f" ({t['detail']})" if t["detail"] else "") + "."]
        if t["checks"]:
            lines += ["", "| check | expected | the drive's answer | ok | ms |", "|---|---|---|---|---|"]
            for ch in t["checks"]:
                ok = {True: "yes", False: "**NO**", None: "observed"}[ch["ok"]]
                lines.append(f"| {ch['what']} | {ch['expected']} | {ch['answer']} | {ok} | "
                             f"{'' if ch['time_ms'] is None else ch['time_ms']} |")
        if t["measured"]:
            lines += ["", "measured: `" + json.dumps(t["measured"], default=str) + "`"]
    return "\n".join(lines) + "\n"


def junit(doc: dict) -> str:
    suite = ET.Element("testsuite", name=f"conformance {doc['bench']}", tests=str(len(doc["tests"])),
                       failures=str(doc["counts"]["fail"]), skipped=str(doc["counts"]["not_run"]),
                       time=str(doc["duration_s"]))
    for t in doc["tests"]:
        case = ET.SubElement(suite, "testcase", classname=f"conformance.{drive_key(doc)}", name=t["name"],
                             time=str(t["duration_s"]))
        if t["outcome"] == "fail":
            ET.SubElement(case, "failure", message="; ".join(t["findings"])[:500]).text = "\n".join(t["findings"])
        elif t["outcome"] == "not_run":
            ET.SubElement(case, "skipped", message=t["detail"])
        if t["findings"] and t["outcome"] == "note":
            ET.SubElement(case, "system-out").text = "\n".join(t["findings"])
    return ET.tostring(suite, encoding="unicode")


def keep(doc: dict, root: Path) -> Path:
    """conformance/<drive>/<stamp>.json|md|xml and latest.json|md|xml; returns the JSON path."""
    folder = root / drive_key(doc)
    folder.mkdir(parents=True, exist_ok=True)
    stamp = doc["started_utc"].replace(":", "").replace("+0000", "Z")
    for name in (stamp, "latest"):
        write_text_atomic(folder / f"{name}.json", json.dumps(doc, indent=1, default=str))
        write_text_atomic(folder / f"{name}.md", markdown(doc))
        write_text_atomic(folder / f"{name}.xml", junit(doc))
    return folder / f"{stamp}.json"


def latest_for_bench(root: Path, bench_config: str | Path) -> dict[str, Any] | None:
    """The newest kept report (latest.json of any drive folder under root) run with this bench config, summarised for
    the service's rig page; None when there is none. Reads files only."""
    wanted = str(Path(bench_config).resolve())
    best = None
    for path in Path(root).glob("*/latest.json"):
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if doc.get("bench_config") == wanted and (best is None or doc["started_utc"] > best[0]["started_utc"]):
            best = (doc, path)
    if best is None:
        return None
    doc, path = best
    return {"verdict": doc["verdict"], "counts": doc["counts"], "started_utc": doc["started_utc"],
            "drive": doc["identity"].get("identity", {}).get("device_name"), "report": str(path.with_suffix(".md")),
            "findings": [f for t in doc["tests"] for f in t["findings"]][:10]}


def compare(a: dict, b: dict) -> dict[str, Any]:
    """Test by test: outcome in A and B, and every measured time that both have."""
    ta, tb = {t["name"]: t for t in a["tests"]}, {t["name"]: t for t in b["tests"]}
    rows = []
    for name in list(ta) + [n for n in tb if n not in ta]:
        x, y = ta.get(name), tb.get(name)
        times = {}
        for ch in (x or {}).get("checks", []):
            other = next((c for c in (y or {}).get("checks", []) if c["what"] == ch["what"]), None)
            if other is not None and (ch["time_ms"] is not None or other["time_ms"] is not None):
                times[ch["what"]] = [ch["time_ms"], other["time_ms"]]
        rows.append({"test": name, "a": x["outcome"] if x else "absent", "b": y["outcome"] if y else "absent",
                     "same": bool(x and y and x["outcome"] == y["outcome"]), "times_ms": times})
    return {"a": {"bench": a["bench"], "identity": a["identity"].get("identity")},
            "b": {"bench": b["bench"], "identity": b["identity"].get("identity")}, "tests": rows}
