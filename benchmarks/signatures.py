"""The whole rig-form shaft-signature set on one seed, timed (issue 36: <= 2 minutes on the shared 2-core machine, so a
lab can afford it before every acceptance); optionally the honest firmware over a range of seeds and the cheat
mutants of tests/mutants.py CHEAT_MUTANTS over seeds 1-5, with the kill table docs/shaft-signatures.md quotes.

The set: the drawn signatures of both drives (bench/signatures/draws.py, on the instruments rigs) and the fixed
rig-form signatures scenarios/pmsm-rig/sig-shaft-*.toml and scenarios/spim-rig/sig-shaft-*.toml. Baseline from the
same run: drive time simulated per wall second (the set's realtime ratio) and the 120 s budget.

    python benchmarks/signatures.py [--seed 1]
    python benchmarks/signatures.py --honest 1-20            # false rejections of the honest firmware
    python benchmarks/signatures.py --mutants 1-5 [--json F] # every cheat through the drawn signatures

Last line: RESULT seed=... runs=... wall_s=... drive_s=... realtime_ratio=... budget_ratio=... failed=...
           [honest_seeds=... honest_false_rejections=... honest_not_judged=...] [mutant_runs=... mutants_weak=...]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.run.orchestrator import run_scenario  # noqa: E402
from bench.inputs.scenario import load_scenario  # noqa: E402
from bench.signatures.draws import draw  # noqa: E402
from bench.signatures.run import run_drawn  # noqa: E402

FIXED = [*sorted(REPO.glob("scenarios/pmsm-rig/sig-shaft-*.toml")),
         *sorted(REPO.glob("scenarios/spim-rig/sig-shaft-*.toml"))]

# what a criterion judges, for the kill table (the names carry the drawn values)
LABELS = [
    (r"^under .*angle error jumps", "pos-err jump under load"),
    (r"lowest speed.*angle error jumps", "pos-err jump at lowest speed"),
    (r"^under .*angle error back", "pos-err return under load"),
    (r"lowest speed.*angle error back", "pos-err return at lowest speed"),
    (r"^hook-free dyno pulse.*\+0\.\.\+0\.05", "pulse dip 0-50 ms"),
    (r"^hook-free dyno pulse.*\+0\.05\.\.\+0\.1", "pulse dip 50-100 ms"),
    (r"estimate.*through the kick|estimate holds", None),
    (r"after the start", "start"),
    (r"right after a step.*kick", "kick after step"),
    (r"right after a reversal.*kick", "kick after reversal"),
    (r"^under .*kick", "kick under load"),
    (r"lowest speed.*kick", "kick at lowest speed"),
    (r"^under .*R_r", "R_r under load"),
    (r"during the ramp.*R_r", "R_r in ramp"),
    (r"r/min under .*R_r", "R_r at low speed"),
    (r"^run ", "run aborted"),
]


ESTIMATE = [(r"^under .*N\*m at .*rad/s", "estimate under load"), (r"lowest speed", "estimate at lowest speed"),
            (r"during the ramp", "estimate in ramp"), (r"^under ", "estimate under load"),
            (r"r/min under", "estimate at low speed")]


def label(name: str) -> str:
    for pattern, lab in LABELS:
        if re.search(pattern, name):
            return lab or next(e for p, e in ESTIMATE if re.search(p, name))
    return name[:40]


def seeds_of(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def signature_set(seed: int, out: Path) -> tuple[int, float, list[str]]:
    failed, drive_s = [], 0.0
    for drive in ("pmsm", "spim"):
        r = run_drawn(drive, seed, out)
        drive_s += draw(drive, seed)[0].duration_s
        failed += [f"{drive} drawn: {f}" for f in r.failed] + [f"{drive} drawn: not judged: {n}" for n in r.not_judged]
    for path in FIXED:
        r = run_scenario(path, out_root=out, seed=seed, rerun_mode="off")
        drive_s += load_scenario(path).duration_s
        failed += [f"{path.parent.name}/{path.stem}: {c.name}" for c in r.criteria if c.status != "pass"]
        if r.verdict != "pass" and not any(c.status != "pass" for c in r.criteria):
            failed.append(f"{path.parent.name}/{path.stem}: run {r.verdict}")
    return 2 + len(FIXED), drive_s, failed


def honest(seeds: list[int], out: Path) -> tuple[int, int]:
    false = unjudged = 0
    for seed in seeds:
        for drive in ("pmsm", "spim"):
            r = run_drawn(drive, seed, out)
            print(f"honest {drive} seed {seed}: {r.verdict}" + (f" {r.failed}" if r.failed else "")
                  + (f" NOT JUDGED {r.not_judged}" if r.not_judged else ""), flush=True)
            false += bool(r.failed)
            unjudged += bool(r.not_judged)
    return false, unjudged


def mutants(seeds: list[int], out: Path, json_path: str | None) -> tuple[int, int]:
    from tests.mutants import CHEAT_MUTANTS, mutant_kernel

    table, weak = {}, 0
    for m in CHEAT_MUTANTS:
        for seed in seeds:
            with mutant_kernel(m):
                r = run_drawn(m.drive, seed, out)
            caught = sorted({label(f) for f in r.failed})
            table.setdefault((m.kind, m.drive, m.name, m.what), {})[seed] = (len(r.failed), caught)
            weak += len(r.failed) < 2
            print(f"{m.drive}/{m.name} seed {seed}: {len(r.failed)} criteria {caught}", flush=True)
    print("\n| class | mutant | what it does | criteria failed, seeds " + ", ".join(map(str, seeds))
          + " | what caught it (any seed) |\n|---|---|---|---|---|")
    for (kind, drive, name, what), per in table.items():
        counts = " / ".join(str(per[s][0]) for s in seeds)
        caught = "; ".join(sorted({c for s in seeds for c in per[s][1]}))
        print(f"| {kind} | {drive}/{name} | {what} | {counts} | {caught} |")
    if json_path:
        Path(json_path).write_text(json.dumps({f"{d}/{n}": {str(s): v for s, v in per.items()}
                                               for (_, d, n, _), per in table.items()}, indent=1))
    return sum(len(p) for p in table.values()), weak


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--honest", help="seed range of the honest sweep, e.g. 1-20")
    ap.add_argument("--mutants", help="seed range of the mutant sweep, e.g. 1-5")
    ap.add_argument("--json", help="write the mutant table here")
    args = ap.parse_args()
    result = {}
    with tempfile.TemporaryDirectory(prefix="signatures-") as tmp:
        out = Path(tmp)
        t0 = time.perf_counter()
        runs, drive_s, failed = signature_set(args.seed, out)
        wall = time.perf_counter() - t0
        for f in failed:
            print("FAILED", f)
        print(f"signature set, seed {args.seed}: {runs} runs, {drive_s:.1f} s of drive time in {wall:.1f} s wall")
        result.update(seed=args.seed, runs=runs, wall_s=f"{wall:.1f}", drive_s=f"{drive_s:.1f}",
                      realtime_ratio=f"{drive_s / wall:.2f}", budget_ratio=f"{wall / 120.0:.2f}", failed=len(failed))
        if args.honest:
            seeds = seeds_of(args.honest)
            false, unjudged = honest(seeds, out)
            result.update(honest_seeds=args.honest, honest_false_rejections=false, honest_not_judged=unjudged)
        if args.mutants:
            n, weak = mutants(seeds_of(args.mutants), out, args.json)
            result.update(mutant_runs=n, mutants_weak=weak)
    print("RESULT " + " ".join(f"{k}={v}" for k, v in result.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
