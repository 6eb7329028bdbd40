"""Every example scenario passes on the bench it names, with its own seed: they are what a newcomer copies first,
so one that fails out of the box teaches the wrong thing (pmsm-start-reversal did: a 2 % flux band its noise left)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.run.orchestrator import run_scenario

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((REPO / "scenarios" / "examples").glob("*.toml"))


def test_there_are_examples():
    assert len(EXAMPLES) >= 4


@pytest.mark.slow
@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.stem)
def test_every_example_passes_on_its_own_bench(example: Path, tmp_path: Path):
    result = run_scenario(example, out_root=tmp_path / "runs", rerun_mode="off")
    failing = [(c["name"], c["value"], c["limit"], c.get("detail")) for c in result.record["criteria"]
               if not c["passed"]]
    assert result.verdict == "pass", (result.record.get("abort_reason"), failing)
    assert result.record["criteria"], "an example with no criteria judges nothing"
