"""`python3 dev.py run` says why a first run is silent for a minute: the simulator's numba kernels are compiled once
(and cached); once the cache is there it says nothing."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("dev_first_run", ROOT / "dev.py")
dev = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(dev)


def test_first_compile_is_seen_from_the_numba_cache(tmp_path):
    cache = tmp_path / "sim_backend" / "pmsm" / "__pycache__"
    cache.mkdir(parents=True)
    assert dev.first_compile(tmp_path)
    (cache / "kernel.run_steps-54.py311.nbi").write_bytes(b"")
    assert not dev.first_compile(tmp_path)


def test_dev_run_prints_the_notice_only_before_the_first_compile(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(dev, "ensure_venv", lambda: Path("python"))
    monkeypatch.setattr(dev.subprocess, "run", lambda args, cwd: calls.append(args) or type("R", (), {"returncode": 0}))
    monkeypatch.setattr(dev, "ROOT", tmp_path)
    assert dev.main(["run"]) == 0
    assert "compiles the simulator's numba kernels" in capsys.readouterr().err
    (tmp_path / "sim_backend" / "__pycache__").mkdir(parents=True)
    (tmp_path / "sim_backend" / "__pycache__" / "x.nbi").write_bytes(b"")
    assert dev.main(["run"]) == 0
    assert capsys.readouterr().err == "" and len(calls) == 2
