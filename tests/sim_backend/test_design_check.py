"""Design check of the MRAS estimators, PMSM paper eq. (13)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_backend.design_check import (characteristic_polynomial, estimator_gains, format_table,
                                      run_design_check)
from sim_backend.drive import load_motor_config

CONFIG = "config/motors/pmsm-paper.toml"


def mimo_determinant(s: complex, w: float, psi: float, a1: float, kp_w: float, ki_w: float, kp_psi: float,
                     ki_psi: float) -> complex:
    """det(I + diag(Gc_w, Gc_psi) G) straight from eq. (9)."""
    F = s + a1
    D = F * F + w * w
    G = np.array([[(s * s + a1 * s + w * w) / (s * D), w * F / (psi * D)],
                  [-a1 * psi / (w * s * D), 1.0 / D]])
    C = np.diag([kp_w + ki_w / s, kp_psi + ki_psi / s])
    return complex(np.linalg.det(np.eye(2) + C @ G))


def test_polynomial_equals_cleared_determinant():
    gains = estimator_gains(load_motor_config(CONFIG))
    rng = np.random.default_rng(0)
    for w in (0.1, -3.0, 150.0, 314.0):
        poly = characteristic_polynomial(w, **gains)
        assert len(poly) == 8  # degree 7: the paper's seven poles
        for _ in range(5):
            s = complex(rng.normal(0, 300), rng.normal(0, 300))
            D = (s + gains["a1"]) ** 2 + w * w
            expected = mimo_determinant(s, w, 0.26, **gains) * s ** 3 * D ** 2
            assert np.polyval(poly, s) == pytest.approx(expected, rel=1e-9)


def test_paper_gains_are_stable_over_fig6_range():
    result = run_design_check(CONFIG)
    assert result["pole_count"] == 7
    assert result["max_real_part"] < 0 and result["stable"]
    speeds = [e["speed_elec_rad_s"] for e in result["per_speed"]]
    assert min(speeds) == pytest.approx(-314) and max(speeds) == pytest.approx(314)
    assert min(abs(v) for v in speeds) == pytest.approx(0.1)
    a1 = result["gains"]["a1"]
    for entry in result["per_speed"]:  # two poles are always -a1 +- j w (D divides the polynomial)
        poles = np.array([complex(*p) for p in entry["poles"]])
        target = complex(-a1, abs(entry["speed_elec_rad_s"]))
        assert np.min(np.abs(poles - target)) < 1e-6 * abs(target)
    ls = result["least_stable"]
    assert ls["pole"][0] == result["max_real_part"]


def test_unstable_gains_are_reported(tmp_path):
    text = open(CONFIG, encoding="utf-8").read().replace("flux_est_kp = 5000.0", "flux_est_kp = -5000.0")
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    result = run_design_check(bad, speeds=[1.0, 100.0])
    assert result["max_real_part"] >= 0 and not result["stable"]
    assert "UNSTABLE" in format_table(result)


def test_table_lists_every_speed():
    result = run_design_check(CONFIG, speeds=[-10.0, 10.0, 200.0])
    table = format_table(result)
    assert len(table.splitlines()) == 4 + 3 + 1
    assert "all poles in the left half plane" in table


def test_missing_gain_names_file_and_field(tmp_path):
    from drivers.contract.errors import InputError
    text = open(CONFIG, encoding="utf-8").read().replace("flux_est_kp = 5000.0", "")
    bad = tmp_path / "nogain.toml"
    bad.write_text(text)
    with pytest.raises(InputError, match=r"nogain\.toml: \[firmware\] flux_est_kp: missing"):
        run_design_check(bad)


def test_non_pmsm_config_is_refused_clearly(tmp_path):
    from drivers.contract.errors import InputError
    other = tmp_path / "other.toml"
    other.write_text('[motor]\nkind = "spim"\n')
    with pytest.raises(InputError, match=r"other\.toml: \[motor\] kind: .*needs kind = 'pmsm'"):
        run_design_check(other)
