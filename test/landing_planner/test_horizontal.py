"""Horizontal position controller: sign conventions against model (2), limits, closed loop."""

import math
import random

from deckland_common.frames import mat_vec, rot_body_to_world
from landing_planner.horizontal import HorizontalController, HorizontalParams, accel_to_tilt
import pytest

G = 9.81


def thrust_accel(roll, pitch, yaw):
    """Horizontal acceleration of model (2) with u_z cφ cθ = m g: g (R e3)_xy / (R e3)_z."""
    r3 = mat_vec(rot_body_to_world(roll, pitch, yaw), (0.0, 0.0, 1.0))
    return G * r3[0] / r3[2], G * r3[1] / r3[2], r3


def test_accel_to_tilt_inverts_model_2_for_all_yaws():
    rng = random.Random(1)
    for _ in range(200):
        yaw = rng.uniform(-math.pi, math.pi)
        ax, ay = rng.uniform(-3, 3), rng.uniform(-3, 3)
        roll, pitch = accel_to_tilt(ax, ay, yaw, G)
        bx, by, _ = thrust_accel(roll, pitch, yaw)
        assert (bx, by) == pytest.approx((ax, ay), abs=1e-9)


def test_frame_conventions_pitch_forward_roll_right():
    # yaw 0 = nose east: forward acceleration → positive pitch (nose down)
    roll, pitch = accel_to_tilt(1.0, 0.0, 0.0)
    assert pitch > 0.0 and roll == pytest.approx(0.0, abs=1e-12)
    # acceleration to the right (−y body = south at yaw 0) → positive roll
    roll, pitch = accel_to_tilt(0.0, -1.0, 0.0)
    assert roll > 0.0 and pitch == pytest.approx(0.0, abs=1e-12)
    # yaw π/2 = nose north: a northward acceleration is "forward"
    roll, pitch = accel_to_tilt(0.0, 1.0, math.pi / 2)
    assert pitch > 0.0 and roll == pytest.approx(0.0, abs=1e-9)


def test_command_accelerates_toward_setpoint_for_all_yaws_and_respects_tilt_limit():
    rng = random.Random(2)
    params = HorizontalParams()
    for _ in range(200):
        ctl = HorizontalController(params)
        yaw = rng.uniform(-math.pi, math.pi)
        sp = (rng.uniform(-20, 20), rng.uniform(-20, 20))
        roll, pitch = ctl.step(sp, (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), yaw, 0.01)
        ax, ay, r3 = thrust_accel(roll, pitch, yaw)
        # acceleration points at the setpoint (parallel to the error at zero velocity)
        n_a, n_e = math.hypot(ax, ay), math.hypot(*sp)
        assert (ax * sp[0] + ay * sp[1]) / (n_a * n_e) == pytest.approx(1.0, abs=1e-9)
        # total tilt (angle of R e3 from vertical) within the limit, accel within its limit
        tilt = math.acos(r3[2])
        assert tilt <= params.max_tilt_rad + 1e-9
        assert n_a <= params.max_accel_mps2 + 1e-9


def test_large_error_saturates_at_the_tilt_limit():
    params = HorizontalParams(max_accel_mps2=10.0, max_tilt_rad=math.radians(20.0))
    ctl = HorizontalController(params)
    roll, pitch = ctl.step((100.0, 50.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.3, 0.01)
    _, _, r3 = thrust_accel(roll, pitch, 0.3)
    assert math.acos(r3[2]) == pytest.approx(math.radians(20.0), abs=1e-9)


def simulate(ctl, setpoint_fn, ff_fn, t_end, yaw=0.7, lag_s=0.1, dt=0.01, wind=(0.0, 0.0)):
    """Point mass driven by the tilt of (2) through a first-order attitude lag."""
    x = y = vx = vy = 0.0
    roll = pitch = 0.0
    t = 0.0
    traj = []
    while t < t_end:
        rc, pc = ctl.step(setpoint_fn(t), ff_fn(t), (x, y), (vx, vy), yaw, dt)
        k = dt / (lag_s + dt)
        roll += k * (rc - roll)
        pitch += k * (pc - pitch)
        ax, ay, _ = thrust_accel(roll, pitch, yaw)
        vx += (ax + wind[0]) * dt
        vy += (ay + wind[1]) * dt
        x += vx * dt
        y += vy * dt
        t += dt
        traj.append((t, x, y, vx, vy))
    return traj


def test_closed_loop_converges_on_lagged_point_mass():
    ctl = HorizontalController(HorizontalParams())
    traj = simulate(ctl, lambda t: (3.0, -2.0), lambda t: (0.0, 0.0), 12.0)
    _, x, y, vx, vy = traj[-1]
    assert math.hypot(x - 3.0, y + 2.0) < 0.02
    assert math.hypot(vx, vy) < 0.02
    # well damped: overshoot past the setpoint along the step direction below 10 %
    d = math.hypot(3.0, 2.0)
    ux, uy = 3.0 / d, -2.0 / d
    assert max(px * ux + py * uy for _, px, py, _, _ in traj) < 1.1 * d


def test_velocity_feed_forward_tracks_a_moving_setpoint():
    v = (0.5, 0.3)
    ctl = HorizontalController(HorizontalParams(ki=0.0))
    traj = simulate(ctl, lambda t: (1.0 + v[0] * t, v[1] * t), lambda t: v, 15.0)
    t, x, y, _, _ = traj[-1]
    assert math.hypot(x - (1.0 + v[0] * t), y - v[1] * t) < 0.02


def test_integrator_removes_constant_disturbance_and_does_not_wind_up():
    params = HorizontalParams(ki=0.3)
    ctl = HorizontalController(params)
    traj = simulate(ctl, lambda t: (0.0, 0.0), lambda t: (0.0, 0.0), 40.0, wind=(0.4, 0.0))
    _, x, y, _, _ = traj[-1]
    assert math.hypot(x, y) < 0.02   # PD alone would sit at 0.4 / kp = 0.33 m
    # a long saturated leg: the integrator stays within its clamp
    ctl2 = HorizontalController(params)
    simulate(ctl2, lambda t: (200.0, 0.0), lambda t: (0.0, 0.0), 10.0)
    ix, iy = ctl2.integral_accel_mps2
    assert abs(ix) <= params.max_integral_accel_mps2 + 1e-12 and abs(iy) < 1e-12


def test_nan_inputs_are_rejected_and_last_command_kept():
    ctl = HorizontalController(HorizontalParams())
    good = ctl.step((1.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.0, 0.01)
    bad = ctl.step((math.nan, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.0, 0.01)
    assert bad == good and ctl.rejected['nan'] == 1
    assert ctl.step((1.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.0, 0.0) == good
    assert ctl.rejected['bad_dt'] == 1


def test_params_validated():
    with pytest.raises(ValueError, match='kp'):
        HorizontalParams(kp=0.0)
    with pytest.raises(ValueError, match='max_tilt_rad'):
        HorizontalParams(max_tilt_rad=2.0)
    with pytest.raises(ValueError, match='ki'):
        HorizontalParams(ki=math.inf)
