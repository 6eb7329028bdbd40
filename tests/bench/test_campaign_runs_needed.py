"""A campaign's report says how many runs its acceptance rate needs: the fewest judged runs, all passing, whose
Wilson lower bound reaches the rate (one fewer does not)."""

from __future__ import annotations

import pytest

from bench.faces.campaign import runs_needed, wilson_interval


@pytest.mark.parametrize("rate, expected", [(0.5, 4), (0.8, 16), (0.9, 35), (0.95, 73)])
def test_runs_needed_is_the_first_count_whose_wilson_bound_meets_the_rate(rate, expected):
    n = runs_needed(rate, 0.95)
    assert n == expected
    assert wilson_interval(n, n, 0.95)[0] >= rate > wilson_interval(n - 1, n - 1, 0.95)[0]


def test_a_rate_of_one_can_never_be_met():
    assert runs_needed(1.0) is None


def test_the_report_says_it(tmp_path):
    import dataclasses
    from pathlib import Path

    from bench.faces.campaign import Acceptance, load_campaign
    from bench.faces.campaign_run import _write_report, summarize

    repo = Path(__file__).resolve().parents[2]
    camp = dataclasses.replace(load_campaign(repo / "campaigns/paper-seeds.toml"),
                               acceptance=Acceptance(rule="wilson", min_pass_rate=0.9, confidence=0.95))
    rows = [{"scenario": "s.toml", "seed": 1, "axes": {}, "verdict": "pass", "run_dir": str(tmp_path), "error": None,
             "criteria": [{"name": "x", "status": "pass", "value": 1.0, "limit": 2.0}]}]
    _write_report(camp, tmp_path, rows, summarize(camp, rows), False)
    assert "met only from 35 judged runs of a criterion, every one passing" in (tmp_path / "report.md").read_text()
