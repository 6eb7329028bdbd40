"""One typed, frozen config per section: every key the docs and the shipped configs describe is accepted by the
section that owns it, an unknown key is refused with the allowed ones, the links get the typed values (the drifted
`retries` now reaches them from a bench config), and a simulated rig is described in one place whatever starts it."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench.inputs.benchconfig import BenchSection, load_bench_config, ServicesSection
from bench.run.links import make_links
from drivers.contract.errors import InputError
from drivers.contract.simulator import SimulatorConfig, SimulatorServeConfig
from drivers.reference import ReferenceConfig
from drivers.transports import DRIVE_TRANSPORTS, LOAD_TRANSPORTS

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
SECTIONS = {
    "bench": [BenchSection], "services": [ServicesSection], "reference": [ReferenceConfig],
    "simulator": [SimulatorConfig], "simulator.serve": [SimulatorServeConfig],
    "drive": [t.config for t in DRIVE_TRANSPORTS.values()], "load": [t.config for t in LOAD_TRANSPORTS.values()],
}

# Keys the docs list in prose rather than as `[section] key`: (section, key, the doc that lists it).
LISTED = [
    *[("drive", k, "canopen.md") for k in (
        "interface", "channel", "bitrate", "can", "profile", "velocity_unit", "velocity_side",
        "encoder_increments_per_rev", "gear_ratio", "rated_current_a", "rated_torque_nm", "units_confirmed", "signals",
        "pdo", "comm_loss", "consumer_time_ms", "abort_option", "bench_node_id", "standstill_mech_rad_s",
        "stop_timeout_s", "boot_timeout_s", "velocity_mode")],
    *[("simulator", k, "canopen.md") for k in ("drive", "gear_ratio", "velocity_side", "fixed_pdo_mapping", "csv_only",
                                               "event_tpdos_only", "boot_delay_s")],
    ("drive", "timeout_s", "serial-protocol.md"), ("drive", "retries", "serial-protocol.md"),
    ("load", "timeout_s", "safety.md"), ("load", "retries", "safety.md"),
]


def _documented() -> set[tuple[str, str, str]]:
    """(section, key, doc) for every `[section] key` written in docs/*.md and README.md, every key of the simulated
    quirks table in docs/rig.md, and the prose lists above (each checked to be in its doc)."""
    found: set[tuple[str, str, str]] = set()
    for path in [*DOCS.glob("*.md"), REPO / "README.md"]:
        text = path.read_text()
        for section, name in re.findall(r"\[(bench|drive|load|reference|simulator|services)\] `?([a-z_]+)\b", text):
            found.add((section, name, path.name))
    quirks = (DOCS / "rig.md").read_text().split("## Simulated quirks", 1)[1].split("\n## ", 1)[0]
    for name in re.findall(r"^\| `([a-z_]+) =", quirks, re.M):
        found.add(("simulator", name, "rig.md"))
    for section, name, doc in LISTED:
        assert re.search(rf"`[^`\n]*\b{name}\b[^`\n]*`", (DOCS / doc).read_text()), \
            f"{doc} no longer lists `{name}`: update LISTED"
        found.add((section, name, doc))
    return found


def test_the_docs_scan_finds_keys():
    sections = {s for s, _, _ in _documented()}
    assert {"bench", "drive", "load", "reference", "simulator", "services"} <= sections
    assert len(_documented()) > 40


@pytest.mark.parametrize("section, name, doc", sorted(_documented()))
def test_every_documented_key_is_accepted(section, name, doc):
    allowed = {k for cls in SECTIONS[section] for k in cls.keys_allowed()}
    assert name in allowed, f"docs/{doc} describes [{section}] {name}, which the config refuses"


def _config_files() -> list[Path]:
    return sorted((REPO / "config" / "benches").glob("*.toml"))


@pytest.mark.parametrize("path", _config_files(), ids=lambda p: p.name)
def test_every_shipped_bench_config_loads_into_typed_sections(path):
    cfg = load_bench_config(path)
    transport = DRIVE_TRANSPORTS[cfg.drive["transport"]]
    assert type(cfg.drive) is transport.config
    if cfg.load:
        assert type(cfg.load) is LOAD_TRANSPORTS[cfg.load["transport"]].config
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.drive.sync_period_s = 1.0           # type: ignore[misc]


def _bench(tmp_path: Path, drive: str, load: str = "", extra: str = "") -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(f'[bench]\nname = "rig"\ntiming = "realtime"\n\n[drive]\n{drive}\n{load}{extra}')
    return path


SERIAL = 'transport = "serial"\nport = "/dev/ttyUSB0"\n'
MODBUS = ('[load]\ntransport = "modbus-tcp"\nmap = "config/load-machines/drivebench-sim.toml"\nhost = "127.0.0.1"\n'
          'port = 502\n')


def test_an_unknown_key_is_one_line_with_the_allowed_keys(tmp_path):
    path = _bench(tmp_path, SERIAL + "retriez = 4\n")
    with pytest.raises(InputError) as err:
        load_bench_config(path)
    (line,) = err.value.problems
    allowed = ", ".join(sorted(DRIVE_TRANSPORTS["serial"].config.keys_allowed()))
    assert line == f"{path}: drive.retriez: unknown key; did you mean 'retries'? (allowed: {allowed})"


def test_an_unknown_key_in_simulator_is_refused_at_validate_time(tmp_path):
    path = _bench(tmp_path, SERIAL, extra='\n[simulator]\nmotor = "toy"\ncsv_onyl = true\n')
    with pytest.raises(InputError, match=r"simulator\.csv_onyl: unknown key; did you mean 'csv_only'\? \(allowed: .*csv_only"):
        load_bench_config(path)


def test_retries_reach_both_links_from_the_bench_config(tmp_path):
    """The links read `retries` and the docs describe it; the bench config used to refuse it as unknown."""
    path = _bench(tmp_path, SERIAL + "retries = 5\n", MODBUS + "retries = 2\n")
    cfg = load_bench_config(path)
    drive, load = make_links(cfg, REPO)
    assert (drive.retries, load.retries) == (5, 2)


def test_defaults_come_from_the_section_class(tmp_path):
    cfg = load_bench_config(_bench(tmp_path, SERIAL, MODBUS))
    drive, load = make_links(cfg, REPO)
    serial, modbus = DRIVE_TRANSPORTS["serial"].config(), LOAD_TRANSPORTS["modbus-tcp"].config()
    assert (drive.baudrate, drive.timeout_s, drive.retries, drive.sync_period_s) == \
        (serial.baudrate, serial.timeout_s, serial.retries, serial.sync_period_s)
    assert (load.unit_id, load.timeout_s, load.retries, load.comm_loss) == \
        (modbus.unit_id, modbus.timeout_s, modbus.retries, modbus.comm_loss)


def test_a_bad_value_names_file_field_and_reason(tmp_path):
    path = _bench(tmp_path, SERIAL + "retries = -1\nbaudrate = \"fast\"\n")
    with pytest.raises(InputError) as err:
        load_bench_config(path)
    assert err.value.problems == [f"{path}: drive.baudrate: must be an integer, got string 'fast'",
                                  f"{path}: drive.retries: must be >= 0, got -1"]


def test_the_simulated_rig_is_described_once_for_the_starter_and_for_sim_serve(tmp_path):
    """`sim serve` and the in-process [services] starter describe the same drive from the same [simulator]."""
    from sim_backend.rig import spec_for_bench
    from sim_backend.serve import load_serve_config

    config = REPO / "config" / "benches" / "sim-generic-e35.toml"
    cfg = load_bench_config(config)
    started = spec_for_bench(cfg.as_dict(), 0)
    text = config.read_text() + '\n[simulator.serve]\ncanopen_socketcand = "127.0.0.1:0"\n'
    served_path = tmp_path / "served.toml"
    served_path.write_text(text.replace('eds = "', f'eds = "{REPO}/').replace('map = "', f'map = "{REPO}/'))
    served = load_serve_config(served_path)
    assert started.drive is not None and started.drive == served.drive
    assert Path(started.motor) == Path(served.motor) and started.instruments == served.instruments
    assert served.socketcand == ("127.0.0.1", 0) and started.socketcand is None


@pytest.mark.slow
def test_sim_serve_refuses_an_unknown_simulator_key_in_one_line(tmp_path):
    config = tmp_path / "bench.toml"
    config.write_text("[simulator]\nmotor = 'toy'\nmotr = 1\n[simulator.serve]\nserial_tcp = '127.0.0.1:0'\n")
    proc = subprocess.run([sys.executable, "-m", "sim_backend.serve", "--config", str(config)], capture_output=True,
                          text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"error: {config}: simulator.motr: unknown key; did you mean 'motor'? "
        f"(allowed: {', '.join(sorted(SimulatorConfig.keys_allowed()))})"]
