"""mavlink_bridge node against the PX4 emulator over UDP loopback (private rclpy context)."""

import math
import random
import socket
import threading
import time

import pytest
from rostest import wait_for

pytestmark = pytest.mark.ros


def free_udp_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
    s.close()
    return port


class EmulatorThread:
    """Runs the emulator at 200 Hz on wall time (this is the test harness, not a core)."""

    def __init__(self, emu):
        self.emu = emu
        self.lock = threading.Lock()
        self.stop = False
        self.state = {'position_enu': (1.0, 2.0, 3.0), 'velocity_enu': (0.5, -0.2, 0.1),
                      'roll': 0.1, 'pitch': 0.2, 'yaw': 0.3, 'rates_flu': (0.01, 0.02, 0.03),
                      'accel_body_flu': (0.0, 0.0, 9.81), 'range_m': 2.0, 'landed': False}
        self.t0 = time.monotonic()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self):
        while not self.stop:
            t = time.monotonic() - self.t0
            with self.lock:
                self.emu.update(t)
                self.emu.publish_state(t, **self.state)
            time.sleep(0.005)

    def close(self):
        self.stop = True
        self.thread.join(timeout=2.0)
        self.emu.close()


@pytest.fixture
def rig(ros_context):
    from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    context, executor = ros_context
    port = free_udp_port()
    bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
        Parameter('connection', value=f'udpin:127.0.0.1:{port}')])
    emu = Px4Emulator(EmulatorParams(bind_port=0, remote_port=port))
    runner = EmulatorThread(emu)
    helper = Node('mavlink_test_helper', context=context)
    executor.add_node(bridge)
    executor.add_node(helper)
    try:
        yield bridge, runner, helper, port
    finally:
        runner.close()


def collect(helper, cls, topic, qos=None):
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    got = []
    latched = topic in ('vehicle/armed', 'vehicle/mode', 'vehicle/landed')
    helper.create_subscription(cls, topic, got.append,
                               qos or (LATCHED_QOS if latched else RELIABLE_QOS))
    return got


def test_heartbeats_and_telemetry_as_enu(rig):
    from deckland_common.frames import euler_to_quaternion
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, Range
    from std_msgs.msg import Bool, String

    _bridge, runner, helper, _ = rig
    odom = collect(helper, Odometry, 'vehicle/odom')
    vel = collect(helper, TwistStamped, 'vehicle/velocity')
    imu = collect(helper, Imu, 'vehicle/imu')
    rng = collect(helper, Range, 'vehicle/range')
    mode = collect(helper, String, 'vehicle/mode')
    armed = collect(helper, Bool, 'vehicle/armed')
    landed = collect(helper, Bool, 'vehicle/landed')
    assert wait_for(lambda: odom and vel and imu and rng and mode and armed and landed)
    assert wait_for(lambda: runner.emu.counters['heartbeats_rx'] >= 1, 3.0)
    # the bridge asked for its telemetry rates with SET_MESSAGE_INTERVAL
    assert runner.emu.intervals_s[30] == pytest.approx(0.01)
    assert (511, 0) in runner.emu.acks
    o = odom[-1]
    assert o.header.frame_id == 'map' and o.child_frame_id == 'base_link'
    p = o.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((1.0, 2.0, 3.0), abs=1e-5)
    q = o.pose.pose.orientation
    assert (q.w, q.x, q.y, q.z) == pytest.approx(euler_to_quaternion(0.1, 0.2, 0.3), abs=1e-5)
    v = vel[-1].twist.linear
    assert (v.x, v.y, v.z) == pytest.approx((0.5, -0.2, 0.1), abs=1e-5)
    assert imu[-1].linear_acceleration.z == pytest.approx(9.81, abs=1e-4)
    assert imu[-1].angular_velocity.y == pytest.approx(0.02, abs=1e-6)
    assert rng[-1].range == pytest.approx(2.0) and rng[-1].header.frame_id == 'lidar_link'
    assert mode[-1].data == 'POSCTL' and armed[-1].data is False and landed[-1].data is False
    with runner.lock:
        runner.state['range_m'] = None
    assert wait_for(lambda: math.isinf(rng[-1].range), 2.0)


def call(helper, srv_type, name, request):
    client = helper.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=3.0)
    fut = client.call_async(request)
    assert wait_for(fut.done, 3.0)
    return fut.result()


def test_commands_offboard_stale_cutoff_and_failsafe(rig):
    from deckland_common.frames import euler_to_quaternion
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    from std_msgs.msg import String
    from std_srvs.srv import SetBool, Trigger

    bridge, runner, helper, _ = rig
    mode = collect(helper, String, 'vehicle/mode')
    pub_att = helper.create_publisher(QuaternionStamped, 'control/attitude', 10)
    pub_thr = helper.create_publisher(WrenchStamped, 'control/thrust', 10)
    assert wait_for(lambda: bridge.core.link_up(time.monotonic()), 3.0)
    with runner.lock:
        runner.state['landed'] = True
    sending = {'thrust': True, 'go': True}

    def publish_loop():
        w, x, y, z = euler_to_quaternion(0.1, 0.05, 1.0)
        while sending['go']:
            now = helper.get_clock().now().to_msg()
            a = QuaternionStamped()
            a.header.stamp = now
            a.quaternion.w, a.quaternion.x, a.quaternion.y, a.quaternion.z = w, x, y, z
            pub_att.publish(a)
            if sending['thrust']:
                f = WrenchStamped()
                f.header.stamp = now
                f.wrench.force.z = 22.0
                pub_thr.publish(f)
            time.sleep(0.02)

    pub = threading.Thread(target=publish_loop, daemon=True)
    pub.start()
    try:
        assert wait_for(lambda: runner.emu.setpoint is not None, 3.0)
        sp = runner.emu.setpoint
        assert (sp.roll_rad, sp.pitch_rad, sp.yaw_rad) == pytest.approx((0.1, 0.05, 1.0),
                                                                        abs=1e-5)
        assert sp.thrust_n == pytest.approx(22.0, abs=1e-3)
        assert call(helper, SetBool, 'bridge/arm', SetBool.Request(data=True)).success
        assert call(helper, Trigger, 'bridge/offboard', Trigger.Request()).success
        assert wait_for(lambda: runner.emu.mode == 'OFFBOARD' and runner.emu.armed, 4.0)
        assert wait_for(lambda: mode and mode[-1].data == 'OFFBOARD', 2.0)
        with runner.lock:
            runner.state['landed'] = False
        # stale thrust: the stream stops within input_timeout_s, attitude alone sends nothing
        sending['thrust'] = False
        time.sleep(0.1)
        n0 = runner.emu.counters['setpoints_rx']
        time.sleep(0.5)
        assert runner.emu.counters['setpoints_rx'] == n0
        # PX4's own offboard-loss failsafe takes over after COM_OF_LOSS_T
        assert wait_for(lambda: runner.emu.failsafe_active, 2.0)
        assert runner.emu.mode == 'AUTO.LAND'
        assert runner.emu.kind == 'failsafe_land'
        assert wait_for(lambda: mode[-1].data == 'AUTO.LAND', 2.0)
    finally:
        sending['go'] = False
        pub.join(timeout=1.0)


def test_garbage_bytes_do_not_crash_the_bridge(rig):
    from nav_msgs.msg import Odometry

    bridge, _runner, helper, port = rig
    odom = collect(helper, Odometry, 'vehicle/odom')
    assert wait_for(lambda: odom, 3.0)
    rng = random.Random(11)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(200):
            s.sendto(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 400))),
                     ('127.0.0.1', port))
        s.sendto(b'\xfd\x20\x00\x00\x00', ('127.0.0.1', port))   # truncated header
    finally:
        s.close()
    time.sleep(0.3)
    n = len(odom)
    assert wait_for(lambda: len(odom) > n + 5, 2.0)
    assert bridge._reader.is_alive()
    assert bridge.core.rejected['bad_data'] > 0


@pytest.mark.parametrize('burst, expect_sent', [(3, 2), (1, 1)])
def test_two_commands_1ms_apart_both_reach_the_autopilot(ros_context, burst, expect_sent):
    """An IMU-triggered and a camera-triggered command of the same instant: with the default
    bucket both SET_ATTITUDE_TARGETs are on the wire at once; a plain 4 ms minimum interval
    (stream_burst 1) drops the second, as the old 9 ms limiter did."""
    from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    context, executor = ros_context
    port = free_udp_port()
    bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
        Parameter('connection', value=f'udpin:127.0.0.1:{port}'),
        Parameter('stream_burst', value=burst)])
    runner = EmulatorThread(Px4Emulator(EmulatorParams(bind_port=0, remote_port=port)))
    helper = Node('mavlink_burst_helper', context=context)
    executor.add_node(bridge)
    executor.add_node(helper)
    try:
        pub_att = helper.create_publisher(QuaternionStamped, 'control/attitude', 10)
        pub_thr = helper.create_publisher(WrenchStamped, 'control/thrust', 10)
        assert wait_for(lambda: bridge.core.link_up(time.monotonic()), 3.0)
        assert wait_for(lambda: pub_thr.get_subscription_count() >= 1, 3.0)
        now_ns = helper.get_clock().now().nanoseconds
        a = QuaternionStamped()
        a.header.stamp.sec, a.header.stamp.nanosec = divmod(now_ns, 10**9)
        a.quaternion.w = 1.0
        pub_att.publish(a)
        assert wait_for(lambda: bridge.core._att_stamp > 0.0, 2.0)
        n0 = runner.emu.counters['setpoints_rx']
        for i, force in enumerate((21.0, 23.0)):
            f = WrenchStamped()
            f.header.stamp.sec, f.header.stamp.nanosec = divmod(now_ns + i * 1_000_000, 10**9)
            f.wrench.force.z = force
            pub_thr.publish(f)
        assert wait_for(lambda: bridge.core.counters['setpoints_sent']
                        + bridge.core.counters['rate_limited'] >= 2, 2.0)
        assert wait_for(lambda: runner.emu.counters['setpoints_rx'] - n0 >= expect_sent, 2.0)
        time.sleep(0.1)
        assert runner.emu.counters['setpoints_rx'] - n0 == expect_sent
        assert bridge.core.counters['rate_limited'] == 2 - expect_sent
        # the autopilot flies the newest command when both went out
        expected = 23.0 if expect_sent == 2 else 21.0
        assert runner.emu.setpoint.thrust_n == pytest.approx(expected, abs=1e-3)
    finally:
        runner.close()


@pytest.mark.parametrize('name, value, needle', [
    ('stream_burst', 0, 'stream_burst'), ('max_stream_rate_hz', -1.0, 'max_stream_rate_hz'),
    ('fresh_period_s', 0.9, 'fresh_period_s')])
def test_bad_stream_parameters_are_rejected(ros_context, name, value, needle):
    from deckland_common.params import ParameterError
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.parameter import Parameter

    context, _ = ros_context
    with pytest.raises(ParameterError, match=needle):
        MavlinkBridgeNode(context=context, parameter_overrides=[
            Parameter('connection', value=f'udpin:127.0.0.1:{free_udp_port()}'),
            Parameter(name, value=value)])
