"""[[instruments]] in a bench config: one typed frozen object each, bad entries one `file: field: reason` line."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from bench.inputs.benchconfig import load_bench_config
from drivers.contract.errors import InputError

REPO = Path(__file__).resolve().parents[2]
BASE = (REPO / "config/benches/sim-pmsm-instruments.toml").read_text()


def _with(tmp_path: Path, old: str, new: str) -> Path:
    assert old in BASE
    path = tmp_path / "bench.toml"
    path.write_text(BASE.replace(old, new, 1).replace('"config/', f'"{REPO}/config/'))
    return path


def test_the_instruments_rigs_name_an_analyser_and_a_scope():
    cfg = load_bench_config(REPO / "config/benches/sim-pmsm-instruments.toml")
    kinds = {i.kind: i for i in cfg.instruments}
    assert set(kinds) == {"power_analyser", "scope", "daq"} and cfg.rig_truths.daq == "daq"
    assert kinds["power_analyser"].channel("p_dc_w").channel == "P4"
    assert kinds["scope"].sample_rate_hz >= 20_000 and len(kinds["scope"].channels) >= 4
    with pytest.raises(dataclasses.FrozenInstanceError):
        kinds["scope"].resource = "x"
    moved = cfg.with_overrides({"instruments": {"scope": "TCPIP::127.0.0.1::4444::SOCKET"}})
    assert [i.resource for i in moved.instruments if i.name == "scope"] == ["TCPIP::127.0.0.1::4444::SOCKET"]


@pytest.mark.parametrize("old,new,line", [
    ('resource = "TCPIP::127.0.0.1::5025::SOCKET"', 'resource = "127.0.0.1:5025"',
     "instruments[1].resource: '127.0.0.1:5025' is not a VISA resource string"),
    ('driver = "yokogawa-wt"', 'driver = "scpi-scope"',
     "instruments[0].driver: 'scpi-scope' cannot drive a power_analyser"),
    ('kind = "scope"', 'kind = "oscilloscope"', "instruments[1].kind: must be one of"),
    ('CHAN3 = { signal = "i_a_a", unit = "A", range = 20.0 }', 'CHAN3 = { signal = "i_a_a", unit = "mA", range = 20.0 }',
     "instruments[1].channels.CHAN3.unit: must be one of"),
    ('CHAN3 = { signal = "i_a_a", unit = "A", range = 20.0 }', 'CHAN3 = { signal = "i_a_a", unit = "A" }',
     "instruments[1].channels.CHAN3.range: missing"),
    ('CHAN4 = { signal = "i_b_a"', 'CHAN4 = { signal = "i_a_a"',
     "instruments[1].channels.CHAN4.signal: 'i_a_a' is given by two channels"),
    ('name = "scope"', 'name = "analyser"', "instruments[1].name: 'analyser' is named twice"),
    ('timeout_s = 2.0\nsample_rate_hz', 'timeout_s = 0\nsample_rate_hz', "instruments[1].timeout_s: must be > 0"),
])
def test_a_bad_instrument_entry_is_one_line(tmp_path, old, new, line):
    path = _with(tmp_path, old, new)
    with pytest.raises(InputError) as err:
        load_bench_config(path)
    assert any(p.startswith(f"{path}: {line}") for p in err.value.problems), err.value.problems


def test_the_contract_imports_no_visa():
    code = ("import sys, drivers.contract.instruments, drivers.contract.simulator, bench.inputs.benchconfig; "
            "print('pyvisa' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
