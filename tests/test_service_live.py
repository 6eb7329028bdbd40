"""`drivebench serve --live`: the Rerun gRPC server and web viewer from the rerun-sdk wheel, runs streaming to it
as recording `run-ID` while teeing to their run.rrd."""

from __future__ import annotations

import urllib.request

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import (SHORT, free_port, make_settings, make_tokens,  # noqa: E402
                                    serve_process, stop_process)


def test_live_runs_stream_to_the_services_rerun_server_and_keep_their_rrd(tmp_path):
    from bench.service.client import Client
    from bench.service.core import Service

    service = Service(make_settings(tmp_path))
    tokens = make_tokens(service.db)
    service.db.dispose()
    port, grpc_port, web_port = free_port(), free_port(), free_port()
    server = serve_process(tmp_path, port, "--live", "--live-grpc-port", str(grpc_port), "--live-web-port",
                           str(web_port))
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=10) as page:
            assert b"<html" in page.read(4096).lower()           # the viewer's page, served from the wheel
        client = Client(f"http://127.0.0.1:{port}", tokens.operator)
        run_id = client.request("POST", "/api/runs", {"scenario": SHORT, "rig": "sim-a"})["id"]
        run = client.wait([run_id], 90, poll_s=0.2)[run_id]
        assert run["state"] == "pass", run
        record = client.request("GET", run["record_url"])
        assert record["rerun"]["mode"] == "connect"
        assert record["rerun"]["url"] == f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        assert record["rerun"]["sinks"] == ["file", "viewer"]      # tee: run.rrd and the live server
        rrd = urllib.request.Request(f"http://127.0.0.1:{port}/api/runs/{run_id}/files/run.rrd",
                                     headers={"Authorization": f"Bearer {tokens.viewer}"})
        with urllib.request.urlopen(rrd, timeout=10) as response:
            assert len(response.read()) > 10_000
        live = urllib.request.Request(f"http://127.0.0.1:{port}/runs/{run_id}/live",
                                      headers={"Authorization": f"Bearer {tokens.viewer}"})
        with urllib.request.urlopen(live, timeout=10) as response:
            html = response.read().decode()
        assert f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy" in html
        assert f"run-{run_id}" in html
    finally:
        stop_process(server)
