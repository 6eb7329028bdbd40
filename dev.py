#!/usr/bin/env python3
"""Set up drivebench's virtual environment when needed, then run the main job or the tests.

    python3 dev.py run [drivebench run arguments]   # default: the PMSM Fig. 8 scenario on the simulator
    python3 dev.py test [pytest arguments]          # the whole test suite (what CI runs)
    python3 dev.py quick [pytest arguments]         # the inner loop: bench, drivers, sim_backend without slow tests
    python3 dev.py setup                            # only create or refresh .venv

Only Python 3.11+ is needed (no make, no shell: the same on a Windows lab PC). The environment is `.venv` in the
repository, installed with `pip install -e ".[EXTRAS]"`; it is refreshed when pyproject.toml, the extras or the
Python version change (a fingerprint in `.venv/.drivebench-installed`), so a second call starts at once.
DRIVEBENCH_EXTRAS names the extras (default "test").
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
MAIN_JOB = ("scenarios/pmsm/fig08-20rads-rs-step.toml",)
DEFAULT_EXTRAS = "test"
# the inner loop (docs/testing.md): every package's tests but the system tests and those marked slow
QUICK = ("-m", "not slow and not system", "tests/bench", "tests/drivers", "tests/sim_backend")


def venv_python(venv: Path) -> Path:
    return venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def fingerprint(pyproject: Path, extras: str) -> str:
    digest = hashlib.sha256(pyproject.read_bytes())
    digest.update(f"\0{extras}\0{sys.version_info[:2]}".encode())
    return digest.hexdigest()


def up_to_date(venv: Path, wanted: str) -> bool:
    stamp = venv / ".drivebench-installed"
    return venv_python(venv).exists() and stamp.exists() and stamp.read_text().strip() == wanted


def ensure_venv(root: Path = ROOT, extras: str | None = None) -> Path:
    extras = extras or os.environ.get("DRIVEBENCH_EXTRAS", DEFAULT_EXTRAS)
    venv = root / ".venv"
    wanted = fingerprint(root / "pyproject.toml", extras)
    python = venv_python(venv)
    if up_to_date(venv, wanted):
        return python
    if not python.exists():
        print(f"dev.py: creating {venv.name} (Python {sys.version.split()[0]})", file=sys.stderr)
        if subprocess.run([sys.executable, "-m", "venv", str(venv)]).returncode != 0:
            sys.exit("dev.py: python -m venv failed (on Debian/Ubuntu: apt-get install python3-venv)")
    print(f'dev.py: installing drivebench[{extras}] into {venv.name} (a first install takes a few minutes)',
          file=sys.stderr)
    for args in (["install", "-q", "--upgrade", "pip"], ["install", "-q", "-e", f".[{extras}]"]):
        if subprocess.run([str(python), "-m", "pip", *args], cwd=root).returncode != 0:
            sys.exit(f"dev.py: pip {' '.join(args)} failed")
    (venv / ".drivebench-installed").write_text(wanted + "\n")
    return python


def first_compile(root: Path) -> bool:
    """No numba cache beside the simulator's kernels yet (numba's cache=True writes *.nbi files in __pycache__)."""
    return not any((root / "sim_backend").glob("**/__pycache__/*.nbi"))


def main(argv: list[str]) -> int:
    if sys.version_info < (3, 11):
        print(f"dev.py: Python 3.11 or newer is needed, this is {sys.version.split()[0]}", file=sys.stderr)
        return 2
    if not argv or argv[0] not in ("run", "test", "quick", "setup"):
        print("usage: python3 dev.py run|test|quick|setup [arguments]", file=sys.stderr)
        return 2
    command, rest = argv[0], argv[1:]
    python = ensure_venv()
    if command == "setup":
        return 0
    if command == "run":
        args = [str(python), "-m", "bench", "run", *(rest or MAIN_JOB)]
        if first_compile(ROOT):
            print("dev.py: a first run compiles the simulator's numba kernels (about a minute on a laptop; cached "
                  "for every later run): nothing is printed until the run starts", file=sys.stderr)
    elif command == "quick":
        args = [str(python), "-m", "pytest", "-n", "2", "-q", *QUICK, *rest]
    else:  # loadgroup: the tests of one firmware mutant share a worker and its numba compile (tests/mutants.py)
        args = [str(python), "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-q", *rest]
    return subprocess.run(args, cwd=ROOT).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
