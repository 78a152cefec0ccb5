"""World faults: gust step, height triggers, the command link and its offboard-loss failsafe."""

import dataclasses
import math

from deck_simulator.scenario import HeaveSpec, load_scenario
from deck_simulator.world import World
import pytest

DT = 1.0 / 400.0


def calm(faults=()):
    sc = load_scenario('paper_calm')
    rz = dataclasses.replace(sc.randomize, start_offset_m=0.0, start_yaw_rad=0.0,
                             heave_phase=False)
    ap = dataclasses.replace(sc.apron, heave=HeaveSpec(model='none'))
    return dataclasses.replace(sc, randomize=rz, apron=ap, faults=faults)


def hover_thrust(w, z_ref, vz_ref=0.0):
    p, v = w.params, w.vehicle
    return p.mass_kg * (p.gravity_mps2 + 3.0 * (z_ref - v.z) + 3.0 * (vz_ref - v.vz)) / (
        w.truth().gamma)


def test_gust_step_adds_its_vector_to_the_wind_and_pushes_the_vehicle():
    faults = [{'type': 'gust_step', 'start_s': 1.0, 'duration_s': 2.0,
               'wind_mps': [4.0, -2.0, 0.0]}]
    a, b = World(calm(), 2), World(calm(faults), 2)
    for k in range(round(4.0 / DT)):
        for w in (a, b):
            if k % 4 == 0:
                w.set_command(0.0, 0.0, 0.0, hover_thrust(w, 2.0))
            w.step(DT)
        ta, tb = a.truth(), b.truth()
        step = (4.0, -2.0, 0.0) if 1.0 <= tb.t_s < 3.0 else (0.0, 0.0, 0.0)
        assert tuple(y - x for x, y in zip(ta.wind_mps, tb.wind_mps, strict=True)) == (
            pytest.approx(step, abs=1e-12))
        if k == round(1.0 / DT) - 1:
            assert tb.position_m == ta.position_m        # identical until the gust
            assert b.active_faults() == ()
        if k == round(1.5 / DT):
            assert b.active_faults() == ('gust_step',)
    # drag pushes downwind (+x, −y) in the gust
    dx = b.truth().position_m[0] - a.truth().position_m[0]
    dy = b.truth().position_m[1] - a.truth().position_m[1]
    assert dx > 0.3 and dy < -0.15 and dx == pytest.approx(-2.0 * dy, rel=0.25)


def test_height_trigger_opens_the_window_when_the_vehicle_goes_below():
    faults = [{'type': 'gust_step', 'start_s': 0.5, 'duration_s': 1.0,
               'trigger_height_m': 1.0, 'wind_mps': [3.0, 0.0, 0.0]},
              {'type': 'lidar_dropout', 'start_s': 0.0, 'duration_s': 0.5,
               'trigger_height_m': 3.0}]
    w = World(calm(faults), 1)
    v = w.vehicle
    cx, cy, _ = w.truth().beacon_position_m
    v.x, v.y = cx + 3.0, cy        # over the ground: height = z
    opened = None
    for k in range(round(6.0 / DT)):
        if k % 4 == 0:
            w.set_command(0.0, 0.0, 0.0, hover_thrust(w, 2.0 - 0.3 * w.t_s, -0.3))
        h = w.truth().height_above_surface_m
        w.step(DT)
        if opened is None and 'gust_step' in w.active_faults():
            opened = (w.t_s, h)
    # below 3 m from the start (but start_s 0): lidar dropout open for 0.5 s from t = 0
    assert w.active_faults(0.25) == ('lidar_dropout',) and 'lidar_dropout' not in (
        w.active_faults(0.6))
    t_on, h_on = opened
    assert h_on == pytest.approx(1.0, abs=0.01)
    assert w.faults.all[0].on == pytest.approx(t_on, abs=DT + 1e-9)
    assert w.active_faults(t_on + 0.99) == ('gust_step',)
    assert w.active_faults(t_on + 1.01) == ()


def link_run(faults, seconds, bad_roll_after=None, seed=3, z_ref=2.0):
    """Hover on truth through ``command_link`` at 100 Hz; returns (world, samples)."""
    w = World(calm(faults), seed)
    cx, cy, _ = w.truth().beacon_position_m
    v = w.vehicle
    v.x, v.y = cx + 3.0, cy
    out = []
    for k in range(round(seconds / DT)):
        if k % 4 == 0:
            roll = 0.0
            if bad_roll_after is not None and bad_roll_after <= w.t_s < 2.0:
                roll = 0.25            # what the companion sends just before the link dies
            ok = w.command_link(w.t_s, roll, 0.0, 0.0, hover_thrust(w, z_ref))
            tr = w.truth()
            out.append((w.t_s, ok, w.failsafe, tr.position_m, tr.velocity_mps,
                        v.cmd_roll, v.cmd_thrust))
        w.step(DT)
    return w, out


def test_link_loss_triggers_failsafe_hold_then_land_and_the_link_comes_back():
    faults = [{'type': 'mavlink_link_loss', 'start_s': 2.0, 'end_s': 6.5,
               'loss_timeout_s': 1.0, 'hold_s': 2.0}]
    w, out = link_run(faults, 9.0, bad_roll_after=1.9)
    assert all(ok for t, ok, *_ in out if not 2.0 <= t < 6.5)
    assert not any(ok for t, ok, *_ in out if 2.0 <= t < 6.5)
    modes = [(t, fs) for t, _, fs, *_ in out]
    t_hold = next(t for t, fs in modes if fs == 'hold')
    t_land = next(t for t, fs in modes if fs == 'land')
    # COM_OF_LOSS_T = 1 s after the last command that got through, the autopilot takes over
    t_last = max(t for t, ok, *_ in out if ok and t < 2.0)
    assert 1.0 < t_hold - t_last <= 1.0 + 0.0101
    assert t_land == pytest.approx(t_hold + 2.0, abs=0.011)
    assert all(fs is None for t, fs in modes if t < 2.99 or t > 6.5)
    # between 2 and 3 s the vehicle keeps the last (bad) command: it accelerates sideways
    at = {round(t, 2): (p, v, roll, thr) for t, _, _, p, v, roll, thr in out}
    assert at[2.98][2] == 0.25 and at[2.98][1][1] < -0.4
    # hold: the vehicle brakes to rest (within its braking distance) and stays there
    p_hold, v_hold = at[round(t_hold, 2)][:2]
    p_end, v_end = at[round(t_land - 0.01, 2)][:2]
    p_mid = at[round(t_land - 0.51, 2)][0]
    speed0 = math.hypot(*v_hold[:2])
    assert speed0 > 1.0 and math.hypot(*v_end[:2]) < 0.1
    assert math.hypot(p_end[0] - p_hold[0], p_end[1] - p_hold[1]) < 0.8 * speed0
    assert math.hypot(p_end[0] - p_mid[0], p_end[1] - p_mid[1]) < 0.05
    assert p_end[2] == pytest.approx(p_hold[2], abs=0.1)
    # land: descending at the land speed (0.7 m/s) over x, y held
    assert at[6.4][1][2] == pytest.approx(-0.7, abs=0.1)
    # the link is back: commands apply again and the vehicle climbs back toward 2 m
    assert at[8.99][0][2] == pytest.approx(2.0, abs=0.35) and at[8.99][2] == 0.0
    in_window = sum(2.0 <= t < 6.5 for t, *_ in out)
    assert w.link_stats['failsafes'] == 1 and w.link_stats['lost'] == in_window
    assert in_window == pytest.approx(450, abs=1)


def test_node_kill_of_a_command_node_is_a_permanent_link_loss_ending_in_a_landing():
    faults = [{'type': 'node_kill', 'node': 'landing_planner', 'start_s': 1.0, 'hold_s': 1.0}]
    w, out = link_run(faults, 8.0)
    c = w.contact
    assert c is not None and c.kind == 'ground'
    assert c.touchdown_speed_mps == pytest.approx(0.7, abs=0.12)
    assert w.failsafe == 'land' and w.vehicle.cmd_thrust == 0.0
    p_fs = next(p for _, _, fs, p, *_ in out if fs == 'hold')
    assert math.hypot(c.position_m[0] - p_fs[0], c.position_m[1] - p_fs[1]) < 0.15
    # a killed pixy_driver empties the camera instead and leaves the link alone
    w2, out2 = link_run([{'type': 'node_kill', 'node': 'pixy_driver', 'start_s': 1.0}], 2.0)
    assert all(ok for _, ok, *_ in out2) and w2.failsafe is None
    assert w2.read_camera()[1] == []


def test_packet_loss_keeps_the_previous_command_at_the_given_rate():
    faults = [{'type': 'mavlink_loss', 'probability': 0.3}]
    w = World(calm(faults), 5)
    results = []
    prev = w.vehicle.cmd_roll
    for k in range(3000):
        roll = 0.001 * (k % 7)
        ok = w.command_link(w.t_s, roll, 0.0, 0.0, hover_thrust(w, 2.0))
        results.append(ok)
        assert w.vehicle.cmd_roll == (roll if ok else prev)
        prev = w.vehicle.cmd_roll
        w.step(0.01 / 4)
    assert results.count(False) / len(results) == pytest.approx(0.3, abs=0.03)
    assert w.failsafe is None       # losing 30 % of a 400 Hz stream never starves 1 s


def test_latency_applies_commands_late_in_order():
    faults = [{'type': 'mavlink_latency', 'start_s': 0.0, 'end_s': 1.0, 'latency_s': 0.1}]
    w = World(calm(faults), 5)
    applied = []
    for k in range(200):              # 100 Hz commands, 4 physics sub-steps each
        t = w.t_s
        w.command_link(t, 0.0, 0.0, 0.0, 20.0 + k * 0.01)
        w.step(DT)                    # the command in force during the tick's first sub-step
        applied.append((t, w.vehicle.cmd_thrust))
        for _ in range(3):
            w.step(DT)
    # the command sent at t is in force from t + 0.1 (sent at 0.5 → used from 0.6)
    at = {round(t, 3): thr for t, thr in applied}
    assert at[0.6] == pytest.approx(20.0 + 50 * 0.01)
    assert at[0.59] == pytest.approx(20.0 + 49 * 0.01)
    trim = World(calm(), 5).vehicle.cmd_thrust
    assert at[0.0] == at[0.05] == trim != 20.0        # nothing arrived yet: the start trim
    assert at[0.95] == pytest.approx(20.0 + 85 * 0.01)
    # after the window: no delay any more, but never reordered behind the queued commands
    thr = [x for _, x in applied][10:]
    assert thr == sorted(thr) and len(set(thr)) > 150
    assert at[1.5] == pytest.approx(20.0 + 150 * 0.01)


def test_command_link_without_link_faults_is_set_command():
    w = World(calm(), 1)
    assert w.command_link(0.0, 0.1, 0.0, 0.0, 20.0) is True
    assert (w.vehicle.cmd_roll, w.vehicle.cmd_thrust) == (0.1, 20.0)
    assert w.command_link(0.0, math.nan, 0.0, 0.0, 20.0) is False
    w2 = World(calm([{'type': 'mavlink_link_loss', 'start_s': 5.0}]), 1)
    assert w2.command_link(0.0, 0.0, 0.0, 0.0, math.inf) is False
    assert w.rejected['nan'] == 1 and w2.rejected['nan'] == 1
    assert w2.command_link(1.0, 0.0, 0.0, 0.0, 20.0) is True
    assert w2.command_link(0.5, 0.3, 0.0, 0.0, 10.0) is False          # stamp went back
    assert w2.rejected['out_of_order'] == 1 and w2.vehicle.cmd_thrust == 20.0
    w3 = World(calm([{'type': 'mavlink_link_loss', 'start_s': 5.0}]), 1)
    w3.command_link(0.0, 0.0, 0.0, 0.0, math.nan)
    for _ in range(800):
        w3.step(DT)
    assert w3.failsafe is None      # monitoring starts only with an accepted command
