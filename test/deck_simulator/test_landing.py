"""Whole-world landings: the ship deck (drop, resting while it rolls, off the pad, into the
sea), the deck pose the sensors see, and the graph's simulator node scoring the same record."""

import dataclasses
import json
import math

from deck_simulator.autopilot import LAND, EmulatedAutopilot
from deck_simulator.outcome import landing_outcome, outcome_dict
from deck_simulator.scenario import load_scenario
from deck_simulator.sensor_suite import ideal_sensors
from deck_simulator.ship_params import ShipParams
from deck_simulator.world import World
from deckland_common.frames import mat_t_vec
import pytest
from simloop_rig import Rig, calm

DT = 1.0 / 400.0

def ship_scenario(name='ship_ss3', **ship):
    sc = load_scenario(name)
    rz = dataclasses.replace(sc.randomize, start_offset_m=0.0, start_yaw_rad=0.0)
    ap = dataclasses.replace(sc.apron, ship=dataclasses.replace(sc.apron.ship, **ship))
    return dataclasses.replace(sc, randomize=rz, apron=ap)

def place_over_pad(w, gap_m, offset_m=(0.0, 0.0)):
    """Motors off, level with the deck, ``gap_m`` above it at ``offset_m`` (deck frame) from
    the pad centre, moving with the deck (so only gravity closes the gap)."""
    ps = w.pad_state()
    v = w.vehicle
    pos = ps.to_world((offset_m[0], offset_m[1], w.params.gear.height_m + gap_m))
    v.x, v.y, v.z = pos
    v.vx, v.vy, v.vz = ps.point_velocity(pos)
    v.set_attitude(*ps.rpy_rad, rates_radps=mat_t_vec(ps.rotation, ps.omega_radps))
    assert w.disarm()
    return ps

def run(w, seconds, until_done=True):
    for _ in range(round(seconds / DT)):
        w.step(DT)
        if until_done and w.landing_done:
            break

def test_a_drop_on_the_moving_ship_deck_lands_on_the_pad_and_settles():
    w = World(load_scenario('ship_ss3'), 1)
    ps = place_over_pad(w, 0.02)
    assert math.hypot(*ps.velocity_mps[:2]) == pytest.approx(2.5, abs=0.3)   # underway
    run(w, 6.0)
    c = w.contact
    assert c is not None and c.kind == 'pad' and c.horizontal_error_m < 0.01
    # relative figures: a 2 cm fall onto a deck moving at 2.5 m/s and heaving
    assert c.touchdown_speed_mps < 0.8 and c.lateral_speed_mps < 0.2
    assert w.landing_done
    out = w.outcome()
    assert out.landing == 'deck' and out.settled and not out.crash, out.reason
    tr = w.truth()
    assert tr.resting_on == 'pad' and tr.deck_rpy_rad != (0.0, 0.0, 0.0)
    assert math.dist(tr.velocity_mps, w.pad_state().point_velocity(tr.position_m)) < 0.05

def test_a_vehicle_resting_on_the_rolling_deck_stays_put():
    """Beam seas, sea state 4: the hull rolls ~9° (significant amplitude); friction 0.6
    holds the gear (tan 9° = 0.16): the feet stay where they landed, nothing bounces."""
    w = World(ship_scenario('ship_ss4', wave_heading_rad=math.pi / 2), 2)
    place_over_pad(w, 0.002)
    run(w, 2.0)
    assert w.landing_done
    rec0 = w.landing_record()
    roll_max = 0.0
    for _ in range(round(20.0 / DT)):
        w.step(DT)
        roll_max = max(roll_max, abs(w.truth().deck_rpy_rad[0]))
        assert w.resting_on == 'pad'
    rec = w.landing_record()
    assert roll_max > math.radians(4.0)
    moved = max(math.dist(a, b) for a, b in zip(rec0.feet_pad_m, rec.feet_pad_m, strict=True))
    assert moved < 0.005
    assert rec.outcome == 'deck' and rec.bounces == 0 and not rec.slid_off_pad

def test_first_contact_off_the_pad_fails_and_off_the_deck_is_in_the_sea():
    w = World(load_scenario('ship_ss3'), 3)
    place_over_pad(w, 0.02, offset_m=(1.5, 0.0))       # on the deck, 1.5 m ahead of the pad
    run(w, 6.0)
    out = w.outcome()
    assert out.contact_kind == 'deck' and out.landing == 'failed'
    assert 'first contact off the pad' in out.reason and not out.crash
    w = World(load_scenario('ship_ss3'), 3)
    ps = w.pad_state()
    place_over_pad(w, 0.02, offset_m=(0.0, 4.0))       # beside the hull: 2.5 m to the sea
    run(w, 6.0)
    out = w.outcome()
    assert out.contact_kind == 'water' and out.crash and 'landed in the water' in out.reason
    assert ps.position_m[2] > 2.0

def test_beacon_lidar_and_deck_velocity_follow_the_tilted_moving_deck():
    sc = load_scenario('ship_turning')
    sc = dataclasses.replace(sc, sensors=ideal_sensors(sc.sensors))
    w = World(sc, 4)
    v = w.vehicle
    for _ in range(round(7.3 / DT)):
        w.step(DT)
        ps = w.pad_state()
        # over the pad, level, 1.5 m above its centre
        v.x, v.y, v.z = ps.position_m[0] + 0.2, ps.position_m[1] - 0.1, ps.position_m[2] + 1.5
        v.set_attitude(0.0, 0.0, 0.3)
    ps = w.pad_state()
    assert ps.as_tuple() == w.ship.pad_state(w.t_s).as_tuple()
    tr = w.truth()
    assert tr.beacon_position_m == ps.position_m
    assert tr.deck_velocity_mps == ps.velocity_mps[:2] and tr.deck_vz_mps == ps.velocity_mps[2]
    assert tr.deck_rpy_rad == ps.rpy_rad and max(map(abs, ps.rpy_rad[:2])) > 1e-3
    # straight down to the tilted plane: z minus the plane's height under (x, y)
    assert w.true_lidar_range() == pytest.approx(v.z - ps.height_under(v.x, v.y), abs=1e-9)
    # the ideal lidar's last reading: the same plane, sampled up to one period (10 ms) ago
    assert w.read_lidar() == pytest.approx(v.z - ps.height_under(v.x, v.y), abs=0.02)
    assert tr.surface_height_m == pytest.approx(ps.height_under(v.x, v.y), abs=1e-9)
    assert tr.over_pad
    # the camera frame's beacon is the pad at the exposure time
    stamp, _ = w.read_camera()
    assert w._beacon_at(stamp) == w.ship.pad_state(stamp).position_m

def test_the_graph_simulator_node_scores_the_same_record_as_the_in_process_world():
    """AUTO.LAND over the pad through the simulator node's loop (emulated PX4 on the wire)
    and the same autopilot flown in-process: the same physics, the same outcome record."""
    sc = calm(start_position_m=[-3.2, -2.0, 2.0])
    rig = Rig(sc, seed=5)
    rig.set_mode(4, 6)                                       # AUTO.LAND
    ap = rig.sim.autopilot
    while ap.mode != LAND:
        rig.sim.advance(DT)
    t_land = rig.sim.world.t_s - DT                          # applied before that sub-step
    for _ in range(200):
        rig.run(0.1)
        if rig.outcomes:
            break
    (graph,) = rig.outcomes
    assert graph['outcome'] == 'deck' and graph['settled'] and graph['impacts'] >= 1
    assert graph['reason'] == 'landed on the pad'
    # in-process: the world with the same autopilot (the emulator's parameters)
    w = World(sc, 5)
    mine = EmulatedAutopilot(rig.emu.params.autopilot_params(), w)
    w.attach_autopilot(mine)
    mine.start_in_air(0.0)
    while w.t_s < t_land - 1e-9:
        w.step(DT)
    assert w.t_s == t_land
    mine.request_mode(w.t_s, LAND)
    while not w.landing_done:
        w.step(DT)
    alone = outcome_dict(landing_outcome(w, 5, None, 0, '', ''))
    assert json.dumps(alone, sort_keys=True) == json.dumps(graph, sort_keys=True)

def test_ship_scenario_keys_are_validated_with_their_path():
    from deck_simulator.scenario import scenario_from_dict
    with pytest.raises(ValueError, match=r'apron\.ship\.speed_mps'):
        scenario_from_dict({'apron': {'ship': {'speed_mps': -1.0}}}, 'x.yaml')
    with pytest.raises(ValueError, match=r'apron\.ship'):
        scenario_from_dict({'apron': {'ship': {}, 'heave': {'model': 'sine'}}}, 'x.yaml')
    with pytest.raises(ValueError, match=r'apron\.size_m'):
        scenario_from_dict({'apron': {'size_m': [6.0, 1.0], 'ship': {}}}, 'x.yaml')
    sc = scenario_from_dict({'apron': {'ship': {'pad_offset_m': [-4, 0, 2],
                                                'spreading_s': None}}}, 'x.yaml')
    assert sc.apron.ship == ShipParams(pad_offset_m=(-4.0, 0.0, 2.0), spreading_s=None)
    assert sc.landing_area_m == (0.0, 0.0)
