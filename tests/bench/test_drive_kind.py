"""A scenario for one drive kind (PMSM, SPIM) is refused on a bench of the other, by one check
(bench.inputs.drive_kind) that `validate --bench`, `run --bench`, the API and the rig page's picker all pass through."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.service_fixtures import SHORT, SCENARIOS, client_for, make_settings
import pytest

REPO = Path(__file__).resolve().parents[2]
CRANE = REPO / "scenarios/examples/pmsm-crane.toml"
SPIM_BENCH = REPO / "config/benches/sim-spim.toml"


@pytest.mark.slow
def test_validate_with_a_bench_of_another_drive_kind_is_one_line_and_exit_2():
    out = subprocess.run([sys.executable, "-m", "bench", "validate", str(CRANE), "--bench", str(SPIM_BENCH)],
                         capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 2, out
    lines = [line for line in out.stderr.splitlines() + out.stdout.splitlines() if "wrong motor" in line]
    assert len(lines) == 1 and "Traceback" not in out.stderr, out
    assert "bench: the scenario is for a PMSM drive" in lines[0] and "sim-spim.toml's drive is SPIM" in lines[0]
    same = subprocess.run([sys.executable, "-m", "bench", "validate", str(CRANE), "--bench",
                           str(REPO / "config/benches/sim-pmsm-instruments.toml")],
                          capture_output=True, text=True, cwd=REPO, timeout=120)
    assert same.returncode == 0, same          # another bench of the same kind is fine


def test_the_api_and_the_rig_pages_picker_refuse_a_scenario_for_another_drive_kind(tmp_path):
    from bench.service.rig_page import rig_scenarios

    with client_for(make_settings(tmp_path)) as api:
        op = {"Authorization": f"Bearer {api.tokens.operator}"}
        answer = api.post("/api/runs", json={"scenario": SHORT, "rig": "spim-a"}, headers=op)
        assert answer.status_code == 422, answer.text
        detail = answer.json()["detail"]
        assert len(detail) == 1 and "is for a PMSM drive" in detail[0] and "SPIM" in detail[0], detail
        assert api.get("/api/runs", headers=op).json() == []       # nothing queued
        by_tag = api.post("/api/runs", json={"scenario": SHORT, "tag": "spim"}, headers=op)
        assert by_tag.status_code == 422 and "is for a PMSM drive" in by_tag.json()["detail"][0], by_tag.text
        page = api.get("/rigs/spim-a", headers=op)
        assert page.status_code == 200 and SHORT not in page.text
    assert SHORT not in rig_scenarios(SCENARIOS, str(SPIM_BENCH))
    assert SHORT in rig_scenarios(SCENARIOS, str(REPO / "config/benches/sim-pmsm.toml"))


def test_a_scenario_for_either_motor_says_so_with_drive_kinds(tmp_path):
    from bench.inputs.scenario import load_scenario
    from drivers.contract.errors import InputError

    generic = REPO / "scenarios/rig/accept-load-step.toml"       # drive_kinds = ["pmsm", "spim"]
    assert load_scenario(generic, REPO / "config/benches/sim-spim-instruments.toml").name == "accept-load-step"
    only_spim = tmp_path / "only-spim.toml"
    only_spim.write_text(generic.read_text().replace('drive_kinds = ["pmsm", "spim"]', 'drive_kinds = ["spim"]')
                         .replace('bench = "config/', f'bench = "{REPO}/config/'))
    try:
        load_scenario(only_spim, REPO / "config/benches/sim-pmsm-instruments.toml")
    except InputError as exc:
        assert exc.problems == [f"{only_spim}: bench: the scenario is for a SPIM drive (drive_kinds = ['spim']) and "
                                f"sim-pmsm-instruments.toml's drive is PMSM: refused, the wrong test on the wrong motor"]
    else:
        raise AssertionError("a SPIM-only scenario was accepted on a PMSM bench")
    bad = tmp_path / "bad.toml"
    bad.write_text(only_spim.read_text().replace('drive_kinds = ["spim"]', 'drive_kinds = ["bldc"]'))
    try:
        load_scenario(bad)
    except InputError as exc:
        assert any("drive_kinds: must be a non-empty array of 'pmsm', 'spim'" in line for line in exc.problems)
    else:
        raise AssertionError("drive_kinds = ['bldc'] was accepted")
