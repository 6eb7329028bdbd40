"""Drawn shaft signatures on the instruments rigs (issue 36), the small CI subset: the honest PMSM and SPIM firmware
pass on seed 1, and one cheat of every class (tests/mutants.py CHEAT_MUTANTS) per drive fails at least two criteria
there. The full sweeps (honest seeds 1-20, every cheat on seeds 1-5) are `python benchmarks/signatures.py --honest 1-20
--mutants 1-5`, quoted in docs/shaft-signatures.md."""

from __future__ import annotations

import hashlib
import json

import pytest

from bench.signatures.run import run_drawn
from tests.mutants import CHEAT_MUTANTS, mutant_kernel

ONE_PER_CLASS = {
    "pmsm": ["blend_10pct", "encoder_0.3s_after_ref_change", "encoder_above_2.5A", "honest_after_first_write"],
    "spim": ["tach_blend_10pct", "watchdog_1rads", "tach_at_start_and_ramps", "honest_after_first_write"],
}


@pytest.mark.slow
@pytest.mark.parametrize("drive", ["pmsm", "spim"])
def test_the_honest_firmware_passes_its_drawn_signature_and_one_cheat_per_class_does_not(drive, tmp_path):
    honest = run_drawn(drive, 1, tmp_path)
    assert honest.verdict == "pass" and not honest.failed and not honest.not_judged, honest.failed
    measured = [c for c in honest.criteria if c.signal == "pos_err_elec_rad"]     # derived after the run (DAQ)
    assert len(measured) == (4 if drive == "pmsm" else 0) and all(c.status == "pass" for c in measured)
    assert (honest.run_dir / "drawn.toml").is_file() and (honest.run_dir / "drawn.json").is_file()
    record = json.loads((honest.run_dir / "record.json").read_text())
    assert record["signature_draws"]["points"] == json.loads(json.dumps(honest.points))   # the draws, in the record
    assert record["verdict"] == "pass" and record["seed"] == 1
    assert hashlib.sha256((honest.run_dir / "drawn.toml").read_bytes()).hexdigest() == record["scenario"]["sha256"]
    weak = {}
    for name in ONE_PER_CLASS[drive]:
        mutant = next(m for m in CHEAT_MUTANTS if m.drive == drive and m.name == name)
        with mutant_kernel(mutant):
            result = run_drawn(drive, 1, tmp_path)
        if len(result.failed) < 2:
            weak[name] = result.failed
    assert not weak, f"cheats rejected fewer than twice on seed 1: {weak}"
    kinds = {m.kind for m in CHEAT_MUTANTS if m.drive == drive and m.name in ONE_PER_CLASS[drive]}
    assert len(kinds) == 4
