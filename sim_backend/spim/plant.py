"""Single-phase induction machine, SPIM paper eqs. (1)-(9), in the physical main (d) / auxiliary (q) winding
variables of the stationary frame, asymmetry included (no variable change).

State: stator and rotor flux linkages [phi_sd, phi_sq, phi_rd, phi_rq] (Wb) and the shaft speed (rad/s mech).
Flux linkages as states keep the right-hand side free of matrix inverses of time-varying terms:
    d-axis  [phi_sd, phi_rd] = [[L_sd, M_srd], [M_srd, L_r]] [i_sd, i_rd]    (5), (7)
    q-axis  [phi_sq, phi_rq] = [[L_sq, M_srq], [M_srq, L_r]] [i_sq, i_rq]    (6), (8)
An open winding (inverter gates off and its current extinguished) has i_s = 0; its stator flux then follows
the rotor flux, phi_s = M/L_r * phi_r.

Electrical angles/speeds: omega_r = n_p * omega_mech.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from sim_backend.mechanics import coulomb_torque, smooth_load_torque_inline

# plant parameter vector (effective values: nominal * injection factor)
P_RSD, P_RSQ, P_RR, P_LSD, P_LSQ, P_LR, P_MSRD, P_MSRQ, P_NP, P_J, P_FRICTION, P_LOAD_MODE, P_LOAD_VALUE = range(13)
# derived: inverse inductance matrices, [[a, -b], [-b, c]] per axis (set by plant_params / derive)
P_INV_D_A, P_INV_D_B, P_INV_D_C, P_INV_Q_A, P_INV_Q_B, P_INV_Q_C = range(13, 19)
N_PLANT_PARAMS = 19

# plant state vector
X_PSD, X_PSQ, X_PRD, X_PRQ, X_WM, X_THETA_M, X_OPEN_D, X_OPEN_Q = range(8)
N_PLANT_STATE = 8


@njit(cache=True, inline="always")
def currents(psd, psq, prd, prq, p, open_d, open_q):
    """(i_sd, i_sq, i_rd, i_rq) from the flux linkages."""
    isd, ird = _axis_currents(psd, prd, p[P_INV_D_A], p[P_INV_D_B], p[P_INV_D_C], p[P_LR], open_d)
    isq, irq = _axis_currents(psq, prq, p[P_INV_Q_A], p[P_INV_Q_B], p[P_INV_Q_C], p[P_LR], open_q)
    return isd, isq, ird, irq


@njit(cache=True, inline="always")
def _axis_currents(ps, pr, inv_a, inv_b, inv_c, lr, open_):
    """(stator, rotor) current of one axis from its flux linkages; an open stator winding carries none."""
    if open_:
        return 0.0, pr / lr
    return inv_a * ps - inv_b * pr, inv_c * pr - inv_b * ps


@njit(cache=True, inline="always")
def torque(isd, isq, ird, irq, p):
    """Electromagnetic torque, eq. (9)."""
    return p[P_NP] * (p[P_MSRQ] * isq * ird - p[P_MSRD] * isd * irq)


@njit(cache=True, inline="always")
def derivatives(psd, psq, prd, prq, wm, vsd, vsq, p, open_d, open_q, coulomb_signed):
    isd, isq, ird, irq = currents(psd, psq, prd, prq, p, open_d, open_q)
    wr = p[P_NP] * wm
    dprd = -p[P_RR] * ird - wr * prq          # (3)
    dprq = -p[P_RR] * irq + wr * prd          # (4)
    if open_d:
        dpsd = p[P_MSRD] / p[P_LR] * dprd
    else:
        dpsd = vsd - p[P_RSD] * isd           # (1)
    if open_q:
        dpsq = p[P_MSRQ] / p[P_LR] * dprq
    else:
        dpsq = vsq - p[P_RSQ] * isq           # (2)
    te = torque(isd, isq, ird, irq, p)
    load = smooth_load_torque_inline(int(p[P_LOAD_MODE]), p[P_LOAD_VALUE], wm)
    dwm = (te - load - coulomb_signed - p[P_FRICTION] * wm) / p[P_J]
    return dpsd, dpsq, dprd, dprq, dwm


@njit(cache=True, inline="always")
def advance(x, p, vsd, vsq, dt, substeps, gates_off):
    """Advance the plant by dt with the winding voltages held, RK4 in `substeps` equal steps.

    With gates_off, a winding whose current crosses zero inside a substep is opened (its diode blocks).
    Returns the mean electromagnetic torque over the interval.
    """
    h = dt / substeps
    psd, psq, prd, prq, wm = x[X_PSD], x[X_PSQ], x[X_PRD], x[X_PRQ], x[X_WM]
    open_d = x[X_OPEN_D] != 0.0
    open_q = x[X_OPEN_Q] != 0.0
    coulomb = coulomb_torque(int(p[P_LOAD_MODE]), p[P_LOAD_VALUE])
    te_sum = 0.0
    isd0, isq0, _, _ = currents(psd, psq, prd, prq, p, open_d, open_q)
    for _ in range(substeps):
        # Coulomb (brake) torque inside the RK4 stages keeps the method 4th order; at rest it holds the shaft
        # while the net smooth torque stays within its magnitude (sim_backend.mechanics convention).
        isd, isq, ird, irq = currents(psd, psq, prd, prq, p, open_d, open_q)
        te = torque(isd, isq, ird, irq, p)
        stuck = False
        cs = 0.0
        if coulomb > 0.0:
            if wm != 0.0:
                cs = coulomb * np.sign(wm)
            else:
                net = te - smooth_load_torque_inline(int(p[P_LOAD_MODE]), p[P_LOAD_VALUE], 0.0)
                if abs(net) <= coulomb:
                    cs = net
                    stuck = True
                else:
                    cs = coulomb * np.sign(net)
        k1 = derivatives(psd, psq, prd, prq, wm, vsd, vsq, p, open_d, open_q, cs)
        k2 = derivatives(psd + 0.5 * h * k1[0], psq + 0.5 * h * k1[1], prd + 0.5 * h * k1[2],
                         prq + 0.5 * h * k1[3], wm + 0.5 * h * k1[4], vsd, vsq, p, open_d, open_q, cs)
        k3 = derivatives(psd + 0.5 * h * k2[0], psq + 0.5 * h * k2[1], prd + 0.5 * h * k2[2],
                         prq + 0.5 * h * k2[3], wm + 0.5 * h * k2[4], vsd, vsq, p, open_d, open_q, cs)
        k4 = derivatives(psd + h * k3[0], psq + h * k3[1], prd + h * k3[2],
                         prq + h * k3[3], wm + h * k3[4], vsd, vsq, p, open_d, open_q, cs)
        wm_before = wm
        psd += h / 6.0 * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0])
        psq += h / 6.0 * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1])
        prd += h / 6.0 * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2])
        prq += h / 6.0 * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3])
        wm += h / 6.0 * (k1[4] + 2.0 * k2[4] + 2.0 * k3[4] + k4[4])
        if stuck or (coulomb > 0.0 and wm * wm_before < 0.0):
            wm = 0.0  # held by the brake, or the brake stopped the shaft within this substep
        x[X_THETA_M] += 0.5 * h * (wm_before + wm)
        te_sum += te
        if gates_off:
            isd, isq, _, _ = currents(psd, psq, prd, prq, p, open_d, open_q)
            if not open_d and isd * isd0 <= 0.0:
                open_d = True
                psd = p[P_MSRD] / p[P_LR] * prd
            if not open_q and isq * isq0 <= 0.0:
                open_q = True
                psq = p[P_MSRQ] / p[P_LR] * prq
    x[X_PSD], x[X_PSQ], x[X_PRD], x[X_PRQ], x[X_WM] = psd, psq, prd, prq, wm
    x[X_OPEN_D] = 1.0 if open_d else 0.0
    x[X_OPEN_Q] = 1.0 if open_q else 0.0
    return te_sum / substeps


@njit(cache=True)
def magnetic_energy(x, p):
    """Stored magnetic energy 1/2 i^T L i = 1/2 (phi . i) summed over both axes (J)."""
    open_d = x[X_OPEN_D] != 0.0
    open_q = x[X_OPEN_Q] != 0.0
    isd, isq, ird, irq = currents(x[X_PSD], x[X_PSQ], x[X_PRD], x[X_PRQ], p, open_d, open_q)
    return 0.5 * (x[X_PSD] * isd + x[X_PSQ] * isq + x[X_PRD] * ird + x[X_PRQ] * irq)


def plant_params(plant: dict, mech: dict, factors: dict[str, float], load_mode: int = 0,
                 load_value: float = 0.0) -> np.ndarray:
    """Effective plant parameter vector from the [plant]/[mechanics] config and injection factors."""
    p = np.zeros(N_PLANT_PARAMS)
    p[P_RSD] = plant["rsd_ohm"] * factors.get("plant_rsd", 1.0)
    p[P_RSQ] = plant["rsq_ohm"] * factors.get("plant_rsq", 1.0)
    p[P_RR] = plant["rr_ohm"] * factors.get("plant_rr", 1.0)
    p[P_LSD] = plant["lsd_h"]
    p[P_LSQ] = plant["lsq_h"]
    p[P_LR] = plant["lr_h"]
    p[P_MSRD] = plant["msrd_h"]
    p[P_MSRQ] = plant["msrq_h"]
    p[P_NP] = plant["pole_pairs"]
    p[P_J] = mech["inertia_kgm2"] * factors.get("plant_inertia", 1.0)
    p[P_FRICTION] = mech["viscous_nm_s_rad"]
    p[P_LOAD_MODE] = load_mode
    p[P_LOAD_VALUE] = load_value
    derive(p)
    return p


def derive(p: np.ndarray) -> None:
    """Fill the derived entries (inverse inductance matrices) after changing inductances in p."""
    for ls, m, a, b, c in ((P_LSD, P_MSRD, P_INV_D_A, P_INV_D_B, P_INV_D_C),
                           (P_LSQ, P_MSRQ, P_INV_Q_A, P_INV_Q_B, P_INV_Q_C)):
        det = p[ls] * p[P_LR] - p[m] * p[m]
        p[a], p[b], p[c] = p[P_LR] / det, p[m] / det, p[ls] / det
