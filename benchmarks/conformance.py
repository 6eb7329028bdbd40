"""The conformance suite's time (issue 33 target: the whole suite on one simulated drive in <= 60 s).

Each simulated drive (drivebench's own, the three vendor-EDS drives), in one process, lockstep virtual time: the whole
suite (`drivebench conformance` minus the process start), wall time from the simulated rig's start to its report.
Baseline from the same run: the suite's fixed cost on that drive — rig started, drive connected, parameters and
mapping read and restored, one test (identity) — so `ratio` says what the tests themselves add. The kernels are
compiled once before the first measurement (a CI process pays that once, whatever it runs); `cold_cli_s` is the whole
`drivebench conformance --bench sim-pmsm` as a new process (imports, kernels, rig, suite, report).

    python benchmarks/conformance.py [--benches sim-pmsm ...]

Last line: RESULT suite_s=<sim-pmsm> target_s=60 max_suite_s=... cold_cli_s=... baseline_s=... ratio=...
           drive_time_s=... tests=... failed=... per-drive suite_s_<name>=...
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.faces.conformance_cli import run_conformance  # noqa: E402

BENCHES = ("sim-pmsm", "sim-generic-e35", "sim-generic-cia402-slave", "sim-generic-technosoft")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--benches", nargs="*", default=list(BENCHES))
    args = parser.parse_args()
    out = Path(tempfile.mkdtemp(prefix="conformance-bench-"))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "bench", "conformance", "--bench", str(REPO / "config/benches" /
                    f"{args.benches[0]}.toml"), "--out", str(out), "--json"], cwd=REPO, capture_output=True, timeout=600)
    cold = time.perf_counter() - t0
    print(f"cold: drivebench conformance --bench {args.benches[0]} as a new process: {cold:.1f} s", flush=True)
    run_conformance(str(REPO / "config/benches" / f"{args.benches[0]}.toml"), out, ("identity",))   # warm-up
    rows = {}
    for name in args.benches:
        bench = str(REPO / "config/benches" / f"{name}.toml")
        t0 = time.perf_counter()
        run_conformance(bench, out, ("identity",))
        baseline = time.perf_counter() - t0
        t0 = time.perf_counter()
        doc, _ = run_conformance(bench, out)
        suite = time.perf_counter() - t0
        c = doc["counts"]
        rows[name] = (suite, baseline, doc)
        print(f"{name:26} suite {suite:6.2f} s (baseline {baseline:5.2f} s, x{suite / baseline:4.1f}); drive time "
              f"{doc['drive_time_s']:6.2f} s; {c['pass']} pass {c['note']} note {c['fail']} fail "
              f"{c['not_run']} not run", flush=True)
    suite, baseline, doc = rows[args.benches[0]]
    per = " ".join(f"suite_s_{k.replace('-', '_')}={v[0]:.2f}" for k, v in rows.items())
    print(f"RESULT suite_s={suite:.2f} target_s=60 max_suite_s={max(v[0] for v in rows.values()):.2f} "
          f"cold_cli_s={cold:.1f} "
          f"baseline_s={baseline:.2f} ratio={suite / baseline:.2f} drive_time_s={doc['drive_time_s']} "
          f"tests={len(doc['tests'])} failed={sum(v[2]['counts']['fail'] for v in rows.values())} {per}")


if __name__ == "__main__":
    main()
