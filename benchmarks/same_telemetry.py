"""Are two sets of runs the same bit for bit? For a refactoring that must not change behaviour: run the same scenarios
with the same seed on the old code and on the new (each into its own --out), then

    python benchmarks/same_telemetry.py OLD_RUNS NEW_RUNS

pairs the run directories by scenario name and compares every telemetry.parquet column byte for byte (NaN included),
the column set and order, and the record's verdict and criterion values. Prints one line per pair and, last,
`RESULT pairs=N identical=M`; exit 0 only when every pair is identical.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq


def runs_by_scenario(root: Path) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for record in sorted(root.glob("*/record.json")):
        name = json.loads(record.read_text())["scenario"]["name"]
        if name in out:
            raise SystemExit(f"{root}: two runs of scenario {name!r}: give one run per scenario")
        out[name] = record.parent
    return out


def differences(a: Path, b: Path) -> list[str]:
    ta, tb = pq.read_table(a / "telemetry.parquet"), pq.read_table(b / "telemetry.parquet")
    if ta.column_names != tb.column_names:
        return [f"columns differ: {ta.column_names} vs {tb.column_names}"]
    if ta.num_rows != tb.num_rows:
        return [f"rows differ: {ta.num_rows} vs {tb.num_rows}"]
    problems = []
    for name in ta.column_names:
        x, y = ta.column(name).to_numpy(), tb.column(name).to_numpy()
        if x.dtype != y.dtype or x.tobytes() != y.tobytes():
            bad = int(np.sum(~((x == y) | (np.isnan(x) & np.isnan(y))))) if x.dtype == y.dtype else len(x)
            problems.append(f"{name}: {bad} of {len(x)} values differ")
    ra, rb = (json.loads((d / "record.json").read_text()) for d in (a, b))
    if ra["verdict"] != rb["verdict"]:
        problems.append(f"verdict {ra['verdict']} vs {rb['verdict']}")
    ca = [(c["name"], c["value"]) for c in ra["criteria"]]
    cb = [(c["name"], c["value"]) for c in rb["criteria"]]
    if ca != cb:
        problems.append("criterion values differ")
    return problems


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__)
        return 2
    old, new = (runs_by_scenario(Path(p)) for p in argv)
    pairs = sorted(set(old) & set(new))
    identical = 0
    for name in pairs:
        problems = differences(old[name], new[name])
        rows = pq.read_metadata(old[name] / "telemetry.parquet").num_rows
        cols = len(pq.read_schema(old[name] / "telemetry.parquet").names)
        print(f"{name}: {rows} rows x {cols} columns: " + ("identical" if not problems else "; ".join(problems)))
        identical += not problems
    for name in sorted(set(old) ^ set(new)):
        print(f"{name}: only in {'the first' if name in old else 'the second'} set")
    print(f"RESULT pairs={len(pairs)} identical={identical}")
    return 0 if pairs and identical == len(pairs) and set(old) == set(new) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
