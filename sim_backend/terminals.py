"""What a lab's instruments see of a simulated drive, per control period: motor-terminal voltages and currents, the
DC link, the shaft. Fed to the simulated power analyser and scope (sim_backend.analyser_sim, scope_sim); the
firmware never sees any of it and the bench only through those instruments' SCPI.

`TappedModel` wraps a PMSM or SPIM DriveModel and steps it one control period at a time (the same arithmetic and the
same random draws as n at once: bit for bit the same telemetry), reading after each period the plant's state:
- the winding voltage averaged over the period, from the plant's own equation u = R i + d(psi_s)/dt:
  u_k = R (i_k + i_k+1)/2 + (psi_s,k+1 - psi_s,k) / T (an averaged inverter holds u through the period, so this is
  what the analyser's and the scope's anti-aliased inputs see; with the gates off it is the back-EMF);
- the winding currents averaged over the period (trapezoid); the DC-link voltage and current (sum over legs of duty x leg current);
- the shaft speed and torque (the load machine's torque on the shaft) and the true rotor angle (for tests only).
PMSM windings are the three phases a, b, c (star, line-to-neutral; powers are u_a i_a + u_b i_b + u_c i_c); SPIM
windings are the main and auxiliary windings (their own terminals).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from drivers.contract.signals import SIGNAL_INDEX

_SPEED = SIGNAL_INDEX["speed_true_mech_rad_s"]
_TORQUE = SIGNAL_INDEX["torque_load_nm"]
_POS_EST = SIGNAL_INDEX["pos_est_elec_rad"]
_POS_ERR = SIGNAL_INDEX["pos_err_elec_rad"]
SQRT3_2 = math.sqrt(3.0) / 2.0


@dataclass
class TerminalBlock:
    t_s: np.ndarray               # (n,) end of each control period, drive clock
    u_v: np.ndarray               # (n, W) winding voltages averaged over the period
    i_a: np.ndarray               # (n, W) winding currents averaged over the period (as u)
    vdc_v: np.ndarray             # (n,)
    idc_a: np.ndarray             # (n,) averaged over the period
    speed_mech_rad_s: np.ndarray  # (n,)
    torque_shaft_nm: np.ndarray   # (n,)
    angle_elec_rad: np.ndarray    # (n,) true field angle (PMSM magnet, SPIM stator flux) at the period's START: tests
    flux_wb: np.ndarray           # (n,) true flux magnitude (at the period's start): tests only


class TappedModel:
    """A DriveModel whose terminals are watched; `listeners` receive each stepped TerminalBlock."""

    def __init__(self, model: Any):
        self._model = model
        self.kind = getattr(model, "kind", "")
        if self.kind not in ("pmsm", "spim"):
            raise ValueError(f"no terminal model for a {self.kind or type(model).__name__} drive")
        self.windings = ("a", "b", "c") if self.kind == "pmsm" else ("main", "aux")
        self.listeners: list[Callable[[TerminalBlock], None]] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._model, name)

    @property
    def time_s(self) -> float:
        return self._model.time_s

    def step(self, n: int) -> np.ndarray:
        m = self._model
        if not self.listeners or n == 0:
            return m.step(n)
        dt = float(m.control_period_s)
        states, regs, rows = [], [], []
        for _ in range(n):
            states.append(m._x.copy())
            regs.append(self._registers())
            rows.append(m.step(1))
        states.append(m._x.copy())
        block = np.concatenate(rows)
        x, r = np.array(states), np.array(regs)
        u, i, vdc, idc = self._pmsm(x, r, dt) if self.kind == "pmsm" else self._spim(x, r, dt)
        t = m.time_s - dt * np.arange(n - 1, -1, -1)
        angle = np.angle(np.exp(1j * (block[:, _POS_EST] + block[:, _POS_ERR])))
        tb = TerminalBlock(t, u, i, vdc, idc, block[:, _SPEED].copy(), block[:, _TORQUE].copy(), angle,
                           block[:, SIGNAL_INDEX["flux_true_wb"]].copy())
        for listener in self.listeners:
            listener(tb)
        return block

    # ---- per kind ----
    def _registers(self) -> list[float]:
        """The inverter registers that drive the coming period."""
        m = self._model
        if self.kind == "pmsm":
            from sim_backend.pmsm import firmware as fw
            from sim_backend.pmsm import kernel as kn
            on = m._inv_s[kn.R_GATES] != 0.0 and m._fw_s[fw.S_RUNNING] != 0.0
            return [m._inv_s[kn.R_M_ALPHA], m._inv_s[kn.R_M_BETA], 1.0 if on else 0.0]
        from sim_backend.spim import kernel as kn
        return [m._ks[kn.K_DA], m._ks[kn.K_DB], m._ks[kn.K_DC], m._ks[kn.K_GATES]]

    def _pmsm(self, x: np.ndarray, r: np.ndarray, dt: float):
        from sim_backend.pmsm import kernel as kn
        from sim_backend.pmsm import plant as pl
        p = self._model._plant_p
        i = x[:, [pl.X_ID, pl.X_IQ]]
        psi = p[pl.P_LS] * i + x[:, [pl.X_PSI_D, pl.X_PSI_Q]]
        i_mean = 0.5 * (i[:-1] + i[1:])
        ua, ub = (p[pl.P_RS] * i_mean + np.diff(psi, axis=0) / dt).T
        i1 = i_mean
        u = np.column_stack((ua, -0.5 * ua + SQRT3_2 * ub, -0.5 * ua - SQRT3_2 * ub))
        cur = np.column_stack((i1[:, 0], -0.5 * i1[:, 0] + SQRT3_2 * i1[:, 1], -0.5 * i1[:, 0] - SQRT3_2 * i1[:, 1]))
        vdc = float(self._model._inv_p[kn.I_VDC])
        # the inverter's DC-link current: the applied vector (SVPWM-limited) times the current, over vdc
        applied = r[:, :2] * vdc
        mag = np.hypot(applied[:, 0], applied[:, 1])
        applied *= np.minimum(1.0, (vdc / math.sqrt(3.0)) / np.maximum(mag, 1e-12))[:, None]
        p_dc = 1.5 * np.sum(applied * i_mean, axis=1) * r[:, 2]
        return u, cur, np.full(len(r), vdc), p_dc / vdc

    def _spim(self, x: np.ndarray, r: np.ndarray, dt: float):
        from sim_backend.spim import inverter as inv
        from sim_backend.spim import plant as pl
        p = self._model._pp
        isd = np.where(x[:, pl.X_OPEN_D] != 0.0, 0.0, p[pl.P_INV_D_A] * x[:, pl.X_PSD] - p[pl.P_INV_D_B] * x[:, pl.X_PRD])
        isq = np.where(x[:, pl.X_OPEN_Q] != 0.0, 0.0, p[pl.P_INV_Q_A] * x[:, pl.X_PSQ] - p[pl.P_INV_Q_B] * x[:, pl.X_PRQ])
        i = np.column_stack((isd, isq))
        i_mean = 0.5 * (i[:-1] + i[1:])
        psi = x[:, [pl.X_PSD, pl.X_PSQ]]
        u = i_mean * np.array([p[pl.P_RSD], p[pl.P_RSQ]]) + np.diff(psi, axis=0) / dt
        vdc = float(self._model._ip[inv.I_VDC])
        idc = (r[:, 0] * i_mean[:, 0] + r[:, 1] * i_mean[:, 1] - r[:, 2] * (i_mean[:, 0] + i_mean[:, 1])) * r[:, 3]
        return u, i_mean, np.full(len(r), vdc), idc
