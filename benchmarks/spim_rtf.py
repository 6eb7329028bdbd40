"""Real-time factor of the simulated SPIM drive (plant + inverter + ADC + firmware at 100 us, one core).

Runs the drive at 1500 r/min with 4 N*m after a warm-up (compile excluded), in blocks of `--block` control
periods as the protocol servers call step(n). The machine may be shared: the figure is pessimistic.
Last line: RESULT rtf_best=... rtf_median=... us_per_step_best=... block=...
"""

from __future__ import annotations

import argparse
import math
import time
import tomllib
from pathlib import Path

from sim_backend.mechanics import LOAD_BRAKE
from sim_backend.spim.model import SpimDrive

CONFIG = Path(__file__).resolve().parents[1] / "config/motors/spim-paper.toml"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds timed")
    ap.add_argument("--block", type=int, default=10, help="control periods per step() call")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats; best and median are reported")
    args = ap.parse_args()
    drive = SpimDrive.from_config(tomllib.loads(CONFIG.read_text()), seed=1)
    drive.set_enabled(True)
    drive.set_speed_ref(1500 * 2 * math.pi / 60)
    drive.step(20000)
    drive.set_load(LOAD_BRAKE, 4.0)
    n_calls = int(args.seconds / drive.control_period_s) // args.block
    sim = n_calls * args.block * drive.control_period_s
    walls = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for _ in range(n_calls):
            drive.step(args.block)
        walls.append(time.perf_counter() - t0)
        print(f"simulated {sim:.1f} s in {walls[-1]:.3f} s wall ({sim / walls[-1]:.0f}x), blocks of {args.block}")
    best, median = min(walls), sorted(walls)[len(walls) // 2]
    print(f"RESULT rtf_best={sim / best:.1f} rtf_median={sim / median:.1f} "
          f"us_per_step_best={best / (sim / drive.control_period_s) * 1e6:.3f} block={args.block}")


if __name__ == "__main__":
    main()
