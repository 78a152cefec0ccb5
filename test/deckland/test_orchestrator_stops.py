"""Clean stops of real rclpy node processes, one per process and composed.

The child node publishes from its callbacks all the time, so a stop always lands inside a
callback. With rclpy's own signal handlers (the old ``run_node``) SIGINT shut the context
down from rclpy's signal thread while the callback was still publishing: ``[FATAL] Exception
in 'timers' callback: ... publisher's context is invalid``. Now a signal only ends the spin;
executor, node and context are shut down in that order: no traceback, no FATAL, status 0.
"""

import io
import os
import signal
import textwrap
import time

from deckland.graph.composed import ComposedSpec, component_table, compose, node_class, ros_args
from deckland.graph.orchestrator import NodeSpec, Orchestrator, members
import pytest

pytestmark = pytest.mark.ros

BUSY = """
    from deckland_common.ros_node import run_node
    from rclpy.node import Node
    from std_msgs.msg import String


    class BusyNode(Node):
        '''Publishes 200 messages per 1 ms timer tick: always inside a callback.'''

        def __init__(self, **kwargs):
            super().__init__('busy', **kwargs)
            self.pub = self.create_publisher(String, 'busy/out', 10)
            self.create_timer(0.001, self.tick)

        def tick(self):
            for _ in range(200):
                self.pub.publish(String(data='x'))


    def main():
        return run_node(BusyNode)
"""


@pytest.fixture
def pkg_env(tmp_path):
    pkg = tmp_path / 'stop_children'
    pkg.mkdir()
    (pkg / '__init__.py').write_text('')
    (pkg / 'busy.py').write_text(textwrap.dedent(BUSY))
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(tmp_path), env.get('PYTHONPATH', '')])
    env['ROS_DOMAIN_ID'] = str(150 + os.getpid() % 50)
    return env


def busy(name):
    return NodeSpec(name=name, package='stop_children', module='busy')


def run_and_stop(nodes, env, sig=signal.SIGINT):
    out = io.StringIO()
    orch = Orchestrator(nodes, out=out, env=env, stop_timeout_s=8.0)
    try:
        orch.start()
        assert orch.wait_ready(60.0) == [], out.getvalue()
        time.sleep(0.5)                                  # well inside the busy callbacks
        for p in orch.procs:
            p.signal(sig)
        for p in orch.procs:
            p.proc.wait(timeout=8.0)
    finally:
        orch.stop()
        orch.close()
    return orch, out.getvalue()


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_node_stopped_inside_its_callbacks_exits_cleanly(pkg_env, sig):
    orch, text = run_and_stop([busy('busy_a')], pkg_env, sig)
    assert 'FATAL' not in text and 'Traceback' not in text, text
    assert 'context is invalid' not in text, text
    assert [p.proc.returncode for p in orch.procs] == [0], text
    assert orch.exits == []


def test_composed_nodes_stopped_inside_their_callbacks_exit_cleanly(pkg_env):
    nodes = compose([busy('busy_a'), busy('busy_b')])
    assert [type(n) for n in nodes] == [ComposedSpec]
    orch, text = run_and_stop(nodes, pkg_env)
    assert set(orch.ready) == {'busy_a', 'busy_b'}          # each node reported by name
    assert len({r['pid'] for r in orch.ready.values()}) == 1  # ... from one process
    assert 'FATAL' not in text and 'Traceback' not in text, text
    assert [p.proc.returncode for p in orch.procs] == [0], text


def test_a_composed_process_that_dies_is_reported_with_every_node_it_held(pkg_env):
    out = io.StringIO()
    orch = Orchestrator(compose([busy('busy_a'), busy('busy_b')]), out=out, env=pkg_env)
    try:
        orch.start()
        assert orch.wait_ready(60.0) == [], out.getvalue()
        orch.by_name['busy_b'].signal(signal.SIGSEGV)     # one component's crash = all
        deadline = time.monotonic() + 10.0
        while not orch.exits and time.monotonic() < deadline:
            orch.check()
            time.sleep(0.05)
    finally:
        orch.stop()
        orch.close()
    (event,) = orch.exits
    assert event.node == 'stack' and event.nodes == ('busy_a', 'busy_b')
    assert event.status == -signal.SIGSEGV and not event.injected
    assert event.as_dict()['nodes'] == ['busy_a', 'busy_b']
    assert 'composed nodes lost with it: busy_a, busy_b' in out.getvalue()


def test_compose_keeps_the_per_process_arguments_and_the_simulator_apart():
    sim = NodeSpec(name='deck_simulator', package='deck_simulator', sim_only=True,
                   parameters={'seed': 3})
    est = NodeSpec(name='est', package='apron_estimator', parameters={'x': 'a b', 'n': 2},
                   remappings={'apron/state': 'other/state'}, params_file='/tmp/p.yaml')
    nodes = compose([sim, est, busy('busy_a')])
    assert nodes[0] is sim and members(nodes[1]) == ['est', 'busy_a']
    argv = est.command()
    assert ros_args(est) == argv[argv.index('--ros-args'):]
    assert ros_args(est)[-4:-2] == ['-r', 'apron/state:=other/state']
    (row_est, _), = [component_table(nodes[1].components)]
    assert row_est == {'name': 'est', 'package': 'apron_estimator', 'module': 'node',
                       'ros_args': ros_args(est)}
    cmd = nodes[1].command()
    assert cmd[1] == '-c' and 'deckland.graph.composed import main' in cmd[2] and len(cmd) == 4
    with pytest.raises(ValueError, match='components must not be empty'):
        ComposedSpec(name='stack', package='deckland', module='graph.composed')


def test_node_class_finds_each_stack_node():
    from rclpy.node import Node
    for pkg in ('pixy_driver', 'mavlink_bridge', 'apron_estimator', 'landing_planner',
                'dob_altitude', 'deck_simulator'):
        assert issubclass(node_class(pkg, 'node'), Node)
    with pytest.raises(ValueError, match='expected one Node subclass'):
        node_class('deckland.graph', 'up')
