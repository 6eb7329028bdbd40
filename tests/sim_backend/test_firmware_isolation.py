"""The PMSM firmware cannot reach plant state: imports, step-function signature, and replay equivalence."""

from __future__ import annotations

import ast
import inspect
import math
from pathlib import Path

import numpy as np
import pytest

from sim_backend.drive import make_drive
from sim_backend.three_phase_inverter import limit_to_linear_range
from sim_backend.pmsm import firmware as fw
from sim_backend.pmsm import kernel as kn
from sim_backend.pmsm import plant as pl

ALLOWED_IMPORTS = {"__future__", "math", "numpy", "numba", "drivers.contract", "drivers.contract.signals",
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


@pytest.mark.slow
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


# ---- the SPIM firmware: the same three guarantees ----

SPIM_ALLOWED_IMPORTS = {"__future__", "math", "numpy", "numba", "sim_backend.numerics"}


def test_spim_firmware_imports_nothing_from_the_plant_or_the_simulator():
    from sim_backend.spim import firmware as sfw
    imports = imported_modules(Path(sfw.__file__))
    assert imports <= SPIM_ALLOWED_IMPORTS, imports - SPIM_ALLOWED_IMPORTS
    source = Path(sfw.__file__).read_text()
    for forbidden in ("plant", "kernel", "mechanics", "inverter", "X_WM", "X_PSD", "X_PRD"):
        assert f"import {forbidden}" not in source and f"pl.{forbidden}" not in source


def test_spim_step_function_takes_only_measurements_own_state_and_params():
    from sim_backend.spim import firmware as sfw
    assert list(inspect.signature(sfw.firmware_step.py_func).parameters) == ["s", "f", "isd_m", "isq_m", "vdc_m",
                                                                              "row"]


def spim_closed_loop(rr_factor: float, n: int, replay: np.ndarray | None = None):
    """The SPIM kernel's loop in Python (plant, inverter, ADC, firmware): measurements and commands per period.
    With `replay`, the firmware is fed those measurements instead of this plant's."""
    from sim_backend.spim import firmware as sfw
    from sim_backend.spim import inverter as sinv
    from sim_backend.spim import kernel as skn
    from sim_backend.spim import plant as spl
    drive = make_drive("config/motors/spim-paper.toml", seed=0, noise=False)
    if rr_factor != 1.0:
        drive.set_plant_param("plant_rr", rr_factor)
    x, pp, ip, fs, fp, ks = drive._x, drive._pp, drive._ip, drive._fs, drive._fp, drive._ks
    fs[sfw.S_ENABLED] = 1.0
    fs[sfw.S_SPEED_TARGET] = 50.0
    row = np.zeros(16)
    measured, commands = np.zeros((n, 3)), np.zeros((n, 4))
    for k in range(n):
        open_d, open_q = x[spl.X_OPEN_D] != 0.0, x[spl.X_OPEN_Q] != 0.0
        isd, isq, _, _ = spl.currents(x[spl.X_PSD], x[spl.X_PSQ], x[spl.X_PRD], x[spl.X_PRQ], pp, open_d, open_q)
        measured[k] = (sinv.adc(isd, 0.0, 0.0, ip[sinv.I_LSB_I]), sinv.adc(isq, 0.0, 0.0, ip[sinv.I_LSB_I]),
                       sinv.adc(ip[sinv.I_VDC], 0.0, 0.0, ip[sinv.I_LSB_VDC]))
        m = replay[k] if replay is not None else measured[k]
        gates_now = ks[skn.K_GATES] != 0.0
        vsd, vsq = sinv.winding_voltages(ks[skn.K_DA], ks[skn.K_DB], ks[skn.K_DC], isd, isq, not gates_now, ip)
        gates_next, da, db, dc = sfw.firmware_step(fs, fp, m[0], m[1], m[2], row)
        commands[k] = (gates_next, da, db, dc)
        if gates_now:
            x[spl.X_OPEN_D] = x[spl.X_OPEN_Q] = 0.0
        spl.advance(x, pp, vsd, vsq, fp[sfw.F_TS], drive._substeps, not gates_now)
        ks[:] = (1.0 if gates_next else 0.0, da, db, dc)
    return measured, commands


def test_spim_same_measurements_same_commands_whatever_the_plant():
    n = 4000                                          # past the magnetising time: the speed loop runs too
    meas_a, cmd_a = spim_closed_loop(1.0, n)
    meas_b, cmd_b = spim_closed_loop(1.4, n)
    assert cmd_a[:, 0].any()                          # the gates came on
    assert not np.allclose(cmd_a, cmd_b)              # a rotor 40 % more resistive changes what the firmware sees...
    _, cmd_b_replayed = spim_closed_loop(1.4, n, replay=meas_a)
    assert cmd_b_replayed.tobytes() == cmd_a.tobytes()  # ...but given plant A's measurements it acts as for A
