"""Bad places to write or listen are bad input: one line `what: option: reason`, exit 2, no traceback, nothing started
(`serve` on a port in use, `serve --scenarios` of a missing folder, `campaign --out` and `report --out` under a
file)."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def _one_line(*args: str) -> str:
    out = subprocess.run([sys.executable, "-m", "bench", *args], capture_output=True, text=True, cwd=REPO, timeout=120)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 2 and len(lines) == 1 and "Traceback" not in out.stderr, (out.returncode, out.stderr)
    return lines[0]


def test_serve_with_a_missing_scenario_root_or_on_a_port_in_use(tmp_path):
    line = _one_line("serve", "--data", str(tmp_path / "data"), "--port", "1", "--scenarios", str(tmp_path / "missing"))
    assert line == f"serve: --scenarios: {tmp_path / 'missing'}: not a directory"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = _one_line("serve", "--data", str(tmp_path / "data"), "--port", str(port))
    assert line.startswith(f"serve: --port: 127.0.0.1:{port}: Address already in use"), line
    assert not (tmp_path / "data").exists()                     # nothing was started or written


@pytest.mark.parametrize("command", ["campaign", "report"])
def test_an_output_path_under_a_file(tmp_path, command):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    if command == "campaign":
        line = _one_line("campaign", str(REPO / "campaigns/inverter-pmsm.toml"), "--out", str(blocker / "results"))
        assert line == f"campaign: --out: {blocker / 'results'}: {blocker} is a file, not a directory"
    else:
        from bench.run.orchestrator import run_scenario

        run_dir = run_scenario(REPO / "tests/data/service/short.toml", None, out_root=tmp_path / "runs",
                               rerun_mode="off").run_dir
        line = _one_line("report", str(run_dir), "--out", str(blocker / "report.md"))
        assert line == f"{blocker}: --out: is a file, not a directory", line
