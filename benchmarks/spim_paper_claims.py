"""The SPIM paper's three test runs on the simulated drive (config/motors/spim-paper.toml), with the numbers.

1. Fig. 6: step to 1500 r/min at 1 s, 4 N*m powder-brake load from 6 s to 16 s, 20 s.
2. Fig. 7: 4 N*m load at 1 s, reversal +1500 -> -1500 r/min.
3. Fig. 8: low speed +15 -> -15 r/min with 1.5 N*m.
Speed-estimate error in % of the 1500 r/min reference (paper: within +-1 % in steady state); low speed in r/min.
Usage: python benchmarks/spim_paper_claims.py [--seed N] [--load-mode brake|torque]
Last line: RESULT key=value ...
"""

from __future__ import annotations

import argparse
import math
import tomllib
from pathlib import Path

import numpy as np

from drivers.contract.signals import SIGNAL_INDEX as SI
from sim_backend.mechanics import LOAD_BRAKE, LOAD_TORQUE
from sim_backend.spim.model import SpimDrive

RPM = 2.0 * math.pi / 60.0
CONFIG = Path(__file__).resolve().parents[1] / "config/motors/spim-paper.toml"


def run(drive: SpimDrive, events: list[tuple[float, str, float]], t_end: float) -> np.ndarray:
    """events: (time_s, 'speed_rpm' | 'load_nm', value), applied in time order."""
    blocks, t = [], 0.0
    for t_ev, what, value in sorted(events) + [(t_end, "end", 0.0)]:
        n = int(round((t_ev - t) / drive.control_period_s))
        if n > 0:
            blocks.append(drive.step(n))
        t = t_ev
        if what == "speed_rpm":
            drive.set_speed_ref(value * RPM)
        elif what == "load_nm":
            drive.set_load(LOAD_MODE, value, enabled=value != 0.0)
    return np.vstack(blocks)


def window(out: np.ndarray, a: float, b: float, ts: float = 1e-4) -> np.ndarray:
    return out[int(round(a / ts)):int(round(b / ts))]


def speed_errors(out: np.ndarray, a: float, b: float, base_rpm: float) -> dict[str, float]:
    w = window(out, a, b)
    est, true, ref = (w[:, SI[c]] / RPM for c in ("speed_est_mech_rad_s", "speed_true_mech_rad_s",
                                                   "speed_ref_mech_rad_s"))
    return {
        "est_minus_true_mean_pct": float(np.mean(est - true) / base_rpm * 100),
        "est_minus_true_absmax_pct": float(np.max(np.abs(est - true)) / base_rpm * 100),
        "est_minus_ref_absmax_pct": float(np.max(np.abs(est - ref)) / base_rpm * 100),
        "true_minus_ref_mean_pct": float(np.mean(true - ref) / base_rpm * 100),
        "true_mean_rpm": float(np.mean(true)),
        "est_mean_rpm": float(np.mean(est)),
        "pos_err_mean_rad": float(np.mean(w[:, SI["pos_err_elec_rad"]])),
    }


def main() -> None:
    global LOAD_MODE
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--load-mode", choices=("brake", "torque"), default="brake")
    args = ap.parse_args()
    LOAD_MODE = LOAD_BRAKE if args.load_mode == "brake" else LOAD_TORQUE
    cfg = tomllib.loads(CONFIG.read_text())
    results = {}

    d = SpimDrive.from_config(cfg, args.seed)
    d.set_enabled(True)
    out = run(d, [(1.0, "speed_rpm", 1500.0), (6.0, "load_nm", 4.0), (16.0, "load_nm", 0.0)], 20.0)
    for name, (a, b) in {"noload": (4.0, 6.0), "load4nm": (12.0, 16.0), "after": (18.0, 20.0)}.items():
        e = speed_errors(out, a, b, 1500.0)
        print(f"fig6 {name:8s} " + " ".join(f"{k}={v:+.3f}" for k, v in e.items()))
        results[f"fig6_{name}_est_err_max_pct"] = e["est_minus_ref_absmax_pct"]
        results[f"fig6_{name}_est_true_mean_pct"] = e["est_minus_true_mean_pct"]
    dip = window(out, 6.0, 7.0)[:, SI["speed_true_mech_rad_s"]].min() / RPM
    print(f"fig6 load-step speed dip: min true speed {dip:.1f} r/min")
    results["fig6_fault"] = d.fault_code()

    d = SpimDrive.from_config(cfg, args.seed)
    d.set_enabled(True)
    out = run(d, [(0.2, "speed_rpm", 1500.0), (1.0, "load_nm", 4.0), (3.0, "speed_rpm", -1500.0)], 6.0)
    for name, (a, b) in {"fwd": (2.0, 3.0), "rev": (5.0, 6.0)}.items():
        e = speed_errors(out, a, b, 1500.0)
        print(f"fig7 {name:8s} " + " ".join(f"{k}={v:+.3f}" for k, v in e.items()))
        results[f"fig7_{name}_est_err_max_pct"] = e["est_minus_ref_absmax_pct"]
        results[f"fig7_{name}_true_rpm"] = e["true_mean_rpm"]
    results["fig7_fault"] = d.fault_code()

    d = SpimDrive.from_config(cfg, args.seed)
    d.set_enabled(True)
    out = run(d, [(0.2, "speed_rpm", 15.0), (1.0, "load_nm", 1.5), (4.0, "speed_rpm", -15.0)], 8.0)
    for name, (a, b) in {"fwd": (3.0, 4.0), "rev": (7.0, 8.0)}.items():
        w = window(out, a, b)
        true = w[:, SI["speed_true_mech_rad_s"]] / RPM
        est = w[:, SI["speed_est_mech_rad_s"]] / RPM
        print(f"fig8 {name:8s} true mean {true.mean():+.2f} r/min (std {true.std():.2f}), est mean {est.mean():+.2f}"
              f" r/min (std {est.std():.2f}), pos_err mean {w[:, SI['pos_err_elec_rad']].mean():+.3f} rad")
        results[f"fig8_{name}_true_rpm"] = float(true.mean())
        results[f"fig8_{name}_est_rpm"] = float(est.mean())
    results["fig8_fault"] = d.fault_code()
    print("RESULT " + " ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in results.items()))


LOAD_MODE = LOAD_BRAKE

if __name__ == "__main__":
    main()
