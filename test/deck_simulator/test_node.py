"""deck_simulator node in-process (private rclpy context) and as a process (SIGINT)."""

import itertools
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time

import pytest
from rostest import wait_for

pytestmark = pytest.mark.ros


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def make_node(context, **params):
    from deck_simulator.node import DeckSimulatorNode
    from rclpy.parameter import Parameter
    return DeckSimulatorNode(context=context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])


@pytest.fixture
def sim(ros_context, tmp_path):
    """The node on free ports: a pymavlink 'udpin' endpoint (as the bridge's default) and a
    bound UDP socket standing in for pixy_driver."""
    from pymavlink import mavutil
    from rclpy.node import Node

    context, executor = ros_context
    mav_port, pixy = free_udp_port(), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    pixy.bind(('127.0.0.1', 0))
    pixy.settimeout(0.5)
    scenario = tmp_path / 'short.yaml'
    scenario.write_text(
        'name: short\ntimeout_s: 6.0\nstart_position_m: [1.0, 2.0, 2.0]\n'
        'wind: {mean_mps: [0.3, 0.0], gust_std_mps: 0.2}\n'
        'randomize: {start_offset_m: 0.3, start_yaw_rad: 0.3}\n', encoding='utf-8')
    node = make_node(context, scenario=str(scenario), seed=5,
                     mavlink_url=f'udpout:127.0.0.1:{mav_port}',
                     pixy_udp_port=pixy.getsockname()[1])
    conn = mavutil.mavlink_connection(f'udpin:127.0.0.1:{mav_port}', dialect='common',
                                      source_system=1, source_component=191)
    helper = Node('simnode_test_helper', context=context)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        yield node, helper, conn, pixy
    finally:
        conn.close()
        pixy.close()


def collect(helper, cls, topic, qos):
    got = []
    helper.create_subscription(cls, topic, got.append, qos)
    return got


def test_truth_pixy_mavlink_hold_and_timeout_outcome(sim):
    from deckland_common.frames import quaternion_to_euler
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    from nav_msgs.msg import Odometry
    from pixy_driver.protocol import PixyParser
    from std_msgs.msg import String

    node, helper, conn, pixy = sim
    vehicle = collect(helper, Odometry, 'sim/truth/vehicle', RELIABLE_QOS)
    apron = collect(helper, Odometry, 'sim/truth/apron', RELIABLE_QOS)
    mode_pub = helper.create_publisher(String, 'planner/mode', LATCHED_QOS)
    assert wait_for(lambda: len(vehicle) > 5 and len(apron) > 5, 10.0)

    # MAVLink telemetry at the 'udpin' endpoint, PX4 style (NED)
    hb = conn.recv_match(type='HEARTBEAT', blocking=True, timeout=3.0)
    assert hb is not None and hb.autopilot == 12 and (hb.custom_mode >> 16) & 0xFF == 3
    att = conn.recv_match(type='ATTITUDE', blocking=True, timeout=2.0)
    assert att is not None and abs(att.roll) < 0.2 and abs(att.pitch) < 0.2
    lp = conn.recv_match(type='LOCAL_POSITION_NED', blocking=True, timeout=2.0)
    assert lp is not None and lp.z == pytest.approx(-2.0, abs=1.0)

    # Pixy datagrams: one frame each, parsed by pixy_driver's parser
    parser = PixyParser()
    frames = []
    end = time.monotonic() + 2.0
    while len(frames) < 20 and time.monotonic() < end:
        try:
            data, _ = pixy.recvfrom(65536)
        except TimeoutError:
            continue
        frames += parser.feed_datagram(data)
    assert len(frames) >= 20 and parser.checksum_errors == 0

    # no offboard setpoints: the vehicle holds its start (truth) for a few seconds
    first = vehicle[0].pose.pose.position
    p0 = (first.x, first.y, first.z)
    assert math.dist(p0[:2], (1.0, 2.0)) <= 0.31 and p0[2] == pytest.approx(2.0, abs=0.05)
    seen = len(vehicle)
    mode_pub.publish(String(data='APPROACH'))                       # the landing trigger
    time.sleep(3.0)
    worst = max(math.dist(p0, (m.pose.pose.position.x, m.pose.pose.position.y,
                               m.pose.pose.position.z)) for m in vehicle[seen:])
    assert worst < 0.3
    rate = (len(vehicle) - seen) / 3.0
    assert 40.0 <= rate <= 55.0                                      # truth_rate_hz 50
    last = vehicle[-1]
    assert last.header.frame_id == 'map' and last.child_frame_id == 'base_link'
    q = last.pose.pose.orientation
    roll, pitch, _ = quaternion_to_euler(q.w, q.x, q.y, q.z)
    assert abs(roll) < 0.1 and abs(pitch) < 0.1
    stamp = last.header.stamp.sec + last.header.stamp.nanosec * 1e-9
    assert abs(stamp - time.time()) < 0.5                            # wall-clock stamps
    a = apron[-1]
    assert (a.pose.pose.position.x, a.pose.pose.position.y) == pytest.approx((-3.2, -2.0))
    assert 0.4 < a.pose.pose.position.z < 0.8                         # deck top (Table 3)

    # timeout (6 s after the trigger): latched outcome, seen by a late subscriber too
    assert wait_for(lambda: node.sim.outcome is not None, 8.0)
    late = collect(helper, String, 'sim/outcome', LATCHED_QOS)
    assert wait_for(lambda: late, 3.0)
    out = json.loads(late[0].data)
    assert out['reason'] == 'timeout' and out['success'] is False and out['seed'] == 5
    assert out['scenario'] == 'short' and out['final_mode'] == 'APPROACH'
    assert out['sim_time_s'] >= 6.0
    assert node.thread_errors == 0


def test_telemetry_leaves_at_its_deadline_like_a_pixhawk(sim):
    """HIGHRES_IMU at 100 Hz: each sample of sim time t leaves at wall time t + a constant
    (absolute deadlines), so the stream is as steady as the OS lets a thread wake. The old
    loop (sleep 10 ms after the work, then step the elapsed time) sent a sample 0-10 ms after
    its time and bunched the stream (p90 of the phase error ~9 ms)."""
    node, _helper, conn, _pixy = sim
    assert conn.recv_match(type='HEARTBEAT', blocking=True, timeout=3.0) is not None
    conn.mav.command_long_send(1, 1, 511, 0, 105, 10_000, 0, 0, 0, 0, 0)   # HIGHRES_IMU 100 Hz
    assert wait_for(lambda: (511, 0) in node.emulator.acks, 3.0)
    samples = []
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        m = conn.recv_match(type='HIGHRES_IMU', blocking=True, timeout=0.2)
        if m is not None:
            samples.append((time.monotonic(), m.time_usec * 1e-6))
    samples = samples[20:]                      # after the rate change settled
    sim_dt = [b[1] - a[1] for a, b in itertools.pairwise(samples)]
    assert sim_dt and all(d == pytest.approx(0.01, abs=2e-3) for d in sim_dt)
    span = samples[-1][0] - samples[0][0]
    assert len(samples) - 1 == pytest.approx(span / 0.01, rel=0.03)         # 100 Hz, no drift
    phase = sorted(rx - t for rx, t in samples)                 # wall − sim, constant ideally
    median = phase[len(phase) // 2]
    dev = sorted(abs(p - median) for p in phase)
    # the old loop's p90 was ~9 ms; absolute deadlines keep it near the OS wake-up jitter,
    # ~1-2 ms on a quiet core (a fresh-clone CI run under the suite's load saw 2.06 ms)
    assert dev[int(0.9 * len(dev))] < 0.004, dev[int(0.9 * len(dev)):]
    assert node.schedule.ticks > 250 and node.thread_errors == 0


def test_garbage_on_the_mavlink_port_is_counted_not_fatal(sim):
    node, _helper, conn, _pixy = sim
    assert conn.recv_match(type='HEARTBEAT', blocking=True, timeout=3.0) is not None
    # conn learned the emulator's address; send junk and a NaN setpoint back to it
    for i in range(20):
        conn.write(bytes([0xFD, 9, 0, 0, i, 1, 1]) + os.urandom(10))
        conn.mav.set_attitude_target_send(0, 1, 1, 0, [math.nan, 0, 0, 0], 0, 0, 0, 0.5)
    assert wait_for(lambda: node.emulator.rejected['nan'] >= 20, 3.0)
    assert node.emulator.rejected['bad_data'] >= 1
    assert node._thread.is_alive() and node.thread_errors == 0
    assert node.sim.last_kind == 'hold'


@pytest.mark.parametrize('params, needle', [
    ({'scenario': 'no_such_scenario'}, "parameter 'scenario'"),
    ({'realtime_factor': -1.0}, "'realtime_factor'"),
    ({'physics_rate_hz': 100.0}, "'physics_rate_hz'"),
    ({'mavlink_url': 'tcp:127.0.0.1:5760'}, "'mavlink_url'"),
    ({'pixy_udp_port': 0}, "'pixy_udp_port'"),
    ({'seed': 'one'}, "'seed'"),
])
def test_bad_parameters_are_rejected_with_a_clear_message(ros_context, params, needle):
    from deckland_common.params import ParameterError
    context, _ = ros_context
    with pytest.raises(ParameterError, match=needle):
        make_node(context, **params)


def test_busy_mavlink_port_is_a_clear_error(ros_context):
    from deckland_common.params import ParameterError
    context, _ = ros_context
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(('127.0.0.1', 0))
        port = busy.getsockname()[1]
        with pytest.raises(ParameterError, match='cannot open the socket'):
            make_node(context, mavlink_url=f'udpin:127.0.0.1:{port}')


def test_process_exits_within_1s_of_sigint_and_rejects_bad_param():
    env = dict(os.environ)
    mav, pixy = free_udp_port(), free_udp_port()
    cmd = [sys.executable, '-m', 'deck_simulator.node', '--ros-args',
           '-p', 'scenario:=paper_calm', '-p', f'mavlink_url:=udpout:127.0.0.1:{mav}',
           '-p', f'pixy_udp_port:={pixy}']
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listen:
        listen.bind(('127.0.0.1', mav))
        listen.settimeout(15.0)
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            listen.recvfrom(65536)                                   # it is running
            time.sleep(0.3)
            t0 = time.monotonic()
            proc.send_signal(signal.SIGINT)
            rc = proc.wait(timeout=5.0)
            took = time.monotonic() - t0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            proc.stdout.close()
            proc.stderr.close()
    assert rc == 0 and took < 1.0
    bad = subprocess.run([*cmd[:4], '-p', 'realtime_factor:=0.0'], env=env,
                         capture_output=True, text=True, timeout=30)
    assert bad.returncode == 2 and "parameter 'realtime_factor'" in bad.stderr


@pytest.mark.parametrize('bridge_scheme, sim_scheme', [('udpin', 'udpout'), ('udpout', 'udpin')])
def test_real_bridge_and_pixy_driver_talk_to_the_simulator(ros_context, bridge_scheme,
                                                           sim_scheme):
    """Both pairings on one port: the bridge's default 'udpin' with ours 'udpout' (PX4 SITL
    style), and `deckland up`'s bridge 'udpout' with ours 'udpin'."""
    from deckland_common.ros_node import RELIABLE_QOS
    from mavlink_bridge.node import MavlinkBridgeNode
    from nav_msgs.msg import Odometry
    from pixy_driver.node import PixyDriverNode
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud, Range

    context, executor = ros_context
    port, pixy_port = free_udp_port(), free_udp_port()
    # the listening side first, as in a launch where the order is arbitrary but ports fixed
    node = make_node(context, scenario='paper_calm', mavlink_url=f'{sim_scheme}:127.0.0.1:{port}',
                     pixy_udp_port=pixy_port)
    bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
        Parameter('connection', value=f'{bridge_scheme}:127.0.0.1:{port}')])
    pixy = PixyDriverNode(context=context, parameter_overrides=[
        Parameter('transport', value='udp'), Parameter('udp_port', value=pixy_port)])
    helper = Node('simnode_pair_helper', context=context)
    for n in (node, bridge, pixy, helper):
        executor.add_node(n)
    odom = collect(helper, Odometry, 'vehicle/odom', RELIABLE_QOS)
    rng = collect(helper, Range, 'vehicle/range', RELIABLE_QOS)
    blocks = collect(helper, PointCloud, 'pixy/blocks', RELIABLE_QOS)
    assert wait_for(lambda: len(odom) > 10 and len(rng) > 5 and len(blocks) > 10, 10.0)
    assert wait_for(lambda: node.emulator.counters['heartbeats_rx'] >= 1, 3.0)
    assert wait_for(lambda: (511, 0) in node.emulator.acks, 3.0)      # rates requested
    pos, _ = node.sim.world.read_local_position()                    # the EKF's, delivered
    p = odom[-1].pose.pose.position
    assert math.dist((p.x, p.y, p.z), pos) < 0.3
