"""The conformance suite's CANopen port and report: the PDO remap on the wire in CiA 301 order, the report formats,
the command's bad input, and drives that break a rule (mutants of the simulated drive) caught by the test that
concerns the rule."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree as ET

import can
import pytest

from bench.faces.conformance_cli import run_conformance
from bench.inputs.benchconfig import load_bench_config
from bench.outputs.conformance_report import compare, junit, markdown
from bench.run.links import started_services
from drivers.canopen.conformance_port import CanopenConformancePort
from drivers.contract import objects as o
from drivers.contract.cia402 import FAULT_RESET_BIT, State

REPO = Path(__file__).resolve().parents[2]
E35 = REPO / "config" / "benches" / "sim-generic-e35.toml"


def _downloads(frames: list[can.Message], node_id: int = 1) -> list[tuple[int, int, int]]:
    """(index, subindex, value) of every expedited SDO download the bench sent."""
    out = []
    for f in frames:
        if f.arbitration_id == o.SDO_RX + node_id and f.data[0] & 0xE0 == 0x20 and f.data[0] & 0x02:
            n = 4 - ((f.data[0] >> 2) & 0x03)
            index, sub = struct.unpack_from("<HB", f.data, 1)
            out.append((index, sub, int.from_bytes(f.data[4:4 + n], "little")))
    return out


def test_the_port_remaps_a_tpdo_in_cia301_order_on_the_wire_and_restores_it():
    cfg = load_bench_config(E35)
    with started_services(cfg, 0) as live:
        port = CanopenConformancePort(live.drive, REPO, "lockstep")
        port.open()
        listener = can.Bus(interface="virtual", channel=live.drive["channel"], receive_own_messages=False)
        try:
            port.start_process_data()
            original = port.pdo_mapping(1)
            while listener.recv(0) is not None:
                pass
            wanted = [(o.VELOCITY_ACTUAL, 0, 32), (o.STATUSWORD, 0, 16)]
            port.remap(1, wanted)
            frames = []
            while (msg := listener.recv(0)) is not None:
                frames.append(msg)
            writes = _downloads(frames)
            cob_writes = [w for w in writes if w[:2] == (o.TPDO_COMM, 1)]
            assert cob_writes[0][2] & o.COB_ID_INVALID and not cob_writes[-1][2] & o.COB_ID_INVALID
            mapping = [w for w in writes if w[0] == o.TPDO_MAP]
            assert mapping == [(o.TPDO_MAP, 0, 0), (o.TPDO_MAP, 1, o.mapping_entry(*wanted[0])),
                               (o.TPDO_MAP, 2, o.mapping_entry(*wanted[1])), (o.TPDO_MAP, 0, 2)]
            assert writes.index(cob_writes[0]) < writes.index(mapping[0])
            assert writes.index(mapping[-1]) < writes.index(cob_writes[-1])
            assert port.pdo_mapping(1) == wanted
            answer = port.cycle()
            assert len(answer.frames[1]) == 6
            assert port.restore_process_data() == []
            assert port.pdo_mapping(1) == original
        finally:
            listener.shutdown()
            port.close()


def _doc(tmp_path: Path, only: tuple[str, ...]) -> dict:
    doc, _ = run_conformance(str(E35), tmp_path, only)
    return doc


def test_report_formats_and_comparison(tmp_path):
    doc = _doc(tmp_path, ("sdo_aborts", "halt"))
    suite = ET.fromstring(junit(doc))
    assert suite.get("failures") == "0" and {c.get("name") for c in suite} >= {"sdo_aborts", "halt", "restored"}
    text = markdown(doc)
    assert "CiA 301 7.2.4.3.17 SDO abort codes" in text and "| halt" not in text.split("## Tests")[0]
    worse = json.loads(json.dumps(doc))
    worse["tests"][1]["outcome"] = "fail"
    rows = {r["test"]: r for r in compare(doc, worse)["tests"]}
    assert not rows[doc["tests"][1]["name"]]["same"] and rows["restored"]["same"]
    assert any(r["times_ms"] for r in rows.values())


def test_a_drive_that_resets_a_fault_on_the_level_of_bit_7_fails_fault_reset_edge(tmp_path, monkeypatch):
    import sim_backend.cia402_device as device

    real = device.next_state

    def level_reset(state, word, previous, fault_active):
        if state is State.FAULT and word & FAULT_RESET_BIT:
            return State.SWITCH_ON_DISABLED
        return real(state, word, previous, fault_active)
    monkeypatch.setattr(device, "next_state", level_reset)
    doc = _doc(tmp_path, ("fault_reset_edge",))
    test = next(t for t in doc["tests"] if t["name"] == "fault_reset_edge")
    assert test["outcome"] == "fail" and "no rising edge" in test["findings"][0]
    assert doc["safe_end"].startswith("SWITCH ON DISABLED")


def test_a_drive_that_ignores_halt_fails_halt_and_is_still_stopped(tmp_path, monkeypatch):
    import sim_backend.device as device

    monkeypatch.setattr(device, "HALT_BIT", 0)
    doc = _doc(tmp_path, ("halt",))
    test = next(t for t in doc["tests"] if t["name"] == "halt")
    assert test["outcome"] == "fail" and "halt" in test["findings"][0]
    assert test["safe_end"].startswith("SWITCH ON DISABLED")
    assert abs(float(test["safe_end"].split("shaft ")[1].split()[0])) < 0.5      # stopped by the safe end


@pytest.mark.parametrize("args, text", [
    (["--bench", "no/such.toml"], "no/such.toml"),
    (["--bench", str(E35), "--only", "nonsense"], "--only: unknown test 'nonsense'"),
    (["--bench", str(E35), "--compare", "no/such.json"], "no/such.json: not a conformance report"),
    (["--bench", str(E35), "--compare", str(E35)], "not a conformance report"),
    (["--bench", str(REPO / "README.md")], "README.md"),
])
def test_bad_input_is_one_line_and_exit_2(args, text):
    proc = subprocess.run([sys.executable, "-m", "bench", "conformance", *args], capture_output=True, text=True,
                          cwd=REPO, timeout=120)
    assert proc.returncode == 2 and text in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_a_drive_that_takes_a_reserved_quick_stop_code_fails_sdo_aborts_and_gets_its_own_back(tmp_path, monkeypatch):
    import sim_backend.canopen.drive_objects as objects

    monkeypatch.setattr(objects, "QUICK_STOP_OPTIONS", range(-32768, 32768))
    doc = _doc(tmp_path, ("sdo_aborts",))
    outcomes = {t["name"]: t for t in doc["tests"]}
    assert outcomes["sdo_aborts"]["outcome"] == "fail"
    finding = outcomes["sdo_aborts"]["findings"][0]
    assert "0x605A = 0x7FFF" in finding and "accepted" in finding
    assert outcomes["restored"]["outcome"] == "pass"          # 0x605A written back and read back


def test_a_drive_that_ignores_0x6007_on_nmt_reset_communication_fails_that_test(tmp_path, monkeypatch):
    from sim_backend.device import SimulatedDevice

    monkeypatch.setattr(SimulatedDevice, "connection_aborted", lambda self, what: None)
    doc = _doc(tmp_path, ("nmt_reset_communication", "nmt_reset_node"))
    outcomes = {t["name"]: t["outcome"] for t in doc["tests"]}
    assert outcomes["nmt_reset_communication"] == "fail" and outcomes["nmt_reset_node"] == "pass"
    assert doc["safe_end"].startswith("SWITCH ON DISABLED") and outcomes["restored"] == "pass"


def test_a_fault_a_test_leaves_ends_the_suite_when_the_bench_never_resets_faults(tmp_path, monkeypatch):
    import sim_backend.cia402_device as device

    real = device.next_state

    def stuck(state, word, previous, fault_active):      # a fault nothing resets
        return state if state is State.FAULT else real(state, word, previous, fault_active)
    monkeypatch.setattr(device, "next_state", stuck)
    doc = _doc(tmp_path, ("fault_reset_edge", "halt", "sdo_aborts"))       # sim-generic-e35: fault_reset = "never"
    outcomes = {t["name"]: t for t in doc["tests"]}
    assert outcomes["fault_reset_edge"]["outcome"] == "fail"
    assert outcomes["fault_reset_edge"]["safe_end"].startswith("FAULT")
    assert any("fault_reset = \"never\"" in f for f in outcomes["fault_reset_edge"]["findings"])
    for name in ("halt", "sdo_aborts"):
        assert outcomes[name]["outcome"] == "not_run" and "FAULT after fault_reset_edge" in outcomes[name]["detail"]
    assert doc["safe_end"].startswith("FAULT") and "may still turn" not in doc["safe_end"]
