"""summary.png shows the judgement: a failing criterion's window is shaded red on its signal's panel, a passing one
green; trips and injections become markers; the limit band sits where the limit is in the signal's unit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from bench.outputs.summary_plot import _band, events_of, write_summary_png


def _reddish_share(png: Path) -> float:
    img = imread(png)[..., :3]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return float(np.mean((r > 0.95) & (g < 0.93) & (b < 0.93) & (r - g > 0.04)))


def _greenish_share(png: Path) -> float:
    img = imread(png)[..., :3]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return float(np.mean((g > 0.9) & (g - r > 0.03) & (g - b > 0.03)))


def _draw(tmp_path: Path, name: str, passed: bool, events=()) -> Path:
    t = np.arange(0, 2.0, 1e-3)
    cols = {"speed_true_mech_rad_s": np.sin(t), "i_sx_a": np.zeros_like(t)}
    crit = {"name": "c", "kind": "peak_abs", "signal": "i_sx_a", "window_s": [0.2, 1.8], "value": 0.5,
            "limit": 0.1 if not passed else 1.0, "passed": passed, "status": "pass" if passed else "fail",
            "unit": "A", "known_gap": None}
    return write_summary_png(tmp_path / f"{name}.png", t, cols, "t", criteria=[crit], events=events)


def test_a_failing_window_is_red_and_a_passing_one_green(tmp_path: Path):
    failing, passing = _draw(tmp_path, "fail", False), _draw(tmp_path, "pass", True)
    assert _reddish_share(failing) > 10 * max(_reddish_share(passing), 1e-4)
    assert _greenish_share(passing) > 10 * max(_greenish_share(failing), 1e-4)


def test_trips_and_injections_are_markers():
    record = {"trips": [{"reason": "overspeed", "t_s": 1.25}, {"reason": "x", "t_s": None}],
              "injections_applied": [{"at_s": 0.5, "name": "plant_rs", "value": 0.8, "applied_t_s": 0.5005}]}
    assert events_of(record) == [{"t_s": 1.25, "kind": "trip", "label": "overspeed"},
                                 {"t_s": 0.5005, "kind": "injection", "label": "plant_rs = 0.8"}]


def test_a_trip_line_is_drawn(tmp_path: Path):
    quiet = _draw(tmp_path, "quiet", True)
    tripped = _draw(tmp_path, "tripped", True, events=[{"t_s": 1.0, "kind": "trip", "label": "overspeed"}])
    assert _reddish_share(tripped) > _reddish_share(quiet) + 1e-4


def test_limit_band_only_where_the_limit_is_in_the_signals_unit():
    assert _band({"kind": "peak_abs", "limit": 0.1}, {}) == (-0.1, 0.1)
    assert _band({"kind": "mean", "limit": 0.05}, {"expected": -0.09}) == pytest.approx((-0.14, -0.04))
    assert _band({"kind": "peak_abs", "limit": 0.1}, {"reference": "speed_ref_mech_rad_s"}) is None   # moves
    assert _band({"kind": "speed_error_max_pct", "limit": 1.0}, {}) is None                          # a %
