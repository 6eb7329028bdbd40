"""Real-time factor of the simulated SPIM drive (plant + inverter + ADC + firmware at 100 us, one core).

Runs the drive at 1500 r/min with 4 N*m after a warm-up (compile excluded), in blocks of `--block` control
periods as the protocol servers call step(n). The machine may be shared: the figure is pessimistic.
Last line: RESULT rtf=... us_per_step=...
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
    args = ap.parse_args()
    drive = SpimDrive.from_config(tomllib.loads(CONFIG.read_text()), seed=1)
    drive.set_enabled(True)
    drive.set_speed_ref(1500 * 2 * math.pi / 60)
    drive.step(20000)
    drive.set_load(LOAD_BRAKE, 4.0)
    n_total = int(args.seconds / drive.control_period_s)
    t0 = time.perf_counter()
    for _ in range(n_total // args.block):
        drive.step(args.block)
    wall = time.perf_counter() - t0
    sim = (n_total // args.block) * args.block * drive.control_period_s
    print(f"simulated {sim:.1f} s in {wall:.3f} s wall, blocks of {args.block} periods")
    print(f"RESULT rtf={sim / wall:.1f} us_per_step={wall / (sim / drive.control_period_s) * 1e6:.3f} block={args.block}")


if __name__ == "__main__":
    main()
