"""Predictions of the drawn shaft signatures from the papers' equations and the motor data (config/motors/*.toml: the
motor's data sheet and the drive's tuning a lab is given), never from the simulator.

PMSM (MRAS/IRFOC paper): a kick of +m elec rad on rho^ is returned by the MRAS (eq. 13's poles; eq. 15a: no steady
angle error with i_sx = 0 and nominal parameters), so rho^ = int w^ (5c) gives back m: int (w - w^) dt = m / p
(mech). The speed PI on w^ moves its integrator by the change of the torque current only, so over a window that
starts and ends at steady state:
    int (w - w*_step) dt = m/p  -  D|D| / (2 R)  -  (dT_L + B D) / (J^ w_c^2 z)
with D the reference step (mech rad/s), R the firmware's reference ramp, dT_L the load-torque change, B the viscous
friction, and the PI's k_i = J^ w_c^2 z / K_t^ (K_t^ = K_t: the torque current change is (dT_L + B D)/K_t).

SPIM (ISFOC paper): the slip PI makes the model q-current of eq. (33), with the firmware's tau_r^ = L_r / R_r^,
equal the measured one, which the machine sets with its true tau_r; the speed loop holds w^ = (w_s - w^_sl)/n_p at
the reference, so the shaft runs (w^_sl - w_sl)/n_p faster (i_sq = T_e / (n_p phi), eq. 27).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.contract.toml_file import read_toml_file


def read_toml(path) -> dict:
    return read_toml_file(path)[0]


@dataclass(frozen=True)
class PmsmData:
    pole_pairs: int
    viscous: float          # N*m/(rad/s)
    inertia_fw: float       # kg m^2, the speed loop's tuning inertia
    speed_bw: float         # rad/s, speed-loop crossover
    zero_fraction: float    # PI zero at this fraction of the crossover
    ramp: float             # mech rad/s^2, the firmware's reference ramp
    rated_torque: float     # N*m

    @classmethod
    def from_motor(cls, path) -> "PmsmData":
        m = read_toml(path)
        fw, pl = m["firmware"], m["plant"]
        rated = 1.5 * m["motor"]["pole_pairs"] * pl["flux_wb"] * pl["rated_current_a"]     # amplitude-invariant
        return cls(m["motor"]["pole_pairs"], m["mechanics"]["viscous_nm_s_rad"], fw["inertia_kgm2"],
                   fw["speed_loop_bandwidth_rad_s"], fw["speed_pi_zero_fraction"], fw["speed_ramp_mech_rad_s2"],
                   min(rated, pl["max_torque_nm"]))

    def shaft_angle(self, kick: float, step: float, load_change: float) -> float:
        """int (w - w*_step) dt over a window from before to after the events, mech rad."""
        ki_kt = self.inertia_fw * self.speed_bw ** 2 * self.zero_fraction
        ramp_lag = step * abs(step) / (2.0 * self.ramp)
        return kick / self.pole_pairs - ramp_lag - (load_change + self.viscous * step) / ki_kt


@dataclass(frozen=True)
class SpimData:
    pole_pairs: int
    rr: float
    lr: float
    lsd: float
    msrd: float
    flux_ref: float
    viscous: float
    inertia: float
    ramp: float
    speed_kp: float         # IP speed loop: N*m/(rad/s) on the estimate
    speed_ki: float         # N*m/rad on the error: on a ramp a the integrator needs ki e = kp a
    speed_filter: float     # rad/s, low-pass on the speed estimate the loop runs on

    @classmethod
    def from_motor(cls, path) -> "SpimData":
        m = read_toml(path)
        pl, fw = m["plant"], m["firmware"]
        return cls(m["motor"]["pole_pairs"], pl["rr_ohm"], pl["lr_h"], pl["lsd_h"], pl["msrd_h"],
                   fw["stator_flux_ref_wb"], m["mechanics"]["viscous_nm_s_rad"], m["mechanics"]["inertia_kgm2"],
                   fw["speed_ramp_rad_s2"], fw["speed_kp_nm_s_rad"], fw["speed_ki_nm_rad"],
                   fw["speed_filter_rad_s"])

    def slip(self, torque: float, rr: float) -> float:
        """Slip (elec rad/s) at which eq. (33) with rotor resistance rr gives the q-current of `torque` (eq. 27)."""
        sigma = 1.0 - self.msrd ** 2 / (self.lsd * self.lr)
        tau = self.lr / rr
        i_sq = torque / (self.pole_pairs * self.flux_ref)
        a = i_sq * self.lsd * (tau * sigma) ** 2
        b = (1.0 - sigma) * tau * self.flux_ref
        c = i_sq * self.lsd
        if abs(a) < 1e-12:
            return c / b
        return (b - math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)      # the small-slip branch

    def rr_offset(self, torque: float, factor: float) -> float:
        """Shaft speed above the reference (mech rad/s) with the firmware's R_r x factor at electrical torque."""
        return (self.slip(torque, self.rr * factor) - self.slip(torque, self.rr)) / self.pole_pairs
