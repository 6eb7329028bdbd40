"""The rig page's drive identity and last probe as a checklist: an operator probes a rig from the page (the service
runs `drivebench probe --json` under a lease of the rig and keeps the result in its database), the page shows the
identity and the checklist, in real Chromium (a screenshot where DRIVEBENCH_SCREENSHOTS names a folder); a held
real rig is not probed under its holder; a viewer cannot probe."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import CHROMIUM, REPO, chromium_page, served_service, shot  # noqa: E402



@pytest.fixture
def served(tmp_path):
    from bench.service.client import Client

    with served_service(tmp_path) as service:
        yield service.url, service.tokens, Client(service.url, service.tokens.operator)


def test_a_held_real_rig_is_not_probed_and_a_viewer_cannot_probe(served):
    from bench.service.client import Client, ClientError

    url, tokens, operator = served
    with pytest.raises(ClientError) as viewer:
        Client(url, tokens.viewer).request("POST", "/api/rigs/sim-a/probe")
    assert viewer.value.status == 403
    Client(url, tokens.operator2).request("POST", "/api/rigs/real-a/lease", {"ttl_s": 600, "reason": "wiring"})
    with pytest.raises(ClientError) as held:
        operator.request("POST", "/api/rigs/real-a/probe")
    assert held.value.status == 409 and "wiring" in str(held.value), held.value.lines
    with pytest.raises(ClientError) as never:
        operator.request("GET", "/api/rigs/real-a/probe")
    assert never.value.status == 404                       # the refused probe left no result behind


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (Debian: apt-get install chromium)")
def test_rig_page_shows_the_drive_identity_and_the_last_probe_as_a_checklist_in_chromium(served):
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed")

    url, tokens, operator = served
    with chromium_page(timeout_ms=120_000, viewport={"width": 1300, "height": 1000},
                      cookie=(url, tokens.operator)) as page:
        page.goto(f"{url}/rigs/sim-a")
        assert "Not probed from this service yet" in page.locator("#probe-when").inner_text()
        assert page.locator("#probe-checklist").count() == 0
        page.click("#probe-now")
        page.wait_for_url(f"{url}/rigs/sim-a#drive")
        rows = page.locator("#probe-checklist tr")
        assert rows.count() >= 5
        identity = page.locator("#drive-identity").inner_text()
        assert "drivebench simulated PMSM drive" in identity and "0x00DB0001" in identity
        assert "by olga" in page.locator("#probe-when").inner_text()
        page.locator("#drive").scroll_into_view_if_needed()
        shot(page, "drivebench-rig-probe")
        shown = [(rows.nth(i).locator("td").nth(1).inner_text(), rows.nth(i).locator("td").nth(0).inner_text())
                 for i in range(1, rows.count())]

    # what the page shows is what `drivebench probe --json` says about this rig's drive, item by item
    cli = subprocess.run([sys.executable, "-m", "bench", "probe", "--bench", str(REPO / "config/benches/sim-pmsm.toml"),
                          "--json"], cwd=REPO, capture_output=True, timeout=120, check=True)
    expected = json.loads(cli.stdout)["checklist"]
    marks = {"ok": "✓ ok", "fix": "✗ fix", "unknown": "? unknown"}
    assert shown == [(c["item"], marks[c["status"]]) for c in expected]
    kept = operator.request("GET", "/api/rigs/sim-a/probe")      # kept in the database
    assert kept["ok"] and kept["by"] == "olga" and kept["checklist"] == expected
    assert ["device name", "drivebench simulated PMSM drive"] in kept["identity"]
    assert not [l for l in operator.request("GET", "/api/rigs/sim-a")["leases"] if l["reason"] == "probe"]
