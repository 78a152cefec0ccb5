"""Physics of the truth vehicle: mixer (1), dynamics (2), ground effect (3)-(4), attitude loop."""

import dataclasses
import math

from deck_simulator.vehicle import Vehicle, VehicleParams, mix, unmix
from deckland_common.frames import rot_body_to_world
import pytest

DT = 1.0 / 400.0
NO_DRAG = {'drag_linear_n_per_mps': 0.0, 'drag_quad_h_kg_per_m': 0.0,
           'drag_quad_v_kg_per_m': 0.0}


def gamma_by_hand(rho, r, zp):
    return 1.0 / (1.0 - rho * r * r / (4.0 * zp) ** 2)


def run(v, seconds, surface=0.0, wind=(0.0, 0.0, 0.0)):
    for _ in range(round(seconds / DT)):
        v.step(DT, surface, *wind)


def test_mixer_inverts_equation_1():
    u = (30.0, 0.4, -0.3, 0.05)
    f = mix(*u, 0.225, 0.016)
    assert unmix(*f, 0.225, 0.016) == pytest.approx(u, abs=1e-12)
    # (1) signs: roll torque from F2 (left) − F4 (right), pitch from F3 (tail) − F1 (nose)
    f1, f2, f3, f4 = mix(0.0, 1.0, 0.0, 0.0, 0.225, 0.016)
    assert f2 > 0 > f4 and f1 == f3 == 0
    f1, f2, f3, f4 = mix(0.0, 0.0, 1.0, 0.0, 0.225, 0.016)
    assert f3 > 0 > f1


@pytest.mark.parametrize('height_m', [3.0, 0.12])
def test_hover_thrust_is_mg_over_true_gamma(height_m):
    p = VehicleParams(**NO_DRAG)
    zp = height_m + p.rotor_height_m
    gamma = gamma_by_hand(p.rho_true, p.prop_radius_m, zp)
    assert p.gamma(zp) == pytest.approx(gamma, rel=1e-12)
    hover = p.mass_kg * p.gravity_mps2 / gamma
    v = Vehicle(p, (0.0, 0.0, height_m), 0.0, hover)
    run(v, 1.0)
    assert abs(v.vz) < 1e-6 and abs(v.z - height_m) < 1e-6
    if height_m < 1.0:
        assert gamma > 1.05       # ground effect is material near the surface
        # thrust m g (ignoring γ) accelerates upward by (γ − 1) g, (3)
        v = Vehicle(p, (0.0, 0.0, height_m), 0.0, p.mass_kg * p.gravity_mps2)
        v.step(DT, 0.0, 0.0, 0.0, 0.0)
        assert v.az == pytest.approx((gamma - 1.0) * p.gravity_mps2, rel=1e-3)


def test_ground_effect_measured_from_surface_below():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 1.0), 0.0, p.mass_kg * p.gravity_mps2)
    v.step(DT, 0.85, 0.0, 0.0, 0.0)   # deck top 0.85 m: z_p = 0.2 m
    assert v.gamma == pytest.approx(gamma_by_hand(p.rho_true, p.prop_radius_m, 0.2), rel=1e-9)
    v.step(DT, 0.0, 0.0, 0.0, 0.0)
    assert v.gamma == pytest.approx(gamma_by_hand(p.rho_true, p.prop_radius_m, 1.05), rel=1e-4)


def test_free_fall_with_zero_thrust():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 50.0), 0.0, 0.0)
    v.cmd_thrust = 0.0
    run(v, 1.0)
    assert v.az == pytest.approx(-p.gravity_mps2, abs=1e-9)
    assert v.vz == pytest.approx(-p.gravity_mps2 * 1.0, rel=1e-6)
    assert v.z == pytest.approx(50.0 - 0.5 * p.gravity_mps2, abs=0.02)


def test_tilted_thrust_accelerates_along_R_e3():
    p = VehicleParams(**NO_DRAG)
    att = (0.15, -0.1, 0.7)
    thrust = 30.0
    v = Vehicle(p, (0.0, 0.0, 20.0), att[2], thrust)
    v.roll, v.pitch = att[0], att[1]
    v.cmd_roll, v.cmd_pitch, v.cmd_yaw, v.cmd_thrust = *att, thrust
    v.step(DT, 0.0, 0.0, 0.0, 0.0)
    r = rot_body_to_world(v.roll, v.pitch, v.yaw)
    gamma = p.gamma(20.0 + p.rotor_height_m)
    u = v.thrust_n * gamma / p.mass_kg
    expect = (u * r[0][2], u * r[1][2], u * r[2][2] - p.gravity_mps2)
    assert (v.ax, v.ay, v.az) == pytest.approx(expect, abs=1e-9)


def test_flu_signs_positive_pitch_forward_positive_roll_right():
    p = VehicleParams(**NO_DRAG)
    hover = p.mass_kg * p.gravity_mps2
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, hover)
    v.cmd_pitch = 0.2
    run(v, 1.0)
    assert v.vx > 1.0 and abs(v.vy) < 1e-6      # nose down → east (yaw 0 = east)
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, hover)
    v.cmd_roll = 0.2
    run(v, 1.0)
    assert v.vy < -1.0 and abs(v.vx) < 1e-6     # right side down → −y


def test_attitude_loop_tracks_roll_step():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, p.mass_kg * p.gravity_mps2)
    v.cmd_roll = 0.2
    t90 = None
    peak = 0.0
    for i in range(round(1.5 / DT)):
        v.step(DT, 0.0, 0.0, 0.0, 0.0)
        peak = max(peak, v.roll)
        if t90 is None and v.roll >= 0.18:
            t90 = (i + 1) * DT
    assert t90 is not None and 0.1 < t90 < 0.4      # a Pixhawk-like response, not instant
    assert peak < 0.2 * 1.1                        # overshoot < 10 %
    assert v.roll == pytest.approx(0.2, abs=0.004)
    assert abs(v.pitch) < 1e-9


def test_yaw_tracks_and_wraps():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 20.0), 3.0, p.mass_kg * p.gravity_mps2)
    v.cmd_yaw = -3.0                 # shortest way is +0.28 rad through ±π
    run(v, 3.0)
    assert abs(math.remainder(v.yaw - (-3.0), 2 * math.pi)) < 0.01
    assert -math.pi <= v.yaw < math.pi


def test_motor_lag_and_thrust_limit():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, 0.0)
    v.cmd_thrust = 20.0
    run(v, p.motor_tau_s)
    assert v.thrust_n == pytest.approx(20.0 * (1 - math.exp(-1)), rel=0.01)
    v.cmd_thrust = 500.0
    run(v, 1.0)
    assert v.thrust_n == pytest.approx(p.thrust_to_weight * p.mass_kg * p.gravity_mps2, rel=1e-6)


def test_wind_drag_pushes_downwind():
    p = VehicleParams()
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, p.mass_kg * p.gravity_mps2)
    v.step(DT, 0.0, 3.0, 0.0, 0.0)
    expect = (p.drag_linear_n_per_mps * 3.0 + p.drag_quad_h_kg_per_m * 9.0) / p.mass_kg
    assert v.ax == pytest.approx(expect, rel=1e-6)
    assert abs(v.ay) < 1e-12


def test_params_validation_names_the_field():
    with pytest.raises(ValueError, match='mass_kg'):
        VehicleParams(mass_kg=-1.0)
    with pytest.raises(ValueError, match='thrust_to_weight'):
        VehicleParams(thrust_to_weight=0.9)
    with pytest.raises(ValueError, match='inertia_kgm2'):
        dataclasses.replace(VehicleParams(), inertia_kgm2=(0.1, 0.1))
