"""The conformance suite on the simulated drives (drivebench's own and the three vendor-EDS drives): it passes on each,
leaves each disabled with its parameters and mapping restored; and each simulator quirk fails or marks exactly the
test that concerns it."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.faces.conformance_cli import run_conformance

REPO = Path(__file__).resolve().parents[2]
BENCHES = REPO / "config" / "benches"
E35 = BENCHES / "sim-generic-e35.toml"
ALWAYS_NOT_RUN = {"bus_off"}       # the virtual CAN interface cannot go bus-off


def _outcomes(doc: dict) -> dict[str, str]:
    return {t["name"]: t["outcome"] for t in doc["tests"]}


def _assert_safe(doc: dict) -> None:
    assert doc["not_restored"] == []
    assert _outcomes(doc)["restored"] == "pass"
    for test in doc["tests"]:
        if test["name"] != "restored":
            assert test["safe_end"].startswith(("SWITCH ON DISABLED", "FAULT")), test
    assert doc["safe_end"].startswith("SWITCH ON DISABLED")


@pytest.mark.parametrize("bench, expected_notes", [
    ("sim-pmsm", {}),
    ("sim-generic-e35", {}),
    ("sim-generic-cia402-slave", {"pdo_remap": "note"}),       # fixed_pdo_mapping = true in the bench config
    ("sim-generic-technosoft", {"pdo_remap": "note"}),
])
def test_the_suite_passes_on_the_simulated_drives_and_leaves_them_as_found(bench, expected_notes, tmp_path):
    doc, kept = run_conformance(str(BENCHES / f"{bench}.toml"), tmp_path)
    outcomes = _outcomes(doc)
    assert doc["verdict"] == "pass", [t["findings"] for t in doc["tests"] if t["outcome"] == "fail"]
    odd = {k: v for k, v in outcomes.items() if v != "pass" and k not in ALWAYS_NOT_RUN}
    assert odd == expected_notes
    _assert_safe(doc)
    assert kept.exists() and kept.with_suffix(".md").exists() and (kept.parent / "latest.xml").exists()
    qs = next(t for t in doc["tests"] if t["name"] == "quick_stop_options")["measured"]
    for code in (1, 2, 3, 5, 6, 7):                 # measured on the reference sensor, from speed
        stop = qs[f"0x605A={code}"]
        assert stop["from_mech_rad_s"] > 45 and stop["standstill"] and 0 < stop["stop_time_s"] < 5
        assert stop["stop_distance_rad"] > 0.1


# quirk (a [simulator] option of the e35 drive) -> the one test it concerns and what it says; everything else passes
QUIRKS = {
    "comm_loss_reaction = false": ("comm_loss_reaction", "fail"),
    "found_running_mech_rad_s = 52.0": ("found_state", "note"),
    "tpdo_stops_after_s = 0.5\ntpdo_stops = 1": ("process_data", "fail"),
    "csv_only = true": ("modes", "note"),
    "event_tpdos_only = true": ("tpdo_sync_transmission", "note"),
    "boot_delay_s = 1.0": ("boot", "note"),
    "fixed_pdo_mapping = true": ("pdo_remap", "note"),
}
# a test that cannot run without what the quirk removes says so, naming it (not a finding)
DEPENDS = {"comm_loss_reaction = false": {"fault_reset_edge": "comm_loss_reaction"}}


@pytest.mark.slow
@pytest.mark.parametrize("quirk", list(QUIRKS), ids=[q.split()[0] for q in QUIRKS])
def test_each_quirk_fails_or_marks_exactly_its_test(quirk, tmp_path):
    text = E35.read_text()
    text = (text.replace("fixed_pdo_mapping = false", quirk) if quirk.startswith("fixed")
            else text + "\n" + quirk + "\n")
    bench = tmp_path / "quirky.toml"
    bench.write_text(text)
    doc, _ = run_conformance(str(bench), tmp_path / "out")
    test, outcome = QUIRKS[quirk]
    odd = {k: v for k, v in _outcomes(doc).items() if v != "pass" and k not in ALWAYS_NOT_RUN}
    depends = DEPENDS.get(quirk, {})
    assert odd == {test: outcome, **{name: "not_run" for name in depends}}
    for name, on in depends.items():
        assert on in next(t for t in doc["tests"] if t["name"] == name)["detail"]
    finding = next(t for t in doc["tests"] if t["name"] == test)["findings"]
    assert finding and all(f.startswith("CiA") for f in finding)      # named with its clause
    _assert_safe(doc)
