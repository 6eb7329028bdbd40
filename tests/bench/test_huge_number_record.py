"""A record.json holding a number of 5,000 digits (beyond Python's 4,300-digit integer conversion) is one line of bad
input and exit 2 for every command that reads a run directory, not a ValueError with a traceback hint."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("command", [["show"], ["evaluate"], ["export", "--format", "csv"]])
def test_a_5000_digit_number_in_record_json_is_one_line(tmp_path, command):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    text = json.dumps({"verdict": "pass", "seed": 1, "criteria": []}).replace('"seed": 1', '"seed": ' + "9" * 5000)
    (run_dir / "record.json").write_text(text)
    out = subprocess.run([sys.executable, "-m", "bench", command[0], str(run_dir), *command[1:]], capture_output=True,
                         text=True, cwd=REPO, timeout=120)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith(f"{run_dir / 'record.json'}: (file): unreadable: Exceeds the limit"), lines[0]
