"""Scenario loading: built-ins, strict validation with the key path in the message."""

from deck_simulator.scenario import builtin_names, load_scenario, scenario_from_dict
from deck_simulator.world import World
import pytest
import yaml


def test_builtins_load_and_match_the_brief():
    assert set(builtin_names()) >= {'paper', 'paper_calm', 'gusty', 'sea_state_3',
                                    'sea_state_4'}
    p = load_scenario('paper')
    assert p.start_position_m == (-2.8, -0.3, 2.0)
    assert p.apron.position_m == (-3.2, -2.0) and p.apron.mean_height_m == 0.6
    assert (p.apron.heave.model, p.apron.heave.stroke_m, p.apron.heave.speed_mps) == (
        'triangle', 0.3, 0.09)
    assert load_scenario('paper_calm').wind.gust_std_mps == 0.0
    assert load_scenario('gusty').wind.mean_mps[0] >= 2.5
    s3, s4 = load_scenario('sea_state_3'), load_scenario('sea_state_4')
    assert (s3.apron.heave.significant_height_m, s3.apron.heave.peak_period_s) == (0.5, 6.0)
    assert (s4.apron.heave.significant_height_m, s4.apron.heave.peak_period_s) == (1.0, 7.0)
    assert s3.apron.mean_height_m == 1.0 and s3.start_position_m[2] == 3.0
    for name in builtin_names():
        World(load_scenario(name), 0).step(0.01)


def err(data):
    with pytest.raises(ValueError) as info:
        scenario_from_dict(data, 'test.yaml')
    return str(info.value)


def test_unknown_keys_are_rejected_with_their_path():
    msg = err({'apron': {'heave': {'model': 'triangle', 'stroke_m': 0.3, 'amplitude_m': 1}}})
    assert 'apron.heave.amplitude_m' in msg and 'test.yaml' in msg
    assert "'wind.gusts'" in err({'wind': {'gusts': 1.0}})
    assert "'bogus'" in err({'bogus': 1})
    assert 'sensors.camera.fov' in err({'sensors': {'camera': {'fov': 60}}})


def test_types_and_ranges_are_checked():
    assert 'apron.heave.stroke_m must be > 0' in err(
        {'apron': {'heave': {'model': 'triangle', 'stroke_m': -0.3}}})
    assert 'start_position_m must have 3 entries' in err({'start_position_m': [0, 0]})
    assert 'timeout_s must be a finite number' in err({'timeout_s': 'long'})
    assert 'apron.heave.model must be one of' in err({'apron': {'heave': {'model': 'waves'}}})
    assert 'vehicle.mass_kg' in err({'vehicle': {'mass_kg': 0.0}})
    assert 'sensors.lidar.noise_m' in err({'sensors': {'lidar': {'noise_m': -1}}})
    assert 'randomize.heave_phase must be true or false' in err(
        {'randomize': {'heave_phase': 1}})
    assert 'faults' in err({'faults': [{'kind': 'gps_loss'}]})
    assert 'top level must be a mapping' in err([1, 2])


def test_overrides_and_file_loading(tmp_path):
    path = tmp_path / 'mine.yaml'
    path.write_text(yaml.safe_dump({
        'name': 'mine', 'vehicle': {'ground_effect': {'body_coeff': 1.0}},
        'sensors': {'camera': {'fov_x_deg': 75.0}},
        'apron': {'heave': {'model': 'sea_state', 'significant_height_m': 0.8,
                            'spectrum': 'pierson_moskowitz'}},
        'faults': []}))
    sc = load_scenario(path)
    assert sc.vehicle.ground_effect.body_coeff == 1.0 and sc.vehicle.mass_kg == 2.71
    assert sc.sensors.camera.fov_x_deg == 75.0 and sc.sensors.camera.fov_y_deg == 47.0
    assert sc.apron.heave.spectrum == 'pierson_moskowitz'
    with pytest.raises(ValueError, match='no such built-in'):
        load_scenario(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('apron: [1, 2\n')
    with pytest.raises(ValueError, match='invalid YAML'):
        load_scenario(bad)
