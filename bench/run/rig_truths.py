"""The mission's truths from a lab's instruments: what the bench derives from a scope/DAQ capture and the power
analyser, with the uncertainty each carries (docs/instruments.md).

- Encoder alignment (PMSM): the dynamometer turns the shaft with the drive disabled; the scope sees a phase's
  open-circuit back-EMF and the encoder's index. u_a = d(psi cos theta)/dt = -w_e psi sin theta rises through zero at
  theta = pi, so at an index edge the rotor's electrical angle is pi + w_e (t_index - t_zero). `align` averages that
  over every index edge of the capture: the rig's index offset, recorded per rig. After it, the true electrical angle
  is theta_index + p (phi_encoder - phi_at_index) and `pos_err_elec_rad` = true - estimated (wrapped).
- PMSM magnet flux from the same capture: psi = sqrt(2) U_rms / w_e (a sinusoidal back-EMF; its harmonics counted
  in U_rms are the flux's error).
- SPIM stator flux from the measured winding voltages and currents: psi = integral(v - R_s i) dt per winding, with
  the integrator's constant removed over whole electrical periods (the capture starts at an unknown flux); R_s is
  stated (and its error enters as dR * I_rms / w_e); the field the ISFOC orients on is the symmetrised machine's
  (`spim_field_flux`, the paper's eqs. (15)-(16) with the stated inductances); its angle against the drive's
  pos_est_elec_rad is the SPIM's position error.
- Power: input (DC link), motor terminals, shaft; losses and efficiency from the analyser's elements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Alignment:
    theta_index_elec_rad: float      # the rotor's electrical angle when the encoder's index passes
    spread_rad: float                # std over the index edges seen
    edges: int
    omega_elec_rad_s: float
    flux_wb: float                   # magnet flux from the open-circuit back-EMF
    uncertainty_rad: float           # stated: spread / sqrt(edges) + half a sample at w_e


def rising_crossings(t: np.ndarray, y: np.ndarray, level: float = 0.0, hysteresis: float = 0.0) -> np.ndarray:
    """Times y rises through `level` (linearly interpolated); after each, y must fall below level - hysteresis."""
    out = []
    armed = y[0] < level - hysteresis
    for k in range(1, y.size):
        if armed and y[k - 1] < level <= y[k]:
            out.append(t[k - 1] + (level - y[k - 1]) / (y[k] - y[k - 1]) * (t[k] - t[k - 1]))
            armed = False
        elif y[k] < level - hysteresis:
            armed = True
    return np.array(out)


def align(t: np.ndarray, u_a: np.ndarray, index_v: np.ndarray) -> Alignment:
    """The encoder-alignment step's result from a capture taken with the drive disabled and the shaft turning
    forward (see the module doc). ValueError (one line) when the capture cannot give it."""
    if np.isnan(u_a).any() or np.isnan(index_v).any():
        raise ValueError("the alignment capture has over-range samples: not judged")
    rms = math.sqrt(float(np.mean(u_a * u_a)))
    zeros = rising_crossings(t, u_a, 0.0, 0.2 * rms)
    edges = rising_crossings(t, index_v, 0.5 * float(np.max(index_v)) if np.max(index_v) > 0 else 1.0)
    if zeros.size < 3 or edges.size < 1:
        raise ValueError(f"the alignment capture shows {zeros.size} back-EMF cycles and {edges.size} index edges: "
                         "turn the shaft faster or capture longer (>= 3 cycles, >= 1 index)")
    period = float(np.mean(np.diff(zeros)))
    w_e = 2 * math.pi / period
    angles = []
    for e in edges:           # between the crossings around the edge the angle runs from pi to 3 pi
        k = int(np.searchsorted(zeros, e))
        if 0 < k < zeros.size:
            angles.append(math.pi + 2 * math.pi * (e - zeros[k - 1]) / (zeros[k] - zeros[k - 1]))
    if not angles:
        raise ValueError("no index edge between two back-EMF zero crossings in the capture")
    mean = math.atan2(np.mean(np.sin(angles)), np.mean(np.cos(angles)))
    spread = float(np.std(np.angle(np.exp(1j * (np.array(angles) - mean))))) if len(angles) > 1 else 0.0
    dt = float(t[1] - t[0])
    # whole cycles only for the rms: a partial cycle biases it
    inside = (t >= zeros[0]) & (t < zeros[-1])
    flux = math.sqrt(2.0 * float(np.mean(u_a[inside] ** 2))) / w_e
    return Alignment(mean, spread, len(angles), w_e, flux, spread / math.sqrt(len(angles)) + 0.5 * w_e * dt)


def electrical_angle(alignment: Alignment, encoder_mech_rad_since_index: np.ndarray, pole_pairs: int) -> np.ndarray:
    """The rotor's true electrical angle from the aligned encoder, wrapped to [-pi, pi)."""
    return wrap(alignment.theta_index_elec_rad + pole_pairs * encoder_mech_rad_since_index)


def wrap(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def stator_flux(t: np.ndarray, v: np.ndarray, i: np.ndarray, rs_ohm: float) -> np.ndarray:
    """A winding's stator flux linkage, integral(v - R_s i) dt, its constant removed over whole electrical periods
    (from the voltage's rising zero crossings; the whole capture's mean when it has fewer than two)."""
    if np.isnan(v).any() or np.isnan(i).any():
        raise ValueError("the capture has over-range samples: the flux is not judged")
    e = v - rs_ohm * i
    dt = np.diff(t, prepend=t[0])
    psi = np.cumsum(0.5 * (e + np.concatenate(([e[0]], e[:-1]))) * dt)
    rms = math.sqrt(float(np.mean(v * v)))
    zeros = rising_crossings(t, psi, float(np.mean(psi)), 0.2 * float(np.std(psi)) if rms else 0.0)
    inside = (t >= zeros[0]) & (t < zeros[-1]) if zeros.size >= 2 else np.ones(t.size, dtype=bool)
    return psi - float(np.mean(psi[inside]))


def spim_field_flux(psi_sd: np.ndarray, psi_sq: np.ndarray, i_sq: np.ndarray, lsd_h: float, lsq_h: float,
                    msrd_h: float, msrq_h: float) -> np.ndarray:
    """The stator flux the SPIM paper's ISFOC orients on (eqs. (15)-(16), the symmetrised machine, k = M_srd/M_srq)
    from the measured physical winding fluxes, as a complex vector: psi_sd + j psi_sq1 with
    psi_sq1 = k (psi_sq - L_sq i_sq) + L_sd i_sq / k (stated machine parameters)."""
    k = msrd_h / msrq_h
    return psi_sd + 1j * (k * (psi_sq - lsq_h * i_sq) + lsd_h * i_sq / k)


def flux_amplitude(psi: np.ndarray) -> float:
    """The amplitude of a sinusoidal flux linkage from its rms."""
    return math.sqrt(2.0 * float(np.mean(psi * psi)))


@dataclass(frozen=True)
class PowerFlow:
    input_w: float           # DC link
    terminal_w: float        # motor terminals (sum of the winding elements)
    shaft_w: float
    inverter_loss_w: float
    motor_loss_w: float
    motor_efficiency_pct: float
    drive_efficiency_pct: float


def power_flow(input_w: float, terminal_w: float, shaft_w: float) -> PowerFlow:
    """Losses and efficiencies from the analyser's three powers (NaN where a power is not judged)."""
    eff = (lambda out, inp: 100.0 * out / inp if inp > 0 and math.isfinite(out) else math.nan)
    return PowerFlow(input_w, terminal_w, shaft_w, input_w - terminal_w, terminal_w - shaft_w,
                     eff(shaft_w, terminal_w), eff(shaft_w, input_w))


def field_angle_rows(truths: Any, t_daq: np.ndarray, signals: dict[str, np.ndarray],
                     t_rows: np.ndarray) -> dict[str, np.ndarray]:
    """The rig's measured field angle (and SPIM flux) on the telemetry's rows from a DAQ record of the run
    ([rig_truths], drivers.contract.instruments.RigTruthsConfig); NaN outside the record or where it clipped."""
    out: dict[str, np.ndarray] = {}
    inside = (t_rows >= t_daq[0]) & (t_rows <= t_daq[-1]) if t_daq.size else np.zeros(t_rows.size, dtype=bool)
    if truths.method == "encoder":
        enc = signals["encoder_angle_mech_rad"]
        theta = np.unwrap(truths.get("encoder_index_elec_rad") + int(truths.get("pole_pairs")) * enc)
        good = np.isfinite(theta)
        angle = np.interp(t_rows, t_daq[good], theta[good]) if good.any() else np.full(t_rows.size, np.nan)
    else:
        u_d, u_q, i_d, i_q = (signals[n] for n in ("u_main_v", "u_aux_v", "i_main_a", "i_aux_a"))
        # from the record's start at standstill with the windings dead: the flux starts at zero, no constant to remove
        psi_d = _integral(t_daq, u_d - truths.get("rs_main_ohm") * i_d)
        psi_q = _integral(t_daq, u_q - truths.get("rs_aux_ohm") * i_q)
        field = spim_field_flux(psi_d, psi_q, i_q, truths.get("lsd_h"), truths.get("lsq_h"), truths.get("msrd_h"),
                                truths.get("msrq_h"))
        good = np.isfinite(field)
        if not good.all():               # an integral is lost from its first clipped sample on
            inside &= t_rows < t_daq[np.argmin(good)]
        angle = np.interp(t_rows, t_daq[good], np.unwrap(np.angle(field[good]))) if good.any() \
            else np.full(t_rows.size, np.nan)
        flux = np.interp(t_rows, t_daq[good], np.abs(field[good])) if good.any() else np.full(t_rows.size, np.nan)
        out["flux_true_wb"] = np.where(inside, flux, np.nan)
    out["field_angle_elec_rad"] = np.where(inside, angle, np.nan)
    return out


def _integral(t: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Trapezoidal running integral, 0 at the first sample."""
    return np.concatenate(([0.0], np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(t))))


def measured_pos_err(field_angle: np.ndarray, pos_est: np.ndarray) -> np.ndarray:
    """pos_err_elec_rad as the drive defines it: the true field angle minus the estimated, wrapped."""
    return wrap(field_angle - pos_est)
