"""Campaign throughput on this machine: the same points with one and with two local workers.

N seeds of a paper scenario (default: the PMSM Fig. 8 R_s step, 5 s of drive time) as a campaign. Figures: runs per
minute with two workers; the per-run overhead beyond the run itself (campaign wall x workers / runs minus the mean
in-worker run time, which includes the run's own record writing); the two-worker efficiency against one worker
from the same run (the baseline). Ray is not measured here (an optional engine; not installed by default).

    python benchmarks/campaign.py [--runs 20] [--scenario scenarios/pmsm/fig08-20rads-rs-step.toml]

Last line: RESULT runs=... runs_per_min=... overhead_s=... efficiency_2w=... wall_1w_s=... wall_2w_s=...
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.campaign import load_campaign  # noqa: E402
from bench.campaign_run import run_campaign  # noqa: E402


def timed(campaign_file: Path, out: Path, workers: int) -> tuple[float, list[dict]]:
    t0 = time.perf_counter()
    rows = run_campaign(load_campaign(campaign_file), out, workers=workers)
    return time.perf_counter() - t0, rows


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--scenario", default="scenarios/pmsm/fig08-20rads-rs-step.toml")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        text = (f'schema_version = 1\nname = "bench"\nscenarios = ["{REPO / args.scenario}"]\n'
                f'seeds = {{ from = 1, count = {args.runs} }}\n')
        camp = tmp / "bench.toml"
        camp.write_text(text)
        timed(camp, tmp / "warm", 2)                     # numba cache, imports: paid before the timing
        wall1, rows1 = timed(camp, tmp / "one", 1)
        wall2, rows2 = timed(camp, tmp / "two", 2)
    per_run = statistics.mean(r["wall_s"] for r in rows2 if r.get("wall_s"))
    overhead = wall2 * 2 / len(rows2) - per_run
    efficiency = wall1 / wall2 / 2
    verdicts = {r["verdict"] for r in rows1 + rows2}
    print(f"{len(rows2)} runs of {args.scenario}: 1 worker {wall1:.1f} s, 2 workers {wall2:.1f} s; a run "
          f"{per_run:.2f} s inside its worker; verdicts {sorted(verdicts)}")
    print(f"RESULT runs={len(rows2)} runs_per_min={len(rows2) / wall2 * 60:.1f} overhead_s={overhead:.3f} "
          f"efficiency_2w={efficiency:.2f} wall_1w_s={wall1:.1f} wall_2w_s={wall2:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
