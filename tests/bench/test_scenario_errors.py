"""Invalid scenario files: every problem reported, one `file: field: reason` line each, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.contract.errors import InputError
from bench.inputs.scenario import load_scenario
from tests.scenario_fixtures import write_bench, write_scenario


@pytest.fixture
def bench_dir(tmp_path: Path) -> Path:
    write_bench(tmp_path)
    return tmp_path


def problems(path: Path, **kw) -> list[str]:
    with pytest.raises(InputError) as e:
        load_scenario(path, **kw)
    lines = str(e.value).splitlines()
    assert lines == e.value.problems
    return lines


def one(path: Path, field: str, reason: str) -> None:
    lines = problems(path)
    hits = [l for l in lines if l.startswith(f"{path}: {field}: ") and reason in l]
    assert hits, f"no line for {field!r} containing {reason!r} in {lines}"


CASES = [
    ("unknown top key", "colour = 1\n", "colour", "unknown key"),
    ("unknown speed kind", '[[speed]]\nkind = "jump"\nat_s = 1.0\n', "speed[0].kind", "must be one of"),
    ("unknown speed key", '[[speed]]\nkind = "step"\nat_s = 1.0\nspeed_rpm = 5\nramp_s = 1\n',
     "speed[0].ramp_s", "unknown key"),
    ("speed without units", '[[speed]]\nkind = "step"\nat_s = 1.0\nspeed = 5\n', "speed[0].speed", "unknown key"),
    ("speed missing", '[[speed]]\nkind = "step"\nat_s = 1.0\n', "speed[0].speed_mech_rad_s", "missing"),
    ("both units", '[[speed]]\nkind = "step"\nat_s = 1.0\nspeed_rpm = 5\nspeed_mech_rad_s = 1\n',
     "speed[0].speed_rpm", "not both"),
    ("wrong type", '[[speed]]\nkind = "step"\nat_s = "1"\nspeed_rpm = 5\n', "speed[0].at_s", "must be a number"),
    ("bool as number", '[[speed]]\nkind = "step"\nat_s = true\nspeed_rpm = 5\n', "speed[0].at_s", "must be a number"),
    ("nan", '[[speed]]\nkind = "step"\nat_s = 1.0\nspeed_rpm = nan\n', "speed[0].speed_rpm", "finite"),
    ("inf", '[[speed]]\nkind = "step"\nat_s = 1.0\nspeed_mech_rad_s = inf\n', "speed[0].speed_mech_rad_s", "finite"),
    ("negative time", '[[speed]]\nkind = "step"\nat_s = -1.0\nspeed_rpm = 5\n', "speed[0].at_s", ">= 0"),
    ("at the end", '[[speed]]\nkind = "step"\nat_s = 10.0\nspeed_rpm = 5\n', "speed[0].at_s", "never take effect"),
    ("after the end", '[[load]]\nkind = "torque"\nstart_s = 1.0\nend_s = 11\ntorque_nm = 5\n', "load[0].end_s",
     "after the end of the run"),
    ("ramp backwards", '[[speed]]\nkind = "ramp"\nstart_s = 2.0\nend_s = 1.0\nspeed_rpm = 5\n',
     "speed[0].end_s", "must be after"),
    ("unordered", '[[speed]]\nkind = "step"\nat_s = 3.0\nspeed_rpm = 5\n[[speed]]\nkind = "step"\nat_s = 1.0\n'
     'speed_rpm = 6\n', "speed[1]", "time order"),
    ("overlap", '[[speed]]\nkind = "ramp"\nstart_s = 1.0\nend_s = 3.0\nspeed_rpm = 5\n[[speed]]\nkind = "step"\n'
     'at_s = 2.0\nspeed_rpm = 6\n', "speed[1]", "overlapping speed[0]"),
    ("reversal from zero", '[[speed]]\nkind = "reversal"\nstart_s = 1.0\nend_s = 2.0\n', "speed[0]", "from zero"),
    ("not an array", '[speed]\nkind = "step"\n', "speed", "array of tables"),
    ("load overlap", '[[load]]\nkind = "torque"\nstart_s = 1.0\nend_s = 5.0\ntorque_nm = 1\n[[load]]\n'
     'kind = "brake"\nstart_s = 4.0\ntorque_nm = 1\n', "load[1]", "overlapping"),
    ("crane missing radius", '[[load]]\nkind = "crane"\nstart_s = 0.0\nmass_kg = 15\n', "load[0].drum_radius_m",
     "missing"),
    ("negative brake", '[[load]]\nkind = "brake"\nstart_s = 0.0\ntorque_nm = -1\n', "load[0].torque_nm", ">= 0"),
    ("unknown hook", '[[injection]]\nat_s = 1.0\nname = "warp_drive"\nvalue = 1\n', "injection[0].name",
     "unknown hook 'warp_drive'"),
    ("hook of the other kind", '[[injection]]\nat_s = 1.0\nname = "fw_rr_ohm"\nvalue = 1\n', "injection[0].name",
     "not a parameter of a pmsm drive"),
    ("injection key", '[[injection]]\nat_s = 1.0\nname = "plant_rs"\nfactor = 1\n', "injection[0].factor",
     "unknown key"),
    ("plant factor", '[[injection]]\nat_s = 1.0\nname = "plant_rs"\nvalue = -0.2\n', "injection[0].value",
     "factor on the nominal plant value"),
    ("freeze flag", '[[injection]]\nat_s = 1.0\nname = "freeze_speed_est"\nvalue = 2\n', "injection[0].value",
     "1 (hold) or 0 (release)"),
    ("fw value", '[[injection]]\nat_s = 1.0\nname = "fw_rs_ohm"\nvalue = 0\n', "injection[0].value", "must be > 0"),
    ("unknown signal", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_q"\nwindow_s = [1, 2]\nlimit = 1\n',
     "criteria[0].signal", "unknown signal 'i_q'"),
    ("window beyond", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [1, 20]\n'
     'limit = 1\n', "criteria[0].window_s", "after the end of the run"),
    ("window reversed", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [2, 1]\n'
     'limit = 1\n', "criteria[0].window_s", "must be after start"),
    ("window negative", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [-1, 1]\n'
     'limit = 1\n', "criteria[0].window_s", "negative"),
    ("window shape", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = 1\nlimit = 1\n',
     "criteria[0].window_s", "two numbers"),
    ("unknown kind", '[[criteria]]\nname = "a"\nkind = "vibes"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\nlimit = 1\n',
     "criteria[0].kind", "must be one of"),
    ("kind param", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\nlimit = 1\n'
     'band_pct = 2\n', "criteria[0].band_pct", "unknown key for kind 'peak_abs'"),
    ("missing expected", '[[criteria]]\nname = "a"\nkind = "mean"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\nlimit = 1\n',
     "criteria[0].expected", "missing"),
    ("settling needs a reference", '[[criteria]]\nname = "a"\nkind = "settling_time"\n'
     'signal = "speed_true_mech_rad_s"\nwindow_s = [1, 2]\nlimit = 1\n', "criteria[0]", "exactly one of"),
    ("reference signal", '[[criteria]]\nname = "a"\nkind = "rms"\nsignal = "i_sx_a"\nreference = "nope"\n'
     'window_s = [1, 2]\nlimit = 1\n', "criteria[0].reference", "unknown signal"),
    ("after_s outside", '[[criteria]]\nname = "a"\nkind = "reversal_time"\nsignal = "speed_true_mech_rad_s"\n'
     'window_s = [1, 2]\nafter_s = 3.0\nlimit = 1\n', "criteria[0].after_s", "outside the window"),
    ("negative limit", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\n'
     'limit = -1\n', "criteria[0].limit", ">= 0"),
    ("missing limit", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\n',
     "criteria[0].limit", "missing"),
    ("duplicate names", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\n'
     'limit = 1\n[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sy_a"\nwindow_s = [1, 2]\nlimit = 1\n',
     "criteria[1].name", "duplicate"),
    ("empty known gap", '[[criteria]]\nname = "a"\nkind = "peak_abs"\nsignal = "i_sx_a"\nwindow_s = [1, 2]\n'
     'limit = 1\nknown_gap = " "\n', "criteria[0].known_gap", "reason"),
]


@pytest.mark.parametrize("body,field,reason", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_each_problem_is_one_line(bench_dir, body, field, reason):
    one(write_scenario(bench_dir, body), field, reason)


def test_every_problem_reported_at_once(bench_dir):
    path = write_scenario(bench_dir, """
colour = 1
[[speed]]
kind = "step"
at_s = -1.0
speed_rpm = nan
[[injection]]
at_s = 1.0
name = "warp_drive"
value = 1
[[criteria]]
name = "a"
kind = "peak_abs"
signal = "i_q"
window_s = [1, 20]
limit = 1
""")
    lines = problems(path)
    assert len(lines) == 6, lines
    assert all(l.startswith(f"{path}: ") and l.count(": ") >= 2 for l in lines)


def test_header_problems(tmp_path):
    write_bench(tmp_path)
    path = write_scenario(tmp_path, "", base="""
schema_version = 2
name = ""
bench = "missing-bench.toml"
duration_s = -1
seed = -3
""")
    lines = "\n".join(problems(path))
    for field, reason in [("schema_version", "unsupported version 2"), ("name", "empty"),
                          ("bench", "bench config not found"), ("duration_s", "> 0"), ("seed", ">= 0"),
                          ("limits", "missing table")]:
        assert f"{path}: {field}: " in lines and reason in lines, (field, lines)


def test_limits_problems(bench_dir):
    base = """
schema_version = 1
bench = "bench.toml"
duration_s = 10.0
[[speed]]
kind = "step"
at_s = 1.0
speed_mech_rad_s = 50.0
[limits]
overspeed_mech_rad_s = 40.0
max_duration_s = 5.0
pos_err_max_elec_rad = 4.0
trip = 1
"""
    lines = "\n".join(problems(write_scenario(bench_dir, "", base=base)))
    for field, reason in [("limits.overspeed_mech_rad_s", "peak reference 50"), ("limits.overcurrent_a", "missing"),
                          ("limits.max_duration_s", "shorter than duration_s"),
                          ("limits.pos_err_max_elec_rad", "never trip"), ("limits.trip", "unknown key")]:
        assert reason in lines and field in lines, (field, lines)


def test_plant_injection_refused_on_a_bench_without_them(tmp_path):
    bench = write_bench(tmp_path, plant_injections=False)
    path = write_scenario(tmp_path, '[[injection]]\nat_s = 1.0\nname = "plant_rs"\nvalue = 0.8\n')
    (line,) = problems(path)
    assert line.startswith(f"{path}: injection[0].name: ")
    assert "needs a simulator" in line and str(bench.resolve()) in line and "plant_injections = false" in line


def test_a_third_party_drive_offers_no_drivebench_parameters(tmp_path):
    """A drive is judged by what its EDS offers: a third-party CiA 402 drive has none of drivebench's hooks,
    whatever the scenario asks for; validation says so before anything connects."""
    write_bench(tmp_path, kind=None)
    ok = write_scenario(tmp_path, "", name="ok.toml")
    assert load_scenario(ok).drive_kind is None
    one(write_scenario(tmp_path, '[[injection]]\nat_s = 1.0\nname = "fw_rr_ohm"\nvalue = 1\n'), "injection[0].name",
        "'fw_rr_ohm' is not a parameter of the drive of bench config")
    one(write_scenario(tmp_path, '[[injection]]\nat_s = 1.0\nname = "fw_bogus"\nvalue = 1\n'), "injection[0].name",
        "unknown hook 'fw_bogus' (known: none: the drive offers no parameters)")


def test_bad_files(tmp_path):
    (line,) = problems(tmp_path / "nope.toml")
    assert line == f"{tmp_path / 'nope.toml'}: (file): not found"
    bad = tmp_path / "bad.toml"
    bad.write_text("schema_version = = 1\n")
    (line,) = problems(bad)
    assert line.startswith(f"{bad}: (file): not valid TOML")
    (line,) = problems(tmp_path)
    assert "is a directory" in line


def test_bench_config_problems_are_listed_with_the_bench_file(tmp_path):
    bench = tmp_path / "bench.toml"
    bench.write_text('[bench]\nname = 3\ntiming = "fast"\n[drive]\ntransport = "canopen"\ninterface = "virtual"\n'
                     'channel = "c"\nnode_id = 200\neds = "nowhere.eds"\n[load]\ntransport = "modbus-tcp"\n'
                     'map = "config/load-machines/drivebench-sim.toml"\nhost = "h"\nport = 70000\n')
    lines = "\n".join(problems(write_scenario(tmp_path, "")))
    for field, reason in [("bench.name", "must be a string"), ("bench.timing", "must be one of"),
                          ("drive.node_id", "<= 127"), ("drive.eds", "file not found"), ("load.port", "<= 65535")]:
        assert f"{bench}: {field}: " in lines and reason in lines, (field, lines)
