"""``deckland up --composed`` against the per-process default: the same nodes and topics
(names and types) on the running graph (no real-time flight needed), the same bag topics and
a landing either way; and a node_kill in composed mode takes the whole stack
process, is reported with every node it held, and ends in the autopilot's failsafe."""

import json
import pathlib
import subprocess
import sys

from deckland.ros.bag import bag_info
import pytest
from rostest import isolated_env

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


def graph_view(composed: bool, env: dict) -> dict:
    """Node names and topics (names, types) of the running graph once every node is ready.

    Read from the DDS graph, which discovery threads keep, not the executors: it holds on a
    loaded machine where a starved composed executor answers no service for a minute. The
    parameters are the same by construction: the composed nodes get the very ``--ros-args``
    of the per-process command lines (deckland/test_orchestrator_stops.py), parsed by the
    same rcl."""
    import argparse
    import io
    import time

    from deckland.graph.composed import compose
    from deckland.graph.orchestrator import Orchestrator, load_graph
    from deckland.graph.up import UdpReservations, default_graph_path, graph_substitutions
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    udp = UdpReservations()
    args = argparse.Namespace(scenario='paper', seed=1, hardware=False, mavlink=None,
                              pixy_port=None, area=(0.0, 0.0))
    nodes = load_graph(default_graph_path(), graph_substitutions(args, udp), False)['nodes']
    orch = Orchestrator(compose(nodes) if composed else nodes, out=io.StringIO(), env=env,
                        pass_fds=udp.fds())
    context = rclpy.Context()
    rclpy.init(context=context, args=[], domain_id=int(env['ROS_DOMAIN_ID']))
    node = rclpy.create_node('viewer', context=context)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    try:
        orch.start()
        assert orch.wait_ready(120.0) == []
        deadline = time.monotonic() + 90.0
        names: set = set()
        while time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
            names = {n for n in node.get_node_names() if n != 'viewer'}
            if set(STACK) | {'deck_simulator'} <= names:   # every node discovered
                break
        topics: set = set()
        while time.monotonic() < deadline:                # until discovery has settled
            time.sleep(1.0)
            seen = {(t.lstrip('/'), tuple(ty)) for t, ty in node.get_topic_names_and_types()
                    if not t.startswith('/parameter_events') and t != '/rosout'}
            if seen == topics:
                break
            topics = seen
        return {'nodes': names, 'topics': topics}
    finally:
        orch.stop()
        orch.close()
        udp.close()
        ex.shutdown()
        node.destroy_node()
        context.try_shutdown()


def test_composed_mode_has_the_nodes_and_topics_of_the_per_process_mode():
    env = isolated_env()
    composed, per_process = graph_view(True, env), graph_view(False, env)
    assert set(STACK) | {'deck_simulator'} <= composed['nodes']
    assert composed['nodes'] == per_process['nodes']
    assert composed['topics'] == per_process['topics']
    assert ('control/thrust', ('geometry_msgs/msg/WrenchStamped',)) in composed['topics']


@pytest.mark.solo
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


@pytest.mark.solo
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
    # the bridge died with the stack: the emulated PX4's own record names the failsafe
    assert report['failsafe'] == 'AUTO.RTL', log
    assert report['crash'] is False and report['safe'] is True, report
    assert 'control/thrust' in {t for t, _ in topic_types(run)}
