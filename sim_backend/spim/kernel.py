"""The SPIM drive loop: plant + three-leg inverter + ADC + firmware + reference sensor, n control periods in
one compiled call.

Timing of one control period k, [t_k, t_k+1]:
  ADC samples the currents and the DC link at t_k -> firmware step k -> duties for period k+1;
  the inverter applies the duties computed at step k-1 during period k; the plant integrates period k.
Telemetry row k: firmware values of step k and reference-sensor values at t_k.
"""

from __future__ import annotations

import math

from numba import njit

from sim_backend.numerics import wrap_angle
from sim_backend.mechanics import LOAD_BRAKE, smooth_load_torque_inline
from sim_backend.spim import firmware as fw
from sim_backend.spim import inverter as inv
from sim_backend.spim import plant as pl

# kernel (power stage) state: gates enabled for the current period and its duties
K_GATES, K_DA, K_DB, K_DC = range(4)
N_KERNEL_STATE = 4
NOISE_CHANNELS = 3  # i_sd, i_sq, v_dc


@njit(cache=True, inline="always")
def load_torque_now(x, pp, te):
    """Shaft load torque the rig's transducer reads (brake at standstill: the torque it holds)."""
    mode = int(pp[pl.P_LOAD_MODE])
    value = pp[pl.P_LOAD_VALUE]
    wm = x[pl.X_WM]
    if mode == LOAD_BRAKE:
        if wm != 0.0:
            return abs(value) * math.copysign(1.0, wm)
        return min(max(te, -abs(value)), abs(value))
    return smooth_load_torque_inline(mode, value, wm)


# nogil: protocol-server threads keep answering while a block steps. error_model numpy: no zero-divisor check and
# branch before each of the ~25 divisions per period (every divisor is a checked positive parameter or guarded)
@njit(cache=True, nogil=True, error_model="numpy")
def run_steps(n, x, pp, ip, fs, fp, ks, noise, use_noise, substeps, out):
    ts = fp[fw.F_TS]
    k_true = pp[pl.P_MSRD] / pp[pl.P_MSRQ]
    for j in range(n):
        open_d = x[pl.X_OPEN_D] != 0.0
        open_q = x[pl.X_OPEN_Q] != 0.0
        isd, isq, ird, irq = pl.currents(x[pl.X_PSD], x[pl.X_PSQ], x[pl.X_PRD], x[pl.X_PRQ], pp, open_d, open_q)
        te = pl.torque(isd, isq, ird, irq, pp)
        n0 = noise[j, 0] if use_noise else 0.0
        n1 = noise[j, 1] if use_noise else 0.0
        n2 = noise[j, 2] if use_noise else 0.0
        isd_m = inv.adc(isd, n0, ip[inv.I_NOISE_I], ip[inv.I_LSB_I])
        isq_m = inv.adc(isq, n1, ip[inv.I_NOISE_I], ip[inv.I_LSB_I])
        vdc_m = inv.adc(ip[inv.I_VDC], n2, ip[inv.I_NOISE_VDC], ip[inv.I_LSB_VDC])

        row = out[j]
        row[:] = 0.0
        gates_now = ks[K_GATES] != 0.0
        vsd, vsq = inv.winding_voltages(ks[K_DA], ks[K_DB], ks[K_DC], isd, isq, not gates_now, ip)
        gates_next, da, db, dc = fw.firmware_step(fs, fp, isd_m, isq_m, vdc_m, row)

        # reference sensor at t_k
        # stator flux of the symmetrised machine, eqs. (15)-(16) without the asymmetric term of (16):
        # phi_sd1 = L_sd i_sd1 + M_srd i_rd, phi_sq1 - (k^2 L_sq - L_sd) i_sq1 = L_sd i_sq1 + M_srd i_rq
        psd1 = x[pl.X_PSD]
        psq1 = pp[pl.P_LSD] * isq / k_true + pp[pl.P_MSRD] * irq
        row[fw.C_SPEED_TRUE] = x[pl.X_WM]
        row[fw.C_FLUX_TRUE] = math.sqrt(psd1 * psd1 + psq1 * psq1)
        row[fw.C_POS_ERR] = wrap_angle(math.atan2(psq1, psd1) - row[fw.C_POS_EST])
        row[fw.C_TORQUE_LOAD] = load_torque_now(x, pp, te - pp[pl.P_FRICTION] * x[pl.X_WM])

        if gates_now:
            x[pl.X_OPEN_D] = 0.0
            x[pl.X_OPEN_Q] = 0.0
        pl.advance(x, pp, vsd, vsq, ts, substeps, not gates_now)
        ks[K_GATES] = 1.0 if gates_next else 0.0
        ks[K_DA] = da
        ks[K_DB] = db
        ks[K_DC] = dc
