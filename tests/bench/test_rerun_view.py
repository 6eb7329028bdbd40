"""Rerun stream: run.rrd readable with the signal entities, batching, flux phasors, fallbacks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.outputs.rerun_view import RerunStream, default_blueprint, rrd_entity_paths, viewer_reachable
from drivers.contract.signals import SIGNAL_NAMES


def block(t0: float, n: int = 1000, dt: float = 1e-4) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    t = t0 + dt * (1 + np.arange(n))
    cols = {name: np.full(n, float(i)) for i, name in enumerate(SIGNAL_NAMES)}
    cols["pos_est_elec_rad"] = (300.0 * t + np.pi) % (2 * np.pi) - np.pi
    cols["pos_err_elec_rad"] = np.full(n, 0.1)
    cols["flux_est_wb"] = np.full(n, 0.25)
    cols["flux_true_wb"] = np.full(n, 0.26)
    return t, cols


def read_store(path):
    from rerun.chunk import RrdReader

    return RrdReader(path).store()


def test_saved_rrd_has_every_signal_and_the_flux_vectors(tmp_path):
    path = tmp_path / "run.rrd"
    stream = RerunStream("save", path, recording_name="test-run")
    for k in range(5):
        t, cols = block(0.1 * k)
        stream.log_columns(t, cols)
    stream.close()
    paths = rrd_entity_paths(path)
    assert {f"/{name}" for name in SIGNAL_NAMES} <= paths
    assert {"/flux_vector/true", "/flux_vector/estimated"} <= paths
    rows: dict[str, int] = {}
    for line in read_store(path).summary().splitlines():  # one line per chunk
        entity, count = line.split()[0], line.split()[1]
        if count.startswith("rows=") and "static=False" in line:
            rows[entity] = rows.get(entity, 0) + int(count[5:])
            if entity == "/speed_est_mech_rad_s":
                assert "timelines=['t_s']" in line   # drive time
    assert rows["/speed_est_mech_rad_s"] == 5000             # every sample of every signal
    assert rows["/flux_vector/true"] == 51    # phasors at 100 Hz of drive time: t in (0, 0.5] -> bins 0..50


def test_flux_vector_geometry(tmp_path, monkeypatch):
    stream = RerunStream("save", tmp_path / "x.rrd")
    sent = {}
    monkeypatch.setattr(stream._rec, "send_columns",
                        lambda entity, indexes, columns: sent.setdefault(entity, list(columns)))
    t, cols = block(0.0, n=200)
    stream._send_flux_vectors(t, cols)
    est = np.asarray(sent["flux_vector/estimated"][0].as_arrow_array().to_pylist()[0][0])
    true = np.asarray(sent["flux_vector/true"][0].as_arrow_array().to_pylist()[0][0])
    assert math.isclose(np.hypot(*est), 0.25 / 0.26, rel_tol=1e-6)   # per unit of the true flux
    assert math.isclose(np.hypot(*true), 1.0, rel_tol=1e-6)
    angle = math.atan2(true[1], true[0]) - math.atan2(est[1], est[0])
    assert math.isclose((angle + math.pi) % (2 * math.pi) - math.pi, 0.1, abs_tol=1e-6)  # = pos_err
    stream._rec = None


def test_rows_are_batched_by_drive_time(tmp_path, monkeypatch):
    stream = RerunStream("save", tmp_path / "x.rrd", batch_s=0.1, min_wall_interval_s=0.0)
    batches = []
    monkeypatch.setattr(stream, "_send", lambda t, cols: batches.append(len(t)))
    for k in range(1000):  # 1 s of 1 kHz live samples
        stream.log_rows([k * 1e-3], [{"speed_est_mech_rad_s": float(k)}])
    stream.flush()
    assert sum(batches) == 1000
    assert all(n >= 100 for n in batches[:-1])  # >= 100 ms of drive time per batch
    stream._rec = None


def test_off_writes_nothing(tmp_path):
    stream = RerunStream("off", tmp_path / "run.rrd")
    stream.log_columns(*block(0.0))
    stream.close()
    assert not stream.enabled and not (tmp_path / "run.rrd").exists()


def test_spawn_without_display_saves_and_says_so(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    said = []
    stream = RerunStream("spawn", tmp_path / "run.rrd", warn=said.append)
    stream.log_columns(*block(0.0))
    stream.close()
    assert len(said) == 1 and "no display" in said[0]
    assert stream.sinks == ["file"]
    assert "/vdc_v" in rrd_entity_paths(tmp_path / "run.rrd")


def test_spawn_failure_falls_back(tmp_path, monkeypatch):
    import rerun as rr

    monkeypatch.setenv("DISPLAY", ":99")
    def no_viewer(**kwargs):
        raise RuntimeError("no rerun binary")

    monkeypatch.setattr(rr, "spawn", no_viewer)
    said = []
    stream = RerunStream("spawn", tmp_path / "run.rrd", warn=said.append)
    stream.close()
    assert stream.sinks == ["file"] and "could not spawn" in said[0]


def test_viewer_reachable_on_closed_port():
    assert not viewer_reachable("rerun+http://127.0.0.1:9/proxy", timeout_s=0.5)


def test_blueprint_shows_every_recorded_signal_once_and_the_flux_phasors():
    from bench.outputs.rerun_view import PLOTS

    views = default_blueprint().root_container.contents
    shown = [entity for view in views[:-2] for entity in view.contents if not entity.startswith("/limits/")]
    assert sorted(shown) == sorted(f"/{name}" for _, names in PLOTS for name in names)
    assert views[-2].origin == "/flux_vector"
    assert views[-1].contents == ["/events/**", "/criteria/**"]          # trips, injections, verdicts
    # a run that records only some signals gets views of those only (no empty plots, no phasor without flux)
    few = default_blueprint(["speed_ref_mech_rad_s", "speed_est_mech_rad_s"]).root_container.contents
    assert [v.contents for v in few[:-1]] == [["/speed_ref_mech_rad_s", "/speed_est_mech_rad_s",
                                               "/limits/speed_ref_mech_rad_s/**", "/limits/speed_est_mech_rad_s/**"]]


def test_bad_mode():
    with pytest.raises(ValueError):
        RerunStream("live", None)


def test_trips_injections_and_the_judgement_are_in_the_recording(tmp_path):
    path = tmp_path / "run.rrd"
    recorded = ("speed_est_mech_rad_s", "i_sx_a")
    stream = RerunStream("save", path, recorded=recorded)
    t = np.arange(1, 1001) * 1e-3
    stream.log_columns(t, {"speed_est_mech_rad_s": np.sin(t), "i_sx_a": np.zeros_like(t)})
    stream.log_event(0.5, "injection", "plant_rs = 0.8")
    stream.log_event(0.9, "trip", "overspeed: 31 > 30 rad/s")
    stream.log_judgement([
        {"name": "i_sx held", "kind": "peak_abs", "signal": "i_sx_a", "window_s": [0.2, 0.8], "value": 0.01,
         "limit": 0.1, "passed": True, "status": "pass", "unit": "A"},
        {"name": "speed", "kind": "speed_error_max_pct", "signal": "speed_est_mech_rad_s", "window_s": [0.2, 0.8],
         "value": 5.0, "limit": 1.0, "passed": False, "status": "fail", "unit": "%"}], params={})
    stream.close()
    paths = rrd_entity_paths(path)
    assert {"/events/injection", "/events/trip", "/criteria/0", "/criteria/1"} <= paths
    assert {"/limits/i_sx_a/0/low", "/limits/i_sx_a/0/high"} <= paths          # a band in the signal's unit
    assert not any(p.startswith("/limits/speed_est_mech_rad_s") for p in paths)  # a % limit: no band
    # nothing declared that this bench never fills: no empty reference currents, estimated torque or phasor
    assert not {"/i_sx_ref_a", "/i_sy_ref_a", "/torque_est_nm", "/flux_vector/true"} & paths
    store = read_store(path).summary()
    assert "/criteria/1" in store and "/events/trip" in store
