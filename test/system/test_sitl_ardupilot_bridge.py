"""The mavlink_bridge node against the real ArduCopter 4.5.6 SITL (its built-in quad): the
findings of issue 17 end to end through the fixed bridge.

ArduCopter runs with the mission's parameters (deckland.sitl.ardupilot.MISSION_PARAMS), its
state estimate from the simulator (``AHRS_EKF_TYPE = 10``: EKF3's ~40 s GPS alignment is not
what is tested) and the SITL rangefinder. An operator on SERIAL1 (TCP 5762) takes off with
ArduCopter's own GUIDED take-off; a helper node publishes ``control/attitude`` and
``control/thrust`` as the stack does. The bridge must stream SCALED_IMU after ArduCopter
refuses HIGHRES_IMU, refuse GUIDED_NOGPS while GUID_OPTIONS is wrong, measure the hover in
ArduCopter's own hover (0.345; MOT_THST_HOVER says 0.39), hold the hover on open-loop m g,
get a landing disarmed (LAND, disarm retried), and survive ArduCopter going away."""

import math
import os
import socket
import threading
import time

from deckland.sitl.ardupilot import ArduPilotNotFoundError, ArduPilotSitl, find_ardupilot
from pymavlink.dialects.v20 import common as mavlink
import pytest
from test_sitl_px4_bridge import call, fit_accel, wait_for

try:
    AP_BIN = find_ardupilot()
    NO_AP = ('ArduCopter SITL not found (set DECKLAND_ARDUPILOT_SITL or provide '
             '../shared/ardupilot-sitl)')
except ArduPilotNotFoundError as exc:
    AP_BIN, NO_AP = None, str(exc)

pytestmark = [pytest.mark.sitl, pytest.mark.sitl_mission, pytest.mark.ros,
              pytest.mark.skipif(AP_BIN is None, reason=NO_AP)]
SITL_PARAMS = {'AHRS_EKF_TYPE': 10, 'RNGFND1_TYPE': 100, 'RNGFND1_ORIENT': 25}
#: the link monitor's limit here: SITL runs niced on a shared 2-core machine and answers
#: TIMESYNC late under load (once 329 setpoints withheld at the 60 ms default, then the stop
#: action flew the rest); the monitor itself is tested in mavlink_bridge/test_monitors.py
LATENCY_S = 0.25
#: and its stop action's: the helper's 100 Hz stream has 0.3 s gaps there under load
STOP_AFTER_S = 0.8


class Operator:
    """A ground station on ArduCopter's SERIAL1 (TCP 5762 + 10 × instance)."""

    def __init__(self, sitl: ArduPilotSitl):
        self.sock = socket.create_connection(('127.0.0.1', sitl.ports['serial1_tcp']), 5.0)

        class _W:
            write = self.sock.sendall

        self.mav = mavlink.MAVLink(_W(), srcSystem=255, srcComponent=190)
        self.stop = False
        self.th = threading.Thread(target=self._drain, daemon=True)
        self.th.start()

    def _drain(self):
        self.sock.settimeout(0.2)
        while not self.stop:
            try:
                if not self.sock.recv(65536):
                    return
            except TimeoutError:
                continue
            except OSError:
                return

    def command(self, cmd, *params):
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self.mav.command_long_send(1, 1, cmd, 0, *p)

    def close(self):
        self.stop = True
        self.th.join(timeout=1.0)
        self.sock.close()


def _cpu_s():
    t = os.times()
    return t.user + t.system


def test_bridge_flies_arducopter_sitl_through_the_findings(ros_context):
    from deckland_common.frames import euler_to_quaternion, quaternion_to_euler
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import QuaternionStamped, TwistStamped, WrenchStamped
    from mavlink_bridge.node import MavlinkBridgeNode
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Imu, Range
    from std_msgs.msg import Bool, String
    from std_srvs.srv import Trigger

    context, executor = ros_context
    sitl = ArduPilotSitl('quad', SITL_PARAMS, nice=10)
    sitl.start()
    op = None
    try:
        sitl.wait_listening()
        t_spawn = time.monotonic()
        bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
            Parameter('connection', value=sitl.connection),
            Parameter('autopilot', value='ardupilot'),
            Parameter('max_link_latency_s', value=LATENCY_S),
            Parameter('stop_after_s', value=STOP_AFTER_S)])
        helper = Node('sitl_helper', context=context)
        executor.add_node(bridge)
        executor.add_node(helper)
        odom, vel, modes, ranges, imus, diags = [], [], [], [], [], []
        helper.create_subscription(Odometry, 'vehicle/odom', odom.append, RELIABLE_QOS)
        helper.create_subscription(TwistStamped, 'vehicle/velocity', vel.append, RELIABLE_QOS)
        helper.create_subscription(String, 'vehicle/mode', modes.append, LATCHED_QOS)
        helper.create_subscription(Range, 'vehicle/range', ranges.append, RELIABLE_QOS)
        helper.create_subscription(Imu, 'vehicle/imu', imus.append, RELIABLE_QOS)
        helper.create_subscription(DiagnosticArray, 'diagnostics', diags.append, RELIABLE_QOS)
        pub_enabled = helper.create_publisher(Bool, 'control/enabled', LATCHED_QOS)
        core = bridge.core
        assert wait_for(lambda: core.link_up(time.monotonic()), 40.0)   # (boot under load)
        # 2, 3, 5: the parameters, with ArduCopter 4.5's names (ATC_ANGLE_BOOST)
        assert wait_for(lambda: {'GUID_OPTIONS', 'ATC_ANGLE_BOOST', 'GUID_TIMEOUT',
                                 'MOT_THST_HOVER', 'FS_GCS_ENABLE', 'SYSID_MYGCS'}
                        <= set(core.autopilot_params), 10.0), core.autopilot_params
        assert core.autopilot_params['ATC_ANGLE_BOOST'] == 0.0       # MISSION_PARAMS
        assert core.autopilot_params['MOT_THST_HOVER'] == pytest.approx(0.39)
        assert 'lands' in core.ardupilot_link_loss()
        # 1: HIGHRES_IMU DENIED once, vehicle/imu from SCALED_IMU (~100 Hz), specific force
        # +g on FLU z at rest
        assert wait_for(lambda: core.imu_msg == 'SCALED_IMU', 5.0)
        assert wait_for(lambda: len(imus) > 10, 10.0)       # (ROS discovery)
        n0 = len(imus)
        time.sleep(1.0)
        # ~100/s asked and measured (docs/results/ardupilot_sitl.json); 43/s at load 50,
        # ArduCopter niced and starved: the fallback's point is that it streams
        assert len(imus) - n0 > 20
        assert imus[-1].linear_acceleration.z == pytest.approx(9.8, abs=0.3)
        texts = [t for _, _, t in core.statustexts]
        assert texts.count('No ap_message for mavlink id (105)') == 1
        assert core.counters['imu_fallback'] == 1
        # 8: on the ground the rangefinder reads below RNGFND1_MIN_CM: -inf (REP-117)
        assert wait_for(lambda: ranges, 5.0) and ranges[-1].range == -math.inf
        op = Operator(sitl)
        # 3: fail closed on GUID_OPTIONS: ArduCopter tells every link when it changes
        op.mav.param_set_send(1, 1, b'GUID_OPTIONS', 0.0, mavlink.MAV_PARAM_TYPE_INT32)
        assert wait_for(lambda: core.autopilot_params.get('GUID_OPTIONS') == 0.0, 5.0)
        res = call(helper, Trigger, 'bridge/offboard', Trigger.Request())
        assert not res.success and 'GUID_OPTIONS = 0' in res.message, res.message
        op.mav.param_set_send(1, 1, b'GUID_OPTIONS', 8.0, mavlink.MAV_PARAM_TYPE_INT32)
        assert wait_for(lambda: core.autopilot_params.get('GUID_OPTIONS') == 8.0, 5.0)
        # ArduCopter's own take-off (GUIDED, 3 m)
        op.command(176, 1, 4)
        assert wait_for(lambda: core.mode == 'GUIDED', 5.0), core.mode
        assert wait_for(lambda: (op.command(400, 1) or True) and core.armed, 20.0, 0.5)
        op.command(22, 0, 0, 0, 0, 0, 0, 3.0)
        assert wait_for(lambda: odom and odom[-1].pose.pose.position.z > 2.7, 20.0)
        # 5: the hover thrust ArduCopter commands in its own hover (MOT_THST_HOVER says 0.39)
        assert wait_for(lambda: core.hover.valid, 20.0), core.hover._samples[-5:]
        hover = core.hover.estimate
        assert 0.32 < hover < 0.37, hover
        state = {'go': True, 'mode': 'hold', 'z_ref': 3.0}
        cal = core.params.thrust
        weight = cal.mass_kg * cal.gravity_mps2
        yaw0 = quaternion_to_euler(*(lambda q: (q.w, q.x, q.y, q.z))(
            odom[-1].pose.pose.orientation))[2]
        pub_att = helper.create_publisher(QuaternionStamped, 'control/attitude', 10)
        pub_thr = helper.create_publisher(WrenchStamped, 'control/thrust', 10)

        def publish():
            w, x, y, z = euler_to_quaternion(0.0, 0.0, yaw0)
            while state['go']:
                now = helper.get_clock().now().to_msg()
                a = QuaternionStamped()
                a.header.stamp = now
                a.quaternion.w, a.quaternion.x, a.quaternion.y, a.quaternion.z = w, x, y, z
                pub_att.publish(a)
                f = WrenchStamped()
                f.header.stamp = now
                if state['mode'] == 'hold':             # u_z = m g, open loop
                    f.wrench.force.z = weight
                else:                                   # a 0.4 m/s descent (PD on odom)
                    state['z_ref'] = max(state['z_ref'] - 0.004, -0.5)
                    zc = odom[-1].pose.pose.position.z
                    vz = vel[-1].twist.linear.z if vel else 0.0
                    f.wrench.force.z = weight * (1.0 + 0.3 * (state['z_ref'] - zc) -
                                                 0.5 * (vz + 0.4))
                pub_thr.publish(f)
                time.sleep(0.01)

        th = threading.Thread(target=publish, daemon=True)
        th.start()
        try:
            res = call(helper, Trigger, 'bridge/offboard', Trigger.Request())
            assert res.success and 'measured' in res.message, res.message
            assert 'on link loss ArduPilot lands' in res.message
            assert wait_for(core.in_offboard, 5.0), core.last_result
            assert core.thrust.hover_thrust_norm == pytest.approx(hover)
            # the hover on open-loop m g: MOT_THST_HOVER's 0.39 would climb at +1.2 m/s^2
            t_off = time.monotonic()
            samples = []
            while time.monotonic() - t_off < 5.0:
                samples.append((time.monotonic() - t_off, odom[-1].pose.pose.position.z))
                time.sleep(0.1)
            accel = fit_accel(samples)
            print(f'hover {hover:.4f}: open-loop vertical acceleration {accel:+.3f} m/s^2')
            assert abs(accel) < 0.15, (hover, accel, samples)
            # 6: down to the ground on thrust, then control/enabled False (the planner's
            # landed): the bridge commands LAND (ArduCopter's land detector never confirms
            # in GUIDED_NOGPS) and retries the disarm until ArduCopter has disarmed
            state['z_ref'] = odom[-1].pose.pose.position.z
            state['mode'] = 'descend'
            assert wait_for(lambda: odom[-1].pose.pose.position.z < 0.1 and
                            abs(vel[-1].twist.linear.z) < 0.1, 20.0)
            time.sleep(1.0)
            t_landed = time.monotonic()
            pub_enabled.publish(Bool(data=False))
            assert wait_for(lambda: not core.armed, 15.0), core.last_result
            t_disarm = time.monotonic() - t_landed
            assert core.counters['stop_actions'] >= 1 and 'LAND' in [m.data for m in modes]
        finally:
            state['go'] = False
            th.join(timeout=1.0)
        # 5: ArduCopter saves a learned hover at disarm (MOT_HOVER_LEARN 2): read afresh
        # (this SITL build keeps 0.39 even after 24 s of its own hover, measured)
        assert wait_for(lambda: 'MOT_THST_HOVER' in core.autopilot_params, 5.0)
        learned = core.autopilot_params['MOT_THST_HOVER']
        # 8: STATUSTEXT in diagnostics; ArduCopter's mode names, none unknown
        link = [s for d in diags[-3:] for s in d.status if s.name.endswith(': link')][-1]
        vals = {kv.key: kv.value for kv in link.values}
        assert vals['statustext_last'] and vals['imu_message'] == 'SCALED_IMU'
        names = [m.data for m in modes]
        assert {'GUIDED', 'GUIDED_NOGPS', 'LAND'} <= set(names)
        assert not any(n.startswith('UNKNOWN') for n in names)
        # 7: ArduCopter goes away: no busy loop, no log storm; back on the same port: the
        # bridge reconnects and reads the new one's parameters
        op.close()
        op = None
        instance = sitl.instance
        sitl.stop()
        time.sleep(0.5)
        c0, t0 = _cpu_s(), time.monotonic()
        time.sleep(3.0)
        cpu = (_cpu_s() - c0) / (time.monotonic() - t0)
        assert cpu < 0.35, cpu
        assert bridge.conn.stats['disconnects'] == 1 and not core.link_up(time.monotonic())
        sitl = ArduPilotSitl('quad', SITL_PARAMS, nice=10, instance=instance)
        sitl.start()
        assert sitl.instance == instance
        assert wait_for(lambda: bridge.conn.stats['connects'] == 2, 10.0), bridge.conn.stats
        assert wait_for(lambda: core.link_up(time.monotonic()), 40.0), (   # (boot, load)
            bridge.conn.stats, core.counters, sitl.log_text()[-1500:])
        assert wait_for(lambda: 'GUID_OPTIONS' in core.autopilot_params, 10.0)
        print(f'ArduCopter SITL: counters {core.counters}; disarmed {t_disarm:.1f} s '
              f'after control/enabled False; learned MOT_THST_HOVER {learned:.3f}; bridge '
              f'process CPU without a peer {cpu:.1%}; spawn-to-now '
              f'{time.monotonic() - t_spawn:.0f} s')
    finally:
        if op is not None:
            op.close()
        sitl.stop()
