"""Sensorless stator-flux-oriented speed control of the SPIM (paper eqs. (10), (20)-(42)), as a DSP runs it.

One call of `firmware_step` is one control period. Inputs: the measured winding currents, the measured
DC-link voltage, the firmware's own previous voltage commands (kept in its state) and its own clock.
Outputs: the three leg duties for the next control period and the telemetry it knows.

Control is done in the paper's symmetrised variables (eq. 10, k = M_srd/M_srq):
    i_sd1 = i_sd, i_sq1 = i_sq / k, v_sd1 = v_sd, v_sq1 = k * v_sq, phi_sq1 = k * phi_sq,
    and in those variables the stator voltage equations read v_sd1 = R_sd i_sd1 + dphi_sd1/dt,
    v_sq1 = k^2 R_sq i_sq1 + dphi_sq1/dt (eq. 12).
Chain (deviations from the paper are listed in docs/firmware.md):
  1. stator flux from the voltage model, written in the controller's frame with phi_sq1 = 0:
        dphi/dt = e_d,   omega_s = e_q / phi,   e = v1 - R1 i1 rotated into the frame
  2. slip estimator of the paper (eqs. 35-42): a model q-current driven by the estimated slip, compared with
     the measured q-current, PI -> estimated slip; rotor speed = omega_s - slip
  3. IP speed controller -> torque reference -> i_q* = T*/(n_p phi*) (eq. 27); i_d* from eq. (26) in steady
     state plus a flux PI on the estimated flux
  4. PI current controllers in the flux frame, centred three-leg modulation, dead-time compensation
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim_backend.numerics import wrap_angle

FAULT_OVERCURRENT = 0x2310

# ---- firmware parameter vector ------------------------------------------------------------------------
(F_TS, F_NP, F_K, F_RD1, F_RQ1, F_LSD, F_SIGMA_D, F_TAU_R, F_LQ1, F_J,
 F_KP_I, F_KI_I, F_FLUX_REF, F_KP_F, F_KI_F, F_KP_W, F_KI_W, F_KP_V, F_KI_V,
 F_T_MAX, F_I_MAX, F_RAMP, F_W_SPEED_LPF, F_W_FF_LPF, F_PHI_MIN, F_I_TRIP, F_M_MAX,
 F_DT_COMP_V, F_DT_COMP_BAND, F_T_MAG, F_COMMON_FIXED, F_DL, F_G_CM, F_T_DEMAG) = range(34)
N_FW_PARAMS = 34

# ---- firmware state vector ----------------------------------------------------------------------------
(S_ENABLED, S_FAULT, S_T_ON, S_THETA, S_PHI, S_WS, S_WS_FF, S_SLIP, S_SLIP_INT, S_IQ_MODEL,
 S_SPEED_EST, S_SPEED_INT, S_FLUX_INT, S_ID_INT, S_IQ_INT, S_U1A_P1, S_U1B_P1, S_U1A_P2, S_U1B_P2,
 S_I1A_PREV, S_I1B_PREV, S_SPEED_TARGET, S_SPEED_REF, S_FREEZE_SLIP, S_FREEZE_FLUX, S_RUNNING,
 S_ID_REF, S_LAM_D, S_LAM_Q, S_CM_D, S_CM_Q, S_T_OFF) = range(32)
N_FW_STATE = 32

# telemetry columns the firmware writes (indices into drivers.contract.signals.SIGNAL_NAMES)
C_SPEED_REF, C_SPEED_EST, C_SPEED_TRUE, C_POS_EST, C_POS_ERR, C_FLUX_EST, C_FLUX_TRUE, C_ISX, C_ISY, \
    C_ISX_REF, C_ISY_REF, C_USX, C_USY, C_TORQUE_EST, C_TORQUE_LOAD, C_VDC = range(16)


def new_state() -> np.ndarray:
    s = np.zeros(N_FW_STATE)
    s[S_T_OFF] = 1e9  # power-up: the machine has been de-energised for long
    return s


@njit(cache=True)
def reset_controllers(s):
    """Zero every estimator and controller state (done at each enable), keep target, freezes and fault."""
    for j in (S_T_ON, S_THETA, S_PHI, S_WS, S_WS_FF, S_SLIP, S_SLIP_INT, S_IQ_MODEL, S_SPEED_EST,
              S_SPEED_INT, S_FLUX_INT, S_ID_INT, S_IQ_INT, S_U1A_P1, S_U1B_P1, S_U1A_P2, S_U1B_P2,
              S_I1A_PREV, S_I1B_PREV, S_SPEED_REF, S_RUNNING, S_ID_REF, S_LAM_D, S_LAM_Q,
              S_CM_D, S_CM_Q):
        s[j] = 0.0


@njit(cache=True, inline="always")  # inlined into the kernel: no call with three arrays per period
def firmware_step(s, f, isd_m, isq_m, vdc_m, row):
    """One control period. Returns (gates_on, d_a, d_b, d_c) to apply during the next period."""
    ts = f[F_TS]
    row[C_VDC] = vdc_m
    if s[S_RUNNING] == 0.0:
        # gates stay blocked while disabled or faulted, and after that for the de-magnetising time: the
        # estimators start from zero flux, so the rotor's residual flux must have decayed first
        if s[S_ENABLED] == 0.0 or s[S_FAULT] != 0.0 or s[S_T_OFF] < f[F_T_DEMAG]:
            s[S_T_OFF] += ts
            return False, 0.5, 0.5, 0.5
        reset_controllers(s)
        s[S_RUNNING] = 1.0
    elif s[S_ENABLED] == 0.0 or s[S_FAULT] != 0.0:
        s[S_RUNNING] = 0.0
        s[S_T_OFF] = ts
        return False, 0.5, 0.5, 0.5
    if abs(isd_m) > f[F_I_TRIP] or abs(isq_m) > f[F_I_TRIP]:
        s[S_FAULT] = FAULT_OVERCURRENT
        s[S_RUNNING] = 0.0
        s[S_T_OFF] = ts
        return False, 0.5, 0.5, 0.5
    running_time = s[S_T_ON]
    s[S_T_ON] += ts
    magnetised = running_time >= f[F_T_MAG]
    k = f[F_K]
    i1a = isd_m
    i1b = isq_m / k

    # 1. voltage-model stator flux in the synchronous frame (phi_q = 0); interval [t_k-1, t_k] had u_k-2.
    #    Oriented flux: phi_s1 - dL * i_sq1 on the q axis (dL = k^2 L_sq - L_sd, the asymmetric term of
    #    eq. 16), i.e. the stator flux of the symmetrical machine, so zeta and Delta T of eqs. (20)-(25) vanish.
    dl = f[F_DL]
    ea = s[S_U1A_P2] - f[F_RD1] * 0.5 * (i1a + s[S_I1A_PREV])
    eb = s[S_U1B_P2] - f[F_RQ1] * 0.5 * (i1b + s[S_I1B_PREV]) - dl * (i1b - s[S_I1B_PREV]) / ts
    th_mid = s[S_THETA] + 0.5 * ts * s[S_WS]
    c = math.cos(th_mid)
    sn = math.sin(th_mid)
    ed = c * ea + sn * eb
    eq = -sn * ea + c * eb
    # pulled towards the current model (eqs. 24-25 as a vector: rotor flux driven by the currents and the
    # estimated slip) with gain g_cm: errors of the integrator decay instead of persisting, and below
    # ~g_cm rad/s the current model takes over from the voltage model
    g = f[F_G_CM]
    eq += g * s[S_CM_Q]
    if s[S_FREEZE_FLUX] == 0.0:
        s[S_PHI] = max(s[S_PHI] + ts * (ed + g * (s[S_CM_D] - s[S_PHI])), 0.0)
    phi = s[S_PHI]
    ws = eq / max(phi, f[F_PHI_MIN])
    s[S_WS] = ws
    s[S_THETA] = wrap_angle(s[S_THETA] + ts * ws)
    s[S_I1A_PREV] = i1a
    s[S_I1B_PREV] = i1b
    a_ff = ts * f[F_W_FF_LPF] / (1.0 + ts * f[F_W_FF_LPF])
    s[S_WS_FF] += a_ff * (ws - s[S_WS_FF])

    c = math.cos(s[S_THETA])
    sn = math.sin(s[S_THETA])
    i_d = c * i1a + sn * i1b
    i_q = -sn * i1a + c * i1b
    flux_ref = f[F_FLUX_REF]

    # 2. slip estimator (eqs. 35-42): model q-current driven by the estimated slip vs measured q-current
    sig_tr = f[F_SIGMA_D] * f[F_TAU_R]
    id_ref_prev = s[S_ID_REF]
    if s[S_FREEZE_SLIP] == 0.0:
        s[S_IQ_MODEL] += ts * (-s[S_IQ_MODEL] / sig_tr
                               + (flux_ref / (f[F_SIGMA_D] * f[F_LSD]) - id_ref_prev) * s[S_SLIP])
        eps = i_q - s[S_IQ_MODEL]
        s[S_SLIP_INT] += f[F_KI_W] * ts * eps
        s[S_SLIP] = f[F_KP_W] * eps + s[S_SLIP_INT]
    slip = s[S_SLIP]
    # current model in the flux frame: lam = (M/L_r) psi_r, d lam/dt = -lam/tau_r + (1-sigma) L i/tau_r
    # - j slip lam (the frame turns at omega_s = omega_r + slip); stator flux = sigma L i + lam
    sig_l = f[F_SIGMA_D] * f[F_LSD]
    mag_l = f[F_LSD] - sig_l
    lam_d, lam_q = s[S_LAM_D], s[S_LAM_Q]
    s[S_LAM_D] = lam_d + ts * ((mag_l * i_d - lam_d) / f[F_TAU_R] + slip * lam_q)
    s[S_LAM_Q] = lam_q + ts * ((mag_l * i_q - lam_q) / f[F_TAU_R] - slip * lam_d)
    s[S_CM_D] = sig_l * i_d + s[S_LAM_D]
    s[S_CM_Q] = sig_l * i_q + s[S_LAM_Q]
    speed_raw = (ws - slip) / f[F_NP]
    a_sp = ts * f[F_W_SPEED_LPF] / (1.0 + ts * f[F_W_SPEED_LPF])
    s[S_SPEED_EST] += a_sp * (speed_raw - s[S_SPEED_EST])
    speed_est = s[S_SPEED_EST]

    # 3. speed ramp, IP speed controller, current references
    accel = 0.0
    if magnetised:
        if running_time < f[F_T_MAG] + ts:  # first speed-loop step: start bumpless from the estimate
            s[S_SPEED_REF] = speed_est
            s[S_SPEED_INT] = f[F_KP_V] * speed_est
        step = f[F_RAMP] * ts
        dref = s[S_SPEED_TARGET] - s[S_SPEED_REF]
        if dref > step:
            dref = step
        elif dref < -step:
            dref = -step
        s[S_SPEED_REF] += dref
        accel = dref / ts
        s[S_SPEED_INT] += f[F_KI_V] * ts * (s[S_SPEED_REF] - speed_est)
        t_ref = s[S_SPEED_INT] - f[F_KP_V] * speed_est + f[F_J] * accel
        t_max = f[F_T_MAX]
        if t_ref > t_max:
            s[S_SPEED_INT] -= t_ref - t_max
            t_ref = t_max
        elif t_ref < -t_max:
            s[S_SPEED_INT] -= t_ref + t_max
            t_ref = -t_max
    else:
        t_ref = 0.0
    iq_ref = t_ref / (f[F_NP] * flux_ref)                                          # (27)
    flux_err = flux_ref - phi
    if s[S_FREEZE_FLUX] == 0.0:
        s[S_FLUX_INT] += f[F_KI_F] * ts * flux_err
    id_ref = (flux_ref + sig_tr * f[F_LSD] * iq_ref * slip) / f[F_LSD] \
        + f[F_KP_F] * flux_err + s[S_FLUX_INT]                                    # (26), steady state
    i_max = f[F_I_MAX]
    if id_ref > i_max:
        s[S_FLUX_INT] -= id_ref - i_max
        id_ref = i_max
    elif id_ref < 0.0:
        id_ref = 0.0
    s[S_ID_REF] = id_ref
    iq_lim = math.sqrt(max(i_max * i_max - id_ref * id_ref, 0.0))
    if iq_ref > iq_lim:
        iq_ref = iq_lim
    elif iq_ref < -iq_lim:
        iq_ref = -iq_lim

    # 4. current PIs in the flux frame, resistive and rotational feed-forward
    e_id = id_ref - i_d
    e_iq = iq_ref - i_q
    d_int_d = f[F_KI_I] * ts * e_id
    d_int_q = f[F_KI_I] * ts * e_iq
    s[S_ID_INT] += d_int_d
    s[S_IQ_INT] += d_int_q
    c0 = c
    s0 = sn
    ra = f[F_RD1] * i1a
    rb = f[F_RQ1] * i1b
    v_d = f[F_KP_I] * e_id + s[S_ID_INT] + c0 * ra + s0 * rb
    v_q = f[F_KP_I] * e_iq + s[S_IQ_INT] - s0 * ra + c0 * rb + s[S_WS_FF] * phi
    # rotate by the angle the frame turns until the middle of the next period (small: series to 5th order)
    da = 1.5 * ts * ws
    da2 = da * da
    cd = 1.0 - da2 * (0.5 - da2 / 24.0)
    sd = da * (1.0 - da2 * (1.0 / 6.0 - da2 / 120.0))
    c1 = c0 * cd - s0 * sd
    s1 = s0 * cd + c0 * sd
    u1a = c1 * v_d - s1 * v_q
    u1b = s1 * v_d + c1 * v_q
    # dL * d(i_sq1)/dt of the reference current vector turning at the frame speed
    u1b += dl * s[S_WS_FF] * (c1 * id_ref - s1 * iq_ref)
    vsd = u1a
    vsq = u1b / k
    # modulation limit of the three-leg inverter
    vdc = max(vdc_m, 1.0)
    if f[F_COMMON_FIXED] != 0.0:
        spread = 2.0 * max(abs(vsd), abs(vsq))
    else:
        spread = max(max(vsd, vsq), 0.0) - min(min(vsd, vsq), 0.0)
    limit = f[F_M_MAX] * vdc
    scale = 1.0
    if spread > limit:
        scale = limit / spread
        s[S_ID_INT] -= d_int_d
        s[S_IQ_INT] -= d_int_q
    vsd *= scale
    vsq *= scale
    s[S_U1A_P2] = s[S_U1A_P1]
    s[S_U1B_P2] = s[S_U1B_P1]
    s[S_U1A_P1] = vsd
    s[S_U1B_P1] = k * vsq
    if f[F_COMMON_FIXED] != 0.0:
        uc = 0.5 * vdc
    else:
        uc = 0.5 * vdc - 0.5 * (max(max(vsd, vsq), 0.0) + min(min(vsd, vsq), 0.0))
    ua = vsd + uc
    ub = vsq + uc
    comp = f[F_DT_COMP_V]
    if comp != 0.0:
        band = f[F_DT_COMP_BAND]
        # signs from the reference currents at the middle of the next period (smooth, no ADC noise, no delay)
        isd_next = c1 * id_ref - s1 * iq_ref
        isq_next = k * (s1 * id_ref + c1 * iq_ref)
        ua += comp * min(max(isd_next / band, -1.0), 1.0)
        ub += comp * min(max(isq_next / band, -1.0), 1.0)
        uc += comp * min(max(-(isd_next + isq_next) / band, -1.0), 1.0)

    # telemetry the firmware knows
    row[C_SPEED_REF] = s[S_SPEED_REF]
    row[C_SPEED_EST] = speed_est
    row[C_POS_EST] = s[S_THETA]
    row[C_FLUX_EST] = phi
    row[C_ISX] = i_d
    row[C_ISY] = i_q
    row[C_ISX_REF] = id_ref
    row[C_ISY_REF] = iq_ref
    row[C_USX] = v_d * scale
    row[C_USY] = v_q * scale
    row[C_TORQUE_EST] = f[F_NP] * phi * i_q                                      # (20), Delta T absorbed
    return True, min(max(ua / vdc, 0.0), 1.0), min(max(ub / vdc, 0.0), 1.0), min(max(uc / vdc, 0.0), 1.0)


def firmware_params(model: dict, fw: dict) -> np.ndarray:
    """Firmware parameter vector from its motor model (fw_* names, SI) and the [firmware] settings."""
    rsd, rsq, rr = model["fw_rsd_ohm"], model["fw_rsq_ohm"], model["fw_rr_ohm"]
    lsd, lsq, lr = model["fw_lsd_h"], model["fw_lsq_h"], model["fw_lr_h"]
    msrd, msrq = model["fw_msrd_h"], model["fw_msrq_h"]
    k = msrd / msrq
    f = np.zeros(N_FW_PARAMS)
    f[F_TS] = fw["control_period_s"]
    f[F_NP] = fw["pole_pairs"]
    f[F_K] = k
    f[F_RD1] = rsd
    f[F_RQ1] = k * k * rsq
    f[F_LSD] = lsd
    f[F_SIGMA_D] = 1.0 - msrd * msrd / (lsd * lr)
    f[F_TAU_R] = lr / rr
    f[F_LQ1] = lsq
    f[F_J] = model["fw_inertia_kgm2"]
    f[F_KP_I] = fw["current_kp_v_per_a"]
    f[F_KI_I] = fw["current_ki_v_per_as"]
    f[F_FLUX_REF] = fw["stator_flux_ref_wb"]
    f[F_KP_F] = fw["flux_kp_a_per_wb"]
    f[F_KI_F] = fw["flux_ki_a_per_wbs"]
    f[F_KP_W] = fw["slip_kp"]
    f[F_KI_W] = fw["slip_ki"]
    f[F_KP_V] = fw["speed_kp_nm_s_rad"]
    f[F_KI_V] = fw["speed_ki_nm_rad"]
    f[F_T_MAX] = fw["torque_max_nm"]
    f[F_I_MAX] = fw["current_max_a"]
    f[F_RAMP] = fw["speed_ramp_rad_s2"]
    f[F_W_SPEED_LPF] = fw["speed_filter_rad_s"]
    f[F_W_FF_LPF] = fw["emf_feedforward_filter_rad_s"]
    f[F_PHI_MIN] = fw["flux_min_wb"]
    f[F_I_TRIP] = fw["overcurrent_trip_a"]
    f[F_M_MAX] = fw["modulation_max"]
    f[F_DT_COMP_V] = fw["dead_time_comp_v"]
    f[F_DT_COMP_BAND] = fw["dead_time_comp_band_a"]
    f[F_T_MAG] = fw["magnetising_time_s"]
    f[F_DL] = k * k * lsq - lsd
    f[F_G_CM] = fw["flux_current_model_gain_rad_s"]
    f[F_T_DEMAG] = fw["demagnetising_time_s"]
    f[F_COMMON_FIXED] = 1.0 if fw["common_leg"] == "fixed" else 0.0
    return f


def slip_pi_design(model: dict, flux_ref: float, rise_time_s: float, zeta: float = 1.0) -> tuple[float, float]:
    """Slip-estimator PI gains from eqs. (39)-(42) (|K_0| used; the sign is in the error definition).

    rise_time_s is the paper's T_r (5 %-95 % rise time); k_c = omega_0 * T_r = 4.75 for zeta = 1.
    """
    lsd, lr, rr, msrd = model["fw_lsd_h"], model["fw_lr_h"], model["fw_rr_ohm"], model["fw_msrd_h"]
    sigma_d = 1.0 - msrd * msrd / (lsd * lr)
    tau_r = lr / rr
    i_d0 = flux_ref / lsd
    k0 = tau_r / lsd * (flux_ref - sigma_d * lsd * i_d0)
    w0 = 4.75 / rise_time_s
    ki = sigma_d * tau_r * w0 * w0 / k0                        # (41)
    kp = (2.0 * sigma_d * tau_r * zeta * w0 - 1.0) / k0      # (42)
    return kp, ki
