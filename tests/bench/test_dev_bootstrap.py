"""dev.py: the two README commands set up .venv only when pyproject.toml, the extras or Python changed."""

import importlib.util
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("dev_bootstrap", ROOT / "dev.py")
dev = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(dev)


def _fake_root(tmp_path: Path, pyproject: str = "[project]\nname = 'x'\n") -> Path:
    (tmp_path / "pyproject.toml").write_text(pyproject)
    python = dev.venv_python(tmp_path / ".venv")
    python.parent.mkdir(parents=True)
    python.write_text("")
    return tmp_path


def test_second_call_does_not_reinstall(tmp_path, monkeypatch):
    root = _fake_root(tmp_path)
    calls = []
    monkeypatch.setattr(subprocess, "run", lambda args, **kw: calls.append(args) or subprocess.CompletedProcess(args, 0))
    dev.ensure_venv(root, "test")
    assert [a[3:5] for a in calls] == [["install", "-q"], ["install", "-q"]] and calls[1][-1] == ".[test]"
    calls.clear()
    dev.ensure_venv(root, "test")
    assert calls == []


@pytest.mark.parametrize("change", ["pyproject", "extras"])
def test_changed_project_or_extras_reinstall(tmp_path, monkeypatch, change):
    root = _fake_root(tmp_path)
    calls = []
    monkeypatch.setattr(subprocess, "run", lambda args, **kw: calls.append(args) or subprocess.CompletedProcess(args, 0))
    dev.ensure_venv(root, "test")
    calls.clear()
    if change == "pyproject":
        (root / "pyproject.toml").write_text("[project]\nname = 'x'\ndependencies = ['numpy']\n")
    dev.ensure_venv(root, "test,service" if change == "extras" else "test")
    assert len(calls) == 2


def test_failed_install_leaves_no_stamp(tmp_path, monkeypatch):
    root = _fake_root(tmp_path)
    monkeypatch.setattr(subprocess, "run", lambda args, **kw: subprocess.CompletedProcess(args, 1))
    with pytest.raises(SystemExit):
        dev.ensure_venv(root, "test")
    assert not (root / ".venv" / ".drivebench-installed").exists()


def test_readme_commands_are_dev_py():
    readme = (ROOT / "README.md").read_text()
    assert "python3 dev.py run\n" in readme and "python3 dev.py test\n" in readme
    ci = (ROOT / ".ci" / "run").read_text()
    assert "dev.py test" in ci
