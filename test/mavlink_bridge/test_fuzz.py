"""Fuzz the mavlink_bridge node: bad MAVLink over UDP loopback and bad ROS commands.

A fake autopilot (a UDP socket and pymavlink's encoder, system 1 component 1) talks to the
bridge listening on a free loopback port; the bridge node runs in a private context
(``ros_context``) on an executor spun in the test thread (see test_fuzz_nodes.Rig), with a
helper node recording every ``vehicle/*`` topic and publishing the ``control/*`` commands.
What the bridge sends back to the autopilot (SET_ATTITUDE_TARGET, LANDING_TARGET) is parsed
and checked for finite numbers too.
"""

from __future__ import annotations

import itertools
import math
import os
import socket
import time

os.environ.setdefault('MAVLINK20', '1')

import pytest
from test_fuzz_nodes import INF, NAN, Rig, build_bad, now_of, run_fuzz, stamp, total

pytestmark = pytest.mark.ros

_NS = itertools.count()
PX4_POSCTL = 3 << 16        # PX4 custom mode: main mode 3 (POSCTL)
ARMED = 128 | 1             # MAV_MODE_FLAG_SAFETY_ARMED | CUSTOM_MODE_ENABLED
ROLL, PITCH, YAW = 0.1, 0.2, 0.3    # the valid telemetry (NED/FRD)


class FakeAutopilot:
    """System ``sysid`` on a UDP socket: encodes telemetry, decodes what the bridge sends."""

    def __init__(self, bridge_port: int, sysid: int = 1):
        from pymavlink.dialects.v20 import common as mavlink2

        self.m = mavlink2
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.sock.setblocking(False)
        self.addr = ('127.0.0.1', bridge_port)
        self.enc = {s: mavlink2.MAVLink(None, srcSystem=s, srcComponent=1) for s in (1, 42)}
        self.sysid = sysid
        self.rx = mavlink2.MAVLink(None)
        self.rx.robust_parsing = True
        self.received: list = []
        self.boot_ms = 0

    def send_raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.addr)

    def send(self, msg, sysid: int = 1) -> None:
        self.send_raw(msg.pack(self.enc[sysid]))

    def heartbeat(self, sysid: int = 1):
        return self.m.MAVLink_heartbeat_message(2, 12, ARMED, PX4_POSCTL, 4, 3)

    def attitude(self, roll=ROLL, pitch=PITCH, yaw=YAW, rates=(0.0, 0.0, 0.0)):
        self.boot_ms += 10
        return self.m.MAVLink_attitude_message(self.boot_ms, roll, pitch, yaw, *rates)

    def local_position(self, x=1.0, y=2.0, z=-3.0, vx=0.5, vy=-0.2, vz=0.1):
        self.boot_ms += 10
        return self.m.MAVLink_local_position_ned_message(self.boot_ms, x, y, z, vx, vy, vz)

    def distance(self, current_cm=200, min_cm=5, max_cm=4000, orientation=25):
        self.boot_ms += 10
        return self.m.MAVLink_distance_sensor_message(self.boot_ms, min_cm, max_cm, current_cm,
                                                      0, 1, orientation, 255)

    def highres_imu(self, acc=(0.0, 0.0, -9.81), gyro=(0.0, 0.0, 0.0)):
        self.boot_ms += 10
        return self.m.MAVLink_highres_imu_message(self.boot_ms * 1000, *acc, *gyro,
                                                  0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)

    def poll(self):
        while True:
            try:
                data, _ = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            for msg in self.rx.parse_buffer(data) or []:
                self.received.append(msg)

    def of_type(self, name):
        self.poll()
        return [m for m in self.received if m.get_type() == name]

    def close(self):
        self.sock.close()


def free_udp_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture
def bridge(ros_context):
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    from geometry_msgs.msg import QuaternionStamped, TwistStamped, WrenchStamped
    from mavlink_bridge.node import MavlinkBridgeNode
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Imu, Range
    from std_msgs.msg import Bool, String

    context, _ = ros_context
    ns = f'/fuzz_bridge_{next(_NS)}'
    port = free_udp_port()
    node = MavlinkBridgeNode(context=context, namespace=ns, parameter_overrides=[
        Parameter('connection', value=f'udpin:127.0.0.1:{port}'),
        Parameter('landing_target_output', value=True)])
    q = RELIABLE_QOS
    rig = Rig(context, node, ns,
              inputs={'control/attitude': (QuaternionStamped, q),
                      'control/thrust': (WrenchStamped, q), 'apron/odom': (Odometry, q),
                      'control/enabled': (Bool, LATCHED_QOS)},
              outputs={'vehicle/odom': (Odometry, q), 'vehicle/velocity': (TwistStamped, q),
                       'vehicle/imu': (Imu, q), 'vehicle/range': (Range, q),
                       'vehicle/armed': (Bool, LATCHED_QOS),
                       'vehicle/mode': (String, LATCHED_QOS),
                       'vehicle/landed': (Bool, LATCHED_QOS)},
              # REP-117: +inf = no return, -inf = too close; nothing else may be infinite
              inf_ok=lambda topic, path, v: topic == 'vehicle/range' and path == 'range')
    ap = FakeAutopilot(port)
    try:
        yield node, rig, ap
    finally:
        ap.close()
        rig.close()


def wait_rx(rig, node, before: int, timeout_s: float = 2.0) -> bool:
    """Spin until the bridge's reader has parsed more messages than ``before``."""
    return rig.spin_until(lambda: rx_count(node) > before, timeout_s)


def rx_count(node) -> int:
    st_ = node.conn.mav.total_packets_received if hasattr(node.conn, 'mav') else 0
    return st_ + node.core.rejected['bad_data']


def bridge_rejected(node) -> int:
    return total(node.core.rejected, node.errors)


def send_and_wait(rig, node, ap, msg, sysid=1):
    n0 = rx_count(node)
    ap.send(msg, sysid)
    assert wait_rx(rig, node, n0), f'bridge never read {msg.get_type()}'
    rig.spin(0.005)


def test_mavlink_garbage_nan_telemetry_and_other_systems(bridge):
    """Garbage/truncated frames, NaN/inf telemetry with valid CRCs, 0/65535 cm ranges, other
    systems and a flood: no crash, no NaN published, counted, valid telemetry afterwards."""
    node, rig, ap = bridge
    rig.wait_matched()
    send_and_wait(rig, node, ap, ap.heartbeat())
    assert rig.spin_until(lambda: node.core.target_system == 1, 2.0)
    send_and_wait(rig, node, ap, ap.attitude())
    send_and_wait(rig, node, ap, ap.local_position())
    assert rig.spin_until(lambda: rig.out['vehicle/odom'], 2.0)

    # 1. garbage, truncated and corrupted frames are counted as bad data
    good = ap.local_position().pack(ap.enc[1])
    garbage = [bytes(range(256)), b'\xfd' * 40, good[:len(good) // 2], good[:-1],
               good[:10] + bytes([good[10] ^ 0xFF]) + good[11:], b'\xfe\x09' + bytes(20)]
    for data in garbage:
        # a cut frame is only known to be bad once the next datagram's bytes arrive (pymavlink
        # keeps a partial frame across UDP datagrams): follow each with a valid one
        # (known weakness, reported: up to ~265 bytes of valid datagrams are lost behind it)
        before = node.core.rejected['bad_data']
        ap.send_raw(data)
        for _ in range(15):
            ap.send(ap.heartbeat())
            if rig.spin_until(lambda b=before: node.core.rejected['bad_data'] > b, 0.05):
                break
        assert node.core.rejected['bad_data'] > before, data
    rig.check_clean()

    # 2. valid CRC, non-finite fields: dropped, counted, nothing published from them
    for msg in (ap.attitude(roll=NAN), ap.attitude(yaw=INF), ap.attitude(rates=(0.0, NAN, 0.0)),
                ap.local_position(x=INF), ap.local_position(vz=NAN),
                ap.highres_imu(acc=(NAN, 0.0, -9.81)), ap.highres_imu(gyro=(0.0, -INF, 0.0))):
        before = bridge_rejected(node)
        n_odom = len(rig.out['vehicle/odom'])
        send_and_wait(rig, node, ap, msg)
        assert bridge_rejected(node) > before, f'{msg} not counted'
        assert len(rig.out['vehicle/odom']) == n_odom or msg.get_type() != 'LOCAL_POSITION_NED'
        rig.check_clean()

    # 3. DISTANCE_SENSOR 65535 cm (UINT16_MAX: unknown) is "no return", +inf; 0 cm (PX4 SIH
    # on the ground) is "too close", -inf (REP-117)
    for cm, max_cm, want in ((0, 4000, -INF), (65535, 4000, INF), (65535, 0, INF),
                             (65535, 65535, INF)):
        n = len(rig.out['vehicle/range'])
        send_and_wait(rig, node, ap, ap.distance(current_cm=cm, max_cm=max_cm))
        assert rig.spin_until(lambda n=n: len(rig.out['vehicle/range']) > n, 2.0)
        assert rig.out['vehicle/range'][-1].range == want, (cm, max_cm)

    # 4. another system's heartbeat and telemetry never become ours (counted)
    att_before = node._att
    before = node.core.rejected['other_system']
    send_and_wait(rig, node, ap, ap.heartbeat(), sysid=42)
    send_and_wait(rig, node, ap, ap.attitude(roll=1.0, pitch=-1.0, yaw=2.0), sysid=42)
    send_and_wait(rig, node, ap, ap.local_position(x=100.0), sysid=42)
    assert node.core.rejected['other_system'] >= before + 3
    assert node.core.target_system == 1 and node._att == att_before
    assert all(abs(o.pose.pose.position.y - 100.0) > 1.0 for o in rig.out['vehicle/odom'])

    # 5. a flood of mixed garbage and valid frames
    t0 = time.monotonic()
    for i in range(3000):
        ap.send_raw(garbage[i % len(garbage)] if i % 3 else ap.attitude().pack(ap.enc[1]))
    rig.spin_until(lambda: time.monotonic() - t0 > 1.0 and rx_count(node) > 2500, 5.0)
    rig.check_clean()
    assert node.errors['recv_exceptions'] == 0

    # 6. valid telemetry still flows, exactly converted (NED/FRD → ENU/FLU); a partial frame
    # left by the garbage first swallows up to ~265 bytes (known weakness, reported)
    from deckland_common.frames import euler_to_quaternion
    hb = node.core.counters['heartbeats_rx']
    for _ in range(40):
        ap.send(ap.heartbeat())
        if rig.spin_until(lambda: node.core.counters['heartbeats_rx'] > hb, 0.05):
            break
    assert node.core.counters['heartbeats_rx'] > hb, 'MAVLink input dead after the flood'
    rig.clear()
    for _ in range(3):
        send_and_wait(rig, node, ap, ap.heartbeat())
        send_and_wait(rig, node, ap, ap.attitude())
        send_and_wait(rig, node, ap, ap.local_position())
        send_and_wait(rig, node, ap, ap.distance())
    assert rig.spin_until(lambda: rig.out['vehicle/odom'] and rig.out['vehicle/range'], 2.0)
    o = rig.out['vehicle/odom'][-1]
    p = o.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((2.0, 1.0, 3.0), abs=1e-6)   # NED (1, 2, −3)
    qq = o.pose.pose.orientation
    expected = euler_to_quaternion(ROLL, -PITCH, math.pi / 2.0 - YAW)
    assert (qq.w, qq.x, qq.y, qq.z) == pytest.approx(expected, abs=1e-6)
    assert rig.out['vehicle/range'][-1].range == pytest.approx(2.0)
    rig.check_clean()
    assert node.errors['recv_exceptions'] == 0


def test_ros_commands_fuzzed_never_reach_the_autopilot_as_nan(bridge):
    """control/attitude, control/thrust, apron/odom with NaN/inf/huge values and bad stamps:
    counted, never a non-finite SET_ATTITUDE_TARGET or LANDING_TARGET, and valid commands
    stream again afterwards."""
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Bool

    node, rig, ap = bridge
    rig.wait_matched()
    rig.send('control/enabled', Bool(data=True))
    send_and_wait(rig, node, ap, ap.heartbeat())

    def attitude(t):
        m = QuaternionStamped()
        stamp(m.header, t)
        m.header.frame_id = 'map'
        m.quaternion.w = 1.0
        return m

    def thrust(t):
        m = WrenchStamped()
        stamp(m.header, t)
        m.header.frame_id = 'base_link'
        m.wrench.force.z = 26.6
        return m

    def apron(t):
        m = Odometry()
        stamp(m.header, t)
        m.header.frame_id, m.child_frame_id = 'map', 'apron'
        m.pose.pose.position.x = 1.0
        m.pose.pose.orientation.w = 1.0
        return m

    def zero_quaternion(m):
        q = m.quaternion
        q.w = q.x = q.y = q.z = 0.0

    hdr = lambda m: m.header  # noqa: E731
    plans = {
        'control/attitude': {
            'make': attitude, 'stamp_header': hdr, 'stamp': ('backwards', 'zero', 'old'),
            'fields': [('quaternion.w', 'f64', lambda v: not math.isfinite(v)),
                       ('quaternion.x', 'f64', lambda v: not math.isfinite(v))],
            'struct': {'zero_quaternion': (zero_quaternion, True)}},
        'control/thrust': {
            'make': thrust, 'stamp_header': hdr, 'stamp': ('backwards', 'zero', 'old'),
            'fields': [('wrench.force.z', 'f64', lambda v: not math.isfinite(v)),
                       ('wrench.force.x', 'f64', lambda v: False),
                       ('wrench.torque.z', 'f64', lambda v: False)]},
        'apron/odom': {
            'make': apron, 'stamp_header': hdr, 'stamp': (),
            'fields': [('pose.pose.position.x', 'f64', lambda v: False),
                       ('pose.pose.position.z', 'f64', lambda v: False),
                       ('twist.twist.linear.x', 'f64', lambda v: False)]},
    }

    def valid_frame():
        ap.send(ap.heartbeat())
        t = now_of(rig)
        rig.send('control/attitude', attitude(t))
        rig.send('control/thrust', thrust(t))
        return t

    def check_sent():
        for m in ap.of_type('SET_ATTITUDE_TARGET'):
            vals = (*m.q, m.thrust, m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate)
            assert all(math.isfinite(v) for v in vals), m
            assert 0.0 <= m.thrust <= 1.0
        for m in ap.of_type('LANDING_TARGET'):
            assert all(math.isfinite(v) for v in (m.x, m.y, m.z, m.angle_x, m.angle_y)), m

    stats = run_fuzz(rig, plans, valid_frame, lambda: total(node.core.rejected),
                     n_examples=25)
    assert stats['must_reject'] >= 15, stats
    assert node.core.rejected['nan'] > 0 and node.core.rejected['out_of_order'] > 0
    rig.spin(0.05)
    check_sent()
    assert ap.of_type('SET_ATTITUDE_TARGET'), 'valid commands were never streamed'

    # a command stamped far in the future must not lock out every later (valid) command
    for kind in ('future', 'max'):
        for topic in ('control/attitude', 'control/thrust'):
            msg, _ = build_bad(plans[topic], [('stamp', kind, None)], now_of(rig), 0.0)
            rig.send(topic, msg)
        ap.received.clear()
        for _ in range(20):
            valid_frame()
            rig.spin(0.012)
        sent = ap.of_type('SET_ATTITUDE_TARGET')
        assert len(sent) >= 5, f'{kind}-stamped command locked the stream: {len(sent)} sent'
        check_sent()
    m = sent[-1]
    assert m.thrust == pytest.approx(node.core.params.thrust.to_norm(26.6), abs=1e-6)
    # level, nose east (ENU yaw 0) = NED yaw +90°: q = ±(√½, 0, 0, √½)
    h = math.sqrt(0.5)
    assert tuple(m.q) == pytest.approx((h, 0.0, 0.0, h), abs=1e-6) \
        or tuple(m.q) == pytest.approx((-h, 0.0, 0.0, -h), abs=1e-6)
    rig.check_clean()

