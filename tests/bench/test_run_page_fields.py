"""The run page of a running run has no blank field: its progress as a number beside the bar, the seed, drive and
revision said to come with the record (not blank), and "duration" split into the scenario's drive time and the run's
wall time, which the page names."""

from __future__ import annotations

import re

from tests.service_fixtures import LONG, client_for, make_settings, wait_until
import pytest

pytestmark = pytest.mark.slow


def _row(page: str, cell_id: str) -> str:
    match = re.search(rf'<td id="{cell_id}">(.*?)</td>', page, re.S)
    assert match, cell_id
    return re.sub(r"<[^>]+>", "", match.group(1)).strip()


def test_a_running_runs_page_says_what_each_field_will_be(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        op = {"Authorization": f"Bearer {api.tokens.operator}"}
        run_id = api.post("/api/runs", json={"scenario": LONG, "rig": "sim-a"}, headers=op).json()["id"]
        wait_until(lambda: (api.get(f"/api/runs/{run_id}", headers=op).json()["progress_s"] or 0) > 0, 90, 0.1,
                   "progress")
        page = api.get(f"/runs/{run_id}", headers=op).text
        text = re.search(r'data-run-progress-text="\d+">(.*?)</span>', page).group(1)
        assert re.fullmatch(r"[\d.]+ s of 60 s drive time \(\d+ %\)", text), text
        for cell in ("run-seed", "run-drive", "run-revision"):
            assert "in the record when the run ends" in _row(page, cell), (cell, _row(page, cell))
        assert _row(page, "run-drive-time").startswith("60 s (the scenario's, on the drive's clock)")
        assert _row(page, "run-wall-time") == "when the run ends"
        assert ">duration<" not in page
        api.post(f"/api/runs/{run_id}/abort", headers=op)
        wait_until(lambda: api.get(f"/api/runs/{run_id}", headers=op).json()["state"] == "aborted", 60, 0.1, "aborted")
        page = api.get(f"/runs/{run_id}", headers=op).text
        assert "(start to end of the run, setup and safe stop included)" in _row(page, "run-wall-time")
        assert _row(page, "run-seed") == "1"            # the record's seed (the scenario's own)
