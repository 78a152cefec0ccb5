"""The honest sensor models against the statistics they claim (docs/world/sensors.md).

Allan deviation of the IMU (noise density, bias random walk, its minimum at the bias
instability), Gauss–Markov autocorrelations and stationary variances, the EKF discretisation
against Van Loan's method, the LIDAR-Lite error envelope and beam footprint, the camera's
distortion round trip and calibration draws, the delay line's latency and stamps, and
determinism and independence of the named streams.
"""

from __future__ import annotations

import math
import random

from deck_simulator.sensor_camera import CameraModel, CameraModelParams, TrueCamera
from deck_simulator.sensor_ekf import AxisErrorParams, LocalPositionModel, LocalPositionParams
from deck_simulator.sensor_imu import (
    AttitudeModel,
    AttitudeModelParams,
    ImuModel,
    ImuModelParams,
    accel_world_through,
    body_rates_from_euler,
    euler_from_matrix,
    small_rotation,
)
from deck_simulator.sensor_lidar import (
    LidarLiteModel,
    LidarLiteParams,
    Surface,
    ground_plane,
    horizontal_rectangle,
)
from deck_simulator.sensor_models import (
    ModelStreams,
    SensorTiming,
    TimingParams,
    gauss_normal,
    model_streams,
    ou_coefficients,
    random_walk_from_instability,
)
from deck_simulator.sensor_suite import SENSOR_NAMES, SensorSuite, SensorSuiteParams
from deck_simulator.sensors import CameraParams, project_point
from deckland_common.frames import rot_body_to_world
import numpy as np
import pytest

G = 9.81


def streams(seed: int, name: str = 'x') -> ModelStreams:
    """Streams with random.gauss normals (the numpy streams are tested through the suite)."""
    return ModelStreams(random.Random(f'{seed}:{name}:draw'),
                        gauss_normal(random.Random(f'{seed}:{name}:noise')),
                        random.Random(f'{seed}:{name}:timing'),
                        gauss_normal(random.Random(f'{seed}:{name}:timing_noise')))


def timing(p: TimingParams, seed: object) -> SensorTiming:
    return SensorTiming(p, random.Random(f'{seed}:t'), gauss_normal(random.Random(f'{seed}:n')))


def allan(rate: np.ndarray, dt: float, m: int) -> float:
    """Overlapping Allan deviation of a rate sequence at τ = m dt."""
    theta = np.concatenate([[0.0], np.cumsum(rate) * dt])
    tau = m * dt
    d = theta[2 * m:] - 2.0 * theta[m:-m] + theta[:-2 * m]
    return float(np.sqrt(np.mean(d * d) / (2.0 * tau * tau)))


def autocorr(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))


# --- timing ---------------------------------------------------------------------------------

def test_latency_is_exactly_as_configured_without_jitter():
    p = TimingParams(rate_hz=40.0, latency_s=0.0125, random_phase=False)
    tm: SensorTiming[int] = timing(p, 1)
    for k in range(200):
        ts = tm.take()
        assert ts == pytest.approx(k / 40.0, abs=1e-12)
        deliver, stamp = tm.push(ts, k)
        assert deliver - ts == pytest.approx(0.0125, abs=1e-12)
        assert stamp == ts                          # 'sample' stamps, no offset, no jitter
    # nothing is delivered before its time, everything after, in order
    last = (199 / 40.0) + 0.0125
    assert tm.pop(0.0125 - 1e-9) == []
    got = tm.pop(last + 1e-9)
    assert [v for _, v in got] == list(range(200))
    assert tm.pending() == 0


def test_arrival_stamps_subtract_the_assumed_latency():
    p = TimingParams(rate_hz=50.0, latency_s=0.036, stamp_mode='arrival',
                     assumed_latency_s=0.030, random_phase=False)
    tm: SensorTiming[int] = timing(p, 2)
    for k in range(20):
        ts = tm.take()
        deliver, stamp = tm.push(ts, k)
        assert stamp == pytest.approx(deliver - 0.030, abs=1e-12)
        assert stamp - ts == pytest.approx(0.006, abs=1e-12)   # the latency it did not assume


def test_latency_jitter_has_the_configured_mean_and_sigma_and_keeps_fifo():
    p = TimingParams(rate_hz=100.0, latency_s=0.008, latency_jitter_s=0.003,
                     stamp_jitter_s=0.0005)
    tm: SensorTiming[int] = timing(p, 3)
    lat, err, delivers = [], [], []
    for k in range(20000):
        ts = tm.take()
        d, s = tm.push(ts, k)
        lat.append(d - ts)
        err.append(s - ts)
        delivers.append(d)
    lat_a = np.array(lat)
    assert min(lat) >= 0.0
    assert np.all(np.diff(delivers) >= 0.0)          # a link never reorders
    # log-normal (mean 8 ms, σ 3 ms); FIFO only lifts the rare sample overtaken by its predecessor
    assert lat_a.mean() == pytest.approx(0.008, abs=1e-4)
    assert lat_a.std() == pytest.approx(0.003, rel=0.05)
    assert np.std(err) == pytest.approx(0.0005, rel=0.05)
    assert abs(np.mean(err) - tm.stamp_offset_s) < 2e-5


def test_per_seed_clock_rate_phase_and_stamp_offset_follow_their_sigmas():
    p = TimingParams(rate_hz=50.0, clock_ppm_std=20.0, stamp_offset_std_s=0.003)
    ppm, phase, offset = [], [], []
    for seed in range(600):
        tm: SensorTiming[int] = timing(p, f'{seed}:t')
        ppm.append((tm.period_s * 50.0 - 1.0) * 1e6)
        phase.append(tm.next_sample_s / tm.period_s)
        offset.append(tm.stamp_offset_s)
    assert np.std(ppm) == pytest.approx(20.0, rel=0.12)
    assert min(phase) >= 0.0 and max(phase) < 1.0
    assert np.mean(phase) == pytest.approx(0.5, abs=0.05)
    assert np.std(offset) == pytest.approx(0.003, rel=0.12)


def test_polling_pattern_never_changes_what_is_delivered():
    p = TimingParams(rate_hz=100.0, latency_s=0.01, latency_jitter_s=0.004,
                     stamp_jitter_s=0.001)

    def run(poll_every: int) -> list[tuple[float, int]]:
        tm: SensorTiming[int] = timing(p, 9)
        out: list[tuple[float, int]] = []
        for k in range(4000):                  # a 400 Hz physics clock
            t = k / 400.0
            while tm.next_sample_s <= t:
                ts = tm.take()
                tm.push(ts, round(ts * 1e4))
            if k % poll_every == 0:
                out.extend(tm.pop(t))
        out.extend(tm.pop(math.inf))
        return out

    assert run(1) == run(37)


@pytest.mark.parametrize('field,value', [('rate_hz', 0.0), ('latency_s', -0.1),
                                         ('latency_jitter_s', 0.5), ('stamp_mode', 'gps'),
                                         ('clock_ppm_std', float('nan'))])
def test_timing_params_name_the_bad_field(field, value):
    kw = {'rate_hz': 50.0, 'latency_s': 0.01, field: value}
    with pytest.raises(ValueError, match=field):
        TimingParams(**kw)


# --- IMU ----------------------------------------------------------------------------------

@pytest.mark.slow
def test_bias_random_walk_bottoms_out_at_the_instability_and_noise_density_holds():
    """Allan deviation of a gyro at rest: N/√τ at short τ, K√(τ/3) at long τ, minimum B."""
    n_d, b_inst = 0.01, 0.01075                     # scaled so that τ* ≈ 1.7 s
    k_rw = random_walk_from_instability(b_inst, n_d)
    assert k_rw == pytest.approx(0.01, rel=1e-3)
    p = ImuModelParams(gyro_noise_density=n_d, gyro_vibration_density=0.0,
                       gyro_bias_instability=b_inst, gyro_turn_on_bias_std=0.0)
    dt = 0.01
    imu = ImuModel(p, streams(4), dt)
    eye = rot_body_to_world(0.0, 0.0, 0.0)
    w = np.array([imu.sample((0.0, 0.0, 0.0), eye, (0.0, 0.0, 0.0))[1][0]
                  for _ in range(200_000)])
    # tolerances: the statistical spread of an overlapping ADEV over 2000 s (checked over
    # seeds: ±1 % below 2 s, ±13 % at 10 s, ±22 % at 20 s)
    taus = (0.05, 0.2, 1.0, math.sqrt(3.0) * n_d / k_rw, 5.0, 10.0, 20.0)
    for tau in taus:
        m = round(tau / dt)
        expected = math.sqrt(n_d ** 2 / (m * dt) + k_rw ** 2 * m * dt / 3.0)
        rel = 0.04 if tau < 2.0 else (0.2 if tau <= 10.0 else 0.3)
        assert allan(w, dt, m) == pytest.approx(expected, rel=rel), tau
    curve = [allan(w, dt, m) for m in range(50, 800, 25)]
    assert min(curve) == pytest.approx(b_inst, rel=0.08)


def test_accelerometer_white_noise_matches_density_plus_vibration():
    p = ImuModelParams(accel_noise_density=0.002, accel_vibration_density=0.03,
                       accel_bias_instability=0.0, accel_turn_on_bias_std=0.0)
    dt = 0.01
    imu = ImuModel(p, streams(5), dt)
    eye = rot_body_to_world(0.0, 0.0, 0.0)
    f = np.array([imu.sample((0.0, 0.0, 0.0), eye, (0.0, 0.0, 0.0))[0]
                  for _ in range(40_000)])
    total = math.hypot(0.002, 0.03)
    for axis in range(3):
        assert allan(f[:, axis], dt, 10) == pytest.approx(total / math.sqrt(0.1), rel=0.04)
    assert f[:, 2].mean() == pytest.approx(G, abs=4 * total / math.sqrt(dt * len(f)))


def test_specific_force_is_body_flu_physics():
    """No noise: a level vehicle accelerating forward reads (a, 0, g); pitched nose-down
    (positive FLU pitch) at rest it reads (−g sinθ, 0, g cosθ)."""
    quiet = ImuModelParams(accel_noise_density=0.0, accel_vibration_density=0.0,
                           accel_bias_instability=0.0, accel_turn_on_bias_std=0.0,
                           gyro_noise_density=0.0, gyro_vibration_density=0.0,
                           gyro_bias_instability=0.0, gyro_turn_on_bias_std=0.0)
    imu = ImuModel(quiet, streams(6), 0.01, gravity_mps2=G)
    f, w = imu.sample((1.5, 0.0, 0.0), rot_body_to_world(0.0, 0.0, 0.0), (0.1, -0.2, 0.3))
    assert f == pytest.approx((1.5, 0.0, G), abs=1e-12)
    assert w == pytest.approx((0.1, -0.2, 0.3), abs=1e-12)
    th = 0.2
    f, _ = imu.sample((0.0, 0.0, 0.0), rot_body_to_world(0.0, th, 0.7), (0.0, 0.0, 0.0))
    assert f == pytest.approx((-G * math.sin(th), 0.0, G * math.cos(th)), abs=1e-12)


def test_turn_on_biases_are_drawn_per_seed_with_their_sigma():
    p = ImuModelParams()
    ba = np.array([ImuModel(p, streams(s), 0.01).accel_bias for s in range(500)])
    bg = np.array([ImuModel(p, streams(s), 0.01).gyro_bias for s in range(500)])
    assert ba.std() == pytest.approx(p.accel_turn_on_bias_std, rel=0.08)
    assert bg.std() == pytest.approx(p.gyro_turn_on_bias_std, rel=0.08)
    assert abs(np.corrcoef(ba[:, 0], bg[:, 0])[0, 1]) < 0.15


def test_body_rates_are_the_rotation_rate_of_the_euler_angles():
    """[ω]× = Rᵀ dR/dt, by central differences of the Z-Y-X rotation."""
    att, rates, h = np.array([0.3, -0.4, 1.2]), np.array([0.5, -0.2, 0.8]), 1e-6
    r = np.array(rot_body_to_world(*att))
    dr = (np.array(rot_body_to_world(*(att + h * rates)))
          - np.array(rot_body_to_world(*(att - h * rates)))) / (2.0 * h)
    w = r.T @ dr
    expected = (w[2, 1], w[0, 2], w[1, 0])
    assert body_rates_from_euler(att[0], att[1], *rates) == pytest.approx(expected, abs=1e-8)


# --- attitude estimate ------------------------------------------------------------------------

def test_attitude_drift_is_gauss_markov_with_its_tau_and_sigma():
    p = AttitudeModelParams(tilt_bias_std_rad=0.0, tilt_noise_rad=0.0, tilt_drift_std_rad=0.004,
                            tilt_drift_tau_s=5.0, yaw_bias_std_rad=0.0, yaw_noise_rad=0.0,
                            yaw_drift_std_rad=0.02, yaw_drift_tau_s=20.0)
    dt = 0.05
    m = AttitudeModel(p, streams(7), dt)
    e = np.array([m.error() for _ in range(200_000)])
    for axis, sigma, tau in ((0, 0.004, 5.0), (1, 0.004, 5.0), (2, 0.02, 20.0)):
        assert e[:, axis].std() == pytest.approx(sigma, rel=0.1)
        for lag_s in (0.5 * tau, tau, 2.0 * tau):
            assert autocorr(e[:, axis], round(lag_s / dt)) == pytest.approx(
                math.exp(-lag_s / tau), abs=0.06)


def test_default_heading_error_exceeds_tilt_error_and_tilt_stays_bounded():
    p = AttitudeModelParams()
    tilt, yaw = [], []
    for seed in range(60):
        m = AttitudeModel(p, streams(seed, 'att'), 0.01)
        for _ in range(3000):                       # 30 s, a landing
            e = m.error()
        tilt.append(math.hypot(e[0], e[1]))
        yaw.append(abs(e[2]))
    assert np.sqrt(np.mean(np.square(yaw))) > 3.0 * np.sqrt(np.mean(np.square(tilt)) / 2.0)
    bound = 6.0 * math.hypot(p.tilt_bias_std_rad, p.tilt_drift_std_rad)
    assert max(tilt) < bound


def test_estimated_attitude_is_the_true_one_rotated_by_the_world_frame_error():
    """R̂ = exp([e]×) R with e the model's world-frame error of that sample; a heading-only
    error leaves roll and pitch of a level vehicle untouched."""
    twin_a = AttitudeModel(AttitudeModelParams(), streams(8), 0.01)
    twin_b = AttitudeModel(AttitudeModelParams(), streams(8), 0.01)
    for roll, pitch, yaw in ((0.0, 0.0, 0.3), (0.1, -0.05, 2.0), (-0.2, 0.15, -1.0)):
        e = twin_a.error()
        est = twin_b.sample(roll, pitch, yaw)
        q = np.array(rot_body_to_world(*est)) @ np.array(rot_body_to_world(roll, pitch, yaw)).T
        assert np.allclose(q, np.array(small_rotation(*e)), atol=1e-12)
        assert np.linalg.norm(e) > 1e-4
    heading_only = AttitudeModelParams(tilt_bias_std_rad=0.0, tilt_drift_std_rad=0.0,
                                       tilt_noise_rad=0.0)
    m = AttitudeModel(heading_only, streams(9), 0.01)
    roll, pitch, yaw = m.sample(0.0, 0.0, 0.5)
    assert (roll, pitch) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert abs(yaw - 0.5) > 1e-4


def test_tilt_error_leaks_gravity_into_horizontal_acceleration():
    """Hovering level, f = (0, 0, g); through an estimate tilted by e about north the
    companion sees a horizontal acceleration g·(e_n, −e_e) and (to 2nd order) no vertical."""
    for e_east, e_north in ((0.01, 0.0), (0.0, -0.02), (0.005, 0.012)):
        est = euler_from_matrix(small_rotation(e_east, e_north, 0.0))
        a = accel_world_through((0.0, 0.0, G), *est, gravity_mps2=G)
        assert a[0] == pytest.approx(G * e_north, rel=1e-3, abs=1e-9)
        assert a[1] == pytest.approx(-G * e_east, rel=1e-3, abs=1e-9)
        assert abs(a[2]) < G * (e_east ** 2 + e_north ** 2)


def test_imu_and_true_attitude_give_back_the_true_acceleration():
    quiet = ImuModelParams(accel_noise_density=0.0, accel_vibration_density=0.0,
                           accel_bias_instability=0.0, accel_turn_on_bias_std=0.0)
    imu = ImuModel(quiet, streams(10), 0.01, gravity_mps2=G)
    att = (0.12, -0.3, 2.2)
    f, _ = imu.sample((0.4, -1.1, 0.7), rot_body_to_world(*att), (0.0, 0.0, 0.0))
    assert accel_world_through(f, *att, gravity_mps2=G) == pytest.approx((0.4, -1.1, 0.7),
                                                                         abs=1e-12)


# --- EKF local position -------------------------------------------------------------------

def _expm(m: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring of a Taylor series (numpy only)."""
    s = max(0, int(np.ceil(np.log2(max(np.abs(m).sum(axis=1).max(), 1e-300)))) + 4)
    a = m / 2.0 ** s
    out, term = np.eye(len(m)), np.eye(len(m))
    for k in range(1, 30):
        term = term @ a / k
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


@pytest.mark.parametrize('tau_v,tau_p,h', [(2.0, 4.0, 0.02), (1.0, 1.0, 0.02), (0.5, 3.0, 1.5),
                                           (3.0, 3.0000001, 0.1)])
def test_ekf_discretisation_matches_van_loan(tau_v, tau_p, h):
    from deck_simulator.sensor_ekf import _Axis
    ap = AxisErrorParams(bias_std_m=0.0, bias_random_walk_m_rts=0.0, velocity_std_mps=0.05,
                         velocity_tau_s=tau_v, position_tau_s=tau_p)
    ax = _Axis(ap, h, [0.0, 0.0, 0.0])
    a = np.array([[-1.0 / tau_v, 0.0], [1.0, -1.0 / tau_p]])
    q = 2.0 * 0.05 ** 2 / tau_v
    big = np.zeros((4, 4))
    big[:2, :2], big[:2, 2:], big[2:, 2:] = -a, np.diag([q, 0.0]), a.T
    e = _expm(big * h)
    phi = e[2:, 2:].T
    qd = phi @ e[:2, 2:]
    assert np.allclose([[ax.f11, 0.0], [ax.f21, ax.f22]], phi, rtol=1e-10, atol=1e-14)
    chol = np.array([[ax.c11, 0.0], [ax.c21, ax.c22]])
    assert np.allclose(chol @ chol.T, qd, rtol=1e-7, atol=1e-16)


@pytest.mark.slow
def test_ekf_error_is_coloured_and_its_velocity_belongs_to_its_position():
    hp = AxisErrorParams(bias_std_m=0.0, bias_random_walk_m_rts=0.0, velocity_std_mps=0.05,
                         velocity_tau_s=2.0, position_tau_s=4.0)
    dt = 0.02
    m = LocalPositionModel(LocalPositionParams(horizontal=hp, vertical=hp), streams(11), dt)
    pe, ve = [], []
    for _ in range(150_000):
        pos, vel = m.sample((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        pe.append(pos[0])
        ve.append(vel[0])
    p, v = np.array(pe), np.array(ve)
    pvv, pvp, ppp = hp.stationary()
    assert v.var() == pytest.approx(pvv, rel=0.1)
    assert p.var() == pytest.approx(ppp, rel=0.15)
    assert np.mean(p * v) == pytest.approx(pvp, rel=0.15)
    for lag_s in (1.0, 2.0, 4.0):
        assert autocorr(v, round(lag_s / dt)) == pytest.approx(math.exp(-lag_s / 2.0), abs=0.05)
    # dp/dt = v − p/τ_p: the finite difference of the position error follows the velocity
    dp = np.diff(p) / dt
    model = v[:-1] - p[:-1] / 4.0
    assert np.corrcoef(dp, model)[0, 1] > 0.97
    assert np.corrcoef(np.diff(p), np.diff(v))[0, 1] < 0.5     # not two white noises


def test_ekf_bias_walks_by_k_sqrt_t_and_starts_with_its_sigma():
    ap = AxisErrorParams(bias_std_m=0.5, bias_random_walk_m_rts=0.03, velocity_std_mps=0.0,
                         velocity_tau_s=1.0, position_tau_s=1.0)
    params = LocalPositionParams(horizontal=ap, vertical=ap)
    b0, b60 = [], []
    for seed in range(400):
        m = LocalPositionModel(params, streams(seed, 'ekf'), 0.1)
        b0.append(m.axes[0].bias)
        for _ in range(600):
            m.sample((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        b60.append(m.axes[0].bias)
    assert np.std(b0) == pytest.approx(0.5, rel=0.1)
    assert np.std(np.array(b60) - np.array(b0)) == pytest.approx(0.03 * math.sqrt(60.0),
                                                                 rel=0.1)


@pytest.mark.slow
def test_ekf_statistics_do_not_depend_on_the_output_rate():
    """The exact discretisation: 10 Hz and 100 Hz sampling see the same stationary error."""
    hp = LocalPositionParams().horizontal
    out = {}
    for dt in (0.01, 0.1):
        m = LocalPositionModel(LocalPositionParams(), streams(12), dt)
        n = round(3000.0 / dt)
        p = np.empty(n)
        for i in range(n):
            p[i] = m.sample((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))[0][0] - m.axes[0].bias
        out[dt] = p.var()
    assert out[0.01] == pytest.approx(hp.stationary()[2], rel=0.15)
    assert out[0.1] == pytest.approx(hp.stationary()[2], rel=0.15)


# --- LIDAR-Lite ---------------------------------------------------------------------------

def _errors_at(range_m: float, seeds: range, per_seed: int = 20) -> np.ndarray:
    p = LidarLiteParams()
    errs = []
    for seed in seeds:
        m = LidarLiteModel(p, streams(seed, 'lidar'))
        for _ in range(per_seed):
            r = m.measure(range_m)
            assert r is not None
            errs.append(r - range_m)
    return np.array(errs)


def test_lidar_error_envelope_follows_the_data_sheet():
    """±2.5 cm typical between 1 and 5 m, ±10 cm beyond 5 m, worse and non-linear below 1 m."""
    seeds = range(200)
    for r in (1.0, 2.0, 3.5, 4.9):
        assert np.quantile(np.abs(_errors_at(r, seeds)), 0.95) <= 0.025
    for r in (5.0, 12.0, 30.0):
        assert np.quantile(np.abs(_errors_at(r, seeds)), 0.95) <= 0.10
    near = [np.mean(np.abs(_errors_at(r, seeds))) for r in (0.8, 0.5, 0.2)]
    assert near[0] > np.mean(np.abs(_errors_at(1.5, seeds)))
    assert near[0] < near[1] < near[2]


def test_lidar_reads_in_centimetres_within_its_range_limits():
    m = LidarLiteModel(LidarLiteParams(noise_std_m=0.0, noise_std_far_m=0.0, offset_std_m=0.0,
                                   scale_std=0.0, near_bias_m=0.0), streams(13))
    for r in (1.234, 2.0, 7.777):
        v = m.measure(r)
        assert v is not None and abs(v * 100.0 - round(v * 100.0)) < 1e-9
        assert abs(v - r) <= 0.005 + 1e-9
    assert m.measure(0.01) is None                      # shorter than min_range_m
    assert m.measure(None) is None
    assert m.measure(float('nan')) is None and m.rejected == 1
    # detection threshold: a 70 % target is seen at 39 m, not at 41 m
    ahead = ((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    for h, seen in ((39.0, True), (41.0, False)):
        ground = [ground_plane(0.7, z=-h)]
        assert (m.footprint_return(*ahead, ground) is not None) == seen


def test_lidar_draws_the_same_numbers_whatever_it_sees():
    a = LidarLiteModel(LidarLiteParams(), streams(14))
    b = LidarLiteModel(LidarLiteParams(), streams(14))
    a.measure(None)
    b.measure(2.0)
    assert a.measure(3.0) == b.measure(3.0)


PAD = horizontal_rectangle(0.0, 0.0, 0.6, 0.525, 0.425, 0.8)
GROUND = ground_plane(0.3)


def test_beam_footprint_geometry_over_a_raised_pad():
    m = LidarLiteModel(LidarLiteParams(), streams(15))
    assert m.footprint_radius_m(2.0) == pytest.approx(0.006 + math.tan(0.004) * 2.0)
    down = (0.0, 0.0, -1.0)
    r, s = m.footprint_return((0.1, 0.1, 2.0), down, [PAD, GROUND])
    assert r == pytest.approx(1.4) and s == pytest.approx(0.8 / 1.4 ** 2)
    r, s = m.footprint_return((0.8, 0.0, 2.0), down, [PAD, GROUND])
    assert r == pytest.approx(2.0) and s == pytest.approx(0.3 / 4.0)
    tilt = 0.2                                           # beam tilted in the x-z plane
    d = (math.sin(tilt), 0.0, -math.cos(tilt))
    r, _ = m.footprint_return((-0.3, 0.0, 2.0), d, [PAD, GROUND])
    assert r == pytest.approx(1.4 / math.cos(tilt), rel=1e-9)


def test_beam_straddling_the_pad_edge_returns_the_stronger_surface():
    """0.6 m between pad top and ground: the returns do not blend; as the footprint slides
    over the edge the pad's share of the energy falls from all to none."""
    m = LidarLiteModel(LidarLiteParams(), streams(16))
    edge = 0.525
    rad = m.footprint_radius_m(1.4)
    strengths = []
    for x in np.linspace(edge - 1.5 * rad, edge + 1.5 * rad, 13):
        r, s = m.footprint_return((float(x), 0.0, 2.0), (0.0, 0.0, -1.0), [PAD, GROUND])
        assert r == pytest.approx(1.4, abs=1e-4) or r == pytest.approx(2.0, abs=1e-4)
        strengths.append((r, s))
    pad_s = [s for r, s in strengths if r < 1.7]
    assert pad_s == sorted(pad_s, reverse=True)
    assert strengths[0][0] < 1.7 and strengths[-1][0] > 1.7


def test_close_surfaces_blend_into_an_energy_weighted_range():
    """A pad 5 cm proud of the deck around it (a painted mat): straddling its edge gives a
    range between the two, weighted by the reflected energy."""
    m = LidarLiteModel(LidarLiteParams(), streams(17))
    mat = horizontal_rectangle(0.0, 0.0, 0.05, 1.0, 1.0, 0.8)
    deck = horizontal_rectangle(0.0, 0.0, 0.0, 10.0, 10.0, 0.2)
    r, s = m.footprint_return((1.0, 0.0, 2.0), (0.0, 0.0, -1.0), [mat, deck])
    w_mat, w_deck = 0.5 * 0.8 / 1.95 ** 2, 0.5 * 0.2 / 2.0 ** 2
    assert r == pytest.approx((w_mat * 1.95 + w_deck * 2.0) / (w_mat + w_deck), abs=3e-3)
    assert s == pytest.approx(w_mat + w_deck, rel=0.1)
    far = m.footprint_return((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), [mat, deck])
    assert far == pytest.approx((1.95, 0.8 / 1.95 ** 2))


def test_tilted_deck_surface_and_fast_path_agree_with_the_sampled_footprint():
    m = LidarLiteModel(LidarLiteParams(), streams(18))
    roll = 0.1                                          # a deck rolled by 0.1 rad
    n = (0.0, -math.sin(roll), math.cos(roll))
    deck = Surface((0.0, 0.0, 0.0), n, (1.0, 0.0, 0.0), 5.0, 3.0, 0.3).check()
    o, d = (0.2, 0.3, 2.0), (0.0, 0.0, -1.0)
    fast = m.footprint_return(o, d, [deck])
    slow = m._sampled(*o, *d, [deck], m.params)
    assert fast is not None and slow is not None
    assert fast[0] == pytest.approx(slow[0], abs=2e-4)
    # the plane through the origin with normal n: z = y tan(roll) under the beam
    assert fast[0] == pytest.approx(2.0 - 0.3 * math.tan(roll), rel=1e-9)


# --- camera -------------------------------------------------------------------------------

def test_distortion_round_trip_over_the_field_of_view():
    p = CameraModelParams(p_std=2e-3)
    for seed in range(20):
        cam = TrueCamera.draw(CameraParams(), p, random.Random(seed))
        for x in np.linspace(-0.75, 0.75, 11):
            for y in np.linspace(-0.5, 0.5, 9):
                xd, yd = cam.distort(float(x), float(y))
                assert cam.undistort(xd, yd) == pytest.approx((x, y), abs=1e-9)


def test_default_lens_reproduces_the_ir_lock_characterisation():
    """ArduPilot AP_IRLock's pixel → 1 m plane model of the IR-LOCK Pixy (standard lens) is
    matched within 0.6 px over the whole image by our k1, k2 at its focal lengths."""
    p = CameraModelParams()
    fx, fy = 1.0 / 0.00293875727162397, 1.0 / 0.003056843086277
    cam = TrueCamera(fx, fy, 160.0, 100.0, p.k1, p.k2, 0.0, 0.0, (0.0, 0.0, 0.0), 320, 200)
    worst = 0.0
    for u in range(0, 320, 8):
        for v in range(0, 200, 8):
            den = (4.43013552642296e-6 * (u - 160.0) ** 2
                   + 4.79331390531725e-6 * (v - 100.0) ** 2 - 1.0)
            x = (-0.00293875727162397 * u + 0.470201163459835) / den
            y = (-0.003056843086277 * v + 0.3056843086277) / den
            # (x, y): the ray's tangents, signed like the pixel offset from (160, 100)
            pu, pv = cam.project_optical(x, y, 1.0)
            worst = max(worst, abs(pu - u), abs(pv - v))
    assert worst < 0.6


def test_undistorted_nominal_camera_is_the_simulators_pinhole():
    """With no distortion and no calibration error the true camera projects exactly as
    sensors.project_point (same mount convention, same intrinsics)."""
    zero = CameraModelParams(k1=0.0, k2=0.0, k_rel_std=0.0, p_std=0.0, focal_rel_std=0.0,
                             principal_point_std_px=0.0, mount_std_rad=(0.0, 0.0, 0.0))
    nominal = CameraParams(mount_rpy_rad=(0.02, -0.03, 0.01))
    cam = TrueCamera.draw(nominal, zero, random.Random(1))
    r = rot_body_to_world(0.1, -0.05, 0.8)
    pos, pt = (1.0, 2.0, 3.0), (1.4, 1.7, 0.6)
    u, v, _ = project_point(nominal, pos, r, pt)
    xo, yo, zo = cam.optical(r, pt[0] - pos[0], pt[1] - pos[1], pt[2] - pos[2])
    assert cam.project_optical(xo, yo, zo) == pytest.approx((u, v), abs=1e-9)


def test_calibration_mismatch_is_drawn_per_seed_with_its_sigmas():
    p = CameraModelParams()
    nominal = CameraParams()
    cams = [TrueCamera.draw(nominal, p, random.Random(s)) for s in range(800)]
    ef = np.array([c.fx / nominal.fx_px - 1.0 for c in cams])
    assert ef.std() == pytest.approx(p.focal_rel_std, rel=0.1)
    assert np.allclose([c.fy / nominal.fy_px - 1.0 for c in cams], ef)    # one lens
    assert np.std([c.cx for c in cams]) == pytest.approx(p.principal_point_std_px, rel=0.1)
    assert np.std([c.cy for c in cams]) == pytest.approx(p.principal_point_std_px, rel=0.1)
    mount = np.array([c.mount_rpy_rad for c in cams])
    for axis in range(3):
        assert mount[:, axis].std() == pytest.approx(p.mount_std_rad[axis], rel=0.1)
    assert np.std([c.k1 for c in cams]) == pytest.approx(abs(p.k1) * p.k_rel_std, rel=0.1)


def test_exposure_time_of_a_row_has_rolling_readout_and_frame_jitter():
    p = CameraModelParams()
    cm = CameraModel(p, CameraParams(), streams(19))
    offsets_top, offsets_bottom = [], []
    for _ in range(4000):
        cm.start_frame()
        offsets_top.append(cm.exposure_offset_s(0.0))
        offsets_bottom.append(cm.exposure_offset_s(200.0))
    top, bottom = np.array(offsets_top), np.array(offsets_bottom)
    assert np.allclose(bottom - top, p.rolling_readout_s)
    assert top.mean() == pytest.approx(-0.5 * p.rolling_readout_s, abs=1e-4)
    assert top.std() == pytest.approx(p.exposure_jitter_s, rel=0.05)


# --- the suite: determinism and independence -----------------------------------------------

def _run_suite(seed: int, extra_imu: int = 0, n: int = 300) -> list:
    s = SensorSuite(SensorSuiteParams(), seed)
    eye = rot_body_to_world(0.05, -0.02, 1.0)
    for _ in range(extra_imu):
        s.imu.sample((0.0, 0.0, 0.0), eye, (0.0, 0.0, 0.0))
    out = []
    for _ in range(n):
        out.append(('att', s.attitude.sample(0.05, -0.02, 1.0)))
        out.append(('pos', s.local_position.sample((1.0, 2.0, 3.0), (0.1, 0.0, 0.0))))
        out.append(('lidar', s.lidar.sample((0.1, 0.1, 2.0), (0.0, 0.0, -1.0), [PAD, GROUND])))
        s.camera.start_frame()
        out.append(('cam', s.camera.exposure_offset_s(100.0)))
        ts = s.camera_timing.take()
        out.append(('cam_t', s.camera_timing.push(ts, [])))
    out.append(('true_camera', (s.camera.camera.fx, s.camera.camera.cx,
                                s.camera.camera.mount_rpy_rad)))
    return out


def test_suite_is_deterministic_for_a_seed_and_differs_between_seeds():
    a, b, c = _run_suite(21), _run_suite(21), _run_suite(22)
    assert a == b
    for (name, x), (_, y) in zip(a, c, strict=True):
        if name not in ('lidar',):              # quantised ranges may coincide
            assert x != y, name


def test_sensor_streams_are_independent():
    """Sampling the IMU more often never moves another sensor's draws, and the noise
    sequences of different sensors are uncorrelated."""
    base = [x for x in _run_suite(23) if x[0] != 'imu']
    assert base == _run_suite(23, extra_imu=1234)
    seqs = {}
    for name in SENSOR_NAMES:
        n = model_streams(23, name).normal
        seqs[name] = np.array([n() for _ in range(5000)])
    bound = 4.0 / math.sqrt(5000)
    names = list(seqs)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert abs(np.corrcoef(seqs[a], seqs[b])[0, 1]) < bound, (a, b)
    # and distinct from the streams the World already draws ('{seed}:imu', '{seed}:imu:normal')
    from deck_simulator.sensors import normal_stream
    old = normal_stream('23:imu:normal')
    new = model_streams(23, 'imu').normal
    assert [old() for _ in range(5)] != [new() for _ in range(5)]
    assert random.Random('23:imu').random() != model_streams(23, 'imu').draw.random()


@pytest.mark.parametrize('args,field', [
    (((0.0, 0.0, math.nan), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), 1.0, 1.0, 0.5), 'center_m'),
    (((0.0, 0.0, 0.0), (0.0, 0.0, 2.0), (1.0, 0.0, 0.0), 1.0, 1.0, 0.5), 'normal'),
    (((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.6, 0.8), 1.0, 1.0, 0.5), 'u_axis'),
    (((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), 0.0, 1.0, 0.5), 'half_u_m'),
    (((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), 1.0, 1.0, 1.5), 'reflectivity'),
])
def test_surface_check_names_the_bad_field(args, field):
    with pytest.raises(ValueError, match=field):
        Surface(*args).check()


@pytest.mark.parametrize('cls,kw,field', [
    (ImuModelParams, {'accel_noise_density': -1.0}, 'accel_noise_density'),
    (AttitudeModelParams, {'yaw_drift_tau_s': 0.0}, 'yaw_drift_tau_s'),
    (AxisErrorParams, {'bias_std_m': float('inf'), 'bias_random_walk_m_rts': 0.0,
                       'velocity_std_mps': 0.0, 'velocity_tau_s': 1.0, 'position_tau_s': 1.0},
     'bias_std_m'),
    (LidarLiteParams, {'min_range_m': 50.0}, 'min_range_m'),
    (LidarLiteParams, {'footprint_rays': 0}, 'footprint_rays'),
    (CameraModelParams, {'rolling_readout_s': 0.03}, 'rolling_readout_s'),
    (CameraModelParams, {'mount_std_rad': (0.0, 0.0)}, 'mount_std_rad'),
])
def test_model_params_name_the_bad_field(cls, kw, field):
    with pytest.raises(ValueError, match=field):
        cls(**kw)


def test_ou_coefficients_are_exact_for_any_step():
    for dt in (0.001, 0.1, 5.0):
        a, q = ou_coefficients(dt, 2.0, 0.3)
        assert a == pytest.approx(math.exp(-dt / 2.0))
        assert q * q / (1.0 - a * a) == pytest.approx(0.09)      # stationary σ kept
