"""How fast a unit error trips, and how fast the shaft turns before it does, on each vendor-EDS simulated rig.

    python benchmarks/unit_trip.py [--rigs e35,technosoft,cia402-slave] [--cases 1.5,1.1,10]

Each case is a drive whose velocity unit counts the MOTOR behind a gear the bench does not apply: the simulated drive
has [simulator] gear_ratio = [m, s] and velocity_side = "motor", and the bench believes the unit counts the driving
shaft (e35: it reads 0x6091 and the bench config states velocity_side = "shaft"; technosoft: its config states
gear_ratio = [1, 1] and the EDS has no 0x6091; cia402_slave: rpm stated, no gear anywhere). The shaft then turns k
times faster than commanded (k = s/m: 1.5, 1.1, 10). scenarios/rig/speed-step-20rads.toml (ramp to 20 rad/s in 0.5 s,
overspeed limit 40 rad/s) runs through bench.run.orchestrator.run_scenario against the in-process simulator; the rig's
true shaft speed is sampled after every simulated SYNC (simulator truth, for this measurement only).

Figures per rig and case: the trip's reason, its drive time, (runs that end) the dynamometer encoder's steady-state
error from 20 rad/s in % (the scenario's first criterion), the time from first motion (|shaft| > 1 rad/s) to the
quick-stop controlword reaching the drive, the peak |shaft speed| over the whole run, and the order (drive time) of
the quick-stop controlword and the load's zero-torque write. "before" figures come from running this script on the
bench code before the change (the simulator quirk alone).
RESULT: worst (largest) peak shaft speed and stop latency over all rigs and cases, and the number of cases that
tripped unit_mismatch.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import sim_backend.rig as sim_rig  # noqa: E402
from bench.run.orchestrator import run_scenario  # noqa: E402
from drivers.canopen.profile import PROFILE_KEYS  # noqa: E402

SCENARIO = REPO / "scenarios/rig/speed-step-20rads.toml"
RIGS = {"e35": "sim-generic-e35", "technosoft": "sim-generic-technosoft", "cia402-slave": "sim-generic-cia402-slave"}
GEARS = {"1.5": (2, 3), "1.1": (10, 11), "10": (1, 10), "ok-3:2": (3, 2)}
QUICK_STOP = 0x0002


def bench_text(rig: str, case: str) -> str:
    """The rig's bench config with the simulated drive's gear quirk, and what the bench is told (wrongly)."""
    text = (REPO / f"config/benches/{RIGS[rig]}.toml").read_text()
    m, s = GEARS[case]
    if case.startswith("ok"):
        # told the truth: e35 reads 0x6091 and is told the side; the others are told gear and side
        told = 'velocity_side = "motor"\n' + ("" if rig == "e35" else f"gear_ratio = [{m}, {s}]\n")
        text = re.sub(r"^gear_ratio = .*\n", "", text, flags=re.M)
        text = text.replace("sync_period_s =", told + "sync_period_s =", 1)
    elif rig == "e35" and "velocity_side" in PROFILE_KEYS:
        text = text.replace("sync_period_s =", 'velocity_side = "shaft"\nsync_period_s =', 1)
    text = text.replace("[simulator]\n", f"[simulator]\ngear_ratio = [{m}, {s}]\nvelocity_side = \"motor\"\n", 1)
    return text


class Watch:
    """The simulator's truth around one run: shaft speed after every SYNC, and when the stop commands arrived."""

    def __init__(self):
        self.speeds: list[tuple[float, float]] = []
        self.quick_stop_t: float | None = None
        self.quick_stop_step: int | None = None
        self.load_zero_t: float | None = None
        self.load_zero_step: int | None = None
        self.order: list[str] = []             # which stop command the device saw first
        self.load_zero_wall: float | None = None     # time.time() of the load's zero write (CAN frames' clock)

    def attach(self, device) -> None:
        advance, write_cw, set_load = device.advance, device.write_controlword, device.set_load

        def advance_watched(n_steps):
            block = advance(n_steps)
            self.speeds.append((device.time_s, float(device.model.load_feedback()[0])))
            return block

        def write_cw_watched(word):
            if word & 0x0F == QUICK_STOP and self.quick_stop_t is None and self.first_motion_t() is not None:
                self.quick_stop_t, self.quick_stop_step = device.time_s, device.step_count
                self.order.append("drive quick stop")
            return write_cw(word)

        def set_load_watched(mode=None, value=None, enabled=None):
            if (enabled is False or value == 0.0) and self.load_zero_t is None and self.first_motion_t() is not None:
                self.load_zero_t, self.load_zero_step = device.time_s, device.step_count
                self.load_zero_wall = time.time()
                self.order.append("load zero")
            return set_load(mode, value, enabled)

        device.advance, device.write_controlword, device.set_load = advance_watched, write_cw_watched, set_load_watched

    def first_motion_t(self, threshold: float = 1.0) -> float | None:
        return next((t for t, v in self.speeds if abs(v) > threshold), None)


def step_scenario(out: Path) -> Path:
    """The issue's case: a step to 20 rad/s at 0.1 s (no ramp), overspeed limit 60 rad/s."""
    text = SCENARIO.read_text()
    text = text.replace('kind = "ramp"\nstart_s = 0.0\nend_s = 0.5\n', 'kind = "step"\nat_s = 0.1\n')
    text = text.replace("overspeed_mech_rad_s = 40.0", "overspeed_mech_rad_s = 60.0")
    path = out / "speed-step-20rads-step.toml"
    path.write_text(text)
    return path


def run_case(rig: str, case: str, out: Path, scenario: Path = SCENARIO, on_build=None) -> dict:
    """One run; `on_build(rig)` is called with the simulated rig before the bench connects (tests: a bus sniffer)."""
    watch = Watch()
    original = sim_rig.build

    @contextlib.contextmanager
    def build_watched(spec, device=None):
        with original(spec, device) as built:
            watch.attach(built.device)
            if on_build is not None:
                on_build(built)
            yield built

    bench = out / f"{rig}-{case}.toml"
    bench.write_text(bench_text(rig, case))
    sim_rig.build = build_watched
    try:
        result = run_scenario(scenario, bench, out_root=out / "runs", rerun_mode="off")
    except Exception as exc:           # a refusal before anything moves (InputError, LinkError)
        return {"rig": rig, "case": case, "verdict": "refused", "reason": str(exc).splitlines()[0][:160],
                "peak": max((abs(v) for _, v in watch.speeds), default=0.0)}
    finally:
        sim_rig.build = original
    record = result.record
    trip = (record.get("trips") or [{}])[0]
    motion = watch.first_motion_t()
    latency = None if motion is None or watch.quick_stop_t is None else watch.quick_stop_t - motion
    return {"rig": rig, "case": case, "verdict": result.verdict, "reason": trip.get("reason"),
            "trip_t_s": trip.get("t_s"), "motion_to_quick_stop_s": latency,
            "peak": max((abs(v) for _, v in watch.speeds), default=0.0),
            "shaft_error_pct": next((c["value"] for c in record["criteria"]
                                     if c["signal"] == "speed_true_mech_rad_s" and c.get("status") != "not_judged"),
                                    None) if result.verdict != "aborted" else None,
            "stop_order": "/".join(watch.order), "load_zero_wall": watch.load_zero_wall,
            "load_after_qs_steps": (None if watch.quick_stop_step is None or watch.load_zero_step is None
                                    else watch.load_zero_step - watch.quick_stop_step)}


def fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rigs", default=",".join(RIGS))
    parser.add_argument("--cases", default="1.5,1.1,10,ok-3:2")
    parser.add_argument("--profile", default="ramp,step",
                        help="ramp: the rig scenario; step: a step at 0.1 s, limit 60")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        scenarios = {"ramp": SCENARIO, "step": step_scenario(Path(tmp))}
        for profile in args.profile.split(","):
            for rig in args.rigs.split(","):
                for case in args.cases.split(","):
                    row = {"profile": profile, **run_case(rig, case, Path(tmp), scenarios[profile])}
                    rows.append(row)
                    print("  ".join(f"{k}={fmt(v)}" for k, v in row.items() if k != "load_zero_wall"), flush=True)
    errors = [r for r in rows if not r["case"].startswith("ok")]
    tripped = sum(r.get("reason") == "unit_mismatch" for r in errors)
    peak = max((r["peak"] for r in errors), default=0.0)
    latency = max((r["motion_to_quick_stop_s"] or 0.0 for r in errors), default=0.0)
    print(f"RESULT cases={len(errors)} unit_mismatch={tripped} worst_peak_shaft_mech_rad_s={peak:.2f} "
          f"worst_motion_to_quick_stop_s={latency:.3f}")


if __name__ == "__main__":
    main()
