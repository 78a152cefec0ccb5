"""Physics of the truth vehicle: mixer (1), the free rigid body, ground effect, contact, loop."""

import dataclasses
import math

from contact_rig import bounce_apex_m
from deck_simulator.contact import Surface, ground_surface
from deck_simulator.rigid_body import RigidBodyParams
from deck_simulator.rotor_ground_effect import RotorGroundEffectParams, multirotor_gain_level
from deck_simulator.vehicle import Vehicle, VehicleParams, mix, unmix
from deckland_common.frames import rot_body_to_world
import pytest

DT = 1.0 / 400.0
NO_DRAG = {'drag_linear_n_per_mps': 0.0, 'drag_quad_h_kg_per_m': 0.0,
           'drag_quad_v_kg_per_m': 0.0}


def run(v, seconds, wind=(0.0, 0.0, 0.0)):
    for _ in range(round(seconds / DT)):
        v.step(DT, *wind)


def level_gain(p, zp):
    """The published level-quadrotor formula (Sanchez-Cuevas et al. 2017) at rotor height zp."""
    return multirotor_gain_level(zp, p.prop_radius_m, math.sqrt(2.0) * p.arm_length_m,
                                 p.arm_length_m, p.ground_effect.body_coeff)


def test_mixer_inverts_equation_1():
    u = (30.0, 0.4, -0.3, 0.05)
    f = mix(*u, 0.225, 0.016)
    assert unmix(*f, 0.225, 0.016) == pytest.approx(u, abs=1e-12)
    # (1) signs: roll torque from F2 (left) − F4 (right), pitch from F3 (tail) − F1 (nose)
    f1, f2, f3, f4 = mix(0.0, 1.0, 0.0, 0.0, 0.225, 0.016)
    assert f2 > 0 > f4 and f1 == f3 == 0
    f1, f2, f3, f4 = mix(0.0, 0.0, 1.0, 0.0, 0.225, 0.016)
    assert f3 > 0 > f1


@pytest.mark.parametrize('height_m', [3.0, 0.3])
def test_hover_thrust_is_mg_over_the_true_ground_effect_gain(height_m):
    p = VehicleParams(**NO_DRAG)
    zp = height_m + p.rotor_height_m
    gamma = level_gain(p, zp)
    assert p.gamma(zp) == pytest.approx(gamma, rel=1e-12)
    hover = p.mass_kg * p.gravity_mps2 / gamma
    v = Vehicle(p, (0.0, 0.0, height_m), 0.0, hover)
    run(v, 1.0)
    assert abs(v.vz) < 1e-6 and abs(v.z - height_m) < 1e-6
    assert v.gamma == pytest.approx(gamma, rel=1e-12)     # every rotor over the ground
    if height_m < 1.0:
        assert gamma > 1.08       # ground effect is material near the surface
        # thrust m g (ignoring γ) accelerates upward by (γ − 1) g
        v = Vehicle(p, (0.0, 0.0, height_m), 0.0, p.mass_kg * p.gravity_mps2)
        v.step(DT, 0.0, 0.0, 0.0)
        assert v.az == pytest.approx((gamma - 1.0) * p.gravity_mps2, rel=1e-3)


def test_hoisted_constants_ground_effect_clamp_and_gravity():
    """Motors at m g: (γ − 1) g up at rotor height z_p, 0 sideways; the clamp at the surface."""
    p = VehicleParams()
    weight = p.mass_kg * p.gravity_mps2
    for z_p in (50.0, 0.6, 0.2):
        v = Vehicle(p, (0.0, 0.0, z_p - p.rotor_height_m), 0.0, weight)
        v.step(1e-4, 0.0, 0.0, 0.0)
        assert v.gamma == pytest.approx(level_gain(p, z_p), rel=1e-12)
        assert v.az == pytest.approx((v.gamma - 1.0) * p.gravity_mps2, rel=1e-6, abs=1e-12)
        assert v.ax == pytest.approx(0.0, abs=1e-12) and v.ay == pytest.approx(0.0, abs=1e-12)
    ge = p.ground_effect
    assert p.gamma(0.0) == ge.max_gain and p.gamma(-1.0) == ge.max_gain
    assert p.gamma(ge.min_height_m) == p.gamma(0.5 * ge.min_height_m)


def test_partial_ground_effect_over_the_pad_edge_pitches_away_from_the_pad():
    """Rotor 1 (nose) over a raised box, the others over the ground far below: rotor 1 gains
    more thrust, so the body pitches nose up (away from the pad)."""
    p = VehicleParams(**NO_DRAG)
    box = Surface('deck', 0.3, 2.0, 1.0, 0.6)
    box.set_pose((0.5, 0.0, 1.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))   # x from 0.2 to 0.8
    v = Vehicle(p, (0.0, 0.0, 1.3), 0.0, p.mass_kg * p.gravity_mps2,
                [box, ground_surface(0.6)])
    v.release_motors()
    v.set_motor_thrusts(*(0.25 * p.mass_kg * p.gravity_mps2,) * 4)   # no attitude loop
    v.step(DT, 0.0, 0.0, 0.0)
    g = v.ground_effect.gain
    assert g[0] == pytest.approx(1.0 / (1.0 - (p.prop_radius_m / (4 * 0.35)) ** 2), rel=1e-9)
    # the others over the ground, 1.35 m below, each without rotor 1's image
    assert g[1] == g[3] and max(g[1], g[2]) < g[0]
    run(v, 0.05)
    assert v.body.q < 0.0 and v.pitch < 0.0          # negative pitch: nose up


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
    v.set_attitude(*att)
    assert (v.roll, v.pitch, v.yaw) == pytest.approx(att, abs=1e-12)
    v.cmd_roll, v.cmd_pitch, v.cmd_yaw, v.cmd_thrust = *att, thrust
    r = rot_body_to_world(*att)
    v.step(DT, 0.0, 0.0, 0.0)
    gamma = p.gamma(20.0 + p.rotor_height_m)
    u = v.thrust_n * gamma / p.mass_kg
    expect = (u * r[0][2], u * r[1][2], u * r[2][2] - p.gravity_mps2)
    assert (v.ax, v.ay, v.az) == pytest.approx(expect, abs=1e-6)


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
        v.step(DT, 0.0, 0.0, 0.0)
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
    assert -math.pi <= v.yaw <= math.pi


def test_euler_rates_are_the_body_rates_mapped():
    """φ̇, θ̇, ψ̇ exported from (p, q, r) by the Z-Y-X kinematics: a finite difference of the
    exported angles over one tick agrees."""
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.4, 0.0)
    v.armed = False
    v.set_attitude(0.3, -0.2, 0.4, (0.5, -0.7, 0.9))
    before = (v.roll, v.pitch, v.yaw)
    rates = (v.roll_rate, v.pitch_rate, v.yaw_rate)
    h = 1e-5
    v.step(h, 0.0, 0.0, 0.0)
    fd = tuple((a - b) / h for a, b in zip((v.roll, v.pitch, v.yaw), before, strict=True))
    assert fd == pytest.approx(rates, rel=1e-3)


def test_motor_lag_and_thrust_limit():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, 0.0)
    v.cmd_thrust = 20.0
    run(v, p.motor_tau_s)
    assert v.thrust_n == pytest.approx(20.0 * (1 - math.exp(-1)), rel=0.01)
    v.cmd_thrust = 500.0
    run(v, 1.0)
    assert v.thrust_n == pytest.approx(p.thrust_to_weight * p.mass_kg * p.gravity_mps2, rel=1e-6)


def test_disarmed_motors_run_down_whatever_the_command():
    p = VehicleParams(**NO_DRAG)
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, p.mass_kg * p.gravity_mps2)
    v.cmd_roll, v.cmd_thrust = 0.3, 40.0
    v.armed = False
    run(v, 5 * p.motor_tau_s)
    assert v.thrust_n < p.mass_kg * p.gravity_mps2 * math.exp(-4.9)   # first-order lag to 0
    assert (v.i_p, v.i_q, v.i_r) == (0.0, 0.0, 0.0) and abs(v.roll) < 1e-9


def test_wind_drag_pushes_downwind():
    p = VehicleParams()
    v = Vehicle(p, (0.0, 0.0, 20.0), 0.0, p.mass_kg * p.gravity_mps2)
    v.step(DT, 3.0, 0.0, 0.0)
    expect = (p.drag_linear_n_per_mps * 3.0 + p.drag_quad_h_kg_per_m * 9.0) / p.mass_kg
    assert v.ax == pytest.approx(expect, rel=1e-6)
    assert abs(v.ay) < 1e-12


def test_contact_substeps_only_within_the_margin_of_a_surface():
    """One physics step per tick until the lowest point is within near_margin_m of a
    surface (plus the motion over the tick); then the contact sub-steps."""
    p = VehicleParams(**NO_DRAG)
    gear = p.gear.height_m
    for clearance, expect in ((0.3, 1), (0.1, 1), (0.04, 4), (0.0, 4)):
        v = Vehicle(p, (0.0, 0.0, gear + clearance), 0.0)
        assert v.begin(DT, 0.0, 0.0, 0.0) == expect, clearance
    # tilted: a prop tip is the lowest point (0.352 m out, 0.05 m up)
    v = Vehicle(p, (0.0, 0.0, 0.25), 0.0)
    v.set_attitude(0.0, math.radians(40.0), 0.0)
    assert v.begin(DT, 0.0, 0.0, 0.0) == 4


def test_a_drop_on_the_ground_rebounds_with_the_gear_restitution():
    """Motors off, level drop from 5 cm (v0 = 0.99 m/s): the rebound apex is the closed form
    of the gear's spring–damper with gravity (≈ e² of the drop, e the flat-drop
    restitution), and it ends at rest at the static deflection m g / K."""
    p = VehicleParams(**NO_DRAG)
    gear, e = p.gear.height_m, p.contact.restitution
    expect = bounce_apex_m(p.contact, RigidBodyParams(p.mass_kg, p.inertia_kgm2,
                                                      p.gravity_mps2),
                           math.sqrt(2 * p.gravity_mps2 * 0.05))
    assert 0.5 * e * e * 0.05 < expect < e * e * 0.05
    v = Vehicle(p, (0.0, 0.0, gear + 0.05), 0.0, 0.0)
    v.armed = False
    apex = -1.0
    rising = False
    for _ in range(round(0.6 / DT)):
        v.step(DT, 0.0, 0.0, 0.0)
        if v.vz > 0.0:
            rising = True
        if rising and v.vz <= 0.0 and apex < 0.0:
            apex = v.z - gear
    # 4 sub-steps per tick keep the restitution within 2.5 % (docs/world/contact.md), so
    # the apex (∝ e²) within 5 %
    assert apex == pytest.approx(expect, rel=0.05)
    run(v, 2.0)
    assert v.z == pytest.approx(gear - p.mass_kg * p.gravity_mps2 / p.contact.stiffness_n_per_m,
                                abs=2e-5)
    assert abs(v.vz) < 1e-4


def test_params_validation_names_the_field():
    with pytest.raises(ValueError, match='mass_kg'):
        VehicleParams(mass_kg=-1.0)
    with pytest.raises(ValueError, match='thrust_to_weight'):
        VehicleParams(thrust_to_weight=0.9)
    with pytest.raises(ValueError, match='inertia_kgm2'):
        dataclasses.replace(VehicleParams(), inertia_kgm2=(0.1, 0.1))
    with pytest.raises(ValueError, match=r'ground_effect\.prop_radius_m'):
        VehicleParams(ground_effect=RotorGroundEffectParams(prop_radius_m=0.1))
    # the ground effect takes the vehicle's props when left at its default
    assert VehicleParams(prop_radius_m=0.1).ground_effect.prop_radius_m == 0.1
    with pytest.raises(AttributeError):
        Vehicle(VehicleParams(), (0.0, 0.0, 1.0)).roll = 0.1    # set_attitude changes it
