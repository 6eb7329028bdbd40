"""The PMSM firmware cannot reach plant state: imports, step-function signature, and replay equivalence."""

from __future__ import annotations

import ast
import inspect
import math
from pathlib import Path

import numpy as np

from sim_backend.drive import make_drive
from sim_backend.inverter import limit_to_linear_range
from sim_backend.pmsm import firmware as fw
from sim_backend.pmsm import kernel as kn
from sim_backend.pmsm import plant as pl

ALLOWED_IMPORTS = {"__future__", "math", "numpy", "numba", "drivers", "drivers.signals",
                   "sim_backend.numerics", "sim_backend.pmsm.numba_cache"}


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(node.module or "")
    return names


def test_firmware_imports_nothing_from_the_plant_or_the_simulator():
    imports = imported_modules(Path(fw.__file__))
    assert imports <= ALLOWED_IMPORTS, imports - ALLOWED_IMPORTS
    source = Path(fw.__file__).read_text()
    for forbidden in ("plant", "kernel", "mechanics", "inverter", "X_W_MECH", "X_PSI"):
        assert f"import {forbidden}" not in source and f"pl.{forbidden}" not in source


def test_step_function_takes_only_measurements_own_state_params_and_time():
    params = list(inspect.signature(fw.firmware_step.py_func).parameters)
    assert params == ["s", "p", "i_a", "i_b", "vdc", "t", "row"]
    # and the drive kernel calls it with ADC outputs only
    call = [n for n in ast.walk(ast.parse(Path(kn.__file__).read_text()))
            if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "firmware_step"]
    assert len(call) == 1
    assert [ast.unparse(a) for a in call[0].args] == ["fw_s", "fw_p", "ia_m", "ib_m", "vdc_m", "t", "row"]


def test_firmware_arrays_do_not_alias_plant_arrays():
    drive = make_drive("config/motors/pmsm-paper.toml", seed=0)
    for fw_array in (drive.firmware_state, drive.firmware_params):
        assert not np.shares_memory(fw_array, drive.plant_state)


def closed_loop(plant_inertia: float, n: int, replay: np.ndarray | None = None):
    """Firmware + plant stepped in Python. With `replay`, the firmware gets those measurements instead of
    its own plant's. Returns (measurements, commands)."""
    p = np.zeros(pl.N_PARAMS)
    p[pl.P_RS], p[pl.P_LS], p[pl.P_FLUX] = 3.58356, 0.02, 0.2592772
    p[pl.P_INERTIA], p[pl.P_VISCOUS], p[pl.P_POLE_PAIRS] = plant_inertia, 2e-4, 3
    x = pl.initial_state(p[pl.P_FLUX], 0.4)
    drive = make_drive("config/motors/pmsm-paper.toml", seed=0, noise=False)
    fp = drive.firmware_params.copy()
    s = fw.new_state(fp[fw.F_FLUX])
    s[fw.S_ENABLE_CMD] = 1.0
    s[fw.S_SPEED_REF_CMD] = 30.0
    row = np.zeros(16)
    measured = np.zeros((n, 3))
    commands = np.zeros((n, 2))
    pending = (0.0, 0.0)
    for k in range(n):
        i_a = x[pl.X_ID]
        i_b = -0.5 * x[pl.X_ID] + 0.5 * math.sqrt(3.0) * x[pl.X_IQ]
        measured[k] = (i_a, i_b, 540.0)
        m = replay[k] if replay is not None else measured[k]
        fw.firmware_step(s, fp, m[0], m[1], m[2], k * 1e-4, row)
        commands[k] = (s[fw.S_M_ALPHA], s[fw.S_M_BETA])
        u_d, u_q = limit_to_linear_range(pending[0] * 540.0, pending[1] * 540.0, 540.0)
        pending = (s[fw.S_M_ALPHA], s[fw.S_M_BETA])
        pl.advance(x, p, u_d, u_q, 0, 0.5, 1e-4, 1)
    return measured, commands


def test_same_measurements_same_commands_whatever_the_plant():
    meas_a, cmd_a = closed_loop(1e-3, 1500)
    meas_b, cmd_b = closed_loop(4e-3, 1500)
    assert not np.allclose(cmd_a, cmd_b)              # a different plant changes what the firmware measures...
    _, cmd_b_replayed = closed_loop(4e-3, 1500, replay=meas_a)
    assert cmd_b_replayed.tobytes() == cmd_a.tobytes()  # ...but given plant A's measurements it acts as for A


def test_the_firmware_never_reads_the_logging_row():
    """The kernel's row holds the previous period's true values when firmware_step runs (it now poisons it with
    NaN first): whatever the row holds, the firmware's state, commands and outputs are the same."""
    drive = make_drive("config/motors/pmsm-paper.toml", seed=0, noise=False)
    fp = drive.firmware_params.copy()
    results = []
    for fill in (0.0, 1e300, math.nan):
        s = fw.new_state(fp[fw.F_FLUX])
        s[fw.S_ENABLE_CMD], s[fw.S_SPEED_REF_CMD] = 1.0, 30.0
        outputs = []
        for k in range(400):
            row = np.full(16, fill)
            fw.firmware_step(s, fp, 0.3 * math.sin(k * 0.01), -0.2, 540.0, k * 1e-4, row)
            outputs.append(row.copy())
        written = np.array(outputs)[:, [i for i in range(16) if i not in (kn.C_SPEED_TRUE, kn.C_POS_ERR,
                                                                          kn.C_FLUX_TRUE, kn.C_TORQUE_LOAD)]]
        assert np.isfinite(written).all()            # every firmware column written every period
        results.append((s.tobytes(), written.tobytes()))
    assert results[0] == results[1] == results[2]


def test_the_kernel_hands_the_firmware_a_poisoned_row():
    source = inspect.getsource(kn.run_steps.py_func)
    before_call = source.split("fw.firmware_step(")[0]
    assert "row[c] = math.nan" in before_call.split("# --- firmware ---")[-1]
