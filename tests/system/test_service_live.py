"""The live view per run (`drivebench serve --live`): no Rerun port at all — the service serves the Rerun web viewer
(from the rerun-sdk wheel) and each run's followed run.rrd on its own address, behind its token; the run page embeds
the viewer on that run's recording only, named `run-ID · scenario` as the page names it. Checked on the listening
sockets, on the served bytes, and in a real browser (Chromium through Playwright; screenshots where
DRIVEBENCH_SCREENSHOTS names a folder)."""

from __future__ import annotations

import os
import time
import urllib.error
import urllib.request

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")
psutil = pytest.importorskip("psutil")

from tests.service_fixtures import (CHROMIUM, chromium_page, served_service, shot, SHORT, wait_until)

LIVE = "live.toml"            # fifty minutes of drive time: watched while it runs, then aborted


@pytest.fixture
def served(tmp_path):
    from bench.service.client import Client

    with served_service(tmp_path, "--live") as service:
        yield service.url, service.port, service.process, service.tokens, Client(service.url, service.tokens.operator)


def _get(url: str, token: str | None, limit: int | None = None, timeout_s: float = 60) -> tuple[int, bytes]:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout_s) as response:
            return response.status, response.read(limit) if limit else response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _listening(pid: int) -> dict[int, set[tuple[str, int]]]:
    """Listening TCP sockets of a process and of every process it started, by pid."""
    root = psutil.Process(pid)
    found = {}
    for proc in [root, *root.children(recursive=True)]:
        try:
            found[proc.pid] = {(c.laddr.ip, c.laddr.port) for c in proc.net_connections(kind="inet")
                               if c.status == psutil.CONN_LISTEN}
        except psutil.NoSuchProcess:
            pass
    return found


def _running(client, run_id: int, timeout_s: float = 90) -> None:
    wait_until(lambda: client.request("GET", f"/api/runs/{run_id}")["state"] == "running", timeout_s, 0.2,
               f"run {run_id} to start")


def test_live_view_is_on_the_api_address_behind_the_token_and_each_stream_is_its_own_run(served, tmp_path):
    from bench.outputs.rerun_view import rrd_recording

    url, port, server, tokens, client = served
    live_id = client.request("POST", "/api/runs", {"scenario": LIVE, "rig": "sim-a"})["id"]
    short_id = client.request("POST", "/api/runs", {"scenario": SHORT, "rig": "sim-a"})["id"]
    _running(client, live_id)

    # the running run's recording arrives while it runs (the stream follows run.rrd), to a viewer token
    status, head = _get(f"{url}/live/runs/{live_id}/recording.rrd", tokens.viewer, limit=4096)
    assert status == 200 and head[:4] == b"RRF2", head[:16]                # an .rrd stream's header
    assert client.request("GET", f"/api/runs/{live_id}")["state"] == "running"

    # nothing listens but the API, on the address it was given: no Rerun gRPC or web port, in no process
    listening = _listening(server.pid)
    assert listening[server.pid] == {("127.0.0.1", port)}, listening
    assert all(ip == "127.0.0.1" for sockets in listening.values() for ip, _ in sockets), listening
    assert len(listening) >= 2, "expected the run process among the service's children"

    # without a token: 401 for the viewer and for every recording; a wrong token too
    for path in ("/live/viewer/index.html", "/live/viewer/re_viewer_bg.wasm",
                 f"/live/runs/{live_id}/recording.rrd", f"/live/runs/{short_id}/recording.rrd"):
        assert _get(url + path, None)[0] == 401, path
        assert _get(url + path, "dbt_not_a_token")[0] == 401, path
    status, index = _get(f"{url}/live/viewer/index.html", tokens.viewer)
    assert status == 200 and b"re_viewer.js" in index and b"fonts.googleapis" not in index   # nothing from the internet
    status, wasm = _get(f"{url}/live/viewer/re_viewer_bg.wasm", tokens.viewer)
    assert status == 200 and wasm[:4] == b"\0asm" and len(wasm) > 1_000_000

    client.request("POST", f"/api/runs/{live_id}/abort")
    runs = client.wait([live_id, short_id], 120, poll_s=0.2)
    assert runs[short_id]["state"] == "pass" and runs[live_id]["state"] == "aborted", runs

    # each run's stream, once it has ended, is that run's whole run.rrd: its recording only, named as its page names it
    for run_id, scenario in ((short_id, "service-short"), (live_id, "service-live")):
        status, streamed = _get(f"{url}/live/runs/{run_id}/recording.rrd", tokens.viewer)
        assert status == 200
        assert streamed == _get(f"{url}/api/runs/{run_id}/files/run.rrd", tokens.viewer)[1]
        saved = tmp_path / f"streamed-{run_id}.rrd"
        saved.write_bytes(streamed)
        name = f"run-{run_id} · {scenario}"
        assert rrd_recording(saved) == (f"run-{run_id}", name)
        status, page = _get(f"{url}/runs/{run_id}", tokens.viewer)
        assert f'<code id="recording-name">{name}</code>' in page.decode()
        record = client.request("GET", f"/api/runs/{run_id}/files/record.json")
        assert record["rerun"]["sinks"] == ["file"]        # no gRPC sink: the service follows the file
    assert _get(f"{url}/live/runs/999/recording.rrd", tokens.viewer)[0] == 404


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (Debian: apt-get install chromium)")
def test_run_page_embeds_the_rerun_viewer_on_that_runs_recording_in_chromium(served, tmp_path):
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    from bench.outputs.rerun_view import rrd_recording

    url, port, server, tokens, client = served
    done_id = client.request("POST", "/api/runs", {"scenario": SHORT, "rig": "sim-a"})["id"]
    assert client.wait([done_id], 120, poll_s=0.2)[done_id]["state"] == "pass"
    live_id = client.request("POST", "/api/runs", {"scenario": LIVE, "rig": "sim-a"})["id"]
    _running(client, live_id)
    with chromium_page(timeout_ms=120_000, viewport={"width": 1400, "height": 1200}, cookie=(url, tokens.viewer),
                      webgl=True) as page:
        recordings: list[tuple[str, int]] = []
        page.on("response", lambda r: recordings.append((r.url, r.status)) if "/live/runs/" in r.url else None)

        # the running run: its page's "live view" opens the viewer on its recording, under the name the page shows
        page.goto(f"{url}/runs/{live_id}")
        assert page.locator("#recording-name").inner_text() == f"run-{live_id} · service-live"
        assert page.locator("#live-viewer").get_attribute("src") is None     # closed: nothing loaded yet
        page.click("#open-live")
        viewer = page.frame_locator("#live-viewer")
        viewer.locator("canvas#the_canvas_id.visible").wait_for(state="visible")
        wait_until(lambda: recordings, 60, 0.2, "the viewer to fetch the recording")
        time.sleep(5)                                   # let it draw what has streamed so far
        shot(page, "drivebench-live-running-run")
        assert recordings == [(f"{url}/live/runs/{live_id}/recording.rrd", 200)], recordings
        assert client.request("GET", f"/api/runs/{live_id}")["state"] == "running"     # it was watched live
        assert viewer.locator("#center_text.visible").count() == 0     # no "Rerun has crashed" panel

        # a finished run's page: the viewer opens on click, on that run's recording and no other
        recordings.clear()
        with page.expect_response(lambda r: r.url.endswith(f"/live/runs/{done_id}/recording.rrd")) as got:
            page.goto(f"{url}/runs/{done_id}")
            assert page.locator("#live-viewer").get_attribute("src") is None     # closed: nothing loaded
            page.click("#live-view summary")
        body = got.value.body()
        shown = page.locator("#recording-name").inner_text()
        assert shown == f"run-{done_id} · service-short"
        (tmp_path / "shown.rrd").write_bytes(body)
        assert rrd_recording(tmp_path / "shown.rrd") == (f"run-{done_id}", shown)   # the data under that name
        viewer.locator("canvas#the_canvas_id.visible").wait_for(state="visible")
        if os.environ.get("DRIVEBENCH_SCREENSHOTS"):
            time.sleep(8)                               # let it draw, for the picture
        shot(page, "drivebench-live-finished-run")
        assert [u for u, _ in recordings] == [f"{url}/live/runs/{done_id}/recording.rrd"], recordings
    if client.request("GET", f"/api/runs/{live_id}")["state"] == "running":
        client.request("POST", f"/api/runs/{live_id}/abort")
    client.wait([live_id], 120, poll_s=0.2)


def test_follow_sends_what_is_appended_until_the_writer_has_ended(tmp_path):
    """The stream behind the live view: bytes appended after it started arrive, it waits for the file to appear, and
    it ends (with everything written) only once the run has ended."""
    import asyncio
    import threading

    from bench.service.live import follow

    path = tmp_path / "run.rrd"
    state = {"exists": False, "ended": False}

    def writer():
        time.sleep(0.3)
        path.write_bytes(b"RRF2" + b"a" * 1000)
        state["exists"] = True
        for k in range(5):
            time.sleep(0.2)
            with open(path, "ab") as f:
                f.write(bytes([k]) * 500)
        time.sleep(0.2)
        with open(path, "ab") as f:
            f.write(b"footer")
        state["ended"] = True

    async def read() -> bytes:
        got = b""
        async for chunk in follow(lambda: path if state["exists"] else None, lambda: state["ended"], poll_s=0.05):
            got += chunk
        return got

    thread = threading.Thread(target=writer)
    thread.start()
    got = asyncio.run(read())
    thread.join()
    assert got == path.read_bytes() and got.endswith(b"footer") and len(got) == 4 + 1000 + 5 * 500 + 6
