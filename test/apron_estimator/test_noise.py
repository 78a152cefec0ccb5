"""Part 5 on the estimator: with sensor noise three times the configured σ the filters stay
consistent (NEES ≈ 1) because they learn the noise from their innovations (NoiseScale,
covariance matching); without it they are overconfident (NEES ≈ 9) and gate half the
camera frames. At the configured noise nothing changes."""

from __future__ import annotations

import math
import random

from apron_estimator.horizontal import HorizontalParams, HorizontalTracker, NoiseScale
from apron_estimator.vertical import VerticalFilter, VerticalParams
import pytest

SEEDS = (1, 2, 3)


def vertical_run(noise_factor: float, adapt: bool, seed: int, duration_s: float = 60.0):
    """Vehicle swinging 0.3 m over a deck heaving 0.15 m (6 s); lidar, altitude and vertical
    speed noise × ``noise_factor``. Mean NEES of the height h = z_v − z_s after 10 s."""
    rng = random.Random(seed)
    vf = VerticalFilter(VerticalParams(adapt_noise=adapt))
    s_lidar = vf.params.sigma_lidar_m * noise_factor
    nees = []
    for k in range(round(duration_s * 100)):
        t = k * 0.01
        zv, vz = 1.5 + 0.3 * math.sin(0.5 * t), 0.15 * math.cos(0.5 * t)
        az = -0.075 * math.sin(0.5 * t)
        zs = 0.6 + 0.15 * math.sin(2 * math.pi * t / 6.0)
        vf.on_accel(t, az + rng.gauss(0.0, 0.1))
        vf.on_altitude(t, zv + rng.gauss(0.0, 0.05 * noise_factor),
                       vz + rng.gauss(0.0, 0.05 * noise_factor))
        vf.on_lidar(t, (zv - zs) + rng.gauss(0.0, s_lidar))
        if t > 10.0:
            P = vf.P
            var = P[0][0] - 2.0 * P[0][2] + P[2][2]
            e = (vf.x[0] - vf.x[2]) - (zv - zs)
            nees.append(e * e / var)
    return sum(nees) / len(nees), vf


def horizontal_run(noise_factor: float, adapt: bool, seed: int, duration_s: float = 60.0,
                   height_m: float = 1.5):
    """A beacon drifting at (0.1, 0.05) m/s, 50 Hz camera, noise × ``noise_factor`` of the
    configured σ(h). Mean NEES per axis of the relative position after 10 s."""
    rng = random.Random(seed)
    hp = HorizontalParams(adapt_noise=adapt)
    tr = HorizontalTracker(hp)
    sig = hp.sigma_m(height_m) * noise_factor
    nees = []
    for k in range(round(duration_s * 50)):
        t = k * 0.02
        x, y = 0.5 + 0.1 * t, -0.3 + 0.05 * t
        tr.on_accel(t, 0.0, 0.0)
        tr.update(t, [(x + rng.gauss(0.0, sig), y + rng.gauss(0.0, sig))], height_m)
        if t > 10.0 and tr.tracked:
            kf = tr.kf
            nees.append(0.5 * ((kf.px - x) ** 2 / kf.ax + (kf.py - y) ** 2 / kf.ay))
    return sum(nees) / max(1, len(nees)), len(nees), tr


@pytest.mark.parametrize('seed', SEEDS)
def test_vertical_filter_stays_consistent_at_three_times_the_lidar_noise(seed):
    nees_fixed, _ = vertical_run(3.0, adapt=False, seed=seed)
    nees, vf = vertical_run(3.0, adapt=True, seed=seed)
    assert nees_fixed > 4.0                       # overconfident: the variance is 9× too small
    assert 0.4 < nees < 1.6                       # consistent (1 expected; lag makes it < 1)
    assert 6.0 < vf.lidar_noise.scale < 12.0      # the learnt variance scale, truth 9
    assert vf.rejected['outlier'] <= 5            # of 6000 samples: no jump taken for noise
    assert vf.surface_epoch == 0


@pytest.mark.parametrize('seed', SEEDS)
def test_horizontal_tracker_stays_consistent_at_three_times_the_camera_noise(seed):
    nees_fixed, _, tr_fixed = horizontal_run(3.0, adapt=False, seed=seed)
    nees, n, tr = horizontal_run(3.0, adapt=True, seed=seed)
    assert nees_fixed > 4.0
    assert tr_fixed.rejected['gated'] > 0.3 * 3000    # half the frames gated away
    assert 0.4 < nees < 1.6 and n > 2400
    assert 6.0 < tr.noise.scale < 12.0
    assert tr.rejected['gated'] < 0.02 * 3000


@pytest.mark.parametrize('seed', SEEDS)
def test_at_the_configured_noise_adaptation_changes_little(seed):
    a, vf = vertical_run(1.0, adapt=True, seed=seed)
    b, _ = vertical_run(1.0, adapt=False, seed=seed)
    assert vf.lidar_noise.scale < 1.3 and abs(a - b) < 0.2
    c, _, tr = horizontal_run(1.0, adapt=True, seed=seed)
    d, _, _ = horizontal_run(1.0, adapt=False, seed=seed)
    assert tr.noise.scale < 1.3 and abs(c - d) < 0.2


def test_noise_scale_is_clamped_and_robust_to_one_outlier():
    ns = NoiseScale(weight=0.02, max_scale=25.0)
    for _ in range(500):
        ns.update(0.5, 0.5, 1.0)      # ν² equal to the prior variance: R looks like zero
    assert ns.scale == 1.0            # never below the configured noise
    ns.update(1e9, 0.0, 1.0)          # one wild innovation
    assert ns.scale <= 1.0 + 0.02 * 4 * 25.0
    for _ in range(2000):
        ns.update(1e4, 0.0, 1.0)
    assert ns.scale == 25.0
    ns.update(math.nan, 0.0, 1.0)
    assert ns.scale == 25.0 and ns.samples == 2501
