"""The cheat mutants of issue 36 (tests/mutants.py CHEAT_MUTANTS): every class has several variants, the edits still
find their targets exactly once in today's firmware and kernel (no compilation: that is the slow sweep's), and the
settings name only the generic block's slots."""

from __future__ import annotations

import importlib
from collections import Counter
from pathlib import Path

from tests.mutants import CHEAT_MUTANTS, CHEAT_SLOTS, _apply

CLASSES = {"partial sensor use", "sensor in transients only", "sensor in a region only", "test-aware firmware"}


def test_every_class_of_the_issue_has_several_variants():
    kinds = Counter(m.kind for m in CHEAT_MUTANTS)
    assert set(kinds) == CLASSES
    assert all(n >= 2 for n in kinds.values()), kinds
    assert Counter(m.drive for m in CHEAT_MUTANTS if m.kind == "sensor in a region only")["spim"] >= 3
    assert len({(m.drive, m.name) for m in CHEAT_MUTANTS}) == len(CHEAT_MUTANTS)


def test_the_cheat_edits_apply_once_to_todays_firmware_and_kernel():
    for drive in ("pmsm", "spim"):
        mutant = next(m for m in CHEAT_MUTANTS if m.drive == drive)
        for module, edits in (("firmware", mutant.firmware), ("kernel", mutant.kernel)):
            source = Path(importlib.import_module(f"sim_backend.{drive}.{module}").__file__).read_text()
            edited = _apply(source, edits, f"{drive} {module}")
            assert edited != source
        assert all(m.firmware is mutant.firmware for m in CHEAT_MUTANTS if m.drive == drive)   # one compilation


def test_the_settings_name_the_generic_blocks_slots():
    for m in CHEAT_MUTANTS:
        settings = dict(m.cheat)
        assert set(settings) <= set(CHEAT_SLOTS) and settings["MODE"] >= 1, m.name
