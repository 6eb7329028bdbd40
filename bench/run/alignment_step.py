"""The encoder-alignment step of a PMSM rig (docs/instruments.md), as a lab runs it once per rig and after any change
of coupling or encoder: the drive connected but disabled (its power stage off: the windings open), the dynamometer
spins the shaft forward in its torque mode and lets it coast, the scope records a phase's open-circuit back-EMF and
the encoder's index, bench.run.rig_truths.align gives the rotor's electrical angle at the index (and the magnet
flux). The result is the [rig_truths] lines for the bench config, printed:

    python -m bench.run.alignment_step --bench config/benches/sim-pmsm-instruments.toml

The step never enables the drive; whatever happens the dynamometer ends at zero torque and disabled.
"""

from __future__ import annotations

import argparse
import math
import sys
from datetime import datetime, timezone
from pathlib import Path

from bench.inputs.benchconfig import BenchConfig, load_bench_config
from bench.run.links import make_links, started_services
from bench.run.rig_truths import Alignment, align
from drivers.api import LoadMode
from drivers.contract.checks import find_repo_root
from drivers.contract.errors import InputError

SPIN_TORQUE_NM = -0.25       # forward (the load's torque opposes positive rotation)
SPIN_MECH_RAD_S = 80.0
SPIN_TIMEOUT_S = 10.0        # drive time
CAPTURE_S = 0.25


def run_alignment(cfg: BenchConfig, seed: int = 0, scope_name: str | None = None) -> Alignment:
    from drivers.instruments import open_instrument

    scope_cfg = next((i for i in cfg.instruments if i.kind in ("scope", "daq")
                      and (scope_name is None or i.name == scope_name)), None)
    if scope_cfg is None or not {"encoder_index_v"} <= {c.signal for c in scope_cfg.channels}:
        raise InputError([f"{cfg.path}: instruments: the alignment step needs a scope recording encoder_index_v and a "
                          "phase voltage (u_a_v)"])
    with started_services(cfg, seed) as live:
        drive, load = make_links(live, find_repo_root(cfg.path))
        if load is None:
            raise InputError([f"{cfg.path}: load: the alignment step needs the dynamometer to turn the shaft"])
        drive.open()
        scope = None
        try:
            drive.configure(("speed_est_mech_rad_s",), (), int(cfg.drive.get("trace_decimation") or 1))
            load.open()
            scope = open_instrument(next(i for i in live.instruments if i.name == scope_cfg.name))
            load.set_load(LoadMode.TORQUE, SPIN_TORQUE_NM)
            load.enable(True)
            t = 0.0
            while load.feedback().speed_mech_rad_s < SPIN_MECH_RAD_S:
                samples = drive.sync()
                t = samples[-1].t_s if samples else t
                if t > SPIN_TIMEOUT_S:
                    raise RuntimeError(f"the shaft did not reach {SPIN_MECH_RAD_S:g} rad/s within "
                                       f"{SPIN_TIMEOUT_S:g} s of the dynamometer's {SPIN_TORQUE_NM:g} N*m")
            load.zero_and_disable()          # coast: the speed holds within a fraction of a percent over the capture
            scope.arm(CAPTURE_S, 0.0)
            scope.force()
            for _ in range(math.ceil(CAPTURE_S / float(cfg.drive["sync_period_s"])) + 2):
                drive.sync()
            scope.wait(5.0)
            cap = scope.fetch()
        finally:
            try:
                load.zero_and_disable()
            finally:
                if scope is not None:
                    scope.close()
                load.close()
                drive.close()
    return align(cap.t_s, cap.signals["u_a_v"], cap.signals["encoder_index_v"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.run.alignment_step")
    parser.add_argument("--bench", required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        result = run_alignment(load_bench_config(Path(args.bench)), args.seed)
    except InputError as exc:
        print(exc, file=sys.stderr)
        return 2
    except Exception as exc:
        print(f"alignment step failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    print(f"encoder_index_elec_rad = {result.theta_index_elec_rad:.5f}\n"
          f"encoder_index_uncertainty_rad = {result.uncertainty_rad:.5f}\n"
          f'aligned_utc = "{stamp}"      # {result.edges} index edges, w_e {result.omega_elec_rad_s:.1f} rad/s, '
          f"magnet flux {result.flux_wb:.6f} Wb")
    return 0


if __name__ == "__main__":
    sys.exit(main())
