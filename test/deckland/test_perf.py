"""Fast-path rewrites of the closed-loop cores keep their meaning (deckland.batch.perf task)."""

import math
import random

from apron_estimator.horizontal import AccelIntegrator
from apron_estimator.vertical import VerticalFilter
from deck_simulator.sensors import Gps, GpsParams, Imu, ImuParams, normal_stream
from deckland.batch.perf import measure_realtime_factor
from landing_planner.planner import _finite
import pytest


def test_normal_stream_is_standard_normal_deterministic_and_keyed():
    a = normal_stream('1:imu:normal')
    xs = [a() for _ in range(20000)]
    n = len(xs)
    mean = sum(xs) / n
    var = sum((x - mean) ** 2 for x in xs) / (n - 1)
    kurt = sum((x - mean) ** 4 for x in xs) / n / var ** 2
    assert abs(mean) < 4.0 / math.sqrt(n)          # ~4 σ of the sample mean
    assert var == pytest.approx(1.0, abs=0.05)
    assert kurt == pytest.approx(3.0, abs=0.2)     # Gaussian tails, not uniform / Laplace
    again = normal_stream('1:imu:normal')
    assert [again() for _ in range(600)] == xs[:600]   # crosses block boundaries
    other = normal_stream('1:gps:normal')
    ys = [other() for _ in range(2000)]
    corr = sum(x * y for x, y in zip(xs, ys, strict=False)) / 2000
    assert ys != xs[:2000] and abs(corr) < 0.1


def test_block_size_does_not_change_the_stream():
    small, big = normal_stream('5:wind:normal', block=7), normal_stream('5:wind:normal')
    assert [small() for _ in range(50)] == [big() for _ in range(50)]


def test_sensor_without_a_normal_source_draws_rng_gauss_as_before():
    """Imu/Gps built from a Random only: value = truth + σ · gauss(0, 1) of that Random, in the
    historical order (attitude: yaw first; GPS: biases, then position, then velocity)."""
    p = ImuParams()
    imu, twin = Imu(p, random.Random(3)), random.Random(3)
    roll, pitch, yaw = imu.attitude(0.1, -0.2, 0.3)
    y = 0.3 + twin.gauss(0.0, p.yaw_noise_rad)
    assert roll == 0.1 + twin.gauss(0.0, p.attitude_noise_rad)
    assert pitch == -0.2 + twin.gauss(0.0, p.attitude_noise_rad)
    assert yaw == pytest.approx(y, abs=1e-15)
    gp = GpsParams()
    gps, twin = Gps(gp, random.Random(4)), random.Random(4)
    bx = twin.gauss(0.0, gp.bias_std_m)
    assert gps.bx == bx
    twin.gauss(0.0, gp.bias_std_m)
    twin.gauss(0.0, gp.alt_bias_std_m)
    pos, _ = gps.read(0.0, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    assert pos[0] == pytest.approx(1.0 + bx + twin.gauss(0.0, gp.noise_m), abs=1e-15)


def test_height_at_equals_state_height():
    vf = VerticalFilter()
    rng = random.Random(8)
    for k in range(300):
        t = 0.01 * k
        vf.on_accel(t, rng.gauss(0.0, 0.3))
        vf.on_altitude(t, 3.0 + rng.gauss(0.0, 0.1), rng.gauss(0.0, 0.1))
        vf.on_lidar(t, 2.2 + 0.2 * math.sin(t) + rng.gauss(0.0, 0.02))
    for t in (2.95, 2.99, 2.99 + 1e-9, 3.0, 3.05, 3.4):
        assert vf.height_at(t) == vf.state(t).height_m
    assert math.isnan(VerticalFilter().height_at(1.0))


def test_accel_integrals_fast_path_matches_exact_integration():
    """Piecewise-constant a: V = ∫a, X = ∫V, exact, queried before, inside and after."""
    acc = AccelIntegrator()
    samples = [(0.0, 1.0), (0.5, -2.0), (1.0, 0.5)]
    for t, a in samples:
        acc.add(t, a, -a)

    def exact(t):
        v = x = 0.0
        for i, (t0, a) in enumerate(samples):
            t1 = samples[i + 1][0] if i + 1 < len(samples) else math.inf
            if t <= t0:
                break
            d = min(t, t1) - t0
            x += v * d + 0.5 * a * d * d
            v += a * d
        return v, x

    for t in (-0.1, 0.0, 0.25, 0.5, 0.75, 1.0, 1.3, 2.0):
        vx, xx, vy, xy = acc.integrals(t)
        ev, ex = exact(t)
        assert (vx, xx) == (pytest.approx(ev, abs=1e-12), pytest.approx(ex, abs=1e-12))
        assert (vy, xy) == (pytest.approx(-ev, abs=1e-12), pytest.approx(-ex, abs=1e-12))


@pytest.mark.parametrize(('values', 'ok'), [
    ((0.0,), True), ((1.0, -2.0, 1e300), True), ((math.nan,), False), ((1.0, math.inf), False),
    ((math.inf, -math.inf), False), ((1.0, 'x'), False), ((None,), False),
])
def test_planner_finite_on_the_sum(values, ok):
    assert _finite(*values) is ok


def test_measure_realtime_factor_reports_one_run():
    r = measure_realtime_factor('paper', runs=1, seed=2)
    assert r['runs'] == 1 and r['sim_time_s'] > 1.0
    assert r['realtime_factor'] > 0.0 and r['realtime_factor_cpu'] > 0.0
    assert r['us_per_physics_step'] > 0.0
    with pytest.raises(ValueError, match='runs'):
        measure_realtime_factor(runs=0)


def test_displacement_equals_difference_of_integrals():
    """Δv = V(t1) − V(t0), Δp = X(t1) − X(t0) − V(t0)(t1 − t0), exactly, wherever t0/t1 fall."""
    rng = random.Random(11)
    acc = AccelIntegrator()
    t = 0.0
    for _ in range(200):
        t += rng.uniform(0.001, 0.02)
        acc.add(t, rng.gauss(0.0, 1.0), rng.gauss(0.0, 1.0))
    for _ in range(300):
        t0 = rng.uniform(-0.1, t + 0.1)
        t1 = t0 + rng.uniform(0.0, 0.5)
        v0x, x0x, v0y, x0y = acc.integrals(t0)
        v1x, x1x, v1y, x1y = acc.integrals(t1)
        want = ((x1x - x0x - v0x * (t1 - t0), v1x - v0x, x1y - x0y - v0y * (t1 - t0), v1y - v0y)
                if t1 > acc._t[0] else (0.0, 0.0, 0.0, 0.0))
        assert acc.displacement(t0, t1) == want
