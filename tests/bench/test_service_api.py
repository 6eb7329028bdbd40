"""The bench service's API contract and security, on the embedded SQLite database with the run queue off (no run
processes): tokens, roles, status codes, scenario root, leases."""

from __future__ import annotations

import re
import time

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from fastapi.routing import APIRoute  # noqa: E402
from starlette.routing import WebSocketRoute  # noqa: E402
from starlette.testclient import WebSocketDenialResponse  # noqa: E402

from bench.service.limits import READ_CACHE_S  # noqa: E402
from tests.service_fixtures import REPO, SCENARIOS, SHORT, Tokens, client_for, make_settings, wait_until  # noqa: E402

H = Tokens.header
CONTRACT_RUN_KEYS = {"id", "state", "verdict", "rig", "scenario", "criteria", "record_url", "live_url"}
PARAMS = {"name": "sim-a", "run_id": "1", "lease_id": "1", "token_id": "1", "fmt": "csv",
          "asset": "swagger-ui.css"}
PUBLIC = {("GET", "/api/health"), ("GET", "/login"), ("POST", "/login"), ("GET", "/openapi.json"), ("GET", "/docs"),
          ("GET", "/docs/{asset}")}


@pytest.fixture
def api(tmp_path):
    with client_for(make_settings(tmp_path, run_queue=False)) as client:
        yield client


def _routes(app):
    for route in app.routes:
        if isinstance(route, APIRoute):
            for method in route.methods - {"HEAD"}:
                yield method, route.path
        elif isinstance(route, WebSocketRoute):
            yield "WS", route.path


def _fill(path: str) -> str:
    path = path.replace("/files/{name}", "/files/record.json")
    return re.sub(r"\{(\w+)\}", lambda m: PARAMS[m.group(1)], path)


def _call(client, method, path, headers=None):
    body = {} if method in ("POST", "PATCH", "PUT") else None
    return client.request(method, _fill(path), json=body, headers=headers or {}, follow_redirects=False)


def test_health_needs_no_token(api):
    assert api.get("/api/health").json()["status"] == "ok"


def test_every_endpoint_but_health_and_login_refuses_a_request_without_a_valid_token(api):
    routes = list(_routes(api.app))
    assert len(routes) > 25
    checked = 0
    for method, path in routes:
        if (method, path) in PUBLIC:
            continue
        for headers in ({}, H("dbt_not-a-token"), {"Authorization": "Basic YWRhOmFkYQ=="}):
            if method == "WS":
                with pytest.raises(WebSocketDenialResponse) as denied:
                    with api.websocket_connect(_fill(path), headers=headers):
                        pass
                assert denied.value.status_code == 401, path
                continue
            response = _call(api, method, path, headers)
            if path.startswith(("/api/", "/live/")) or path == "/metrics":   # /live/: the viewer and its data
                assert response.status_code == 401, (method, path, response.status_code)
                assert response.headers["www-authenticate"] == "Bearer"
            else:   # a page: the browser goes to the login page
                assert response.status_code == 303 and response.headers["location"] == "/login", (method, path)
            checked += 1
    assert checked >= 3 * 25


MUTATING = [(m, p) for m, p in (("POST", "/api/runs"), ("POST", "/api/runs/{run_id}/abort"),
                                 ("POST", "/api/rigs/{name}/lease"), ("POST", "/api/leases/{lease_id}/extend"),
                                 ("DELETE", "/api/leases/{lease_id}"), ("PATCH", "/api/rigs/{name}"),
                                 ("POST", "/api/tokens"), ("DELETE", "/api/tokens/{token_id}"),
                                 ("POST", "/api/rigs/{name}/probe"))]


def test_a_viewer_gets_403_on_every_mutating_endpoint(api):
    api_mutating = {(m, p) for m, p in _routes(api.app) if m in ("POST", "PATCH", "PUT", "DELETE")
                    and p.startswith("/api/")}
    assert api_mutating == set(MUTATING)          # a new mutating endpoint must be added to this test
    for method, path in MUTATING:
        response = _call(api, method, path, H(api.tokens.viewer))
        assert response.status_code == 403, (method, path, response.status_code, response.text)
    for path in ("/ui/runs/1/abort", "/ui/rigs/sim-a/reserve", "/ui/leases/1/release", "/ui/rigs/sim-a/probe"):
        response = api.post(path, data={"hours": "1", "reason": "x"}, headers=H(api.tokens.viewer))
        assert response.status_code == 403, path


def test_a_page_error_is_a_page_and_an_api_error_stays_json(api):
    viewer = H(api.tokens.viewer)
    page = api.get("/runs/999999", headers=viewer)
    assert page.status_code == 404 and page.headers["content-type"].startswith("text/html")
    assert "999999" in page.text and "<html" in page.text.lower()
    refused = api.post("/ui/rigs/sim-a/reserve", data={"hours": "1", "reason": "x"}, headers=viewer)
    assert refused.status_code == 403 and "reserving needs the operator role" in refused.text
    assert refused.headers["content-type"].startswith("text/html")
    bad_seed = api.post("/ui/runs", data={"scenario": "x.toml", "target": "rig:sim-a", "seed": "abc"},
                        headers=H(api.tokens.operator))
    assert bad_seed.status_code == 422 and "seed: must be an integer" in bad_seed.text
    assert api.get("/api/runs/999999", headers=viewer).json()["detail"]
    assert api.get("/api/runs/999999", headers=viewer).headers["content-type"] == "application/json"


def test_operator_may_not_do_admin_things(api):
    op = H(api.tokens.operator)
    assert api.post("/api/tokens", json={"name": "x", "role": "admin"}, headers=op).status_code == 403
    assert api.get("/api/tokens", headers=op).status_code == 403
    assert api.patch("/api/rigs/sim-a", json={"enabled": False}, headers=op).status_code == 403


def test_tokens_are_stored_hashed_and_shown_once(api, tmp_path):
    from bench.service.auth import hash_token

    created = api.post("/api/tokens", json={"name": "ci", "role": "operator"}, headers=H(api.tokens.admin))
    assert created.status_code == 201
    token = created.json()["token"]
    assert api.get("/api/rigs", headers=H(token)).status_code == 200
    listed = api.get("/api/tokens", headers=H(api.tokens.admin)).text
    assert token not in listed and hash_token(token) not in listed
    api.service.db.engine.dispose()
    stored = b"".join(p.read_bytes() for p in (tmp_path / "data").glob("drivebench.sqlite*"))
    for value in (token, api.tokens.admin, api.tokens.viewer):
        assert value.encode() not in stored
        assert hash_token(value).encode() in stored
    revoked = api.delete(f"/api/tokens/{created.json()['id']}", headers=H(api.tokens.admin))
    assert revoked.status_code == 200
    assert api.get("/api/rigs", headers=H(token)).status_code == 401


def test_rigs_contract(api):
    rigs = api.get("/api/rigs", headers=H(api.tokens.viewer)).json()
    assert [r["name"] for r in rigs] == ["real-a", "sim-a", "spim-a"]
    for rig in rigs:
        assert {"name", "tags", "state", "lease"} <= rig.keys()
        assert rig["state"] == "free" and rig["lease"] is None
    assert "simulated" in rigs[1]["tags"] and "real" in rigs[0]["tags"]
    assert api.get("/api/rigs/nope", headers=H(api.tokens.viewer)).status_code == 404
    assert "paths" in api.get("/openapi.json", headers=H(api.tokens.viewer)).json()


def test_the_api_documents_itself_without_a_token_from_local_assets(api):
    """OpenAPI and its Swagger UI are public (they describe, they hold no data); the UI's script and style come from
    the service itself, not a CDN a lab network may not reach."""
    doc = api.get("/openapi.json")
    assert doc.status_code == 200 and "/api/runs" in doc.json()["paths"]
    page = api.get("/docs")
    assert page.status_code == 200 and "/docs/swagger-ui-bundle.js" in page.text and "cdn" not in page.text.lower()
    js = api.get("/docs/swagger-ui-bundle.js")
    assert js.status_code == 200 and len(js.content) > 500_000 and "SwaggerUIBundle" in js.text[:2_000_000]
    assert api.get("/docs/other.js", follow_redirects=False).status_code in (303, 404)    # not public, not there


def test_metrics_in_prometheus_text(api):
    from prometheus_client.parser import text_string_to_metric_families

    op = H(api.tokens.operator)
    assert api.get("/metrics").status_code == 401                          # a viewer token, like the API
    api.patch("/api/rigs/sim-a", json={"enabled": False}, headers=H(api.tokens.admin))
    for _ in range(3):
        assert api.post("/api/runs", json={"scenario": f"service/{SHORT}", "rig": "sim-a"}, headers=op).status_code \
            == 201
    api.post("/api/rigs/real-a/lease", json={"ttl_s": 60, "reason": "wiring"}, headers=op)
    response = api.get("/metrics", headers=H(api.tokens.viewer))
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for family in text_string_to_metric_families(response.text) for s in family.samples}
    assert samples[("drivebench_runs", (("state", "queued"),))] == 3
    assert samples[("drivebench_queue_length", (("target", "sim-a"),))] == 3
    assert samples[("drivebench_queue_oldest_wait_seconds", (("target", "sim-a"),))] >= 0
    assert samples[("drivebench_leases_active", (("kind", "manual"),))] == 1
    assert samples[("drivebench_lease_events_total", (("event", "created"),))] == 1
    assert ("drivebench_run_duration_seconds_count", ()) in samples


def test_a_queued_run_says_why_it_waits(api):
    op, adm = H(api.tokens.operator), H(api.tokens.admin)
    api.patch("/api/rigs/sim-a", json={"enabled": False}, headers=adm)
    run = api.post("/api/runs", json={"scenario": f"service/{SHORT}", "rig": "sim-a"}, headers=op).json()
    waiting = api.get(f"/api/runs/{run['id']}", headers=op).json()["waiting"]
    assert waiting == "rig sim-a is disabled by an admin"
    api.patch("/api/rigs/sim-a", json={"enabled": True}, headers=adm)
    # the run queue is off in this fixture, so its host slots are what holds a startable run
    # (a setting changed behind the API's back shows within the answers' age, READ_CACHE_S)
    api.service.runner.settings.max_parallel = 0
    assert wait_until(lambda: api.get(f"/api/runs/{run['id']}", headers=op).json()["waiting"].startswith(
        "host slots: this service instance runs 0 of its 0 runs at once (--max-parallel); rig sim-a is free"),
        READ_CACHE_S + 0.5, 0.05, "the host-slot reason")
    api.service.runner.settings.max_parallel = 2
    assert wait_until(lambda: api.get(f"/api/runs/{run['id']}", headers=op).json()["waiting"]
                      == "starting: rig sim-a is free", READ_CACHE_S + 0.5, 0.05, "the starting reason")
    # a real rig reserved by someone else
    api.post("/api/rigs/real-a/lease", json={"ttl_s": 60, "reason": "wiring"}, headers=H(api.tokens.operator2))
    other = api.post("/api/runs", json={"scenario": f"service/{SHORT}", "rig": "real-a"}, headers=op)
    if other.status_code == 201:         # submitting to a rig someone else reserved may be refused outright (409)
        waiting = api.get(f"/api/runs/{other.json()['id']}", headers=op).json()["waiting"]
        assert waiting.startswith("rig real-a is reserved by oscar until ")
    else:
        assert other.status_code == 409 and "reserved by oscar" in other.text
    page = api.get(f"/runs/{run['id']}", headers=op)
    assert 'id="waiting"' in page.text and "starting: rig sim-a is free" in page.text


def test_the_run_list_and_the_queue_page_give_each_queued_run_the_reason_its_own_page_gives(api):
    """The list reads the rigs and the queue once for all its runs: each run's reason must still be its own."""
    op = H(api.tokens.operator)
    ids = [api.post("/api/runs", json={"scenario": f"service/{SHORT}", "rig": rig}, headers=op).json()["id"]
           for rig in ("sim-a", "sim-a", "real-a")]
    time.sleep(0.3)
    own = {i: api.get(f"/api/runs/{i}", headers=op).json()["waiting"] for i in ids}
    assert own[ids[0]].startswith("starting: rig sim-a is free")
    assert own[ids[1]].startswith(f"behind run {ids[0]}, queued earlier")
    listed = {r["id"]: r["waiting"] for r in api.get("/api/runs?state=queued", headers=op).json()}
    assert {i: listed[i] for i in ids} == own
    page = api.get("/", headers=op).text
    for i in ids:
        assert f'data-run-waiting="{i}">{own[i]}<' in page.replace("&#39;", "'")


def test_submit_get_list_and_cancel_a_run(api):
    op, op2, adm = H(api.tokens.operator), H(api.tokens.operator2), H(api.tokens.admin)
    created = api.post("/api/runs", json={"scenario": f"service/{SHORT}", "rig": "sim-a", "seed": 7}, headers=op)
    assert created.status_code == 201, created.text
    assert created.json()["state"] == "queued" and set(created.json()) >= {"id", "state"}
    run_id = created.json()["id"]
    run = api.get(f"/api/runs/{run_id}", headers=H(api.tokens.viewer)).json()
    assert CONTRACT_RUN_KEYS <= run.keys()
    assert (run["state"], run["rig"], run["seed"], run["owner"]) == ("queued", "sim-a", 7, "olga")
    also = api.post("/api/runs", json={"scenario": SHORT, "tag": "pmsm"}, headers=op2).json()["id"]
    listed = api.get("/api/runs", params={"rig": "sim-a", "state": "queued", "limit": 10}, headers=op).json()
    assert [r["id"] for r in listed] == [run_id]
    assert len(api.get("/api/runs", params={"limit": 1}, headers=op).json()) == 1
    assert api.get("/api/runs", params={"state": "flying"}, headers=op).status_code == 422
    assert api.get("/api/runs/999", headers=op).status_code == 404
    assert api.post("/api/runs/999/abort", headers=op).status_code == 404
    assert api.post(f"/api/runs/{also}/abort", headers=op).status_code == 403      # not olga's run
    cancelled = api.post(f"/api/runs/{run_id}/abort", headers=op)
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    assert api.post(f"/api/runs/{run_id}/abort", headers=op).status_code == 409    # already final
    assert api.post(f"/api/runs/{also}/abort", headers=adm).json()["state"] == "cancelled"
    assert api.get(f"/api/runs/{also}", headers=op).json()["reason"] == "cancelled by ada before it started"


@pytest.mark.slow
@pytest.mark.parametrize("path", ["../../etc/passwd", "/etc/passwd", "service/../../../pyproject.toml",
                                  "service/../../../scenarios/pmsm/fig08-20rads-rs-step.toml", "link-out.toml"])
def test_scenario_paths_outside_the_scenario_root_are_refused(api, path, tmp_path):
    link = SCENARIOS / "link-out.toml"
    try:
        if path == "link-out.toml":
            link.symlink_to(REPO / "scenarios" / "pmsm" / "fig08-20rads-rs-step.toml")
        response = api.post("/api/runs", json={"scenario": path, "rig": "sim-a"}, headers=H(api.tokens.operator))
    finally:
        link.unlink(missing_ok=True)
    assert response.status_code == 422
    assert response.json()["detail"] == [f"request: scenario: {path}: outside the scenario root (give a path under "
                                         f"service/ or send scenario_toml)"]


def test_bad_scenarios_give_the_clis_lines(api):
    from drivers.contract.errors import InputError
    from bench.inputs.prepared import prepare_run

    op = H(api.tokens.operator)
    with pytest.raises(InputError) as cli:
        prepare_run(SCENARIOS / "bad.toml", REPO / "config/benches/sim-pmsm.toml")
    expected = [line.replace(str(SCENARIOS / "bad.toml"), "service/bad.toml") for line in cli.value.problems]
    response = api.post("/api/runs", json={"scenario": "service/bad.toml", "rig": "sim-a"}, headers=op)
    assert response.status_code == 422 and response.json()["detail"] == expected
    inline = api.post("/api/runs", json={"scenario_toml": (SCENARIOS / "bad.toml").read_text(), "rig": "sim-a",
                                         "filename": "ci/bad.toml"}, headers=op)
    assert inline.json()["detail"] == [line.replace("service/bad.toml", "ci/bad.toml") for line in expected]
    assert all(re.match(r"^[^:]+: [^:]+: .+", line) for line in expected)
    for body, line in ((({"rig": "sim-a"}), "request: scenario: give exactly one of"),
                       ({"scenario": SHORT}, "request: rig: give exactly one of"),
                       ({"scenario": SHORT, "rig": "nope"}, "request: rig: no rig named 'nope'"),
                       ({"scenario": SHORT, "tag": "nope"}, "request: tag: no rig has tag 'nope'"),
                       ({"scenario": SHORT, "rig": "sim-a", "seed": "x"}, "request: seed: "),
                       ({"scenario": "missing.toml", "rig": "sim-a"}, "missing.toml: (file): not found")):
        response = api.post("/api/runs", json=body, headers=op)
        assert response.status_code == 422, body
        assert response.json()["detail"][0].startswith(line), response.json()


def test_a_tag_keeps_only_the_rigs_of_the_scenarios_drive_kind(api):
    spim = (REPO / "scenarios/spim/fig06-1500rpm-load-step.toml").read_text()
    op = H(api.tokens.operator)
    assert api.post("/api/runs", json={"scenario_toml": spim, "tag": "pmsm"}, headers=op).status_code == 422
    run_id = api.post("/api/runs", json={"scenario_toml": spim, "tag": "simulated"}, headers=op).json()["id"]
    with api.service.db.session() as s:
        from bench.service.db import Run
        assert s.get(Run, run_id).candidates == ["spim-a"]


def test_leases_on_a_real_rig(api):
    olga, oscar, ada = H(api.tokens.operator), H(api.tokens.operator2), H(api.tokens.admin)
    held = api.post("/api/rigs/real-a/lease", json={"ttl_s": 60, "reason": "wiring the encoder"}, headers=olga)
    assert held.status_code == 201 and set(held.json()) >= {"id", "expires_utc"}
    lease_id = held.json()["id"]
    rig = api.get("/api/rigs/real-a", headers=oscar).json()
    assert rig["state"] == "reserved" and rig["lease"]["holder"] == "olga"
    assert rig["lease"]["reason"] == "wiring the encoder"
    refused = api.post("/api/rigs/real-a/lease", json={"ttl_s": 60}, headers=oscar)
    assert refused.status_code == 409 and "leased by olga" in refused.json()["detail"]
    submitted = api.post("/api/runs", json={"scenario": SHORT, "rig": "real-a"}, headers=oscar)
    assert submitted.status_code == 409
    assert api.post("/api/runs", json={"scenario": SHORT, "rig": "real-a"}, headers=olga).status_code == 201
    assert api.post("/api/rigs/nope/lease", json={"ttl_s": 5}, headers=olga).status_code == 404
    assert api.post("/api/rigs/real-a/lease", json={"ttl_s": -1}, headers=olga).status_code == 422
    assert api.post(f"/api/leases/{lease_id}/extend", json={"ttl_s": 120}, headers=oscar).status_code == 403
    extended = api.post(f"/api/leases/{lease_id}/extend", json={"ttl_s": 120}, headers=olga)
    assert extended.status_code == 200 and extended.json()["expires_utc"] > held.json()["expires_utc"]
    assert api.delete(f"/api/leases/{lease_id}", headers=oscar).status_code == 403
    broken = api.delete(f"/api/leases/{lease_id}", headers=ada)                      # an admin breaks it
    assert broken.status_code == 200 and broken.json()["released_by"] == "ada"
    assert api.get("/api/rigs/real-a", headers=oscar).json()["state"] == "free"
    assert api.post("/api/rigs/real-a/lease", json={"ttl_s": 60}, headers=oscar).status_code == 201
    assert api.delete("/api/leases/999", headers=ada).status_code == 404
    # a simulated rig is shared: a person's lease there blocks nobody
    assert api.post("/api/rigs/sim-a/lease", json={"ttl_s": 60}, headers=olga).status_code == 201
    assert api.post("/api/rigs/sim-a/lease", json={"ttl_s": 60}, headers=oscar).status_code == 201


def test_a_lease_that_is_not_extended_expires(api):
    olga, oscar = H(api.tokens.operator), H(api.tokens.operator2)
    lease_id = api.post("/api/rigs/real-a/lease", json={"ttl_s": 0.4}, headers=olga).json()["id"]
    assert api.post("/api/rigs/real-a/lease", json={"ttl_s": 1}, headers=oscar).status_code == 409
    time.sleep(0.5)
    assert api.get("/api/rigs/real-a", headers=oscar).json()["state"] == "free"
    assert api.post(f"/api/leases/{lease_id}/extend", headers=olga).status_code == 409
    assert api.post("/api/rigs/real-a/lease", json={"ttl_s": 1}, headers=oscar).status_code == 201


def test_validation_errors_are_lines(api):
    response = api.post("/api/rigs/real-a/lease", json={"reason": "x"}, headers=H(api.tokens.operator))
    assert response.status_code == 422
    assert response.json()["detail"] == ["request: ttl_s: Field required"]


@pytest.mark.slow
def test_failing_since_names_the_run_and_revision_a_failing_streak_began_at(api):
    from bench.service.db import CriterionValue, Run

    with api.service.db.session() as s:
        for k, (rev, x_ok, y_ok) in enumerate((("aaa", True, False), ("bbb", False, True), ("ccc", False, True)), 1):
            s.add(Run(id=k, state="pass" if x_ok else "fail", verdict="pass" if x_ok else "fail", rig="sim-a",
                      scenario="service/short.toml", scenario_file="x.toml", scenario_name="svc", owner="olga",
                      revision=rev, submitted_ts=1000.0 + k, started_ts=1000.5 + k, ended_ts=1001.0 + k))
            s.flush()
            for name, ok in (("X", x_ok), ("Y", y_ok)):
                s.add(CriterionValue(run_id=k, name=name, value=1.0, limit=0.5, passed=ok,
                                     status="pass" if ok else "fail"))
            s.add(CriterionValue(run_id=k, name="Z", value=None, limit=0.5, passed=False, status="not_judged"))
    failing = api.get("/api/failing", headers=H(api.tokens.viewer)).json()
    assert [(f["criterion"], f["since"]["run_id"], f["since"]["revision"], f["runs_failing"], f["last_pass"]["run_id"])
            for f in failing] == [("X", 2, "bbb", 2, 1)]           # Y recovered; Z was never judged
    page = api.get("/history", headers=H(api.tokens.viewer))
    assert 'id="failing"' in page.text and "run #2</a>, revision bbb" in page.text
    # several criteria at once, over revisions (or time, or run id)
    trend = api.get("/trend?scenario=svc&criterion=X&criterion=Y&x=revision", headers=H(api.tokens.viewer))
    assert trend.status_code == 200 and trend.text.count('class="trend-points"') == 2
    assert "/trend.png?scenario=svc&amp;criterion=X&amp;criterion=Y&amp;x=revision" in trend.text
    for axis in ("revision", "time", "run"):
        png = api.get(f"/trend.png?scenario=svc&criterion=X&criterion=Y&x={axis}", headers=H(api.tokens.viewer))
        assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n", axis


def test_a_change_shows_within_the_cache_age_and_never_after_an_event_or_a_write_that_told_of_it(api):
    viewer, admin = H(api.tokens.viewer), H(api.tokens.admin)

    def enabled(headers=viewer) -> bool:
        return api.get("/api/rigs/sim-a", headers=headers).json()["enabled"]

    def shows_within_the_cache_age(value: bool, headers=viewer) -> None:
        t0 = time.monotonic()
        while enabled(headers) is not value:
            assert time.monotonic() - t0 < READ_CACHE_S, "the change did not show within the answers' age"
            time.sleep(0.005)

    assert enabled() is True and enabled(admin) is True
    api.service.set_rig_enabled("sim-a", False)     # a change this service does not see (another instance's)
    assert enabled() is True                        # the answer in memory...
    assert enabled({**viewer, "Cache-Control": "no-cache"}) is False    # ...unless the client asks for the state now
    api.service.set_rig_enabled("sim-a", True)
    shows_within_the_cache_age(True)                # and within the answers' age for everyone
    api.service.set_rig_enabled("sim-a", False)     # a change it sees, as the runner's: read again at once
    api.service.events.changed()
    shows_within_the_cache_age(False)

    with api.websocket_connect("/api/events", headers=viewer) as events:
        api.service.set_rig_enabled("sim-a", True)
        api.service.events.publish({"type": "rig", "id": None, "name": "sim-a"})
        assert events.receive_json()["name"] == "sim-a"
        assert enabled() is True                    # the event's reader never gets an answer older than it

    assert api.patch("/api/rigs/sim-a", json={"enabled": False}, headers=admin).status_code == 200
    assert enabled(admin) is False and enabled() is False     # a write through the API: every read after it
