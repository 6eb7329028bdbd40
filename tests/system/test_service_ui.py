"""The web UI in a real browser: Debian's chromium driven by Playwright (the system browser, nothing downloaded).
Log in with a token, see the rigs, submit a run, watch it finish on its page (websocket), open the record, abort a
run, reserve and release a rig, filter the history, plot a criterion's trend."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")
pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")

from tests.service_fixtures import (CHROMIUM, chromium_page, served_service, shot, LONG, SHORT, wait_until)

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (Debian: apt-get install chromium)")
TIMEOUT_MS = 60_000


@pytest.fixture
def served(tmp_path):
    with served_service(tmp_path, "--lease-ttl", "3") as service:
        yield service.url, service.tokens


@pytest.fixture
def page():
    with chromium_page(timeout_ms=TIMEOUT_MS) as page:
        yield page


def _api(url: str, token: str, method: str, path: str, body: dict | None = None) -> dict:
    import json
    import urllib.request

    request = urllib.request.Request(url + path, method=method, data=json.dumps(body).encode() if body else None,
                                     headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read())


def login(page, url, token):
    page.goto(url + "/")
    assert page.url.endswith("/login")                         # no cookie: the login page
    page.fill("#token", "dbt_wrong")
    page.click("button[type=submit]")
    page.wait_for_url("**/login?failed=1")
    page.locator("#login-failed").wait_for(state="visible")    # is_visible() does not wait for the new page
    assert page.locator("#login-failed").is_visible()
    page.fill("#token", token)
    page.click("button[type=submit]")
    page.wait_for_url(url + "/")


def test_an_operator_runs_a_scenario_and_reads_its_record_in_the_browser(served, page):
    url, tokens = served
    login(page, url, tokens.operator)
    rigs = page.locator("#rigs tr[data-rig]")
    assert rigs.count() == 3
    assert page.locator('#rigs tr[data-rig="sim-a"]').inner_text().count("free") == 1

    page.fill("#submit-form input[name=scenario]", SHORT)
    page.select_option("#submit-form select[name=target]", "rig:sim-a")
    page.click("#submit-form button[type=submit]")
    page.wait_for_url("**/runs/1")
    # the page follows the run over the websocket and reloads with the verdict table when it ends
    page.locator("#run-state", has_text="pass").wait_for()
    page.locator("#criteria").wait_for()
    assert "stable: position error within pi/4" in page.locator("#criteria").inner_text()
    assert page.locator("#verdict").inner_text() == "pass"
    page.wait_for_function("document.querySelector('#summary').naturalWidth > 100")
    downloads = page.locator("#downloads").inner_text()
    for name in ("record.json", "summary.png", "run.rrd", "junit.xml"):
        assert name in downloads
    with page.expect_download() as download:
        page.click("#downloads a:text('record.json')")
    assert b'"verdict": "pass"' in open(download.value.path(), "rb").read()
    # units beside the limits; the telemetry as CSV (and MDF4) for other tools
    header = page.locator("#criteria tr").first.inner_text()
    assert "unit" in header and "\trad\t" in page.locator("#criteria").inner_text()
    with page.expect_download() as download:
        page.click("#exports a:text('CSV')")
    csv_head = open(download.value.path(), "rb").read(200).decode()
    assert csv_head.startswith('"t_s","speed_ref_mech_rad_s"'), csv_head
    shot(page, "run-page")

    page.goto(url + "/runs/1/live")
    assert page.locator("#rrd-link").get_attribute("href") == "/api/runs/1/files/run.rrd"

    # a long run on the real rig, aborted from its page
    page.goto(url + "/")
    page.fill("#submit-form input[name=scenario]", LONG)
    page.select_option("#submit-form select[name=target]", "rig:real-a")
    page.click("#submit-form button[type=submit]")
    page.wait_for_url("**/runs/2")
    page.locator("#run-state", has_text="running").wait_for()
    page.wait_for_function("document.querySelector('#run-progress') "
                           "&& document.querySelector('#run-progress').value > 0.2")
    # a run queued behind it says why it waits, on its page and in the queue
    queued = _api(url, tokens.operator, "POST", "/api/runs", {"scenario": SHORT, "rig": "real-a"})
    page.goto(f"{url}/runs/{queued['id']}")
    assert page.locator("#waiting").inner_text() == "rig real-a is busy with run 2"
    page.goto(url + "/")
    assert "rig real-a is busy with run 2" in page.locator("#queue").inner_text()
    shot(page, "queue-why-waiting")
    # the operator's rig page: the run on it now with drive time, ETA and log tail; the scenario picker
    page.goto(url + "/rigs/real-a")
    assert page.locator("#current-run").inner_text().startswith("run #2 service-long")
    assert "s drive time" in page.locator("#current-progress").inner_text()
    options = page.locator("#rig-scenario option").all_inner_texts()
    assert SHORT in options and "bad.toml" not in options                   # only what validates on the rig
    assert not page.locator("code").first.inner_text().startswith("/")      # no absolute path of the host
    shot(page, "rig-page")
    page.goto(url + "/runs/2")
    page.on("dialog", lambda dialog: dialog.accept())
    page.click("#abort")
    page.locator("#run-state", has_text="aborted").wait_for()
    page.locator("#aborted-by", has_text="olga").wait_for()

    # two runs side by side: what differs, criteria deltas, the signals overlaid
    page.goto(url + "/runs/1")
    page.fill("#exports input[name=b]", "2")
    page.click("#exports button[type=submit]")
    page.wait_for_url("**/compare?a=1&b=2")
    identity = page.locator("#identity").inner_text()
    assert "service-short" in identity and "service-long" in identity and "differs" in identity
    assert page.locator("#compare-criteria tr").count() >= 2
    page.wait_for_function("document.querySelector('#compare-plot').naturalWidth > 100")
    shot(page, "compare")

    # history: filter by state (once the run queued behind the aborted one has passed: forked from the fork
    # server it may pass before this page is read, so it is waited for, and counted)
    wait_until(lambda: _api(url, tokens.operator, "GET", f"/api/runs/{queued['id']}")["state"] == "pass", 60, 0.1,
               "the queued run to pass")
    page.goto(url + "/history?state=aborted")
    rows = page.locator("#history tr[data-run]")
    assert rows.count() == 1 and "service-long" in rows.first.inner_text()
    page.select_option("#filters select[name=state]", "pass")
    page.click("#filters button[type=submit]")
    page.wait_for_url("**state=pass**")
    assert page.locator("#history tr[data-run]").count() == 2          # run 1 and the run queued behind run 2

    # trend of a criterion over runs
    page.goto(url + "/trend?scenario=service-short&criterion=stable%3A+position+error+within+pi%2F4")
    page.wait_for_function("document.querySelector('#trend-plot').naturalWidth > 100")
    assert page.locator("#trend-points tr").count() == 3          # header + run 1 + the run queued behind run 2


def test_reservations_are_visible_and_an_admin_breaks_them(served, page):
    url, tokens = served
    login(page, url, tokens.operator)
    page.goto(url + "/rigs/real-a")
    page.fill("#reserve-form input[name=reason]", "replacing the encoder")
    page.click("#reserve-form button[type=submit]")
    page.locator("#rig-state", has_text="reserved").wait_for()
    page.goto(url + "/")
    row = page.locator('#rigs tr[data-rig="real-a"]')
    assert "olga" in row.inner_text() and "replacing the encoder" in row.inner_text()

    page.context.clear_cookies()
    login(page, url, tokens.operator2)
    page.goto(url + "/rigs/real-a")
    assert page.locator("#leases button").count() == 0          # not oscar's to release
    page.context.clear_cookies()
    login(page, url, tokens.admin)
    page.goto(url + "/rigs/real-a")
    page.click("#leases button:text('break')")
    page.locator("#rig-state", has_text="free").wait_for()

    page.context.clear_cookies()
    login(page, url, tokens.viewer)
    assert page.locator("#submit-form").count() == 0            # a viewer sees no submit form
    started = time.monotonic()
    page.goto(url + "/logout")
    page.goto(url + "/history")
    assert page.url.endswith("/login") and time.monotonic() - started < 30
