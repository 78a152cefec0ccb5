"""One ``deckland up --scenario fault_node_kill`` run end to end: ``dob_altitude`` is SIGKILLed
5 s after the trigger, the bridge's thrust input goes stale and it stops streaming, the emulated
PX4 takes the offboard-loss action the scenario configures (``action: return`` → AUTO.RTL after
COM_OF_LOSS_T = 0.3 s: brake, climb to 2 m, fly back to where OFFBOARD was engaged, clear of the
deck, and land there) and the vehicle comes down without a crash. Checked from report.json
(written by up.py from the simulator's outcome, the autopilot modes seen on vehicle/mode and the
orchestrator's events) and the recorded bag."""

import json
import pathlib
import subprocess
import sys

from deck_simulator.scenario import load_scenario
from deckland.ros.bag import bag_info
import pytest
from rostest import isolated_env

pytestmark = pytest.mark.timing   # a graph on the wall clock: reruns on a miss

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))


@pytest.mark.solo
def test_node_kill_of_the_altitude_controller_ends_in_a_failsafe_landing(tmp_path):
    (fault,) = load_scenario('fault_node_kill').faults
    assert (fault.type, fault.node, fault.start_s) == ('node_kill', 'dob_altitude', 5.0)
    run = tmp_path / 'run'
    res = subprocess.run([DECKLAND, 'up', '--scenario', 'fault_node_kill', '--record', str(run),
                          '--timeout', '45'], capture_output=True, text=True, timeout=60,
                         env=isolated_env())
    log = res.stdout + res.stderr
    report = json.loads((run / 'report.json').read_text())
    # the kill happened on time and is not counted as a crash
    (kill,) = report['injected_faults']
    assert kill['node'] == 'dob_altitude' and kill['killed'] is True, log
    assert 5.0 <= kill['at_s'] < 5.5
    assert 'crashed_nodes' not in report, log
    assert 'dob_altitude (pid' in log and 'was killed (fault injection): killed by SIGKILL' in log
    # the chain: OFFBOARD until the kill, then the autopilot's own offboard-loss action
    modes = report['autopilot_modes']
    names = [m['mode'] for m in modes]
    assert 'OFFBOARD' in names, log
    assert report['failsafe'] == 'AUTO.RTL', log
    t_failsafe = next(m['t_s'] for m in modes if m['mode'] == report['failsafe'])
    # stale after the bridge's input timeout (0.2 s), failsafe after COM_OF_LOSS_T (0.3 s)
    assert kill['at_s'] + 0.3 <= t_failsafe <= kill['at_s'] + 3.0, modes
    # ... and the outcome is a deliberate landing, never a crash
    assert report['reason'] != 'timeout', log
    assert report['crash'] is False and report['safe'] is True, report
    assert report['contact_kind'] == 'ground', report     # at home, not over the deck
    assert report['touchdown_speed_mps'] < 1.0
    assert report['time_to_land_s'] > kill['at_s'] + 1.0     # it came down after the failsafe
    assert res.returncode == (0 if report['success'] else 1)
    assert 'autopilot failsafe AUTO.' in res.stdout and '==== deckland up: summary' in res.stdout
    info = bag_info(run, recover=False)
    topics = {t.name.lstrip('/') for t in info.topics}
    assert {'control/thrust', 'vehicle/mode', 'sim/outcome'} <= topics
