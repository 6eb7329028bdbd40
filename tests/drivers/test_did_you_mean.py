"""An unknown key close to an allowed one is answered with "did you mean": one line still, the allowed keys still
listed; a key close to none gets no guess."""

from __future__ import annotations

import pytest

from drivers.contract.checks import Problems
from drivers.contract.errors import InputError

ALLOWED = ("overcurrent_a", "overspeed_mech_rad_s", "overspeed_rpm", "vdc_max_v")


def _lines(table: dict) -> list[str]:
    p = Problems("s.toml")
    p.unknown_keys(table, ALLOWED, "limits")
    with pytest.raises(InputError) as err:
        p.raise_if_any()
    return err.value.problems


def test_a_typo_gets_the_key_it_was_meant_to_be():
    assert _lines({"overcurent_a": 10.0}) == [
        "s.toml: limits.overcurent_a: unknown key; did you mean 'overcurrent_a'? (allowed: overcurrent_a, "
        "overspeed_mech_rad_s, overspeed_rpm, vdc_max_v)"]


def test_a_key_close_to_none_gets_no_guess():
    assert _lines({"colour": 1}) == [
        "s.toml: limits.colour: unknown key (allowed: overcurrent_a, overspeed_mech_rad_s, overspeed_rpm, vdc_max_v)"]
