"""``deckland up`` / ``deckland campaign`` with ``--autopilot ardupilot-sitl`` (deckland.sitl).

Without ArduCopter: what a mission gives ArduCopter (the JSON physics at the world's rate, the
paper's vehicle) and the graph (the simulator as its physics, the bridge on SERIAL0 with the
map anchored at the world's origin), the world ticking the JSON backend, the campaign's
failsafe bookkeeping for ArduPilot, and the clear error when the binary is missing. With
ArduCopter (``sitl``, skipped when the binary is not found): a paper mission lands.
"""

import json
import pathlib
import subprocess
import sys
from types import SimpleNamespace

from deck_simulator.scenario import load_scenario
from deckland.sitl import SITL_AUTOPILOTS, SitlNotFoundError, SitlStartError
from deckland.sitl.ardupilot import (
    JSON_RATE_HZ,
    MISSION_PARAMS,
    ArduPilotMission,
    ArduPilotNotFoundError,
    ArduPilotStartError,
    failsafe_check,
    find_ardupilot,
    mission_params,
    require_ardupilot,
)
import pytest
from rostest import isolated_env

try:
    AP_BIN = find_ardupilot()
    NO_AP = ('ArduCopter SITL not found (set DECKLAND_ARDUPILOT_SITL or provide '
             '../shared/ardupilot-sitl)')
except ArduPilotNotFoundError as exc:
    AP_BIN, NO_AP = None, str(exc)

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))


def test_mission_params_fly_the_papers_vehicle_on_the_worlds_physics_rate():
    sc = load_scenario('paper')
    p = mission_params(sc)
    assert p['SIM_RATE_HZ'] == JSON_RATE_HZ == 400
    assert p['FRAME_TYPE'] == 6                                    # PLUSREV (ardupilot_json)
    assert p['MOT_THST_HOVER'] == pytest.approx(1.0 / sc.vehicle.thrust_to_weight, abs=1e-4)
    assert MISSION_PARAMS['GUID_OPTIONS'] == 8 and MISSION_PARAMS['FS_GCS_ENABLE'] == 5


@pytest.mark.skipif(AP_BIN is None, reason=NO_AP)
def test_the_graph_is_pointed_at_arducopter_and_anchored_at_the_worlds_origin():
    mission = ArduPilotMission(load_scenario('paper'))
    mission.sitl.instance = 3                                      # (not started)
    nodes = [SimpleNamespace(name=n, parameters={}) for n in
             ('deck_simulator', 'mavlink_bridge', 'landing_planner')]
    mission.configure_graph(nodes)
    sim, bridge, planner = (n.parameters for n in nodes)
    assert sim == {'autopilot': 'ardupilot-sitl', 'ardupilot_physics_port': 9032,
                   'physics_rate_hz': 400.0}
    assert bridge['connection'] == 'tcp:127.0.0.1:5790' and bridge['autopilot'] == 'ardupilot'
    lat, lon, alt, _ = mission.home
    assert bridge['map_origin_llh'] == f'{lat:.7f},{lon:.7f},{alt:g}' and planner == {}
    assert mission.OFFBOARD_MODE == 'GUIDED_NOGPS' and mission.NAME == 'ArduCopter'


def test_ardupilot_is_one_more_entry_of_the_registry():
    ap = SITL_AUTOPILOTS['ardupilot-sitl']
    assert ap.load('mission') is ArduPilotMission and ap.report_key == 'ardupilot'
    assert ap.load('find') is require_ardupilot and ap.load('failsafe_check') is failsafe_check
    sc = load_scenario('paper')
    p = ap.load('params')(sc)
    assert p == {**MISSION_PARAMS, **mission_params(sc)}
    assert p['GUID_OPTIONS'] == 8 and p['SIM_RATE_HZ'] == JSON_RATE_HZ
    # up/campaign catch the generic errors
    assert issubclass(ArduPilotNotFoundError, SitlNotFoundError)
    assert issubclass(ArduPilotStartError, SitlStartError)


@pytest.mark.skipif(AP_BIN is None, reason=NO_AP)
def test_the_mission_object_uses_the_registry_params():
    """(Building an ArduPilotMission looks for the firmware: skipped without it.)"""
    sc = load_scenario('paper')
    assert ArduPilotMission(sc).params == SITL_AUTOPILOTS['ardupilot-sitl'].load('params')(sc)


def test_failsafe_check_wants_land_after_guided_nogps_landed_and_disarmed():
    good = {'contact_kind': 'ground', 'crash': False, 'ardupilot': {
        'armed_at_end': False, 'landed_state_at_end': 1, 'modes': [
            {'mode': 'GUIDED'}, {'mode': 'GUIDED_NOGPS'}, {'mode': 'LAND'}]}}
    assert failsafe_check(good, {})['ok']
    hold = {**good, 'ardupilot': {**good['ardupilot'], 'modes': [{'mode': 'GUIDED_NOGPS'}]}}
    chk = failsafe_check(hold, {})
    assert chk['action_expected'] == 'LAND'
    assert not chk['ok'] and chk['action_seen'] == ''              # the unattended hover
    armed = {**good, 'ardupilot': {**good['ardupilot'], 'armed_at_end': True}}
    assert not failsafe_check(armed, {})['ok']


def test_up_and_campaign_say_when_arducopter_is_missing(tmp_path):
    env = isolated_env(DECKLAND_ARDUPILOT_SITL=str(tmp_path / 'nothing'))
    res = subprocess.run([DECKLAND, 'up', '--autopilot', 'ardupilot-sitl'],
                         capture_output=True, text=True, timeout=60, env=env)
    assert res.returncode == 2 and 'DECKLAND_ARDUPILOT_SITL' in res.stderr
    res = subprocess.run([DECKLAND, 'campaign', '--autopilot', 'ardupilot-sitl', '--runs',
                          '1'], capture_output=True, text=True, timeout=60, env=env)
    assert res.returncode == 2 and 'DECKLAND_ARDUPILOT_SITL' in res.stderr


@pytest.mark.sitl
@pytest.mark.sitl_mission
@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.skipif(AP_BIN is None, reason=NO_AP)
def test_up_ardupilot_sitl_lands_on_the_deck_and_cleans_up(tmp_path):
    out = tmp_path / 'report.json'
    res = subprocess.run([DECKLAND, 'up', '--autopilot', 'ardupilot-sitl', '--scenario',
                          'paper', '--seed', '100001', '--timeout', '90', '--startup-timeout',
                          '90', '--report', str(out)], capture_output=True, text=True,
                         timeout=400, env=isolated_env())
    log = res.stdout + res.stderr
    assert out.exists(), log[-3000:]
    report = json.loads(out.read_text())
    ap = report['ardupilot']
    assert ap['params_wrong_after_boot'] == {}, ap
    assert report['autopilot_modes'][0]['mode'] == 'GUIDED_NOGPS', log[-3000:]
    assert report['success'] and report['contact_kind'] == 'pad', log[-3000:]
    assert ap['armed_at_end'] is False, log[-3000:]
    assert 'ArduCopter stopped, its working directory removed' in log
    print(f"ArduCopter mission: {report['reason']}, error {report['horizontal_error_m']:.3f} "
          f"m, touchdown {report['touchdown_speed_mps']:.2f} m/s, lockstep "
          f"{report['lockstep']}")
