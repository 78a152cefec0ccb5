"""Every scenario key does what it says: each leaf of the Scenario dataclasses, written in YAML
as a user would, loads through the campaign's path and changes the run (issue 12, part 4)."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import pathlib
import typing

from deck_simulator.scenario import (
    _HEAVE_KEYS,
    HeaveSpec,
    Scenario,
    load_scenario,
    scenario_from_dict,
)
from deck_simulator.ship_link import ShipEncoder, ShipTelemetryParams
from deck_simulator.ship_params import ShipParams
from deck_simulator.world import SENSOR_STREAMS, World
from deckland.batch.runner import RunConfig, run_landing
import pytest
import yaml

DT = 1.0 / 400.0
#: keys that are not a leaf of the world's configuration: ``faults`` is a list of fault
#: entries with their own schema (each type's keys are tested by
#: deck_simulator/test_faults_scenario.py)
NOT_LEAVES = {'faults'}
#: alternatives for string keys (the first valid one that differs from the default is used)
STRINGS = {'model': ['sine', 'sea_state', 'triangle', 'none'],
           'spectrum': ['pierson_moskowitz', 'jonswap'],
           'stamp_mode': ['sample', 'arrival'], 'name': ['renamed'], 'kind': ['skids']}
DATA = pathlib.Path(load_scenario.__code__.co_filename).parent / 'data'
#: the YAML every variant starts from: the paper's (heave, wind with gusts, randomisation)
BASE = yaml.safe_load((DATA / 'paper.yaml').read_text(encoding='utf-8'))
#: keys that act only in a situation the defaults do not create: ``context`` is added to
#: both runs, ``with_value`` to the varied one only (a key mirrored by another), and the
#: candidate values are given (where a generic change is too small to show)
SPECIAL: dict[tuple[str, ...], dict] = {
    ('timeout_s',): {'candidates': [1.0]},   # the flight is cut at 2 s
    ('sensors', 'camera', 'false_blob_lifetime_s'): {
        'context': {'sensors': {'camera': {'false_blob_rate_hz': 30.0}}}},
    ('sensors', 'lidar', 'near_bias_spread'): {
        'context': {'sensors': {'lidar': {'near_bias_m': 0.05}}}},
    ('sensors', 'lidar', 'far_range_m'): {
        'context': {'sensors': {'lidar': {'near_range_m': 0.2}}}, 'candidates': [0.5]},
    ('sensors', 'lidar', 'noise_std_far_m'): {
        'context': {'sensors': {'lidar': {'near_range_m': 0.2, 'far_range_m': 0.5}}}},
    ('sensors', 'lidar', 'max_range_m'): {'candidates': [1.0]},
    ('sensors', 'lidar', 'footprint_rays'): {'candidates': [1]},   # the centre ray only
    ('sensors', 'lidar', 'merge_distance_m'): {'candidates': [1.0]},   # pad + ground blend
    ('sensors', 'lidar', 'deck_reflectivity'): {'ship': True},   # the deck around the pad
    ('apron', 'heave', 'model'): {'candidates': ['sine']},
    ('sensors', 'lidar', 'min_range_m'): {'candidates': [0.5]},
    ('sensors', 'lidar', 'reference_reflectivity'): {
        'context': {'sensors': {'lidar': {'max_range_m': 2.5}}}, 'candidates': [0.05, 1.0]},
    ('sensors', 'true_camera', 'p_std'): {'candidates': [0.01]},
    ('vehicle', 'gear', 'skid_points'): {'context': {'vehicle': {'gear': {'kind': 'skids'}}}},
    ('vehicle', 'ground_effect', 'max_gain'): {'candidates': [1.01]},
    ('vehicle', 'ground_effect', 'min_height_m'): {'candidates': [0.3]},
    ('vehicle', 'ground_effect', 'prop_radius_m'): {
        'with_value': {'vehicle': {'prop_radius_m': 0.1}}, 'candidates': [0.1]},
    ('vehicle', 'prop_radius_m'): {
        'with_value': {'vehicle': {'ground_effect': {'prop_radius_m': 0.1}}},
        'candidates': [0.1]},
    ('vehicle', 'rate_i_limit_radps2'): {'candidates': [0.01]},
    ('vehicle', 'thrust_to_weight'): {'candidates': [1.2]},
    ('outcome', 'tip_over_tilt_rad'): {'candidates': [0.01]},
    ('outcome', 'max_bounce_height_m'): {'candidates': [0.001]},
    # ppm of a clock stamped in ms: a change shows after seconds only when it is large
    ('ship_telemetry', 'clock_drift_ppm'): {'candidates': [2000.0, 500.0]},
    ('ship_telemetry', 'outage_start_s'): {
        'with_value': {'ship_telemetry': {'outage_duration_s': 2.0}}, 'candidates': [1.0]},
    ('ship_telemetry', 'outage_duration_s'): {
        'with_value': {'ship_telemetry': {'outage_start_s': 1.0}}, 'candidates': [2.0]},
}


def _yaml_value(v):
    if isinstance(v, tuple):
        return [_yaml_value(x) for x in v]
    return v


def leaves(cls: type, obj, path: tuple[str, ...] = ()):
    """(path, default value) of every leaf under the dataclass ``cls`` (instance ``obj``)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if not path and f.name in NOT_LEAVES:
            continue
        tp, value = hints[f.name], getattr(obj, f.name)
        here = (*path, f.name)
        if here == ('apron', 'ship'):
            yield from leaves(ShipParams, load_scenario('ship_ss3').apron.ship, here)
        elif here == ('ship_telemetry',):
            yield from leaves(ShipTelemetryParams, load_scenario('ship_ss3').ship_telemetry,
                              here)
        elif dataclasses.is_dataclass(tp):
            yield from leaves(tp, value, here)
        else:
            yield here, value


def context(path: tuple[str, ...]) -> dict:
    """The YAML a key is varied in: a ship for the ship's keys, the heave model whose key it
    is for the heave's; else the paper's scenario (plus the key's SPECIAL context)."""
    if path[:2] == ('apron', 'ship') or path[0] == 'ship_telemetry' \
            or SPECIAL.get(path, {}).get('ship'):
        return yaml.safe_load((DATA / 'ship_ss3.yaml').read_text(encoding='utf-8'))
    extra = SPECIAL.get(path, {}).get('context', {})
    if path[:2] == ('apron', 'heave'):
        model = 'none' if path[2] == 'model' else next(
            m for m in ('triangle', 'sine', 'sea_state') if path[2] in _HEAVE_KEYS[m])
        ctx = merge(BASE, {'apron': {}})
        ctx['apron'] = {**ctx['apron'], 'heave': {'model': model}}   # that model's keys only
        return ctx
    return merge(BASE, extra)


def candidates(path: tuple[str, ...], value):
    """Values to try for a key, the strongest change first."""
    name = path[-1]
    if 'candidates' in SPECIAL.get(path, {}):
        return SPECIAL[path]['candidates']
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [value * 2 + 1, value + 1, max(1, value - 1)]
    if isinstance(value, float):
        if value == 0.0 or not math.isfinite(value):
            return [0.5, 0.05, 0.01, 2.0, 1e-3, 0.1]
        return [value * 0.1, value * 3.0, value * 0.5, value * 1.5, value + 0.05, -value]
    if value is None:
        return [0.05, 0.5, 1.0]
    if isinstance(value, str):
        return [s for s in STRINGS.get(name, []) if s != value]
    if isinstance(value, tuple):
        out = []
        for scale, add in ((1.5, 0.1), (0.5, 0.05), (1.1, 0.01), (1.0, 0.02), (0.0, 0.0)):
            out.append(tuple(v * scale + add if isinstance(v, float) else v for v in value))
        return out
    raise AssertionError(f'no candidates for {name} = {value!r}')


def nested(path: tuple[str, ...], value) -> dict:
    out: dict = {path[-1]: _yaml_value(value)}
    for key in reversed(path[:-1]):
        out = {key: out}
    return out


def merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_like_campaign(data: dict, tmp_path: pathlib.Path) -> Scenario:
    """Written to a file; the driver's ``load_scenario(path)`` validates it, the worker
    parses the same text (deckland.batch.backends)."""
    path = tmp_path / 'scenario.yaml'
    text = yaml.safe_dump(data, sort_keys=False)
    path.write_text(text, encoding='utf-8')
    driver = load_scenario(path)
    worker = scenario_from_dict(yaml.safe_load(text) or {}, str(path))
    assert driver == worker
    return worker


def _digest(*parts) -> str:
    return hashlib.sha256(repr(parts).encode()).hexdigest()


def drop(sc: Scenario, on_pad: bool = True) -> str:
    """A vehicle held with the lidar spot on the pad's edge, then let down (a thrust kick,
    reduced thrust, a yaw command) onto the pad (or beside it, on the ground or the sea),
    disarmed when resting: its path, every sensor sample, the landing record."""
    w = World(sc, 3)
    w.queued = frozenset(SENSOR_STREAMS)
    ps = w.pad_state() if w.ship is not None else None
    bx, by, bz = ps.position_m if ps is not None else w.truth().beacon_position_m
    v = w.vehicle
    p = w.params
    mg = p.mass_kg * p.gravity_mps2
    path, samples = [], []
    n = round(0.3 / DT)
    for k in range(n):     # the lidar spot swept across the pad's edge, 1.2 m above it
        v.x, v.y, v.z = bx + w.pad_half_x - 0.02 + 0.04 * k / n, by, bz + 1.2
        v.vx = v.vy = v.vz = 0.0
        w.step(DT)
    v.x, v.y, v.z = (bx + 0.05, by - 0.03, bz + 0.45) if on_pad else (
        bx + w.pad_half_x + 1.0, by, max(bz, 0.0) + 0.45)
    v.vx, v.vz = 0.2, -0.3
    for k in range(round(2.7 / DT)):
        if k % 4 == 0:
            w.set_command(0.02, -0.01, 0.3, (1.6 if k < 40 else 0.75) * mg)
            if w.resting_on is not None:
                w.disarm(w.t_s)
        w.step(DT)
        if k % 20 == 0:
            path.append((v.x, v.y, v.z, v.roll, v.pitch, v.yaw, w.truth().wind_mps))
    for name in SENSOR_STREAMS:
        samples.append(w.delivered(name))
    return _digest(path, samples, w.landing_record(), w.rejected)


def drop_beside(sc: Scenario) -> str:
    return drop(sc, on_pad=False)


def flight(sc: Scenario) -> str:
    """The first two seconds of the closed-loop landing (the stack flying), traced."""
    sc = dataclasses.replace(sc, timeout_s=min(sc.timeout_s, 2.0))
    r = run_landing(sc, 5, RunConfig(record=True))
    return _digest(r.trace, r.summary())


#: every leaf with its value in the YAML it is varied in (the paper's; the ship's for its own)
ALL = sorted(leaves(Scenario, load_scenario('paper')))


def test_the_key_list_covers_every_section():
    tops = {p[0] for p, _ in ALL}
    assert tops == {f.name for f in dataclasses.fields(Scenario)} - NOT_LEAVES
    assert ('sensors', 'camera', 'mount_rpy_rad') in {p for p, _ in ALL}
    assert ('sensors', 'true_camera', 'timing', 'rate_hz') in {p for p, _ in ALL}
    assert ('apron', 'ship', 'speed_mps') in {p for p, _ in ALL}
    assert len(ALL) > 150


def test_the_readme_example_loads_as_a_list(tmp_path):
    sc = load_like_campaign({'sensors': {'camera': {'mount_rpy_rad': [0.03, -0.03, 0.02]}}},
                            tmp_path)
    assert sc.sensors.camera.mount_rpy_rad == (0.03, -0.03, 0.02)


def test_a_partial_section_keeps_the_other_defaults(tmp_path):
    base = Scenario()
    sc = load_like_campaign({'sensors': {'true_camera': {'timing': {'latency_s': 0.02}},
                                         'local_position': {'vertical': {'bias_std_m': 0.1}}}},
                            tmp_path)
    t0, t1 = base.sensors.true_camera.timing, sc.sensors.true_camera.timing
    assert t1 == dataclasses.replace(t0, latency_s=0.02)
    assert t1.stamp_mode == 'arrival' and t1.latency_jitter_s > 0.0
    v0 = base.sensors.local_position.vertical
    assert sc.sensors.local_position.vertical == dataclasses.replace(v0, bias_std_m=0.1)
    assert sc.sensors.local_position.horizontal == base.sensors.local_position.horizontal


@pytest.mark.parametrize('key, replacement', [
    ('sensors.camera.rate_hz', 'sensors.true_camera.timing.rate_hz'),
    ('sensors.lidar.noise_m', 'sensors.lidar.noise_std_m'),
    ('sensors.gps', 'sensors.local_position')])
def test_retired_keys_are_refused_with_their_replacement(tmp_path, key, replacement):
    data = nested(tuple(key.split('.')), {'x': 1} if key.endswith('gps') else 1.0)
    with pytest.raises(ValueError, match=replacement.replace('.', r'\.')):
        load_like_campaign(data, tmp_path)


def test_unknown_keys_are_refused_with_their_full_path(tmp_path):
    with pytest.raises(ValueError, match=r'sensors\.true_camera\.timing\.rate'):
        load_like_campaign({'sensors': {'true_camera': {'timing': {'rate': 10}}}}, tmp_path)
    with pytest.raises(ValueError, match=r'apron\.ship.*sped'):
        load_like_campaign(merge(context(('apron', 'ship', 'x')), {'apron': {'ship': {
            'sped': 1.0}}}), tmp_path)


def test_a_sensor_rate_the_physics_cannot_realise_is_refused(tmp_path):
    sc = load_like_campaign({'sensors': {'lidar': {'timing': {'rate_hz': 1000}}}}, tmp_path)
    with pytest.raises(ValueError, match='exceeds the physics rate 400'):
        World(sc, 1)
    with pytest.raises(ValueError, match='control_hz'):
        RunConfig(control_hz=300)


def ship_link(sc: Scenario) -> str:
    """Four seconds of the ship's MAVLink stream as it arrives (deck_simulator.ship_link),
    encoded from the ship's system id as the graph sends it; '' without ship telemetry."""
    st = sc.ship_telemetry
    if st is None:
        return ''
    w = World(sc, 3)
    enc = ShipEncoder(st.sysid, st.compid)
    out = []
    for _ in range(round(4.0 / DT)):
        w.step(DT)
        out.extend((t, enc.encode(m)) for t, m in w.read_ship_telemetry())
    return _digest(out)


#: cheapest first; a key must change one of them
CHECKS = (ship_link, drop, drop_beside, flight)


@pytest.mark.timeout(900)   # ~30 s of CPU; the wall time follows the machine's load
def test_every_key_changes_the_run(tmp_path):
    """Each leaf, set to the first candidate value that loads, changes the drop onto the pad,
    the drop beside it or the first two seconds of the landing (each compared with the same
    YAML without the key); the label ``name`` changes the report."""
    refs: dict[str, list[str | None]] = {}
    silent, refused = [], []
    for path, default in ALL:
        ctx = context(path)
        key = repr(ctx)
        refs.setdefault(key, [None] * len(CHECKS))
        extra = SPECIAL.get(path, {}).get('with_value', {})
        for value in candidates(path, default):
            try:
                sc = load_like_campaign(merge(merge(ctx, extra), nested(path, value)),
                                        tmp_path)
            except ValueError:
                continue
            break
        else:
            refused.append('.'.join(path))
            continue
        if path == ('name',):
            assert sc.name == value
            continue
        ref = refs[key]
        for i, check in enumerate(CHECKS):
            if ref[i] is None:
                ref[i] = check(load_like_campaign(ctx, tmp_path))
            if check(sc) != ref[i]:
                break
        else:
            silent.append(f"{'.'.join(path)} = {value!r}")
    assert not refused, f'no candidate value loads for {refused}'
    assert not silent, f'these keys changed nothing: {silent}'


def test_heave_model_keys_are_those_of_the_model():
    for model, keys in _HEAVE_KEYS.items():
        assert keys <= {f.name for f in dataclasses.fields(HeaveSpec)}, model
