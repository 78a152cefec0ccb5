"""The smooth 1-D reference generator: continuity, limits, no overshoot, ramps, shift."""

import itertools
import math
import random

from hypothesis import given, settings
from hypothesis import strategies as st
from landing_planner.reference import (
    ReferenceGenerator,
    ReferenceLimits,
    stopping_displacement,
)
import pytest

A, J, DT = 0.5, 2.0, 0.01


def run(gen, target, vmax, t_end, dt=DT):
    zs, vs, accs = [gen.z_m], [gen.z_dot_mps], [gen.z_ddot_mps2]
    for _ in range(round(t_end / dt)):
        z, v, a = gen.step(target, vmax, dt)
        zs.append(z)
        vs.append(v)
        accs.append(a)
    return zs, vs, accs


def test_descent_start_has_no_step_in_rate_and_bounded_accel_and_jerk():
    gen = ReferenceGenerator(ReferenceLimits(A, J), 2.0)
    _zs, vs, accs = run(gen, 0.5, 0.4, 8.0)
    # ż_d is continuous: it changes by at most A·dt per step (a step to 0.4 would be 0.4)
    assert max(abs(b - a) for a, b in itertools.pairwise(vs)) <= A * DT + 1e-12
    assert max(abs(a) for a in accs) <= A + 1e-12
    # z̈_d is continuous too (jerk-limited): the (16) feed-forward never steps
    assert max(abs(b - a) for a, b in itertools.pairwise(accs)) <= J * DT + 1e-12
    # first step moves the rate by a jerk-limited amount only
    assert abs(vs[1]) <= 0.5 * J * DT * DT + 1e-12


def test_reaches_target_without_overshoot_both_directions():
    for start, target in ((2.0, 0.5), (0.5, 3.5), (0.0, 0.02)):
        gen = ReferenceGenerator(ReferenceLimits(A, J), start)
        zs, vs, _ = run(gen, target, 0.4, 15.0)
        sign = math.copysign(1.0, target - start)
        assert max(sign * (z - target) for z in zs) <= 1e-9
        assert zs[-1] == target and vs[-1] == 0.0


def test_ramp_at_constant_speed():
    gen = ReferenceGenerator(ReferenceLimits(A, J), 0.0)
    zs, vs, accs = run(gen, -10.0, 0.4, 20.0)
    # after the jerk-limited start (< 1.5 s) the rate is exactly the commanded speed
    mid = range(int(2.0 / DT), int(15.0 / DT))
    assert all(abs(vs[i] + 0.4) < 1e-9 for i in mid)
    assert all(abs(accs[i]) < 1e-9 for i in mid)
    # and z_d is a straight line of slope −0.4 m/s
    i0, i1 = mid.start, mid.stop - 1
    assert (zs[i1] - zs[i0]) / ((i1 - i0) * DT) == pytest.approx(-0.4, abs=1e-9)
    assert max(abs(v) for v in vs) <= 0.4 + 1e-9


def test_shift_moves_position_only():
    gen = ReferenceGenerator(ReferenceLimits(A, J), 2.0)
    run(gen, 0.5, 0.4, 1.5)
    before = gen.state()
    gen.shift(-0.6)
    after = gen.state()
    assert after[0] == pytest.approx(before[0] - 0.6, abs=1e-12)
    assert after[1:] == before[1:]
    # and the next step continues smoothly (no rate step) toward the same target
    gen.step(0.5, 0.4, DT)
    assert abs(gen.z_dot_mps - after[1]) <= A * DT + 1e-12


def test_speed_limit_change_decelerates_smoothly():
    """DESCEND 0.4 m/s → FINAL 0.2 m/s: the rate falls at ≤ A, no step."""
    gen = ReferenceGenerator(ReferenceLimits(A, J), 2.0)
    run(gen, -5.0, 0.4, 3.0)
    _, vs, _accs = run(gen, -5.0, 0.2, 3.0)
    assert max(abs(b - a) for a, b in itertools.pairwise(vs)) <= A * DT + 1e-12
    assert vs[-1] == pytest.approx(-0.2, abs=1e-9)
    assert min(vs) >= -0.4 - 1e-9


def test_stopping_point_is_where_it_stops():
    rng = random.Random(7)
    for _ in range(20):
        v = rng.uniform(-0.6, 0.6)
        a = rng.uniform(-A, A)
        gen = ReferenceGenerator(ReferenceLimits(A, J), 1.0)
        gen.reset(1.0, v, a)
        stop = gen.stopping_point()
        zs, _vs, _ = run(gen, stop, 1.0, 6.0, dt=0.001)
        assert zs[-1] == pytest.approx(stop, abs=2e-3)


def test_stopping_displacement_of_trapezoid_matches_closed_form():
    # from rest-acceleration a=0, v large: a ramps to −A (A/J s), holds, ramps back
    v = 1.0
    d = stopping_displacement(v, 0.0, A, J)
    # time-symmetric profile: distance = v · (v/A + A/J) / 2
    assert d == pytest.approx(v * (v / A + A / J) / 2.0, rel=1e-9)
    assert stopping_displacement(-v, 0.0, A, J) == pytest.approx(-d, rel=1e-12)


def test_bad_input_leaves_state_unchanged():
    gen = ReferenceGenerator(ReferenceLimits(A, J), 1.0)
    run(gen, 0.0, 0.4, 0.5)
    s = gen.state()
    for args in ((math.nan, 0.4, DT), (0.0, math.inf, DT), (0.0, 0.4, -DT), (0.0, 0.4, 0.0)):
        assert gen.step(*args) == s
    gen.shift(math.nan)
    gen.reset(math.nan)
    assert gen.state() == s


def test_limits_validated():
    with pytest.raises(ValueError, match='max_jerk_mps3'):
        ReferenceLimits(0.5, 0.0)
    with pytest.raises(ValueError, match='max_accel_mps2'):
        ReferenceLimits(math.nan, 1.0)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(start=st.floats(-2.0, 2.0), target=st.floats(-2.0, 2.0),
       vmax=st.floats(0.1, 1.5), v0=st.floats(-0.3, 0.3))
def test_property_bounded_and_no_overshoot(start, target, vmax, v0):
    gen = ReferenceGenerator(ReferenceLimits(A, J), start)
    gen.reset(start, v0, 0.0)
    zs, vs, accs = run(gen, target, vmax, abs(target - start) / vmax + 8.0)
    assert all(map(math.isfinite, zs))
    assert max(abs(a) for a in accs) <= A + 1e-12
    assert max(abs(b - a) for a, b in itertools.pairwise(accs)) <= J * DT + 1e-9
    # the initial motion may be impossible to stop before the target; from the first
    # standstill on (v0 braked), the reference never passes the target
    i0 = next((i for i, v in enumerate(vs) if v * v0 <= 0.0), 0) if v0 != 0.0 else 0
    sign = math.copysign(1.0, target - zs[i0])
    assert max(sign * (z - target) for z in zs[i0:]) <= 1e-5   # rounding of the phases: µm
    assert zs[-1] == pytest.approx(target, abs=1e-3)
    assert max(abs(v) for v in vs) <= max(vmax, abs(v0)) * 1.02 + 1e-6
