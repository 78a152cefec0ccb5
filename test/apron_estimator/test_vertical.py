"""Vertical filter: heaving deck, surface jumps (re-base), dropouts, outliers, bad input."""

from dataclasses import astuple
import math
import random

from apron_estimator.vertical import VerticalFilter, VerticalParams
from filterpy.kalman import KalmanFilter
import numpy as np
import pytest


def deck(t, irregular):
    """Deck height, speed, acceleration: one sinusoid or three incommensurate ones."""
    comps = ((0.5, 2 * math.pi / 6.0, 0.0),) if not irregular else (
        (0.3, 2 * math.pi / 5.0, 0.3), (0.25, 2 * math.pi / 7.3, 1.1),
        (0.15, 2 * math.pi / 3.1, 2.0))
    z = 0.8 + sum(a * math.sin(w * t + p) for a, w, p in comps)
    v = sum(a * w * math.cos(w * t + p) for a, w, p in comps)
    acc = -sum(a * w * w * math.sin(w * t + p) for a, w, p in comps)
    return z, v, acc


def fly(vf, duration_s, surface, seed, start=0.0, vehicle=None, lidar=None):
    """Drive the filter at 400 Hz accel / 100 Hz lidar / 20 Hz altitude; yield (t, truth)."""
    rng = random.Random(seed)
    dt = 0.0025
    for k in range(int(duration_s / dt)):
        t = start + k * dt
        zs, vs, acc_s = surface(t)
        zv, vv = vehicle(t) if vehicle else (3.0, 0.0)
        vf.on_accel(t, rng.gauss(0.0, 0.2))
        if k % 4 == 0:
            rng_m = zv - zs + rng.gauss(0.0, 0.02)
            vf.on_lidar(t, lidar(t, rng_m) if lidar else rng_m)
        if k % 20 == 0:
            vf.on_altitude(t, zv + rng.gauss(0.0, 0.3), vv + rng.gauss(0.0, 0.1))
        if k % 4 == 0:
            yield t, (zv, vv, zs, vs, acc_s)


def closing_speed_errors(model, irregular, seed=1):
    vf = VerticalFilter(VerticalParams(surface_model=model))
    errs, accs = [], []
    for t, (_, vv, _, vs, acc_s) in fly(vf, 40.0, lambda t: deck(t, irregular), seed):
        if t > 10.0:
            errs.append(vf.state(t).closing_speed_mps - (vv - vs))
            accs.append(acc_s)
    return errs, accs


@pytest.mark.parametrize('irregular', [False, True])
def test_closing_speed_unbiased_under_heave_and_better_than_two_state(irregular):
    rms = {}
    for model in ('accel', 'velocity'):
        errs, accs = closing_speed_errors(model, irregular)
        n = len(errs)
        mean = sum(errs) / n
        rms[model] = math.sqrt(sum(e * e for e in errs) / n)
        # error regressed on the deck acceleration (s): a lagging model shows up here
        slope = sum(e * a for e, a in zip(errs, accs, strict=True)) / sum(a * a for a in accs)
        if model == 'accel':
            assert abs(mean) < 0.02
            assert abs(slope) < 0.08
    assert rms['accel'] < 0.1
    assert rms['accel'] < 0.7 * rms['velocity']


def jump_surface(t):
    """Ground until 5 s, a heaving deck (top 0.6 ± 0.3 m) under the lidar 5-15 s, ground."""
    if 5.0 <= t < 15.0:
        w = 2 * math.pi / 6.0
        return 0.6 + 0.3 * math.sin(w * t), 0.3 * w * math.cos(w * t), 0.0
    return 0.0, 0.0, 0.0


def run_jumps(params):
    vf = VerticalFilter(params)
    worst_after = 0.0
    heights = []
    for t, (zv, vv, zs, vs, _) in fly(vf, 20.0, jump_surface, seed=3,
                                      vehicle=lambda t: (2.0, 0.0)):
        s = vf.state(t)
        if 5.1 < t < 5.5 or 15.1 < t < 15.5:
            worst_after = max(worst_after, abs(s.closing_speed_mps - (vv - vs)))
            heights.append(abs(s.height_m - (zv - zs)))
    return vf, worst_after, max(heights)


def test_surface_jump_rebases_without_a_closing_speed_spike():
    vf, worst, height_err = run_jumps(VerticalParams())
    assert vf.surface_epoch == 2
    assert vf.last_rebase_m == pytest.approx(-(0.6 + 0.3 * math.sin(2 * math.pi * 15 / 6)),
                                             abs=0.05)
    assert worst < 0.3            # bounded transient while v_s is re-learnt
    assert height_err < 0.06
    # the same jumps treated as motion (re-base disabled) spike the closing speed
    naive, worst_naive, _ = run_jumps(VerticalParams(jump_threshold_m=50.0, jump_sigma=1e3))
    assert naive.surface_epoch == 0
    assert worst_naive > 2.0


def test_first_rebase_size_and_epoch_in_the_state():
    vf = VerticalFilter()
    for _t, _ in fly(vf, 5.5, jump_surface, seed=4, vehicle=lambda t: (2.0, 0.0)):
        pass
    s = vf.state(5.5)
    assert s.surface_epoch == 1 and s.valid
    assert s.last_rebase_m == pytest.approx(0.6 + 0.3 * math.sin(2 * math.pi * 5 / 6), abs=0.05)
    assert s.surface_height_m == pytest.approx(0.6 + 0.3 * math.sin(2 * math.pi * 5.5 / 6),
                                               abs=0.06)


def test_dropouts_and_timeout():
    vf = VerticalFilter()
    ground = lambda t: (0.0, 0.0, 0.0)  # noqa: E731
    dropout = lambda t, r: None if 3.0 <= t < 3.3 or 5.0 <= t < 6.0 else r  # noqa: E731
    valid = {}
    for t, (zv, _, zs, _, _) in fly(vf, 8.0, ground, seed=5, lidar=dropout):
        s = vf.state(t)
        valid[round(t, 2)] = s.valid
        assert abs(s.height_m - (zv - zs)) < (0.08 if s.valid else 0.3)
    assert valid[3.29] and valid[5.49]         # short gaps keep the estimate valid
    assert not valid[5.6] and not valid[5.99]  # > lidar_timeout_s (0.5 s)
    assert valid[6.1]
    assert vf.surface_epoch == 0
    assert vf.rejected['dropout'] == 130


def test_spikes_do_not_rebase_or_corrupt():
    vf = VerticalFilter()
    ground = lambda t: (0.0, 0.0, 0.0)  # noqa: E731
    spikes = {2.0: 1, 3.0: 2, 4.0: 1}   # start time → number of consecutive bad samples

    def lidar(t, r):
        for t0, n in spikes.items():
            if t0 <= t < t0 + 0.01 * n - 1e-9:
                return r - 1.2   # e.g. a bird or the deck edge flickering
        return r

    worst = 0.0
    for t, (zv, vv, zs, vs, _) in fly(vf, 6.0, ground, seed=6, lidar=lidar):
        if t > 1.0:
            s = vf.state(t)
            worst = max(worst, abs(s.height_m - (zv - zs)),
                        abs(s.closing_speed_mps - (vv - vs)) / 5.0)
    assert vf.surface_epoch == 0
    assert vf.rejected['outlier'] == 4
    assert worst < 0.06


def test_bad_input_never_raises_or_propagates():
    vf = VerticalFilter()
    for _t, _ in fly(vf, 1.0, lambda t: (0.0, 0.0, 0.0), seed=7):
        pass
    before = vf.state(1.0)
    vf.on_lidar(float('nan'), 2.0)
    vf.on_lidar(1.1, float('nan'))
    vf.on_lidar(1.1, float('inf'))     # REP-117 "no return"
    vf.on_lidar(1.1, 100.0)            # out of range
    vf.on_lidar(0.5, 2.0)              # far in the past
    vf.on_lidar(1.1, 2.0, roll_rad=1.2)
    vf.on_altitude(1.1, float('nan'))
    vf.on_altitude(1.1, 3.0, float('inf'))
    vf.on_accel(float('inf'), 0.0)
    vf.on_accel(0.2, 0.0)              # out of order
    r = vf.rejected
    assert r['nan'] == 5 and r['dropout'] == 1 and r['range'] == 1 and r['tilt'] == 1
    assert r['out_of_order'] == 2
    assert vf.state(1.0) == before
    assert all(math.isfinite(v) for v in astuple(vf.state(2.0)))


def test_not_valid_before_the_first_lidar_sample():
    vf = VerticalFilter()
    assert not vf.state(0.0).valid
    vf.on_altitude(0.0, 5.0, 0.0)
    assert not vf.state(0.1).valid
    vf.on_lidar(0.2, 4.2)
    s = vf.state(0.2)
    assert s.valid and s.height_m == pytest.approx(4.2)
    assert s.vehicle_altitude_m == pytest.approx(5.0) and s.surface_height_m == pytest.approx(0.8)


def test_lidar_is_tilt_corrected():
    vf = VerticalFilter()
    vf.on_lidar(0.0, 2.0 / (math.cos(0.2) * math.cos(-0.1)), roll_rad=0.2, pitch_rad=-0.1)
    assert vf.state(0.0).height_m == pytest.approx(2.0)


def test_predict_update_equal_filterpy():
    """The unrolled 5×5 predict / scalar updates against filterpy with the same F, Q, H, R."""
    p = VerticalParams(adapt_noise=False)   # a fixed R, as filterpy's
    vf = VerticalFilter(p)
    vf.on_altitude(0.0, 3.0, 0.1)
    vf.on_lidar(0.001, 2.5)
    kf = KalmanFilter(dim_x=5, dim_z=1)
    kf.x = np.array(vf.x, dtype=float).reshape(5, 1)
    kf.P = np.array(vf.P, dtype=float)
    rng = random.Random(9)
    t = 0.001
    tau, sa2, qv = p.surface_tau_s, p.surface_accel_sigma_mps2 ** 2, p.vehicle_accel_psd_m2ps3
    for _ in range(200):
        dt = rng.uniform(0.002, 0.02)
        t += dt
        phi = math.exp(-dt / tau)
        qs = 2 * sa2 / tau
        kf.F = np.array([[1, dt, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, dt, dt * dt / 2],
                         [0, 0, 0, 1, dt], [0, 0, 0, 0, phi]], dtype=float)
        Q = np.zeros((5, 5))
        Q[0:2, 0:2] = qv * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
        Q[2:5, 2:5] = qs * np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6],
                                     [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                                     [dt ** 3 / 6, dt ** 2 / 2, 0.0]])
        Q[4, 4] = sa2 * (1 - phi * phi)
        kf.Q = Q
        kf.predict()
        if rng.random() < 0.5:
            h = 2.5 + rng.gauss(0, 0.03)
            vf.on_lidar(t, h)
            kf.update(np.array([[h]]), R=p.sigma_lidar_m ** 2, H=np.array([[1., 0, -1, 0, 0]]))
        else:
            z = 3.0 + rng.gauss(0, 0.2)
            vf.on_altitude(t, z)
            kf.update(np.array([[z]]), R=p.sigma_altitude_m ** 2,
                      H=np.array([[1., 0, 0, 0, 0]]))
        assert np.allclose(kf.x.ravel(), vf.x, atol=1e-9)
        assert np.allclose(kf.P, np.array(vf.P), atol=1e-9)


@pytest.mark.parametrize('kwargs', [
    {'surface_model': 'jerk'}, {'jump_confirm': 0}, {'sigma_lidar_m': 0.0},
    {'range_min_m': 50.0}, {'max_tilt_rad': 2.0}])
def test_bad_params_raise(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        VerticalParams(**kwargs)
