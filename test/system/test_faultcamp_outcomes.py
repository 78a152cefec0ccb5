"""Fault campaigns: every fault ends safely (docs/failsafe.md).

A few seeded closed-loop runs per built-in ``fault_<type>`` scenario through ``run_landing``:
the outcome is never a crash, and the behaviour behind it is the documented one.
"""

from __future__ import annotations

import dataclasses
import math

from deck_simulator.outcome import classify
from deck_simulator.scenario import builtin_names, load_scenario
from deck_simulator.world import World
from deckland.batch.runner import RunConfig, RunResult, run_landing
import pytest

SEEDS = (100000, 100001, 100002)
SAFE = ('deck', 'fallback', 'hold')


def _runs(name: str, seeds=SEEDS) -> list[RunResult]:
    sc = load_scenario(name)
    return [run_landing(sc, s, RunConfig()) for s in seeds]


def test_every_fault_type_has_a_builtin_scenario():
    names = set(builtin_names())
    for kind in ('beacon_occlusion', 'camera_dropout', 'false_blobs', 'lidar_dropout',
                 'lidar_outliers', 'gps_jump', 'gust_step', 'mavlink_loss', 'mavlink_latency',
                 'mavlink_link_loss', 'node_kill'):
        assert f'fault_{kind}' in names


@pytest.mark.parametrize('name', ['fault_beacon_occlusion', 'fault_camera_dropout',
                                  'fault_lidar_outliers', 'fault_gust_step',
                                  'fault_mavlink_loss'])
def test_sensor_and_disturbance_faults_still_land_on_the_deck(name):
    for r in _runs(name):
        assert r.outcome == 'deck', (r.seed, r.reason)
        assert r.touchdown_speed_mps < 0.5 and r.horizontal_error_m < 0.15


def test_false_blob_next_to_the_beacon_lands_on_the_pad_or_holds_never_on_the_edge():
    # the glint is 0.6 m from the beacon, outside the pad: landing on it is an edge strike
    for r in _runs('fault_false_blobs', (100002, 100007, 100017)):   # edge strikes before
        assert r.outcome in ('deck', 'hold'), (r.seed, r.reason)
        if r.outcome == 'deck':
            assert r.horizontal_error_m < 0.2


def test_node_kill_engages_the_autopilot_failsafe_and_lands_softly_away_from_the_deck():
    sc = load_scenario('fault_node_kill')
    spec = sc.faults[0]
    for r in _runs('fault_node_kill'):
        # the scenario's action: return, flown to the end as AUTO.RTL (its final descent too)
        assert spec.action == 'return'
        assert r.failsafes == 1 and r.failsafe_mode == 'return'
        assert r.outcome in ('fallback', 'hold'), (r.seed, r.reason)
        if r.outcome == 'fallback':
            # MPC_LAND_SPEED of the scenario, well below the crash speed
            assert r.touchdown_speed_mps == pytest.approx(spec.land_speed_mps, abs=0.1)


def test_link_loss_mid_descent_is_caught_before_the_stale_command_reaches_the_deck():
    for r in _runs('fault_mavlink_link_loss'):
        assert r.failsafes == 1
        assert r.outcome in SAFE, (r.seed, r.reason)


def test_failsafe_return_climbs_flies_home_and_lands_at_the_land_speed():
    sc = load_scenario('fault_node_kill')
    sc = dataclasses.replace(sc, faults=[{'type': 'node_kill', 'node': 'dob_altitude',
                                          'start_s': 2.0, 'loss_timeout_s': 0.3,
                                          'hold_s': 1.0, 'action': 'return',
                                          'land_speed_mps': 0.4, 'min_alt_m': 2.5,
                                          'reengage_offboard': False}])
    w = World(sc, 7)
    v = w.vehicle
    home = (v.x, v.y)
    hover = v.cmd_thrust
    z_max = 0.0
    modes = set()
    for k in range(round(40.0 / w.physics_dt_s)):
        t = w.t_s
        if k % 4 == 0:
            # the stack flies ~1 m/s² forward until it dies at 2 s
            w.command_link(t, 0.0, 0.1, v.yaw, hover)
        w.step(w.physics_dt_s)
        z_max = max(z_max, v.z)
        modes.add(w.failsafe)
        if w.contact is not None:
            break
    assert {'hold', 'return', 'land'} <= modes
    assert z_max == pytest.approx(2.5, abs=0.15)           # climbed to min_alt_m first
    c = w.contact
    assert c is not None and c.kind == 'ground'
    assert math.hypot(c.position_m[0] - home[0], c.position_m[1] - home[1]) < 0.35
    assert c.touchdown_speed_mps == pytest.approx(0.4, abs=0.1)
    # it stays in the failsafe: a command arriving now is not applied
    thrust_before = v.cmd_thrust
    w.command_link(w.t_s, 0.3, 0.3, 0.0, 40.0)
    w.step(w.physics_dt_s)
    assert w.failsafe == 'land' and v.cmd_thrust == thrust_before


def test_classify_names_the_safety_class_of_a_run():
    assert classify(True, 'pad', math.nan, math.nan) == 'crash'
    assert classify(False, 'pad', math.nan, math.nan) == 'deck'
    assert classify(False, 'ground', math.nan, math.nan) == 'fallback'
    assert classify(False, 'none', 0.1, 2.0) == 'hold'
    assert classify(False, 'none', 1.5, 2.0) == 'unstable'          # too fast
    assert classify(False, 'none', 0.1, 2.0, roll_rad=0.6) == 'unstable'   # too tilted
    assert classify(False, 'none', 0.1, 0.1) == 'unstable'          # too low
    assert classify(False, 'none', math.nan, math.nan) == 'unstable'
    # the runner's record is the simulator's, plus the runner's own fields
    r = RunResult(seed=1, scenario='s', controller='dob')
    assert r.outcome == '' and r.contact_kind == 'none' and math.isnan(r.link_degraded_s)
