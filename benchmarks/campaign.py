"""Campaign throughput on this machine: the same points with one and with two local workers.

N seeds of a paper scenario (default: the PMSM Fig. 8 R_s step, 5 s of drive time) as a campaign. Figures: runs per
minute with two workers; the per-run overhead beyond the run itself (campaign wall x workers / runs minus the mean
in-worker run time, which includes the run's own record writing); the two-worker efficiency against one worker
from the same run (the baseline). With Ray installed (the [ray] extra): the time to start a local two-CPU Ray
instance, then the same points on it after a warm-up campaign (its workers' imports paid, as for the local pool),
as a ratio of the two-worker local pool's wall time.

    python benchmarks/campaign.py [--runs 20] [--scenario scenarios/pmsm/fig08-20rads-rs-step.toml] [--no-ray]

Last line: RESULT runs=... runs_per_min=... overhead_s=... efficiency_2w=... wall_1w_s=... wall_2w_s=...
           ray_start_s=... ray_vs_local=...   (the last two "n/a" without Ray)
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

from bench.faces.campaign import load_campaign  # noqa: E402
from bench.faces.campaign_run import run_campaign  # noqa: E402


def timed(campaign_file: Path, out: Path, workers: int, engine: str = "local") -> tuple[float, list[dict]]:
    t0 = time.perf_counter()
    rows = run_campaign(load_campaign(campaign_file), out, workers=workers, engine=engine)
    return time.perf_counter() - t0, rows


def ray_figures(camp: Path, tmp: Path) -> tuple[float, float, list[dict]] | None:
    """(seconds to start a local Ray instance, campaign wall time on it once warm, rows); None without Ray."""
    try:
        import ray
    except ImportError:
        return None
    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    start_s = time.perf_counter() - t0
    try:
        timed(camp, tmp / "ray-warm", 2, "ray")
        wall, rows = timed(camp, tmp / "ray", 2, "ray")
    finally:
        ray.shutdown()
    return start_s, wall, rows


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--scenario", default="scenarios/pmsm/fig08-20rads-rs-step.toml")
    parser.add_argument("--no-ray", action="store_true")
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
        on_ray = None if args.no_ray else ray_figures(camp, tmp)
    per_run = statistics.mean(r["wall_s"] for r in rows2 if r.get("wall_s"))
    overhead = wall2 * 2 / len(rows2) - per_run
    efficiency = wall1 / wall2 / 2
    verdicts = {r["verdict"] for r in rows1 + rows2 + (on_ray[2] if on_ray else [])}
    print(f"{len(rows2)} runs of {args.scenario}: 1 worker {wall1:.1f} s, 2 workers {wall2:.1f} s; a run "
          f"{per_run:.2f} s inside its worker; verdicts {sorted(verdicts)}")
    ray_part = "ray_start_s=n/a ray_vs_local=n/a"
    if on_ray:
        start_s, wall_ray, _ = on_ray
        print(f"Ray: local instance started in {start_s:.1f} s; the points in {wall_ray:.1f} s on 2 CPUs once warm")
        ray_part = f"ray_start_s={start_s:.1f} ray_vs_local={wall_ray / wall2:.2f}"
    print(f"RESULT runs={len(rows2)} runs_per_min={len(rows2) / wall2 * 60:.1f} overhead_s={overhead:.3f} "
          f"efficiency_2w={efficiency:.2f} wall_1w_s={wall1:.1f} wall_2w_s={wall2:.1f} {ray_part}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
