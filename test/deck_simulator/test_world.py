"""World: landings scored over the whole contact, the deck models, sensors, determinism, input."""

import dataclasses
import math

from deck_simulator.scenario import HeaveSpec, load_scenario
from deck_simulator.sensor_suite import ideal_sensors
from deck_simulator.world import World
import pytest

DT = 1.0 / 400.0


def calm(heave=None, **apron):
    sc = load_scenario('paper_calm')
    rz = dataclasses.replace(sc.randomize, start_offset_m=0.0, start_yaw_rad=0.0,
                             heave_phase=False)
    ap = dataclasses.replace(sc.apron, heave=heave or HeaveSpec(model='none'), **apron)
    return dataclasses.replace(sc, randomize=rz, apron=ap)


def place(world, x, y, z, vz=0.0):
    v = world.vehicle
    v.x, v.y, v.z, v.vz = x, y, z, vz


def descend_until_contact(world, vz_ref=-0.3, seconds=20.0, thrust=None):
    """Descend at vz_ref with a vertical-speed P loop on truth, the true ground-effect gain
    divided out (a P loop alone hovers on the cushion near a surface), or a fixed thrust."""
    p = world.params
    v = world.vehicle
    for k in range(round(seconds / DT)):
        if k % 4 == 0:
            u = thrust if thrust is not None else p.mass_kg * (
                p.gravity_mps2 + 3.0 * (vz_ref - v.vz)) / v.gamma
            world.set_command(0.0, 0.0, v.yaw, u)
        world.step(DT)
        if world.contact is not None:
            break
    return world.contact


def run_until_done(world, seconds=10.0):
    for _ in range(round(seconds / DT)):
        world.step(DT)
        if world.landing_done:
            break


def test_soft_landing_on_the_pad_settles_on_the_heaving_deck_and_scores_deck():
    w = World(calm(HeaveSpec(model='sine', amplitude_m=0.15, period_s=6.0)), seed=1)
    cx, cy, _ = w.truth().beacon_position_m
    place(w, cx + 0.05, cy, 1.5)
    c = descend_until_contact(w)
    assert c is not None and c.kind == 'pad'
    assert c.horizontal_error_m == pytest.approx(0.05, abs=1e-3)
    assert 0.05 < c.touchdown_speed_mps < 0.6 and c.lateral_speed_mps < 0.01
    assert not w.landing_done                        # armed: not settled yet
    # motors idle (the controller's landed thrust), then disarmed: it rides the deck
    w.set_command(0.0, 0.0, 0.0, 0.0)
    for _ in range(round(1.0 / DT)):
        w.step(DT)
    assert w.resting_on == 'pad' and w.disarm()
    p = w.params
    sag = p.mass_kg * p.gravity_mps2 / p.contact.stiffness_n_per_m
    for _ in range(round(3.0 / DT)):
        w.step(DT)
        tr = w.truth()
        assert tr.position_m[2] == pytest.approx(tr.deck_height_m + p.gear.height_m - sag,
                                                 abs=2e-4)
        assert tr.velocity_mps[2] == pytest.approx(tr.deck_vz_mps, abs=2e-3)
    assert w.landing_done and not w.armed
    out = w.outcome()
    assert out.landed_on_deck and out.landing == 'deck' and out.settled
    assert not out.crash and not out.fallback and out.reason == 'landed on the pad'
    assert out.impacts == 1 and out.bounces == 0


def test_deck_rising_into_a_hovering_vehicle_counts_the_deck_speed():
    w = World(calm(HeaveSpec(model='sine', amplitude_m=0.3, period_s=4.0)), seed=2)
    cx, cy, _ = w.truth().beacon_position_m
    place(w, cx, cy, 0.85 + w.params.gear.height_m)   # the deck rises through 0.85 m
    p = w.params
    v = w.vehicle
    before = None
    for _ in range(round(8.0 / DT)):
        before = (v.vz, w.truth().deck_vz_mps)
        w.set_command(0.0, 0.0, 0.0, p.mass_kg * p.gravity_mps2 / v.gamma)   # hover
        w.step(DT)
        if w.contact is not None:
            break
    c = w.contact
    assert c is not None and c.kind == 'pad'
    assert before[1] > 0.05          # the deck rose into the hover (its cushion lifts the
    #                                  vehicle a little: the motors lag the gain)
    # relative along the (level) deck normal, seen before the contact force acted (the
    # deck accelerates by ≤ A ω² = 0.74 m/s² over the 2.5 ms between)
    assert c.touchdown_speed_mps == pytest.approx(before[1] - before[0], abs=0.005)


def test_flying_into_the_side_of_the_apron_is_an_edge_strike_and_a_crash():
    w = World(calm(), seed=3)
    cx, cy, top = w.truth().beacon_position_m
    p = w.params
    # beside the box, the gear 5 cm below its top, moving into its side at 0.5 m/s
    place(w, cx + w.pad_half_x + p.gear.half_length_m + 0.02, cy, top - 0.05 + p.gear.height_m)
    w.vehicle.vx = -0.5
    w.set_command(0.0, 0.0, 0.0, p.mass_kg * p.gravity_mps2)
    run_until_done(w, 1.0)
    assert w.contact.kind == 'edge' and w.landing_done
    out = w.outcome()
    assert out.crash and out.landing == 'crash' and 'edge strike' in out.reason


def test_landing_half_over_the_edge_is_never_a_success():
    """Centre of mass above the pad's edge line: two feet on the pad, two over the drop."""
    w = World(calm(), seed=3)
    cx, cy, _ = w.truth().beacon_position_m
    place(w, cx + w.pad_half_x, cy, 1.2)
    assert descend_until_contact(w) is not None
    w.disarm()
    run_until_done(w, 5.0)
    out = w.outcome()
    assert not out.landed_on_deck and out.landing in ('crash', 'failed'), out.reason


def test_ground_contact_is_fallback_and_hard_drop_is_crash():
    w = World(calm(), seed=4)
    cx, cy, _ = w.truth().beacon_position_m
    place(w, cx + 3.0, cy, 1.0)
    c = descend_until_contact(w)
    assert c.kind == 'ground'
    assert c.horizontal_error_m == pytest.approx(3.0, abs=1e-3)
    out = w.outcome()
    assert out.fallback and not out.crash and not out.landed_on_deck
    # motors off from 3 m without drag: touchdown speed ≈ √(2 g h) > crash limit
    sc = calm()
    w = World(dataclasses.replace(sc, vehicle=dataclasses.replace(
        sc.vehicle, drag_linear_n_per_mps=0.0, drag_quad_v_kg_per_m=0.0)), seed=4)
    place(w, cx + 3.0, cy, 3.0)
    w.disarm()
    c = descend_until_contact(w, thrust=0.0)
    assert c.kind == 'ground'
    gear = w.params.gear.height_m
    assert c.touchdown_speed_mps == pytest.approx(math.sqrt(2 * 9.81 * (3.0 - gear)), rel=0.01)
    assert w.landing_done and w.outcome().crash


def test_hover_start_is_trimmed():
    w = World(calm(), seed=5)
    z0 = w.truth().position_m[2]
    for _ in range(400):
        w.step(DT)
    assert abs(w.truth().position_m[2] - z0) < 1e-3


def test_a_deck_drifting_at_half_a_metre_per_second_carries_the_landed_vehicle():
    """The existing drift key (issue 13's translating deck): the pad moves, a vehicle resting
    on it moves with it by friction and settles relative to it."""
    w = World(calm(drift_velocity_mps=(0.5, 0.0)), seed=6)
    cx, cy, top = w.truth().beacon_position_m
    p = w.params
    place(w, cx, cy, top + p.gear.height_m + 0.02)
    w.vehicle.vx = 0.5
    w.disarm()
    run_until_done(w, 4.0)
    tr = w.truth()
    assert tr.deck_velocity_mps == (0.5, 0.0)
    assert tr.velocity_mps[0] == pytest.approx(0.5, abs=1e-3)
    assert tr.position_m[0] - tr.beacon_position_m[0] == pytest.approx(0.0, abs=0.01)
    out = w.outcome()
    assert out.landing == 'deck' and out.settled and out.lateral_speed_mps < 0.01


def held_at(world, x, y, z, seconds=0.02):
    """Hold the vehicle at (x, y, z) for ``seconds`` of physics (the sensors sample it)."""
    for _ in range(round(seconds / DT)):
        place(world, x, y, z)
        world.step(DT)


def test_lidar_drops_by_deck_height_when_pad_comes_under():
    sc = calm()
    sc = dataclasses.replace(sc, sensors=ideal_sensors(sc.sensors))
    w = World(sc, seed=6)
    cx, cy, top = w.truth().beacon_position_m
    held_at(w, cx + 1.5, cy, 2.0)
    assert w.read_lidar() == pytest.approx(2.0, abs=1e-6)
    held_at(w, cx + 0.3, cy, 2.0)
    assert w.read_lidar() == pytest.approx(2.0 - top, abs=1e-6)
    assert top == pytest.approx(0.6)


def test_camera_sees_beacon_below_and_stamp_is_exposure_time():
    sc = calm()
    cam = dataclasses.replace(sc.sensors.camera, pixel_noise_px=0.0, dropout_prob=0.0)
    sensors = ideal_sensors(dataclasses.replace(sc.sensors, camera=cam))
    w = World(dataclasses.replace(sc, sensors=sensors), 7)
    cx, cy, _ = w.truth().beacon_position_m
    held_at(w, cx, cy, 2.0, 0.1)
    stamp, blocks = w.read_camera()
    period = 1.0 / sensors.true_camera.timing.rate_hz
    # ideal timing: the frame of the last period boundary, stamped at its exposure
    assert stamp == pytest.approx(period * math.floor(w.t_s / period + 1e-6), abs=1e-9)
    assert len(blocks) == 1 and blocks[0][1:3] == (160, 100)


def closed_loop_streams(seed, scenario='paper', seconds=3.0):
    w = World(load_scenario(scenario), seed)
    out = []
    p = w.params
    for k in range(round(seconds / DT)):
        if k % 4 == 0:
            pos, vel = w.read_local_position()
            w.set_command(0.0, 0.05, 0.0,
                          p.mass_kg * (p.gravity_mps2 + 2.0 * (2.0 - pos[2]) - 1.5 * vel[2]))
            out.append((pos, vel, w.read_lidar(), w.read_attitude(), w.read_accel_world()))
        if k % 8 == 0:
            out.append(w.read_camera())
        w.step(DT)
    out.append(w.truth())
    return out


@pytest.mark.parametrize('scenario', ['paper', 'ship_ss4'])
def test_determinism_same_seed_same_streams_different_seed_differs(scenario):
    a = closed_loop_streams(11, scenario)
    assert a == closed_loop_streams(11, scenario)
    assert a != closed_loop_streams(12, scenario)


def test_sub_stepping_equals_fine_steps():
    a = World(load_scenario('gusty'), 3)
    b = World(load_scenario('gusty'), 3)
    for _ in range(50):
        a.step(0.01)
        for _ in range(4):
            b.step(0.0025)
    assert a.truth() == b.truth()


def test_bad_input_is_rejected_and_counted():
    w = World(calm(), seed=8)
    before = w.truth()
    w.step(float('nan'))
    w.step(-1.0)
    assert w.rejected['bad_dt'] == 2 and w.truth() == before
    w.set_command(0.1, 0.0, 0.0, 20.0)
    w.set_command(float('nan'), 0.0, 0.0, 20.0)
    w.set_command(0.0, 0.0, 0.0, float('inf'))
    assert w.rejected['nan'] == 2
    assert (w.vehicle.cmd_roll, w.vehicle.cmd_thrust) == (0.1, 20.0)
    assert not w.command_link(0.0, 0.0, math.nan, 0.0, 20.0) and w.rejected['nan'] == 3
    assert not w.autopilot.active                  # a rejected command engages nothing


def test_per_run_randomisation_comes_from_the_seed():
    sc = load_scenario('paper')
    starts = {World(sc, s).truth().position_m[:2] for s in range(20)}
    assert len(starts) == 20
    for s in range(20):
        x, y, _ = World(sc, s).truth().position_m
        assert math.hypot(x + 2.8, y + 0.3) <= sc.randomize.start_offset_m + 1e-9
    # GPS bias makes the reported position differ from truth by decimetres
    errs = []
    for s in range(50):
        w = World(sc, s)
        pos, _ = w.read_local_position()
        errs.append(math.hypot(pos[0] - w.truth().position_m[0],
                               pos[1] - w.truth().position_m[1]))
    assert max(errs) > 0.8


def test_true_lidar_range_is_the_full_matrix_formula_bit_for_bit():
    import random

    from deck_simulator.sensors import lidar_true_range
    from deckland_common.frames import rot_body_to_world
    w = World(calm(), seed=2)
    cx, cy, ztop = w.truth().beacon_position_m
    rng = random.Random(5)
    for _ in range(500):
        v = w.vehicle
        v.x, v.y, v.z = cx + rng.uniform(-2, 2), cy + rng.uniform(-2, 2), rng.uniform(-0.1, 3)
        v.set_attitude(rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6),
                       rng.uniform(-math.pi, math.pi))
        ref = lidar_true_range((v.x, v.y, v.z), rot_body_to_world(v.roll, v.pitch, v.yaw),
                               (cx, cy), ztop, (w.pad_half_x, w.pad_half_y))
        assert w.true_lidar_range() == ref


def test_a_beacon_far_outside_the_view_is_never_drawn():
    """The rolling shutter's exposure row of a beacon off the sensor is the nearest row: the
    frame's readout bounds every exposure time. Unbounded, a beacon 75° off the axis took its
    row from the distortion polynomial (thousands of rows), its exposure time seconds away, and
    was drawn from the pose extrapolated that far with the body rates: phantom detections of a
    deck 9.5 m away (paper_translating seed 100005), which the stack then chased."""
    w = World(calm(), seed=3)
    cx, cy = w.scenario.apron.position_m
    v = w.vehicle
    drawn = 0
    for k in range(200):
        a = 2.0 * math.pi * k / 200
        place(w, cx + 9.5 * math.cos(a), cy + 9.5 * math.sin(a), 3.0)
        v.vx, v.vy = 3.0 * math.cos(a), 3.0 * math.sin(a)
        v._roll_rate, v._pitch_rate, v._yaw_rate = (1.5 * math.sin(3 * a), 1.5 * math.cos(5 * a),
                                                   0.8)
        drawn += len(w._render_frame(10.0, 10.02))
    assert drawn == 0


def test_the_autopilot_holds_the_commanded_heading_on_its_estimate():
    """docs/world/sensors.md: a heading setpoint is held on the autopilot's estimate (what
    ATTITUDE reports), so the true heading is off by the estimate's heading error; before,
    the true heading was held and the reported yaw stayed off by the error for good."""
    sc = calm()
    sc = dataclasses.replace(sc, sensors=dataclasses.replace(
        sc.sensors, attitude=dataclasses.replace(sc.sensors.attitude, yaw_bias_std_rad=0.1)))
    w = World(sc, seed=3)
    err = w.sensor_suite.attitude.heading_error_rad
    assert abs(err) > 0.05                       # a heading error worth measuring
    p, v = w.params, w.vehicle
    place(w, 0.0, 0.0, 2.0)
    for k in range(round(6.0 / DT)):
        if k % 4 == 0:
            w.set_command(0.0, 0.0, 0.5, p.mass_kg * (p.gravity_mps2 - 3.0 * v.vz) / v.gamma)
        w.step(DT)
    reported = w.read_attitude()[2]
    assert reported == pytest.approx(0.5, abs=0.01)
    assert v.yaw == pytest.approx(0.5 - w.sensor_suite.attitude.heading_error_rad, abs=0.01)
