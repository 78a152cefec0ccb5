"""``deckland up --composed`` against the per-process default: the same topics (names and
types) in the bag and a landing either way; and a node_kill in composed mode takes the whole
stack process, is reported with every node it held, and ends in the autopilot's failsafe."""

import json
import pathlib
import subprocess
import sys

from conftest import isolated_env
from deckland.bag import bag_info
import pytest

pytestmark = pytest.mark.ros

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))
STACK = ['pixy_driver', 'mavlink_bridge', 'apron_estimator', 'landing_planner', 'dob_altitude']


def fly(tmp_path, name, *extra, scenario='paper', timeout=90):
    run = tmp_path / name
    res = subprocess.run([DECKLAND, 'up', '--scenario', scenario, '--record', str(run),
                          '--timeout', str(timeout), *extra], capture_output=True, text=True,
                         timeout=timeout + 90, env=isolated_env())
    report = json.loads((run / 'report.json').read_text())
    return res, report, run


def topic_types(run):
    return {(t.name.lstrip('/'), t.msgtype) for t in bag_info(run, recover=False).topics}


def test_composed_mode_lands_with_the_same_topics_as_one_process_per_node(tmp_path):
    res_c, rep_c, run_c = fly(tmp_path, 'composed', '--composed')
    log = res_c.stdout[-3000:] + res_c.stderr[-2000:]
    assert rep_c['composed'] is True
    assert 'started stack (pid' in res_c.stdout and 'started deck_simulator' in res_c.stdout
    assert 'Traceback' not in log and 'FATAL' not in log, log
    res_p, rep_p, run_p = fly(tmp_path, 'per_process')
    assert rep_p['composed'] is False
    assert topic_types(run_c) == topic_types(run_p)
    assert res_c.returncode == 0 and rep_c['success'] is True, log
    assert res_p.returncode == 0 and rep_p['success'] is True, res_p.stdout[-3000:]


def test_a_node_kill_in_composed_mode_takes_the_stack_and_ends_in_the_failsafe(tmp_path):
    res, report, run = fly(tmp_path, 'kill', '--composed', scenario='fault_node_kill',
                           timeout=45)
    log = res.stdout + res.stderr
    (kill,) = report['injected_faults']
    assert kill['node'] == 'dob_altitude' and kill['killed'] is True, log
    assert kill['nodes_lost'] == STACK                    # the price of one process
    assert 'dob_altitude (composed in stack)' in log
    assert 'composed nodes lost with it: ' + ', '.join(STACK) in log
    assert 'crashed_nodes' not in report, log
    assert report['failsafe'] == 'AUTO.RTL', log
    assert report['crash'] is False and report['safe'] is True, report
    assert 'control/thrust' in {t for t, _ in topic_types(run)}
