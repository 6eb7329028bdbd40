"""A token may follow at most MAX_FOLLOWS_PER_TOKEN live recordings at once (200 followers of one run took 64 % of a
core and pushed /api/runs p99 to 360 ms): the next is 429, another token is not held back, and a closed stream frees
its place. Against `drivebench serve` over real sockets, on a running run."""

from __future__ import annotations

import http.client
import time

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import served_service, wait_until

LIVE = "live.toml"         # fifty minutes of drive time: running throughout, aborted at the end


def _open(port: int, path: str, token: str) -> tuple[http.client.HTTPConnection, http.client.HTTPResponse]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    conn.request("GET", path, headers={"Authorization": f"Bearer {token}"})
    return conn, conn.getresponse()


def test_live_followers_are_capped_per_token(tmp_path):
    from bench.service.client import Client
    from bench.service.live import MAX_FOLLOWS_PER_TOKEN

    with served_service(tmp_path, "--lease-ttl", "3") as served:
        client = Client(served.url, served.tokens.operator)
        run_id = client.request("POST", "/api/runs", {"scenario": LIVE, "rig": "sim-a"})["id"]
        wait_until(lambda: client.request("GET", f"/api/runs/{run_id}")["state"] == "running", 90, 0.2, "running")
        path = f"/live/runs/{run_id}/recording.rrd"
        opened = [_open(served.port, path, served.tokens.operator) for _ in range(MAX_FOLLOWS_PER_TOKEN)]
        try:
            assert [r.status for _, r in opened] == [200] * MAX_FOLLOWS_PER_TOKEN
            conn, refused = _open(served.port, path, served.tokens.operator)
            body = refused.read().decode(errors="replace")
            conn.close()
            assert refused.status == 429 and f"at most {MAX_FOLLOWS_PER_TOKEN} at once per token" in body, body
            other = _open(served.port, path, served.tokens.viewer)        # another token: its own count
            assert other[1].status == 200
            other[0].close()
            opened.pop()[0].close()                                       # a closed stream frees its place
            deadline = time.monotonic() + 10
            while True:
                conn, again = _open(served.port, path, served.tokens.operator)
                if again.status == 200 or time.monotonic() > deadline:
                    break
                again.read()
                conn.close()
                time.sleep(0.3)
            assert again.status == 200
            conn.close()
        finally:
            for conn, _ in opened:
                conn.close()
            client.request("POST", f"/api/runs/{run_id}/abort")
