"""Wall time of the acceptance suite (tests/system/test_acceptance_suite.py) as CI runs it: pytest -n WORKERS.

Prints each scenario's test time (pytest --durations), the simulated drive time per wall second, and last
`RESULT wall_s=... workers=... scenarios=... passed=... failed=... drive_s=... drive_s_per_wall_s=...`.
The machine may be shared: numbers are pessimistic then.
Usage: python benchmarks/suite.py [--workers 2] [--out DIR] (runs are kept in DIR, default a temp dir).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.inputs.scenario import load_scenario  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="drivebench-suite-"))
    scenarios = sorted((ROOT / "scenarios" / "pmsm").glob("*.toml")) + sorted((ROOT / "scenarios" / "spim").glob("*.toml"))
    drive_s = sum(load_scenario(p).duration_s for p in scenarios)
    cmd = [sys.executable, "-m", "pytest", "tests/system/test_acceptance_suite.py", "-q", "-p", "no:cacheprovider",
           "--durations=0", "--drivebench-out", str(out)]
    if args.workers > 1:
        cmd += ["-n", str(args.workers)]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.monotonic() - t0
    for line in proc.stdout.splitlines():
        if re.match(r"^\s*[\d.]+s call\s", line):
            print(line.strip())
    summary = next((line for line in reversed(proc.stdout.splitlines()) if " in " in line and "passed" in line
                    or "failed" in line), "")
    if proc.returncode != 0:
        for line in [ln for ln in proc.stdout.splitlines() if ln.startswith(("E ", "FAILED", "ERROR"))][:30]:
            print(line)
    print(summary.strip("= "))
    passed = int(m.group(1)) if (m := re.search(r"(\d+) passed", summary)) else 0
    failed = int(m.group(1)) if (m := re.search(r"(\d+) failed", summary)) else 0
    print(f"{len(scenarios)} scenarios, {drive_s:g} s of drive time, {wall:.1f} s wall on {args.workers} worker(s): "
          f"{drive_s / wall:.2f} drive s per wall s; runs in {out}")
    print(f"RESULT wall_s={wall:.1f} workers={args.workers} scenarios={len(scenarios)} passed={passed} "
          f"failed={failed} drive_s={drive_s:g} drive_s_per_wall_s={drive_s / wall:.3f}")
    return 0 if proc.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
