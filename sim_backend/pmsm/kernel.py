"""The PMSM drive loop: ADC -> firmware -> PWM register (one-period delay) -> inverter -> plant.

One numba call runs n control periods. Reference-sensor columns (true speed, angle error, true flux,
load torque) are filled here from the plant; the firmware never receives them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from drivers.contract import signals
from drivers.contract.signals import SIGNAL_INDEX
from sim_backend import mechanics, numerics, three_phase_inverter
from sim_backend.three_phase_inverter import adc_sample, limit_to_linear_range, switching_error_voltage
from sim_backend.pmsm import firmware as fw
from sim_backend.pmsm import plant as pl
from sim_backend.pmsm.numba_cache import drop_stale_cache

drop_stale_cache(__file__, [fw.__file__, pl.__file__, three_phase_inverter.__file__, mechanics.__file__,
                            signals.__file__, numerics.__file__])

# inverter / measurement parameters (inv_params array)
I_VDC = 0
I_DEAD_TIME = 1
I_DEVICE_DROP = 2
I_ERROR_WIDTH = 3
I_CURRENT_NOISE = 4
I_CURRENT_LSB = 5         # A, 0 = ideal
I_CURRENT_FULL_SCALE = 6
I_VDC_NOISE = 7
I_VDC_LSB = 8             # V, 0 = ideal
I_VDC_FULL_SCALE = 9
I_SUBSTEPS = 10
N_INV_PARAMS = 11

# inverter state: the PWM compare registers hold the command until the next period starts
R_M_ALPHA = 0
R_M_BETA = 1
R_GATES = 2
N_INV_STATE = 3

NOISE_CHANNELS = 3  # i_a, i_b, vdc

C_SPEED_TRUE = SIGNAL_INDEX["speed_true_mech_rad_s"]
C_POS_ERR = SIGNAL_INDEX["pos_err_elec_rad"]
C_POS_EST = SIGNAL_INDEX["pos_est_elec_rad"]
C_FLUX_TRUE = SIGNAL_INDEX["flux_true_wb"]
C_TORQUE_LOAD = SIGNAL_INDEX["torque_load_nm"]


@njit(cache=True, nogil=True)  # the protocol servers' threads keep running while a block is stepped
def run_steps(n: int, step0: int, x: np.ndarray, plant_p: np.ndarray, load_mode: int, load_value: float,
              inv_p: np.ndarray, inv_s: np.ndarray, fw_s: np.ndarray, fw_p: np.ndarray,
              noise: np.ndarray, use_noise: bool, out: np.ndarray) -> None:
    period = fw_p[fw.F_PERIOD]
    substeps = int(inv_p[I_SUBSTEPS])
    ideal = not use_noise
    i_lsb = 0.0 if ideal else inv_p[I_CURRENT_LSB]
    v_lsb = 0.0 if ideal else inv_p[I_VDC_LSB]
    row = np.empty(out.shape[1])
    i_noise = 0.0 if ideal else inv_p[I_CURRENT_NOISE]
    v_noise = 0.0 if ideal else inv_p[I_VDC_NOISE]
    vdc_true = inv_p[I_VDC]
    for k in range(n):
        # --- measurement at t_k (two phase current sensors, DC-link divider) ---
        i_alpha = x[pl.X_ID]
        i_beta = x[pl.X_IQ]
        i_a = i_alpha
        i_b = -0.5 * i_alpha + 0.5 * math.sqrt(3.0) * i_beta
        n_a = 0.0 if ideal else noise[k, 0]
        n_b = 0.0 if ideal else noise[k, 1]
        n_v = 0.0 if ideal else noise[k, 2]
        ia_m = adc_sample(i_a, i_noise, n_a, i_lsb, inv_p[I_CURRENT_FULL_SCALE], True)
        ib_m = adc_sample(i_b, i_noise, n_b, i_lsb, inv_p[I_CURRENT_FULL_SCALE], True)
        vdc_m = adc_sample(vdc_true, v_noise, n_v, v_lsb, inv_p[I_VDC_FULL_SCALE], False)

        # --- firmware --- (the row still holds the last period's true values: poisoned, so the firmware cannot use
        # them; it writes every firmware column itself, the reference sensor the four true ones below)
        t = (step0 + k) * period
        for c in range(row.shape[0]):
            row[c] = math.nan
        fw.firmware_step(fw_s, fw_p, ia_m, ib_m, vdc_m, t, row)

        # --- reference sensor at t_k (logging only) ---
        row[C_SPEED_TRUE] = x[pl.X_W_MECH]
        # true field vector seen from the estimated frame: its angle is the position error
        to_est = complex(fw_s[fw.S_TO_FRAME_RE], fw_s[fw.S_TO_FRAME_IM])
        seen = complex(x[pl.X_PSI_D], x[pl.X_PSI_Q]) * to_est
        row[C_POS_ERR] = math.atan2(seen.imag, seen.real)
        row[C_FLUX_TRUE] = plant_p[pl.P_FLUX]
        row[C_TORQUE_LOAD] = pl.load_torque(x, load_mode, load_value)

        for c in range(row.shape[0]):
            out[k, c] = row[c]

        # --- inverter: the register written last period drives this period; a trip blocks at once ---
        gates_on = fw_s[fw.S_RUNNING] != 0.0 and inv_s[R_GATES] != 0.0
        u_d = 0.0
        u_q = 0.0
        if gates_on:
            u_d, u_q = limit_to_linear_range(inv_s[R_M_ALPHA] * vdc_true, inv_s[R_M_BETA] * vdc_true, vdc_true)
            e_d, e_q = switching_error_voltage(i_alpha, i_beta, vdc_true, inv_p[I_DEAD_TIME], period,
                                               inv_p[I_DEVICE_DROP], inv_p[I_ERROR_WIDTH])
            u_d += e_d
            u_q += e_q
        inv_s[R_M_ALPHA] = fw_s[fw.S_M_ALPHA]
        inv_s[R_M_BETA] = fw_s[fw.S_M_BETA]
        inv_s[R_GATES] = fw_s[fw.S_RUNNING]

        # --- plant over [t_k, t_k+1] ---
        if not gates_on:
            # gates blocked: the winding current freewheels through the diodes into the DC link and dies
            # within the period; the open winding then shows its back-EMF (peak line EMF at 3000 rpm,
            # 423 V, stays below vdc, so the diodes do not conduct again)
            x[pl.X_ID] = 0.0
            x[pl.X_IQ] = 0.0
            w_e = plant_p[pl.P_POLE_PAIRS] * x[pl.X_W_MECH]
            u_d = -w_e * x[pl.X_PSI_Q]
            u_q = w_e * x[pl.X_PSI_D]
        pl.advance(x, plant_p, u_d, u_q, load_mode, load_value, period, substeps)
        if not gates_on:
            x[pl.X_ID] = 0.0
            x[pl.X_IQ] = 0.0
