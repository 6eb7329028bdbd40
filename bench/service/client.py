"""`drivebench submit`: the CI client of the bench service. Standard library only (urllib), so a CI job needs
drivebench without the [service] extra."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable
from xml.etree import ElementTree as ET

from bench.service.limits import MAX_SCENARIO_CHARS

FINAL = ("pass", "fail", "aborted", "error", "cancelled")
REQUEST_TIMEOUT_S = 30.0



class ClientError(Exception):
    """One or more `file: field: reason` lines (bad input, refused, or the service unreachable)."""

    def __init__(self, lines: list[str], status: int | None = None):
        super().__init__("\n".join(lines))
        self.lines = lines
        self.status = status


@dataclass
class Client:
    server: str
    token: str
    timeout_s: float = REQUEST_TIMEOUT_S

    def __post_init__(self) -> None:
        parsed = urllib.parse.urlsplit(self.server)
        try:
            parsed.port                      # raises on a port that is not a number or out of range
        except ValueError as exc:
            raise ClientError([f"{self.server}: (server): {exc}"]) from None
        if parsed.scheme not in ("http", "https") or not parsed.hostname:
            raise ClientError([f"{self.server}: (server): must be an http:// or https:// URL with a host"])
        if any(c in self.token for c in "\r\n\0"):
            raise ClientError(["(token): contains a line break or NUL"])

    def url(self, path: str) -> str:
        return urllib.parse.urljoin(self.server.rstrip("/") + "/", path.lstrip("/"))

    def request(self, method: str, path: str, body: dict | None = None) -> Any:
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.url(path), data=data, method=method,
                                     headers={"Authorization": f"Bearer {self.token}",
                                              "Content-Type": "application/json", "Accept": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as response:
                return json.loads(response.read() or b"null")
        except urllib.error.HTTPError as exc:
            try:
                detail = json.loads(exc.read() or b"{}").get("detail")
            except ValueError:
                detail = None
            lines = detail if isinstance(detail, list) else [f"{self.server}: {method} {path}: {exc.code} "
                                                              f"{detail or exc.reason}"]
            raise ClientError([str(line) for line in lines], exc.code) from None
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise ClientError([f"{self.server}: (server): cannot reach the bench service: {reason}"]) from None

    def submit(self, scenario: str, rig: str | None, tag: str | None, seed: int | None) -> dict:
        """A local file is sent as its text (the service may run another checkout); any other path is taken as a
        path under the service's scenario root."""
        body: dict[str, Any] = {"rig": rig} if rig else {"tag": tag}
        path = Path(scenario)
        if path.is_file():
            try:
                text = path.read_text(encoding="utf-8")
            except UnicodeDecodeError:
                raise ClientError([f"{scenario}: (file): not a text file (UTF-8 TOML expected)"]) from None
            except OSError as exc:
                raise ClientError([f"{scenario}: (file): cannot read: {exc.strerror or exc}"]) from None
            if len(text) > MAX_SCENARIO_CHARS:
                raise ClientError([f"{scenario}: (file): {len(text)} characters; the service takes scenarios up to "
                                   f"{MAX_SCENARIO_CHARS}"])
            body.update(scenario_toml=text, filename=scenario)
        else:
            body["scenario"] = scenario
        if seed is not None:
            body["seed"] = seed
        return self.request("POST", "/api/runs", body)

    def wait(self, run_ids: list[int], timeout_s: float, poll_s: float = 1.0,
             on_change: Callable[[dict], None] | None = None) -> dict[int, dict]:
        deadline = time.monotonic() + timeout_s
        last: dict[int, dict] = {}
        pending = list(run_ids)
        while pending:
            for run_id in list(pending):
                run = self.request("GET", f"/api/runs/{run_id}")
                if on_change and (run_id not in last or last[run_id]["state"] != run["state"]):
                    on_change(run)
                last[run_id] = run
                if run["state"] in FINAL:
                    pending.remove(run_id)
            if pending:
                if time.monotonic() > deadline:
                    raise ClientError([f"{self.server}: (wait): runs {', '.join(map(str, pending))} not finished "
                                       f"after {timeout_s:g} s"])
                time.sleep(poll_s)
        return last


def write_junit(path: Path, runs: list[dict], server: str) -> None:
    """One testsuite per run, one testcase per criterion (as `drivebench run` writes junit.xml)."""
    root = ET.Element("testsuites")
    for run in runs:
        name = run.get("scenario_name") or run.get("scenario") or f"run-{run['id']}"
        suite = ET.SubElement(root, "testsuite", name=name)
        suite.set("timestamp", str(run.get("started_utc") or ""))
        if isinstance(run.get("duration_s"), (int, float)):
            suite.set("time", f"{run['duration_s']:.3f}")          # the run's wall time, as `drivebench run`'s
        properties = ET.SubElement(suite, "properties")
        for key, value in _run_properties(run, server):
            ET.SubElement(properties, "property", name=key, value=value)
        failures = errors = skipped = 0
        criteria = run.get("criteria") or []
        for c in criteria:
            case = ET.SubElement(suite, "testcase", classname=f"drivebench.{name}", name=str(c.get("name")))
            window = c.get("window_s")
            if isinstance(window, list) and len(window) == 2 and all(isinstance(v, (int, float)) for v in window):
                case.set("time", f"{max(0.0, float(window[1]) - float(window[0])):.6g}")   # drive time it judges
            case_props = ET.SubElement(case, "properties")
            for key in ("kind", "signal", "unit", "value", "limit", "status"):
                ET.SubElement(case_props, "property", name=key, value="" if c.get(key) is None else str(c.get(key)))
            text = f"value {c.get('value')}, limit {c.get('limit')}: {c.get('detail', '')}"
            if c.get("status") == "not_judged" or (not c.get("passed") and c.get("known_gap")):
                skipped += 1
                ET.SubElement(case, "skipped", message=str(c.get("detail") or c.get("known_gap"))).text = text
            elif not c.get("passed"):
                failures += 1
                ET.SubElement(case, "failure", message=text).text = text
        if run["state"] not in ("pass", "fail") or run.get("verdict") == "incomplete":
            errors += 1
            case = ET.SubElement(suite, "testcase", classname=f"drivebench.{name}", name="run")
            ET.SubElement(case, "error", message=f"run {run['state']}: {run.get('reason') or ''}").text = \
                urllib.parse.urljoin(server.rstrip("/") + "/", f"runs/{run['id']}")
        suite.set("tests", str(len(criteria) + (1 if errors else 0)))
        suite.set("failures", str(failures))
        suite.set("errors", str(errors))
        suite.set("skipped", str(skipped))
    ET.indent(root)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)


def _run_properties(run: dict, server: str) -> list[tuple[str, str]]:
    """What ran on what, as `drivebench run`'s junit.xml says it, plus where the service keeps the run."""
    drive = run.get("drive") or {}
    software = run.get("software") or {}
    pairs = [("run_id", run.get("id")), ("url", urllib.parse.urljoin(server.rstrip("/") + "/", f"runs/{run['id']}")),
             ("rig", run.get("rig")), ("state", run.get("state")), ("verdict", run.get("verdict")),
             ("seed", run.get("seed")), ("scenario_sha256", run.get("scenario_sha256")),
             ("drive", drive.get("device_name") if isinstance(drive, dict) else drive),
             ("firmware_version", run.get("firmware_version")), ("software_version", software.get("version")),
             ("git_revision", run.get("revision")), ("owner", run.get("owner")), ("started_utc", run.get("started_utc")),
             ("ended_utc", run.get("ended_utc"))]
    return [(key, str(value)) for key, value in pairs if value not in (None, "")]
