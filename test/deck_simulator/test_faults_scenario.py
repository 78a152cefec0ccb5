"""Fault entries in scenarios: built-in fault scenarios, strict validation, determinism."""

import dataclasses
import math

from deck_simulator.faults import FAULT_TYPES, GustStep, parse_faults
from deck_simulator.scenario import builtin_names, load_scenario, scenario_from_dict
from deck_simulator.world import World
import pytest

DT = 1.0 / 400.0


#: fault scenarios whose fault is not a faults.py type: the ship's telemetry outage is the
#: ship link's own (deck_simulator.ship_link, ``ship_telemetry.outage_*``)
NOT_FAULTS_PY = ('fault_telemetry_loss',)


def test_every_fault_type_has_a_builtin_scenario_with_that_one_fault():
    names = [n for n in builtin_names() if n.startswith('fault_') and n not in NOT_FAULTS_PY]
    assert {n[len('fault_'):] for n in names} == set(FAULT_TYPES)
    for name in names:
        sc = load_scenario(name)
        assert sc.name == name
        assert [f.type for f in sc.faults] == [name[len('fault_'):]]
        # the rest is the paper experiment
        assert dataclasses.replace(sc, name='paper', faults=()) == load_scenario('paper')
        w = World(sc, 0)
        w.step(0.01)
        w.read_camera()
        w.read_lidar()
        w.read_local_position()


def test_the_telemetry_loss_scenario_is_ship_ss3_with_an_outage_mid_approach():
    sc = load_scenario('fault_telemetry_loss')
    st = sc.ship_telemetry
    assert st is not None and not sc.faults
    assert (st.outage_start_s, st.outage_duration_s) == (4.0, 30.0)
    base = load_scenario('ship_ss3')
    assert base.ship_telemetry is not None
    assert dataclasses.replace(sc, name='ship_ss3', ship_telemetry=base.ship_telemetry) == base


def test_the_brief_numbers_of_the_fault_scenarios():
    f = {n: load_scenario(n).faults[0] for n in builtin_names()
         if n.startswith('fault_') and n not in NOT_FAULTS_PY}
    assert f['fault_beacon_occlusion'].duration_s == 3.0
    assert (f['fault_false_blobs'].mode, f['fault_false_blobs'].near_beacon_m) == (
        'persistent', 0.6)
    assert (f['fault_lidar_dropout'].duration_s, f['fault_lidar_dropout'].trigger_height_m) == (
        1.0, 0.5)
    assert f['fault_gps_jump'].magnitude_m == 1.5
    assert math.hypot(*f['fault_gust_step'].wind_mps) == 4.0
    assert f['fault_mavlink_link_loss'].duration_s == 3.0


def err(faults):
    with pytest.raises(ValueError) as info:
        scenario_from_dict({'faults': faults}, 'test.yaml')
    msg = str(info.value)
    assert msg.startswith("scenario 'test.yaml': ")
    return msg


def test_bad_fault_entries_give_clear_errors():
    assert 'faults[0].type must be one of' in err([{'type': 'gps_loss'}])
    assert 'faults[0].type must be one of' in err([{'kind': 'gps_jump'}])
    assert "unknown key 'faults[1].magnitude'" in err(
        [{'type': 'gps_jump'}, {'type': 'gps_jump', 'magnitude': 2}])
    assert 'faults[0].end_s must be > start_s (5.0)' in err(
        [{'type': 'beacon_occlusion', 'start_s': 5, 'end_s': 4}])
    assert 'faults[0].start_s must be >= 0' in err([{'type': 'gust_step', 'start_s': -1}])
    assert 'faults[0].start_s must be a finite number' in err(
        [{'type': 'gust_step', 'start_s': 'soon'}])
    assert 'faults[0].probability must be in [0, 1]' in err(
        [{'type': 'lidar_dropout', 'probability': 1.5}])
    assert 'give end_s or duration_s, not both' in err(
        [{'type': 'lidar_dropout', 'end_s': 3, 'duration_s': 1}])
    assert 'faults[0].duration_s must be > 0' in err(
        [{'type': 'lidar_dropout', 'duration_s': 0}])
    assert 'faults[0].node must be one of' in err([{'type': 'node_kill'}])
    assert 'position_m or near_beacon_m is required' in err(
        [{'type': 'false_blobs', 'mode': 'persistent'}])
    assert "faults[0].mode must be 'window' or 'bursts'" in err(
        [{'type': 'camera_dropout', 'mode': 'sometimes'}])
    assert 'faults[0].wind_mps must have 3 entries' in err(
        [{'type': 'gust_step', 'wind_mps': [1, 2, 3, 4]}])
    assert 'faults[0].trigger_height_m must be > 0' in err(
        [{'type': 'gust_step', 'trigger_height_m': -0.5}])
    assert 'faults[0] must be a mapping' in err(['gps_jump'])
    assert 'faults must be a list' in err({'type': 'gps_jump'})
    assert "faults[0].direction must be 'short', 'long' or 'both'" in err(
        [{'type': 'lidar_outliers', 'direction': 'up'}])
    assert 'faults[0].latency_s must be in (0, 10]' in err(
        [{'type': 'mavlink_latency', 'latency_s': 0}])


def test_entries_are_normalised():
    sc = scenario_from_dict({'faults': [
        {'type': 'gust_step', 'start_s': 2, 'duration_s': 1.5, 'wind_mps': [3, -1]},
        {'type': 'gps_jump', 'start_s': 1, 'end_s': float('inf')},
        {'type': 'lidar_dropout'}]})
    g, j, d = sc.faults
    assert isinstance(g, GustStep) and (g.start_s, g.end_s, g.wind_mps) == (2.0, 3.5,
                                                                            (3.0, -1.0, 0.0))
    assert j.end_s == math.inf and d.start_s == 0.0 and d.end_s == math.inf
    # a Scenario built in code accepts mappings too (dataclasses.replace)
    sc2 = dataclasses.replace(load_scenario('paper'), faults=[{'type': 'lidar_dropout'}])
    assert sc2.faults == parse_faults([{'type': 'lidar_dropout'}])
    assert dataclasses.replace(load_scenario('paper'), faults=None).faults == ()


def streams(sc, seed=5, seconds=3.0):
    w = World(sc, seed)
    p = w.params
    out = []
    for k in range(round(seconds / DT)):
        if k % 4 == 0:
            pos, vel = w.read_local_position()
            w.set_command(0.02, 0.05, 0.0,
                          p.mass_kg * (p.gravity_mps2 + 2.0 * (2.0 - pos[2]) - 1.5 * vel[2]))
            out.append((pos, vel, w.read_lidar(), w.read_attitude(), w.read_accel_world()))
        if k % 8 == 0:
            out.append(w.read_camera())
        w.step(DT)
    out.append(w.truth())
    return out, w


@pytest.mark.parametrize('name', ['paper', 'gusty'])
def test_empty_faults_and_never_opening_faults_are_bit_identical(name):
    base = load_scenario(name)
    assert base.faults == ()
    a, wa = streams(base)
    b, _ = streams(scenario_from_dict({**_as_dict(base), 'faults': []}))
    assert a == b
    assert wa.faults is None and wa.active_faults() == ()
    # every fault type present but opening only after the run: the fault code paths (and
    # their own random streams) run, yet every sensor stream is the same bit for bit
    late = [{'type': t, 'start_s': 1000.0, **extra} for t, extra in (
        ('beacon_occlusion', {}), ('camera_dropout', {'mode': 'bursts'}),
        ('false_blobs', {}), ('false_blobs', {'mode': 'persistent', 'near_beacon_m': 0.6}),
        ('lidar_dropout', {}), ('lidar_outliers', {}), ('gps_jump', {}), ('gust_step', {}),
        ('mavlink_loss', {}), ('mavlink_latency', {}), ('mavlink_link_loss', {}),
        ('node_kill', {'node': 'pixy_driver'}))]
    c, wc = streams(dataclasses.replace(base, faults=late))
    assert c == a
    assert wc.faults is not None and wc.active_faults(1000.0) == tuple(f['type'] for f in late)


def test_a_fault_on_one_sensor_leaves_the_others_untouched():
    base = load_scenario('paper_calm')
    a, _ = streams(base)
    b, _ = streams(dataclasses.replace(base, faults=[{'type': 'lidar_outliers',
                                                      'probability': 0.5}]))
    lidar_a = [x[2] for x in a[:-1] if len(x) == 5]
    lidar_b = [x[2] for x in b[:-1] if len(x) == 5]
    assert lidar_a != lidar_b
    strip = [(x[0], x[1], x[3], x[4]) if len(x) == 5 else x for x in a[:-1]]
    assert strip == [(x[0], x[1], x[3], x[4]) if len(x) == 5 else x for x in b[:-1]]
    assert a[-1] == b[-1]


def _as_dict(sc):
    """The scenario back as a YAML-like mapping (to go through the loader)."""
    def conv(v):
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)
                    if not (type(v).__name__ == 'HeaveSpec' and f.name not in _heave_keys(v))}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v
    return conv(sc)


def _heave_keys(h):
    from deck_simulator.scenario import _HEAVE_KEYS
    return _HEAVE_KEYS[h.model]
