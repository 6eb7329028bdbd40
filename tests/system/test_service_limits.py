"""The service bounded by construction (issue 23): bodies limited per route before parsing, a viewer's body never
read, ids and names a database or file system cannot hold answered 4xx, plots rendered once per content off the event
loop, and idle connections that cannot lock the API out of a process with few file descriptors."""

from __future__ import annotations

import resource
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import pytest

pytest.importorskip("fastapi")

from tests.service_fixtures import REPO, SCENARIOS, Tokens, client_for, free_port, make_settings, stop_process, \
    wait_until, write_rigs  # noqa: E402

H = Tokens.header


@pytest.fixture
def api(tmp_path):
    with client_for(make_settings(tmp_path, run_queue=False)) as client:
        yield client


def test_a_body_over_the_routes_limit_is_413_by_its_content_length(api):
    big = {"scenario_toml": "x" * 3_000_000, "rig": "sim-a"}
    r = api.post("/api/runs", json=big, headers=H(api.tokens.operator))
    assert r.status_code == 413 and "takes at most 1048576" in r.json()["detail"]
    r = api.post("/api/rigs/sim-a/lease", json={"ttl_s": 10, "reason": "x" * 100_000},
                 headers=H(api.tokens.operator))
    assert r.status_code == 413 and "takes at most 65536" in r.json()["detail"]


def test_a_chunked_body_is_counted_as_it_arrives(api):
    def chunks():
        yield b'{"rig": "sim-a", "scenario_toml": "'
        for _ in range(20):
            yield b"x" * 65536
        yield b'"}'
    r = api.post("/api/runs", content=chunks(), headers={**H(api.tokens.operator), "Content-Type": "application/json"})
    assert r.status_code == 413 and "over 1048576 bytes" in r.json()["detail"]


def test_a_viewer_or_a_stranger_is_refused_before_the_body_is_read(api):
    read = []

    def chunks():
        read.append(1)
        yield b"{}"
    r = api.post("/api/runs", content=chunks(), headers={**H(api.tokens.viewer), "Content-Type": "application/json"})
    assert r.status_code == 403 and "needs the operator role" in r.json()["detail"]
    r = api.post("/api/runs", content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 401
    assert api.service.list_runs() == []


def test_a_scenario_of_up_to_the_stated_size_is_taken(api):
    text = (SCENARIOS / "short.toml").read_text()
    text += "#" * (250_000 - len(text)) + "\n"
    r = api.post("/api/runs", json={"scenario_toml": text, "filename": "big.toml", "rig": "sim-a"},
                 headers=H(api.tokens.operator))
    assert r.status_code == 201, r.text


@pytest.mark.parametrize("method,path", [("GET", "/api/runs/{n}"), ("POST", "/api/runs/{n}/abort"),
                                         ("GET", "/api/runs/{n}/files/record.json"),
                                         ("POST", "/api/leases/{n}/extend"), ("DELETE", "/api/leases/{n}"),
                                         ("DELETE", "/api/tokens/{n}"), ("GET", "/runs/{n}")])
def test_ids_beyond_64_bits_are_422_not_500(api, method, path):
    for n in (2**63, 2**70, -1):
        r = api.request(method, path.format(n=n), headers=H(api.tokens.admin))
        assert r.status_code == 422, (n, r.status_code, r.text[:200])


def test_path_components_over_255_bytes_are_4xx_not_500(api):
    long = "a" * 300
    for method, path, body in [("GET", f"/api/rigs/{long}", None), ("GET", f"/api/runs/1/files/{long}", None),
                               ("POST", "/api/runs", {"scenario": f"{long}/x.toml", "rig": "sim-a"}),
                               ("POST", "/api/runs", {"scenario": f"{long}.toml", "rig": "sim-a"})]:
        r = api.request(method, path, json=body, headers=H(api.tokens.admin))
        assert 400 <= r.status_code < 500, (path, r.status_code, r.text[:200])


def test_one_plot_is_rendered_once_for_many_concurrent_viewers(api):
    statuses = []

    def fetch():
        statuses.append(api.get("/trend.png?criterion=speed_rms&scenario=x", headers=H(api.tokens.viewer)).status_code)
    threads = [threading.Thread(target=fetch) for _ in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert statuses == [200] * 20
    assert api.app.state.plots.renders == 1


def test_idle_connections_cannot_lock_out_the_api_of_a_process_with_few_descriptors(tmp_path):
    """1,100 silent connections against a service limited to 400 descriptors: the API still answers, and the silent
    ones are closed at the head timeout."""
    write_rigs(tmp_path)
    port = free_port()
    subprocess.run([sys.executable, "-m", "bench", "token", "create", "--role", "viewer", "--name", "v", "--data",
                    str(tmp_path / "data")], cwd=REPO, check=True, capture_output=True, timeout=60)

    def few_fds():
        resource.setrlimit(resource.RLIMIT_NOFILE, (400, 400))
    log = open(tmp_path / "serve.log", "ab")
    proc = subprocess.Popen([sys.executable, "-m", "bench", "serve", "--data", str(tmp_path / "data"), "--port",
                             str(port), "--rigs", str(tmp_path / "rigs.toml"), "--scenarios", str(SCENARIOS)],
                            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, preexec_fn=few_fds,
                            start_new_session=True)
    idle: list[socket.socket] = []

    def health() -> bool:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=2) as r:
                return r.status == 200
        except OSError:
            return False
    try:
        wait_until(health, 30, 0.1, "serve to answer")
        for _ in range(1100):
            idle.append(socket.create_connection(("127.0.0.1", port), timeout=5))
        time.sleep(1.0)
        t0 = time.monotonic()
        assert health()
        assert time.monotonic() - t0 < 2.0
    finally:
        for s in idle:
            s.close()
        stop_process(proc)
        log.close()
    text = (tmp_path / "serve.log").read_text()
    assert "Traceback" not in text and text.count("\n") < 10, text[-2000:]
