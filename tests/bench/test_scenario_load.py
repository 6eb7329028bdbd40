"""Valid scenario files: profiles, units, loads, injections, limits, criteria as the bench will see them."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import pytest

from bench.inputs.benchconfig import load_bench_config
from drivers.contract.errors import InputError
from bench.inputs.scenario import GRAVITY_M_S2, default_max_duration_s, load_scenario
from drivers.contract.load_map import LoadMode
from tests.scenario_fixtures import REPO, write_bench, write_scenario


@pytest.fixture
def bench_dir(tmp_path: Path) -> Path:
    write_bench(tmp_path)
    return tmp_path


def test_speed_profile_hold_step_ramp_reversal(bench_dir):
    path = write_scenario(bench_dir, """
[[speed]]
kind = "hold"
start_s = 0.0
end_s = 1.0
speed_mech_rad_s = 1.0
[[speed]]
kind = "step"
at_s = 2.0
speed_rpm = 300
[[speed]]
kind = "ramp"
start_s = 4.0
end_s = 5.0
speed_mech_rad_s = 50.0
[[speed]]
kind = "reversal"
start_s = 6.0
end_s = 8.0
""")
    s = load_scenario(path)
    w300 = 300 * math.pi / 30
    assert s.speed_ref_at(0.5) == 1.0
    assert s.speed_ref_at(1.5) == 1.0            # gap holds the previous end value
    assert s.speed_ref_at(2.0) == pytest.approx(w300)
    assert s.speed_ref_at(3.99) == pytest.approx(w300)
    assert s.speed_ref_at(4.5) == pytest.approx((w300 + 50) / 2)   # ramp from the previous value
    assert s.speed_ref_at(5.5) == 50.0
    assert s.speed_ref_at(7.0) == pytest.approx(0.0, abs=1e-12)   # reversal midpoint
    assert s.speed_ref_at(7.5) == pytest.approx(-25.0)
    assert s.speed_ref_at(9.9) == -50.0
    assert [seg.kind for seg in s.speed_segments] == ["hold", "step", "ramp", "reversal"]
    assert s.speed_segments[1].end_s == 4.0                       # open step ends where the next begins


def test_speed_is_zero_before_first_segment(bench_dir):
    s = load_scenario(write_scenario(bench_dir, '[[speed]]\nkind = "step"\nat_s = 1.0\nspeed_mech_rad_s = 5.0\n'))
    assert s.speed_ref_at(0.0) == 0.0
    assert s.speed_ref_at(0.999) == 0.0
    assert s.speed_ref_at(1.0) == 5.0


def test_load_profile_kinds_and_steps(bench_dir):
    s = load_scenario(write_scenario(bench_dir, """
[[load]]
kind = "torque"
start_s = 1.0
torque_nm = 2.0
[[load]]
kind = "viscous"
start_s = 3.0
end_s = 4.0
coeff_nm_per_rad_s = 0.05
[[load]]
kind = "brake"
start_s = 5.0
torque_nm = 1.5
[[load]]
kind = "crane"
start_s = 7.0
mass_kg = 15.0
drum_radius_m = 0.02
"""))
    assert s.load_at(0.5) == (LoadMode.TORQUE, 0.0)
    assert s.load_at(1.0) == (LoadMode.TORQUE, 2.0)
    assert s.load_at(2.99) == (LoadMode.TORQUE, 2.0)      # open segment runs to the next one
    assert s.load_at(3.5) == (LoadMode.VISCOUS, 0.05)
    assert s.load_at(4.5) == (LoadMode.TORQUE, 0.0)       # gap after an explicit end_s: no load
    assert s.load_at(6.0) == (LoadMode.BRAKE, 1.5)
    mode, value = s.load_at(9.0)
    assert mode == LoadMode.TORQUE and value == pytest.approx(15.0 * GRAVITY_M_S2 * 0.02)
    assert s.load_at(10.0) == (LoadMode.TORQUE, 0.0)


def test_injections_sorted_and_plant_subset(bench_dir):
    s = load_scenario(write_scenario(bench_dir, """
[[injection]]
at_s = 3.0
name = "plant_rs"
value = 0.8
[[injection]]
at_s = 1.0
name = "flux_est_scale"
value = 1.1
[[injection]]
at_s = 2.0
name = "fw_rs_ohm"
value = 3.0
"""))
    assert [i.at_s for i in s.injections] == [1.0, 2.0, 3.0]
    assert [i.name for i in s.simulator_injections()] == ["plant_rs"]


def test_limits_defaults_and_units(bench_dir):
    base = """
schema_version = 1
bench = "bench.toml"
duration_s = 4.0
[limits]
overspeed_rpm = 3000
overcurrent_a = 5.0
"""
    s = load_scenario(write_scenario(bench_dir, "", base=base, name="my-scenario.toml"))
    assert s.name == "my-scenario"                         # defaults to the file stem
    assert s.seed is None and s.description == ""
    assert s.limits.overspeed_mech_rad_s == pytest.approx(100 * math.pi)
    assert s.limits.max_duration_s == default_max_duration_s(4.0)
    assert s.limits.pos_err_max_elec_rad is None and s.limits.vdc_max_v is None


def test_criteria_params_and_hash(bench_dir):
    path = write_scenario(bench_dir, """
[[criteria]]
name = "flux offset"
kind = "mean"
signal = "flux_est_wb"
reference = "flux_true_wb"
expected = 0.0
window_s = [5, 10]
limit = 0.01
known_gap = "no R_s adaptation"
""")
    s = load_scenario(path)
    (c,) = s.criteria
    assert c.window_s == (5.0, 10.0) and c.limit == 0.01 and c.known_gap == "no R_s adaptation"
    assert c.params == {"reference": "flux_true_wb", "expected": 0.0}
    assert s.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert s.bench == (bench_dir / "bench.toml").resolve()
    assert s.drive_kind == "pmsm"


def test_bench_override(bench_dir, tmp_path_factory):
    other = tmp_path_factory.mktemp("other")
    override = write_bench(other, plant_injections=False)
    path = write_scenario(bench_dir, '[[injection]]\nat_s = 1.0\nname = "plant_rs"\nvalue = 0.8\n')
    assert load_scenario(path).bench == (bench_dir / "bench.toml").resolve()
    with pytest.raises(InputError) as e:
        load_scenario(path, bench=override)
    assert "plant_injections = false" in str(e.value)


@pytest.mark.parametrize("example", sorted((REPO / "scenarios" / "examples").glob("*.toml")), ids=lambda p: p.name)
def test_examples_are_valid(example, tmp_path):
    """Each example validates against the repo bench it names, and every criterion reads signals that bench
    measures (so the example can pass, not only parse)."""
    from bench.inputs.benchconfig import measurable_signals
    from bench.inputs.criteria import signals_of

    s = load_scenario(example)
    assert s.criteria and s.duration_s > 0 and s.bench.name.startswith("sim-")
    measurable = measurable_signals(load_bench_config(s.bench))
    for spec in s.criteria:
        assert set(signals_of(spec)) <= measurable, (spec.name, set(signals_of(spec)) - measurable)


def test_repo_bench_configs_parse_when_their_files_exist():
    for path in sorted((REPO / "config" / "benches").glob("*.toml")):
        try:
            cfg = load_bench_config(path)
        except InputError as e:
            assert all("file not found" in line for line in e.problems), str(e)
            continue
        assert cfg.path == str(path.resolve())
        if cfg.drive["transport"] == "canopen":
            assert Path(cfg.drive["eds"]).is_absolute()
        if cfg.simulator is not None:
            assert Path(cfg.simulator["motor"]).is_absolute()
