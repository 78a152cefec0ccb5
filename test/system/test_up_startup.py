"""Start-up without races: the graph's listening sockets are bound before the nodes start and
handed to them by fd, so a port cannot be taken between pick and bind; readiness is an explicit
line per node on a pipe; a driver without its device says so (readiness, diagnostics, summary).
"""

import argparse
import socket
import sys
import textwrap
import time

from deck_simulator.transport import make_mavlink_link
from deckland.graph.mission_report import summary_lines
from deckland.graph.orchestrator import NodeSpec, Orchestrator
from deckland.graph.up import UdpReservations, graph_substitutions
from deckland_common.readiness import parse_ready_line, ready_line
from pixy_driver.protocol import encode_frame
import pytest


def sim_args():
    return argparse.Namespace(scenario='paper', seed=1, hardware=False, mavlink=None,
                              pixy_port=None, area=(0.0, 0.0))


def squat(port: int) -> socket.socket | None:
    """What any other process may do meanwhile (an ephemeral bind, a DDS participant's
    well-known port): bind the port. None when it is already taken."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(('127.0.0.1', port))
    except OSError:
        s.close()
        return None
    return s


def test_a_port_cannot_be_taken_between_pick_and_bind_and_the_driver_reads_it(ros_context):
    """On the old code (a port picked free, bound later by the driver) the squatter got the
    port and the driver failed with EADDRINUSE; now the port is held from the pick on."""
    from pixy_driver.node import PixyDriverNode
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud

    context, executor = ros_context
    udp = UdpReservations()
    try:
        subs = graph_substitutions(sim_args(), udp)
        port, fd = subs['pixy_udp_port'], subs['pixy_udp_fd']
        assert fd in udp.fds() and port > 0
        assert squat(port) is None, 'the Pixy port was free for anyone to take'
        assert squat(int(subs['sim_mavlink_url'].rsplit(':', 1)[1])) is None
        node = PixyDriverNode(context=context, parameter_overrides=[
            Parameter('transport', value='udp'), Parameter('udp_port', value=port),
            Parameter('udp_fd', value=fd)])
        assert node.device_problem() == '' and node.udp_port_bound == port
        got = []
        sub_node = __import__('rclpy').create_node('listener', context=context)
        sub_node.create_subscription(PointCloud, 'pixy/blocks', got.append, 10)
        executor.add_node(node)
        executor.add_node(sub_node)
        frame = encode_frame([(1, 160, 100, 10, 8)])
        deadline = time.monotonic() + 10.0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            while not got and time.monotonic() < deadline:
                tx.sendto(frame, ('127.0.0.1', port))
                time.sleep(0.1)
        assert got and got[0].points[0].x == 160.0
    finally:
        udp.close()


def test_the_simulators_mavlink_socket_is_the_inherited_one():
    udp = UdpReservations()
    try:
        port, fd = udp.bind()
        link = make_mavlink_link(f'udpin:127.0.0.1:{port}', fd)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b'hello', ('127.0.0.1', port))
            deadline = time.monotonic() + 2.0
            got = []
            while not got and time.monotonic() < deadline:
                got = link.receive()
                time.sleep(0.01)
        assert got and got[0][0] == b'hello'
        link.close()                          # its own duplicate: the reservation stays
        assert squat(port) is None
        with pytest.raises(OSError, match='not a UDP socket bound to port'):
            make_mavlink_link(f'udpin:127.0.0.1:{port + 1 if port < 65535 else 1}', fd)
    finally:
        udp.close()


def test_readiness_lines_round_trip_and_reject_garbage():
    line = ready_line('pixy_driver', 42, 'cannot open x' * 100).decode()
    assert line.endswith('\n') and len(line) < 512      # one atomic pipe write
    msg = parse_ready_line(line)
    assert msg['node'] == 'pixy_driver' and msg['pid'] == 42 and len(msg['problem']) == 300
    for bad in ('', 'ready\n', '{"node": "x"}\n', '[1, 2]\n', '{"node": "a", "pid": "b"}'):
        assert parse_ready_line(bad) is None


CHILDREN = {
    # reports ready after READY_DELAY_S, then sleeps until stopped
    'slowready': """
        import os, time
        from deckland_common.readiness import write_ready
        def main():
            time.sleep(float(os.environ.get('READY_DELAY_S', '0')))
            write_ready(os.environ.get('READY_NAME', 'slowready'),
                        os.environ.get('READY_PROBLEM', ''))
            try:
                time.sleep(60)
            except KeyboardInterrupt:
                return 0
    """,
}


@pytest.fixture
def pkg_env(tmp_path):
    pkg = tmp_path / 'pkgs' / 'readykids'
    pkg.mkdir(parents=True)
    (pkg / '__init__.py').write_text('')
    for name, src in CHILDREN.items():
        (pkg / f'{name}.py').write_text(textwrap.dedent(src))
    import os
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path / 'pkgs'), *sys.path]))


def test_wait_ready_waits_for_the_line_not_for_a_sleep(pkg_env):
    import io
    env = dict(pkg_env, READY_DELAY_S='1.0', READY_NAME='late')
    orch = Orchestrator([NodeSpec('late', 'readykids', 'slowready')], out=io.StringIO(),
                        env=env)
    try:
        t0 = time.monotonic()
        orch.start()
        assert orch.wait_ready(0.3) == ['late']          # not yet: it has not said so
        assert orch.wait_ready(20.0) == []
        assert time.monotonic() - t0 >= 1.0
        assert orch.device_problems() == {}
    finally:
        orch.stop()
        orch.close()


def test_a_node_without_its_device_is_ready_with_the_problem_named(pkg_env):
    import io
    out = io.StringIO()
    env = dict(pkg_env, READY_NAME='cam', READY_PROBLEM='cannot open /dev/ttyACM0: no such')
    orch = Orchestrator([NodeSpec('cam', 'readykids', 'slowready')], out=out, env=env)
    try:
        orch.start()
        assert orch.wait_ready(20.0) == []
        assert orch.device_problems() == {'cam': 'cannot open /dev/ttyACM0: no such'}
        assert 'cam is up without its device: cannot open /dev/ttyACM0' in out.getvalue()
    finally:
        orch.stop()
        orch.close()
    report = {'success': False, 'reason': 'start-up failed',
              'device_problems': orch.device_problems()}
    text = '\n'.join(summary_lines(report, 3, None))
    assert 'device problem    cam: cannot open /dev/ttyACM0: no such' in text


def test_a_respawned_node_must_report_ready_again(pkg_env):
    import io
    import signal
    env = dict(pkg_env, READY_NAME='r', READY_DELAY_S='0.0')
    orch = Orchestrator([NodeSpec('r', 'readykids', 'slowready', respawn=True,
                                  respawn_delay_s=0.0)], out=io.StringIO(), env=env)
    try:
        orch.start()
        assert orch.wait_ready(20.0) == []
        first = orch.by_name['r'].proc.pid
        orch.by_name['r'].signal(signal.SIGKILL)
        orch.by_name['r'].proc.wait(5.0)
        assert not orch.is_ready('r')                    # the dead pid's line does not count
        deadline = time.monotonic() + 20.0
        while orch.by_name['r'].proc.pid == first and time.monotonic() < deadline:
            orch.check()
            time.sleep(0.05)
        assert orch.wait_ready(20.0) == [] and orch.ready['r']['pid'] != first
    finally:
        orch.stop()
        orch.close()


def test_pixy_driver_without_its_port_says_so_in_diagnostics(ros_context):
    from diagnostic_msgs.msg import DiagnosticStatus
    from pixy_driver.node import PixyDriverNode
    from rclpy.parameter import Parameter

    context, _ = ros_context
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(('127.0.0.1', 0))
    port = taken.getsockname()[1]
    try:
        node = PixyDriverNode(context=context, parameter_overrides=[
            Parameter('transport', value='udp'), Parameter('udp_port', value=port)])
        try:
            problem = node.device_problem()
            assert problem.startswith(f'cannot open udp://127.0.0.1:{port}:')
            assert 'Address already in use' in problem
            sent = []
            node._diag_pub.publish = sent.append
            node._publish_diagnostics()
            (status,) = sent[0].status
            assert status.level == DiagnosticStatus.ERROR and problem in status.message
        finally:
            node.destroy_node()
    finally:
        taken.close()
