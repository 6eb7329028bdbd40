"""`drivebench probe`'s checklist: a gear ratio already stated in the bench config is not asked for again, and a
drive whose TPDOs are all disabled is not "ok, 0 valid TPDO(s)"."""

from __future__ import annotations

from types import SimpleNamespace

from bench.faces.checklist import checklist


def _drive(tpdos: list[dict]) -> dict:
    return {"device_type": {"cia402": True, "raw": "0x00020192", "profile": 402},
            "supported_modes": ["profile_velocity"], "profile": {}, "tpdos": tpdos,
            "units": {"velocity_0x60A9": "not on this drive", "gear_0x6091": "not on this drive"},
            "heartbeat": {"consumer_0x1016": [1], "abort_connection_0x6007": 3},
            "node_id": 1, "bench_node_id": {"id": 126}, "state": "SWITCH ON DISABLED", "error_code_0x603F": 0}


def test_a_stated_gear_ratio_is_ok_and_no_valid_tpdo_is_not(tmp_path):
    stated = SimpleNamespace(drive={"gear_ratio": (1.0, 1.0)}, load={})
    items = {i.item: i for i in checklist(_drive([{"number": 1, "valid": False, "transmission_type": 1}]), stated)}
    assert items["gear"].status == "ok" and items["gear"].config_line == ""
    assert "states gear_ratio = [1, 1]" in items["gear"].detail
    assert items["PDO transmission"].status != "ok" and "none of the 1 TPDOs is valid" in items["PDO transmission"].detail
    silent = SimpleNamespace(drive={}, load={})
    items = {i.item: i for i in checklist(_drive([{"number": 1, "valid": True, "transmission_type": 1}]), silent)}
    assert items["gear"].status == "unknown" and items["gear"].config_line.startswith("gear_ratio = [1, 1]")
    assert items["PDO transmission"].status == "ok"
