"""landing_planner node end to end through topics and services (private rclpy context).

A helper node plays the bridge (vehicle/odom, vehicle/velocity, vehicle/landed) and the
estimator (apron/state) at 100 Hz and records what the node publishes. Expected values come
from physics, not from recorded outputs: the inverse of the translational rows of model (2)
(a_forward = g tan θ, a_left = −g tan φ / cos θ at hover thrust) with the FLU sign convention,
the PID law a = k_p e + k_d (v_ff − v) of the horizontal loop, and the paper's Steps 1-16.
"""

from dataclasses import replace
import itertools
import math
import random
import subprocess
import sys
import threading
import time

import pytest
from rostest import wait_for

pytestmark = pytest.mark.ros

G = 9.81
_NS = itertools.count(random.SystemRandom().randrange(10**6))


@pytest.fixture
def ros(ros_context):
    """``ros_context`` whose nodes leave the executor (and finish their callbacks) first.

    rclpy 7.1's ``Executor.shutdown`` does not wait for running callbacks, so destroying the
    nodes right after it can hit a callback in flight; removing them beforehand avoids it.
    """
    yield ros_context
    _, executor = ros_context
    for node in list(executor.get_nodes()):
        executor.remove_node(node)
    time.sleep(0.05)


def quat_to_euler(w, x, y, z):
    """Z-Y-X Euler from a unit quaternion, written independently of deckland_common."""
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def stamp_s(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


class Helper:
    """Publishes the node's inputs at 100 Hz and records its outputs."""

    def __init__(self, context, executor, position=(0.0, 0.0, 2.0), yaw_rad=0.0,
                 height_m=2.0):
        from deckland_common.contract import ApronState, VerticalState
        from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, QuaternionStamped, TwistStamped
        from nav_msgs.msg import Odometry
        from rclpy.node import Node
        from std_msgs.msg import Bool, String
        from std_srvs.srv import Trigger

        from deckland_interfaces.msg import ApronState as ApronStateMsg
        from deckland_interfaces.msg import PlannerReference, PlannerStatus

        self._msgs = {'Odometry': Odometry, 'TwistStamped': TwistStamped, 'Bool': Bool,
                      'ApronState': ApronStateMsg}
        self._Trigger = Trigger
        self.VerticalState = VerticalState
        # a namespace of its own: latched messages of other tests' nodes never reach us
        self.ns = f'/plannode_{next(_NS)}'
        self.node = Node('plannode_test_helper', context=context, namespace=self.ns)
        self.position = position
        self.yaw_rad = yaw_rad
        self.frame = 'map'
        self.apron = ApronState.untracked(0.0)
        self.set_height(height_m)
        self.publish_vehicle = True
        self.publish_apron = True
        self.corrupt = None     # callable(ApronState message) -> message
        self.lock = threading.Lock()
        self.apron_stamps: list[float] = []
        self.out = {k: [] for k in ('attitude', 'reference', 'setpoint', 'mode', 'status',
                                    'enabled', 'diagnostics')}
        n = self.node
        self.pub_odom = n.create_publisher(Odometry, 'vehicle/odom', RELIABLE_QOS)
        self.pub_vel = n.create_publisher(TwistStamped, 'vehicle/velocity', RELIABLE_QOS)
        self.pub_landed = n.create_publisher(Bool, 'vehicle/landed', LATCHED_QOS)
        self.pub_apron = n.create_publisher(ApronStateMsg, 'apron/state', RELIABLE_QOS)
        for key, cls, topic, qos in (
                ('attitude', QuaternionStamped, 'control/attitude', RELIABLE_QOS),
                ('reference', PlannerReference, 'planner/reference', RELIABLE_QOS),
                ('status', PlannerStatus, 'planner/status', LATCHED_QOS),
                ('setpoint', PoseStamped, 'planner/setpoint', RELIABLE_QOS),
                ('mode', String, 'planner/mode', LATCHED_QOS),
                ('enabled', Bool, 'control/enabled', LATCHED_QOS),
                ('diagnostics', DiagnosticArray, 'diagnostics', RELIABLE_QOS)):
            n.create_subscription(cls, topic, self._recorder(key), qos)
        self.clients = {name: n.create_client(Trigger, f'planner/{name}')
                        for name in ('start_landing', 'abort', 'takeoff')}
        executor.add_node(n)
        self.running = False
        n.create_timer(0.01, self._tick)

    def set_height(self, height_m, tracked_at=None):
        """Hover over a surface at z = position.z − height; optionally track a beacon."""
        vert = self.VerticalState(True, height_m, 0.0, self.position[2], 0.0,
                                  self.position[2] - height_m, 0.0, 0.0, 0, 0.0)
        st = replace(self.apron, vertical=vert)
        if tracked_at is not None:
            rel = (tracked_at[0] - self.position[0], tracked_at[1] - self.position[1])
            st = replace(st, tracked=True, visible=True, time_since_seen_s=0.0,
                         rel_position_m=rel, apron_position_m=tuple(tracked_at),
                         apron_velocity_mps=(0.0, 0.0))
        self.apron = st

    def _recorder(self, key):
        def record(msg):
            with self.lock:
                self.out[key].append(msg)
        return record

    def get(self, key):
        with self.lock:
            return list(self.out[key])

    def clear(self, *keys):
        with self.lock:
            for k in keys:
                self.out[k].clear()

    def now_s(self):
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _tick(self):
        if not self.running:
            return
        m = self._msgs
        stamp = self.node.get_clock().now().to_msg()
        if self.publish_vehicle:
            od = m['Odometry']()
            od.header.stamp = stamp
            od.header.frame_id = self.frame
            p = od.pose.pose.position
            p.x, p.y, p.z = self.position
            q = od.pose.pose.orientation
            q.w, q.z = math.cos(self.yaw_rad / 2.0), math.sin(self.yaw_rad / 2.0)
            self.pub_odom.publish(od)
            tw = m['TwistStamped']()
            tw.header = od.header
            self.pub_vel.publish(tw)
        if self.publish_apron:
            t = stamp.sec + stamp.nanosec * 1e-9
            msg = self.apron_msg(t)
            if self.corrupt is not None:
                msg = self.corrupt(msg)
            self.pub_apron.publish(msg)
            with self.lock:
                self.apron_stamps.append(t)

    def apron_msg(self, t):
        from deckland_common.messages import fill_apron_state
        return fill_apron_state(self._msgs['ApronState'](), replace(self.apron, t_s=t))

    def start(self):
        assert wait_for(lambda: self.node.count_subscribers('apron/state') >= 1
                        and self.node.count_publishers('control/attitude') >= 1)
        time.sleep(0.2)  # let the endpoints match before the first sample
        self.running = True

    def call(self, name, timeout_s=5.0):
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=5.0)
        future = client.call_async(self._Trigger.Request())
        assert wait_for(future.done, timeout_s)
        return future.result()

    def modes(self):
        return [m.data for m in self.get('mode')]


def make_node(context, executor, helper=None, **params):
    from landing_planner.node import LandingPlannerNode
    from rclpy.parameter import Parameter
    ns = helper.ns if helper is not None else '/plannode_params'
    node = LandingPlannerNode(context=context, namespace=ns, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])
    executor.add_node(node)
    return node


def attitude_euler(msg):
    q = msg.quaternion
    return quat_to_euler(q.w, q.x, q.y, q.z)


def test_start_landing_tilts_toward_the_area_by_the_pid_law(ros):
    """Area 5 m east of a vehicle yawed 0: APPROACH, nose down (positive pitch), no roll.

    With k_i = 0 and the vehicle at rest at the origin, the horizontal law gives
    a = k_p (s − p) + k_d v_ff along x, and (2) at hover thrust gives θ = atan(a / g).
    """
    context, executor = ros
    helper = Helper(context, executor)
    node = make_node(context, executor, helper, landing_area_x_m=5.0, landing_area_y_m=0.0,
                     xy_ki=0.0)
    helper.start()
    assert wait_for(lambda: helper.modes() == ['IDLE'])
    assert wait_for(lambda: len(helper.get('attitude')) > 5)   # IDLE hover: holding here
    res = helper.call('start_landing')
    assert res.success, res.message
    assert wait_for(lambda: helper.modes()[-1:] == ['APPROACH'])
    helper.clear('attitude', 'reference')
    time.sleep(1.5)
    # one command per apron state the helper gets out (event-driven): a slow helper needs longer
    assert wait_for(lambda: len(helper.get('attitude')) > 50, 6.0)
    att, ref = helper.get('attitude'), helper.get('reference')
    assert len(att) > 50 and len(ref) >= len(att)
    kp, kd = node.horizontal.params.kp, node.horizontal.params.kd
    refs = {}
    for r in ref:
        refs.setdefault((r.header.stamp.sec, r.header.stamp.nanosec), []).append(r)
    checked = 0
    for a in att[-40:]:
        roll, pitch, yaw = attitude_euler(a)
        assert a.header.frame_id == 'map'
        assert abs(yaw) < 1e-9 and abs(roll) < 1e-9
        assert pitch > 0.0     # setpoint to the east, nose east: nose down
        assert pitch <= node.horizontal.params.max_tilt_rad + 1e-9
        matches = []
        for r in refs[(a.header.stamp.sec, a.header.stamp.nanosec)]:
            assert r.vertical_frame == r.VERTICAL_RELATIVE and r.header.frame_id == 'map'
            sx, sy = r.setpoint_m
            assert sx > 0.0 and abs(sy) < 1e-9
            assert r.velocity_ff_mps[0] > 0.0           # feed-forward along the path
            assert abs(r.z_d_m - 2.0) < 0.05            # approach height 2 m
            assert not r.precise_xy and r.thrust_enabled
            a_cmd = min(kp * sx + kd * r.velocity_ff_mps[0], 3.0)  # max_accel (< g tan 20°)
            matches.append(abs(G * math.tan(pitch) - a_cmd) < 1e-6)
        # several ticks may share an apron stamp: one of them is this command's reference
        assert any(matches)
        checked += 1
    assert checked == 40
    # commands are stamped with the t_s of an apron state that was sent
    sent = {round(t, 6) for t in helper.apron_stamps}
    assert all(round(stamp_s(a.header), 6) in sent for a in att[-40:])


def test_yawed_vehicle_rolls_right_toward_an_area_on_its_right(ros):
    """Nose north (yaw +90°), area east = to the right: positive roll (right side down)."""
    context, executor = ros
    helper = Helper(context, executor, yaw_rad=math.pi / 2.0)
    make_node(context, executor, helper, landing_area_x_m=5.0, landing_area_y_m=0.0)
    helper.start()
    assert helper.call('start_landing').success
    helper.clear('attitude')
    time.sleep(1.0)
    assert wait_for(lambda: len(helper.get('attitude')) > 30, 5.0)  # one per apron state
    att = helper.get('attitude')
    assert len(att) > 30
    for a in att[-20:]:
        roll, pitch, yaw = attitude_euler(a)
        assert yaw == pytest.approx(math.pi / 2.0, abs=1e-9)   # heading latched at start
        assert roll > 0.01 and abs(pitch) < 0.2 * roll


def test_abort_holds_and_services_report_refusals(ros):
    context, executor = ros
    helper = Helper(context, executor)
    node = make_node(context, executor, helper, landing_area_x_m=3.0)
    helper.start()
    res = helper.call('abort')
    assert not res.success and 'IDLE' in res.message
    assert helper.call('start_landing').success
    assert wait_for(lambda: helper.modes()[-1:] == ['APPROACH'])
    res = helper.call('start_landing')
    assert not res.success and 'already landing' in res.message
    res = helper.call('abort')
    assert res.success
    assert wait_for(lambda: helper.modes()[-1:] == ['HOLD'])
    assert not helper.call('takeoff').success          # already airborne
    # HOLD keeps the vehicle where it was: setpoint ≈ current position, no tilt build-up
    helper.clear('reference')
    time.sleep(0.3)
    assert math.hypot(*helper.get('reference')[-1].setpoint_m) < 0.2
    assert helper.modes() == ['IDLE', 'APPROACH', 'HOLD']
    # planner/status: one latched message per mode, with the previous mode and the reason
    from deckland_interfaces.msg import PlannerStatus
    st = helper.get('status')
    assert [(s.previous_mode, s.mode) for s in st] == [
        (PlannerStatus.MODE_IDLE, PlannerStatus.MODE_IDLE),
        (PlannerStatus.MODE_IDLE, PlannerStatus.MODE_APPROACH),
        (PlannerStatus.MODE_APPROACH, PlannerStatus.MODE_HOLD)]
    assert st[-1].reason == node.planner.reason and st[-1].reason


def _all_finite_outputs(helper):
    vals = []
    for a in helper.get('attitude'):
        q = a.quaternion
        vals += [q.w, q.x, q.y, q.z, stamp_s(a.header)]
    for r in helper.get('reference'):
        vals += [*r.setpoint_m, *r.velocity_ff_mps, r.z_d_m, r.z_d_dot_mps, r.z_d_ddot_mps2,
                 stamp_s(r.header)]
    for s in helper.get('setpoint'):
        vals += [s.pose.position.x, s.pose.position.y, s.pose.position.z]
    return all(math.isfinite(x) for x in vals)


def test_bad_apron_states_are_rejected_and_never_published(ros):
    context, executor = ros
    helper = Helper(context, executor)
    node = make_node(context, executor, helper, landing_area_x_m=2.0)
    helper.start()
    assert helper.call('start_landing').success
    time.sleep(0.3)

    def nan_height(m):
        m.vertical.height_m = math.nan
        return m
    helper.corrupt = nan_height
    assert wait_for(lambda: node.rejected['non_finite'] > 20)

    def nan_velocity(m):
        m.apron_velocity_mps = (0.0, math.nan)
        return m
    n_bad = node.rejected['non_finite']
    helper.corrupt = nan_velocity
    assert wait_for(lambda: node.rejected['non_finite'] > n_bad + 5)
    # the last good state went stale: the planner got the core's fallback (vertical invalid)
    # and entered its safe mode after invalid_timeout_s; commands kept flowing (vehicle fresh)
    assert wait_for(lambda: node.counts['apron_fallback'] > 10)
    assert wait_for(lambda: helper.modes()[-1:] == ['HOLD'])
    assert 'vertical state invalid' in node.planner.reason
    n_att = len(helper.get('attitude'))
    assert wait_for(lambda: len(helper.get('attitude')) > n_att, 2.0)   # watchdog steps
    assert _all_finite_outputs(helper)
    stamps = [stamp_s(a.header) for a in helper.get('attitude')]
    assert all(b >= a for a, b in itertools.pairwise(stamps))   # never backwards
    # nothing non-finite reached the core except the node's own stale-vehicle signal (a
    # loaded machine may starve the 100 Hz helper for a moment)
    assert node.planner.rejected['nan'] == node.withheld['vehicle_stale']


def test_stale_vehicle_withholds_commands_then_resumes(ros):
    context, executor = ros
    helper = Helper(context, executor)
    node = make_node(context, executor, helper, landing_area_x_m=2.0, input_timeout_s=0.3)
    helper.start()
    assert helper.call('start_landing').success
    assert wait_for(lambda: len(helper.get('attitude')) > 10)
    helper.publish_vehicle = False
    t_stop = time.monotonic()
    time.sleep(0.45)   # timeout 0.3 s + margin
    helper.clear('attitude', 'reference', 'setpoint')
    time.sleep(0.5)
    assert helper.get('attitude') == [] and helper.get('reference') == []
    assert helper.get('setpoint') == []
    # one withheld tick per apron state the helper gets out (event-driven)
    assert wait_for(lambda: node.withheld['vehicle_stale'] > 20, 3.0)
    # the planner kept running on "vehicle invalid": safe mode (HOLD) after 0.5 s
    assert wait_for(lambda: helper.modes()[-1:] == ['HOLD'], 2.0)
    assert 'vehicle state invalid' in node.planner.reason
    assert time.monotonic() - t_stop >= 0.3 + 0.5 - 0.05
    helper.publish_vehicle = True
    assert wait_for(lambda: len(helper.get('attitude')) > 10)
    assert _all_finite_outputs(helper)


def test_wrong_frame_and_bad_odom_are_rejected(ros):
    context, executor = ros
    helper = Helper(context, executor)
    node = make_node(context, executor, helper)
    helper.frame = 'odom'
    helper.start()
    assert wait_for(lambda: node.rejected['bad_frame'] > 20)
    assert helper.get('attitude') == [] and node.withheld['no_vehicle'] > 0
    helper.frame = 'map'
    helper.position = (math.inf, 0.0, 2.0)
    assert wait_for(lambda: node.rejected['non_finite'] > 10)
    assert helper.get('attitude') == []
    helper.position = (0.0, 0.0, 2.0)
    assert wait_for(lambda: len(helper.get('attitude')) > 5)


def test_full_sequence_to_landed_disables_control(ros):
    """Tracked beacon under the vehicle: ALIGN → DESCEND (ż_d < 0) → FINAL → LANDED."""
    context, executor = ros
    helper = Helper(context, executor)
    node = make_node(context, executor, helper, acceptance_hold_s=0.3)
    helper.set_height(2.0, tracked_at=(0.05, 0.0))
    helper.start()
    assert wait_for(lambda: helper.get('enabled')[-1:] and helper.get('enabled')[-1].data)
    assert helper.call('start_landing').success
    assert wait_for(lambda: 'DESCEND' in helper.modes(), 3.0), helper.modes()
    assert helper.modes()[:4] == ['IDLE', 'APPROACH', 'ALIGN', 'DESCEND']
    time.sleep(0.8)
    assert helper.get('reference')[-1].z_d_dot_mps < -0.05
    assert helper.get('reference')[-1].precise_xy
    helper.set_height(0.45, tracked_at=(0.05, 0.0))
    assert wait_for(lambda: helper.modes()[-1:] == ['FINAL'], 2.0), helper.modes()
    helper.pub_landed.publish(helper._msgs['Bool'](data=True))
    assert wait_for(lambda: helper.modes()[-1:] == ['LANDED'], 2.0), helper.modes()
    assert wait_for(lambda: not helper.get('enabled')[-1].data)
    time.sleep(0.1)
    helper.clear('attitude')
    time.sleep(0.3)
    assert helper.get('attitude') == []           # no attitude commands after LANDED
    assert node.withheld['thrust_disabled'] > 10
    assert [m.data for m in helper.get('enabled')] == [True, False]


def test_diagnostics_report_counters_ages_and_mode(ros):
    context, executor = ros
    helper = Helper(context, executor)
    make_node(context, executor, helper)
    helper.start()
    assert wait_for(lambda: len(helper.get('diagnostics')) >= 2, 3.0)
    status = helper.get('diagnostics')[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert values['mode'] == 'IDLE'
    assert float(values['apron_age_s']) < 0.3 and float(values['odom_age_s']) < 0.3
    assert 'rejected_non_finite' in values and 'planner_rejected_nan' in values
    assert 0 < int(values['steps_per_s']) <= 110   # (a loaded CI machine runs slower)


def test_bad_parameters_are_rejected_with_clear_messages(ros):
    from deckland_common.params import ParameterError
    context, executor = ros
    with pytest.raises(ParameterError, match='acceptance_radius_m'):
        make_node(context, executor, None, acceptance_radius_m=-0.1)
    with pytest.raises(ParameterError, match='final_approach_height_m'):
        make_node(context, executor, None,
                  final_approach_height_m=3.0)   # above the approach height
    with pytest.raises(ParameterError, match='descent_profile'):
        make_node(context, executor, None, descent_profile='plummet')
    with pytest.raises(ParameterError, match='max_tilt_rad'):
        make_node(context, executor, None, max_tilt_rad=1.2)
    with pytest.raises(ParameterError, match='landing_area_x_m'):
        make_node(context, executor, None, landing_area_x_m='east')


def test_main_exits_with_status_2_on_a_bad_parameter():
    proc = subprocess.run(
        [sys.executable, '-m', 'landing_planner.node', '--ros-args', '-p',
         'acceptance_radius_m:=-0.5'], capture_output=True, text=True, timeout=20)
    assert proc.returncode == 2
    assert "'acceptance_radius_m'" in proc.stderr and 'must be > 0' in proc.stderr


def test_every_core_field_is_a_parameter():
    from dataclasses import fields

    from landing_planner.horizontal import HorizontalParams
    from landing_planner.node_params import HORIZONTAL_FIELDS, PARAMS, PLANNER_DESCRIPTIONS
    from landing_planner.planner import PlannerParams
    names = {s.name for s in PARAMS}
    for f in fields(PlannerParams):
        if f.name == 'landing_area_m':
            assert {'landing_area_x_m', 'landing_area_y_m'} <= names
        else:
            assert f.name in names and f.name in PLANNER_DESCRIPTIONS
    assert {v[0] for v in HORIZONTAL_FIELDS.values()} == {f.name for f in
                                                           fields(HorizontalParams)}
    assert all(s.description for s in PARAMS)


def test_every_apron_state_is_answered_in_its_callback(ros):
    """Event-driven: a burst of five apron states 2 ms apart (faster than any 100 Hz timer)
    gives five attitude commands and references, stamped with exactly those five t_s; a
    timer-clocked loop would use the latest state only, once per period. While the states
    are fresh the watchdog never steps (no fallback)."""
    context, executor = ros
    helper = Helper(context, executor)
    # a long input timeout: a loaded machine may stall the helper; nothing may go stale here
    node = make_node(context, executor, helper, landing_area_x_m=2.0, input_timeout_s=2.0)
    helper.start()
    assert wait_for(lambda: len(helper.get('attitude')) > 10)
    helper.publish_apron = False
    n_sent = -1
    while n_sent != len(helper.apron_stamps):   # the helper's last apron state is out
        n_sent = len(helper.apron_stamps)
        time.sleep(0.05)
    fallback0 = node.counts['apron_fallback']
    sent = []
    for _ in range(5):
        t = max(helper.now_s(), helper.apron_stamps[-1] + 1e-3)
        helper.pub_apron.publish(helper.apron_msg(t))
        sent.append(t)
        time.sleep(0.002)

    def answered(key):
        stamps = [stamp_s(x.header) for x in helper.get(key)]
        return [t for t in sent if min(abs(s - t) for s in stamps) < 1e-6]
    assert wait_for(lambda: len(answered('attitude')) == 5, 2.0), (answered('attitude'), sent)
    assert len(answered('reference')) == 5
    assert node.counts['apron_fallback'] == fallback0
