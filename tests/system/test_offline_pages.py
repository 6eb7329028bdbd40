"""Nothing leaves the building: the API page (/docs) renders the app's OpenAPI 3.1 document with the Swagger UI the
package ships, and the run page's embedded Rerun viewer makes no request outside 127.0.0.1 (no usage analytics, no
"latest release" query). Chromium through Playwright, every request to another host refused and recorded."""

from __future__ import annotations

import time
import urllib.parse

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import CHROMIUM, SHORT, chromium_page, served_service, shot, wait_until

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (Debian: apt-get install chromium)")


def _refuse_outside(page) -> list[str]:
    """Every request of the page's context (frames, workers) to a host other than 127.0.0.1 is aborted and kept."""
    outside: list[str] = []

    def route(r):
        if urllib.parse.urlsplit(r.request.url).hostname in ("127.0.0.1", None):
            r.continue_()
        else:
            outside.append(r.request.url)
            r.abort()

    page.context.route("**/*", route)
    page.context.on("request", lambda req: outside.append(req.url) if urllib.parse.urlsplit(req.url).scheme
                    in ("http", "https", "ws", "wss") and urllib.parse.urlsplit(req.url).hostname != "127.0.0.1"
                    and req.url not in outside else None)
    return outside


@pytest.fixture
def served(tmp_path):
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    with served_service(tmp_path, "--lease-ttl", "3") as service:
        yield service


def test_docs_renders_the_apis_operations_from_the_package_alone(served):
    with chromium_page(timeout_ms=60_000, viewport={"width": 1400, "height": 1000}) as page:
        outside = _refuse_outside(page)
        page.goto(f"{served.url}/docs")
        page.locator(".opblock").first.wait_for(state="visible")
        shown = page.locator(".opblock-summary-path").all_inner_texts()
        shot(page, "drivebench-docs")
        assert "Unable to render" not in page.content()
        paths = {p.replace("\u200b", "").strip() for p in shown}
        assert {"/api/runs", "/api/runs/{run_id}/abort", "/api/health"} <= paths, sorted(paths)
        assert page.locator(".info .title").inner_text().startswith("drivebench bench service")
    assert outside == [], outside


def test_the_run_pages_rerun_viewer_makes_no_request_outside_127_0_0_1(served):
    from bench.service.client import Client

    client = Client(served.url, served.tokens.operator)
    run_id = client.request("POST", "/api/runs", {"scenario": SHORT, "rig": "sim-a"})["id"]
    assert client.wait([run_id], 120, poll_s=0.2)[run_id]["state"] == "pass"
    with chromium_page(timeout_ms=120_000, viewport={"width": 1400, "height": 1200},
                       cookie=(served.url, served.tokens.viewer), webgl=True) as page:
        outside = _refuse_outside(page)
        fetched: list[str] = []
        page.on("response", lambda r: fetched.append(r.url) if "/live/runs/" in r.url and r.ok else None)
        page.goto(f"{served.url}/runs/{run_id}")
        page.click("#live-view summary")
        viewer = page.frame_locator("#live-viewer")
        viewer.locator("canvas#the_canvas_id.visible").wait_for(state="visible")
        wait_until(lambda: fetched, 60, 0.2, "the viewer to fetch the recording")
        time.sleep(8)             # the viewer's start-up requests (analytics, update check) go out within seconds
        assert viewer.locator("#center_text.visible").count() == 0      # it runs: no "Rerun has crashed" panel
    assert outside == [], outside
