"""The efficiency map from runs' loss_pct criteria on an analyser: points, seeds averaged, uncertainty, the plot."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bench.outputs.efficiency_map import main, map_points


def _run(root, seed, points, u=0.5):
    run = root / f"run{seed}"
    (run / "instruments").mkdir(parents=True)
    t = np.arange(0, 1.0 * len(points), 0.1)
    cols = {k: np.zeros_like(t) for k in ("p_dc_w", "p_shaft_w", "speed_shaft_mech_rad_s", "torque_shaft_nm")}
    criteria = []
    for i, (w, q, eff) in enumerate(points):
        sel = (t >= i) & (t < i + 1)
        out = w * q
        cols["speed_shaft_mech_rad_s"][sel], cols["torque_shaft_nm"][sel] = w, q
        cols["p_shaft_w"][sel], cols["p_dc_w"][sel] = out, out / (eff / 100 + 0.001 * seed)
        e = 100 * out / (out / (eff / 100 + 0.001 * seed))
        criteria.append({"name": f"map ({w},{q})", "kind": "loss_pct", "signal": "analyser:p_dc_w",
                         "window_s": [i + 0.2, i + 0.8], "value": 100 - e + u, "status": "pass"})
    pq.write_table(pa.table({"t_s": t, **cols}), run / "instruments/analyser.parquet")
    (run / "record.json").write_text(json.dumps({"scenario": {"name": "map"}, "seed": seed, "criteria": criteria,
        "lab_instruments": {"analysers": {"analyser": {"file": "instruments/analyser.parquet"}}}}))


def test_points_are_read_per_window_and_seeds_averaged_and_the_map_is_drawn(tmp_path, capsys):
    grid = [(w, q, 80 + w / 20 + q) for w in (50.0, 150.0, 250.0) for q in (1.0, 2.0, 3.0)]
    for seed in (1, 2):
        _run(tmp_path, seed, grid)
    rows = map_points(tmp_path)
    assert len(rows) == 9 and all(r["runs"] == 2 for r in rows)
    first = next(r for r in rows if r["point"] == "map (50.0,1.0)")
    assert first["speed_mech_rad_s"] == pytest.approx(50.0) and first["torque_nm"] == pytest.approx(1.0)
    assert first["efficiency_pct"] == pytest.approx(83.5 + 0.15, abs=1e-6)      # seeds +0.1 and +0.2 points
    assert first["seed_spread_pct"] == pytest.approx(0.1, abs=1e-6)
    assert first["uncertainty_pct"] == pytest.approx(0.5)
    assert main([str(tmp_path), "--out", str(tmp_path / "m")]) == 0
    assert (tmp_path / "m.png").stat().st_size > 10_000 and (tmp_path / "m.csv").read_text().count("\n") == 10
    assert "9 points" in capsys.readouterr().out


def test_too_few_points_is_one_line_and_exit_2(tmp_path, capsys):
    _run(tmp_path, 1, [(50.0, 1.0, 90.0)])
    assert main([str(tmp_path)]) == 2
    assert "a map needs at least 3" in capsys.readouterr().err
