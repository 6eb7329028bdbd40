"""The service's rig page shows the newest kept conformance report of the rig's bench config (a read of the kept
file: conformance/<drive>/latest.json beside the scenario root), and nothing for a rig without one."""

from __future__ import annotations

import dataclasses

from bench.faces.conformance_cli import run_conformance
from bench.outputs.conformance_report import latest_for_bench
from tests.service_fixtures import REPO, Tokens, client_for, make_settings
import pytest

pytestmark = pytest.mark.slow

PMSM = REPO / "config" / "benches" / "sim-pmsm.toml"


def test_the_rig_page_shows_the_latest_conformance_report_of_its_bench(tmp_path):
    (tmp_path / "scenarios").mkdir()
    doc, kept = run_conformance(str(PMSM), tmp_path / "conformance", ("sdo_aborts",))
    summary = latest_for_bench(tmp_path / "conformance", PMSM)
    assert summary["verdict"] == doc["verdict"] == "pass" and summary["report"] == str(kept.parent / "latest.md")
    assert latest_for_bench(tmp_path / "conformance", REPO / "config" / "benches" / "sim-spim.toml") is None
    settings = dataclasses.replace(make_settings(tmp_path, run_queue=False), scenario_root=tmp_path / "scenarios")
    with client_for(settings) as client:
        viewer = Tokens.header(client.tokens.viewer)
        page = client.get("/rigs/real-a", headers=viewer).text          # its bench: sim-pmsm.toml
        assert 'id="conformance"' in page and "PASS" in page and "latest.md" in page
        assert 'id="conformance"' not in client.get("/rigs/spim-a", headers=viewer).text     # sim-spim.toml: none
