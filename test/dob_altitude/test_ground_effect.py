"""Ground-effect gain γ of the paper's (4) and its clamps (dob_altitude.ground_effect)."""

import math

from dob_altitude.ground_effect import ground_effect_gain
from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

R = 0.127


def gamma_4(rho, r, z_p):
    """(4) written out independently: γ = 1 / (1 − ρ r² / (4 z_p)²)."""
    return 1.0 / (1.0 - rho * r ** 2 / (4.0 * z_p) ** 2)


@pytest.mark.parametrize('rho', [0.5, 1.0, 1.3])
@pytest.mark.parametrize('z_p', [0.09, 0.12, 0.2, 0.5, 1.0, 3.0])
def test_matches_equation_4_inside_the_clamps(rho, z_p):
    expected = gamma_4(rho, R, z_p)
    assert expected < 1.5  # the chosen heights are all above the clamp
    assert ground_effect_gain(rho, R, z_p, 0.05, 1.5) == pytest.approx(expected, rel=1e-12)


def test_far_from_ground_is_free_air():
    assert ground_effect_gain(1.0, R, 10.0) == pytest.approx(1.0, abs=1e-4)
    assert ground_effect_gain(1.0, R, math.inf) == 1.0
    assert ground_effect_gain(0.0, R, 0.2) == 1.0
    # a negative ρ (not physical) never gives γ < 1
    assert ground_effect_gain(-1.0, R, 0.2) == 1.0


def test_height_clamp_and_gain_clamp():
    at_min = ground_effect_gain(0.5, R, 0.05, 0.05, 3.0)
    assert at_min == pytest.approx(gamma_4(0.5, R, 0.05))
    # below the minimum height, negative heights, NaN and -inf are all "at the clamp"
    for h in (0.01, 0.0, -0.3, math.nan, -math.inf):
        assert ground_effect_gain(0.5, R, h, 0.05, 3.0) == at_min
    # with ρ = 1, (4) at z_p = 0.05 m is 1.676: capped to max_gain
    assert gamma_4(1.0, R, 0.05) > 1.5
    assert ground_effect_gain(1.0, R, 0.05, 0.05, 1.5) == 1.5
    assert ground_effect_gain(1.0, R, math.nan, 0.05, 1.5) == 1.5
    # where (4) has its pole (z_p = r √ρ / 4) or is negative beyond it: still the cap
    assert ground_effect_gain(1.0, R, R / 4.0, 0.01, 1.5) == 1.5
    assert ground_effect_gain(1.0, R, 0.02, 0.01, 1.5) == 1.5
    assert ground_effect_gain(1.0, R, 0.5, 0.05, 1.0) == 1.0


@settings(derandomize=True, max_examples=200, deadline=None)
@given(rho=st.floats(0.0, 2.0), h1=st.floats(-1.0, 50.0), h2=st.floats(-1.0, 50.0),
       gmax=st.floats(1.0, 3.0))
def test_bounded_and_non_increasing_with_height(rho, h1, h2, gmax):
    lo, hi = min(h1, h2), max(h1, h2)
    g_lo = ground_effect_gain(rho, R, lo, 0.05, gmax)
    g_hi = ground_effect_gain(rho, R, hi, 0.05, gmax)
    assert 1.0 <= g_hi <= g_lo <= gmax
