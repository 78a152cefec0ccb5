"""Fuzz every node's subscriptions with bad input, end to end through topics.

Each node runs in-process in a private context (``ros_context``) on a SingleThreadedExecutor
spun *in the test thread*: ``spin_once`` re-raises any exception a callback lets escape, and we
catch and record it (every subscription callback is also wrapped, to count deliveries and to
record exceptions with the topic that caused them). A helper node publishes the inputs and
records every output topic; every float of every output message is checked recursively.

Per bad message the harness knows whether the node *must* refuse it (a non-finite number in a
field the node reads, a wrong layout, a stale or future stamp, ...) and then asserts that the
node's rejection counters grew. Values the node may legitimately accept (huge but finite
numbers, non-finite numbers in fields it does not read) carry no such expectation; they only
must never make the node raise or publish a NaN/inf. After the fuzzing each node must again
produce the physically right output for valid input.

Hypothesis draws the bad messages (derandomized: the same examples on every run).
"""

from __future__ import annotations

import array
import collections
import itertools
import json
import math
import socket
import threading
import time
import traceback

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

pytestmark = pytest.mark.ros

NAN, INF = math.nan, math.inf
G = 9.81
_NS = itertools.count()

#: special float64 values every field is tried with
F64_SPECIAL = (NAN, INF, -INF, 1e308, -1e308, 0.0, -0.0, 5e-324, -1e-300, 1e6, -1e6)
#: the same for float32 fields (a ROS float32 field refuses |x| > 3.4e38)
F32_SPECIAL = (NAN, INF, -INF, 3.4e38, -3.4e38, 0.0, -0.0, 1e-45, 1e6, -1e6)
F64 = st.one_of(st.sampled_from(F64_SPECIAL), st.floats(allow_nan=True, allow_infinity=True))
F32 = st.one_of(st.sampled_from(F32_SPECIAL),
                st.floats(width=32, allow_nan=True, allow_infinity=True))
STAMP_KINDS = ('old', 'future', 'zero', 'backwards', 'max')

FUZZ_SETTINGS = {'deadline': None, 'derandomize': True, 'database': None,
                 'suppress_health_check': list(HealthCheck)}


# --------------------------------------------------------------------------- helpers

def stamp(header, t_s: float) -> None:
    sec = math.floor(t_s)
    header.stamp.sec, header.stamp.nanosec = int(sec), min(int((t_s - sec) * 1e9), 999_999_999)


def non_finite_paths(value, path: str = ''):
    """Yield (path, value) of every non-finite float inside a ROS message, recursively."""
    if isinstance(value, float):
        if not math.isfinite(value):
            yield path, value
    elif isinstance(value, np.ndarray):
        if value.dtype.kind == 'f':
            for i in np.flatnonzero(~np.isfinite(value)):
                yield f'{path}[{i}]', float(value.flat[i])
    elif isinstance(value, array.array):
        if value.typecode in 'fd':
            for i, v in enumerate(value):
                if not math.isfinite(v):
                    yield f'{path}[{i}]', v
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from non_finite_paths(v, f'{path}[{i}]')
    elif hasattr(value, 'get_fields_and_field_types'):
        for name in value.get_fields_and_field_types():
            yield from non_finite_paths(getattr(value, name), f'{path}.{name}' if path else name)


def _resolve(msg, path: str):
    """The object holding the last element of ``path`` and that element's key/index."""
    obj = msg
    parts = path.replace('[', '.[').split('.')
    for part in parts[:-1]:
        obj = obj[int(part[1:-1])] if part.startswith('[') else getattr(obj, part)
    last = parts[-1]
    return obj, (int(last[1:-1]) if last.startswith('[') else last)


def set_path(msg, path: str, value) -> bool:
    """Set ``msg.<path>`` (``a.b[3].c``); False if the path does not exist (any more)."""
    try:
        obj, key = _resolve(msg, path)
        if isinstance(key, int):
            obj[key] = value
        else:
            setattr(obj, key, value)
    except (IndexError, AttributeError, KeyError):
        return False
    return True


def wait_until(pred, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return bool(pred())


class Rig:
    """The node under test plus a helper node, both spun by an executor in the test thread.

    ``inputs``: topic → (type, qos) published by the helper; ``outputs``: topic → (type, qos)
    recorded by the helper. ``inf_ok(topic, path, value)`` says where an infinity is part of
    the contract (REP-117 ranges, ``apron_state_v1`` fields 1 and 4); NaN never is.
    """

    def __init__(self, context, node, namespace: str, inputs: dict, outputs: dict,
                 inf_ok=None) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.node = node
        self.ns = namespace
        self.helper = Node('fuzz_helper', context=context, namespace=namespace)
        self.executor = SingleThreadedExecutor(context=context)
        self.errors: list[str] = []
        self.delivered: collections.Counter = collections.Counter()
        self.bad_outputs: list[str] = []
        self.out: dict[str, list] = {t: [] for t in outputs}
        self._inf_ok = inf_ok or (lambda topic, path, value: False)
        self._lock = threading.Lock()
        for sub in list(node.subscriptions):
            sub.callback = self._wrap(self._relative(sub.topic_name), sub.callback)
        self.pubs = {t: self.helper.create_publisher(cls, t, qos)
                     for t, (cls, qos) in inputs.items()}
        for t, (cls, qos) in outputs.items():
            self.helper.create_subscription(cls, t, self._recorder(t), qos)
        self.executor.add_node(node)
        self.executor.add_node(self.helper)

    def _relative(self, topic: str) -> str:
        prefix = self.ns.rstrip('/') + '/'
        return topic[len(prefix):] if topic.startswith(prefix) else topic.lstrip('/')

    def _wrap(self, topic, cb):
        def wrapped(msg):
            with self._lock:
                self.delivered[topic] += 1
            try:
                return cb(msg)
            except BaseException:
                with self._lock:
                    self.errors.append(f'{topic}: {traceback.format_exc()}')
                raise
        return wrapped

    def _recorder(self, topic):
        def record(msg):
            for path, value in non_finite_paths(msg):
                if math.isnan(value) or not self._inf_ok(topic, path, value):
                    with self._lock:
                        self.bad_outputs.append(f'{topic}.{path} = {value!r}')
            with self._lock:
                self.out[topic].append(msg)
        return record

    def spin(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        while True:
            try:
                self.executor.spin_once(timeout_sec=0.002)
            except Exception:  # a callback raised: record it, keep spinning
                self.errors.append(traceback.format_exc())
            if time.monotonic() >= end:
                return

    def spin_until(self, pred, timeout_s: float = 3.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if pred():
                return True
            self.spin(0.005)
        return bool(pred())

    def wait_matched(self, timeout_s: float = 5.0) -> None:
        def matched():
            return (all(p.get_subscription_count() >= 1 for p in self.pubs.values())
                    and all(self.helper.count_publishers(self.helper.resolve_topic_name(t))
                            >= 1 for t in self.out))
        assert self.spin_until(matched, timeout_s), 'publishers and subscribers never matched'

    def send(self, topic: str, msg, timeout_s: float = 2.0) -> None:
        """Publish and spin until the node's callback has run on it."""
        n0 = self.delivered[topic]
        self.pubs[topic].publish(msg)
        assert self.spin_until(lambda: self.delivered[topic] > n0, timeout_s), \
            f'{topic}: message never delivered'

    def clear(self) -> None:
        with self._lock:
            for v in self.out.values():
                v.clear()

    def last(self, topic):
        with self._lock:
            return self.out[topic][-1] if self.out[topic] else None

    def check_clean(self) -> None:
        assert not self.errors, 'exception escaped a callback:\n' + '\n'.join(self.errors[:3])
        assert not self.bad_outputs, f'non-finite numbers published: {self.bad_outputs[:10]}'

    def close(self) -> None:
        for n in (self.node, self.helper):
            self.executor.remove_node(n)
        self.executor.shutdown(timeout_sec=1.0)
        self.helper.destroy_node()
        self.node.destroy_node()


def now_of(rig: Rig) -> float:
    return rig.helper.get_clock().now().nanoseconds * 1e-9


def apply_stamp(header, kind: str, now: float, last_valid: float) -> None:
    """Bad stamps: 100 s old/ahead, zero, just before the last valid one, the int32 limit."""
    if kind == 'old':
        stamp(header, now - 100.0)
    elif kind == 'future':
        stamp(header, now + 100.0)
    elif kind == 'zero':
        header.stamp.sec, header.stamp.nanosec = 0, 0
    elif kind == 'backwards':
        stamp(header, last_valid - 0.05)
    elif kind == 'max':
        header.stamp.sec, header.stamp.nanosec = 2 ** 31 - 1, 999_999_999


# --------------------------------------------------------------------------- fuzz plans
#
# A topic plan is: make(now) -> valid message; float fields (path, 'f64'|'f32',
# must_reject(value)); the stamp kinds the node must refuse; structural corruptions
# (name -> (fn(msg), must_reject)).

def _nonfinite(v):
    return not math.isfinite(v)


def _never(_v):
    return False


def _beyond_16g(v):
    return not abs(v) <= 16.0 * 9.80665


def mutation_strategy(plan):
    fields = plan['fields']
    choices = []
    if fields:
        choices.append(st.tuples(st.just('field'), st.integers(0, len(fields) - 1),
                                 st.one_of(F64, F32)))
    if plan.get('stamp'):
        choices.append(st.tuples(st.just('stamp'), st.sampled_from(STAMP_KINDS), st.none()))
    if plan.get('struct'):
        choices.append(st.tuples(st.just('struct'), st.sampled_from(sorted(plan['struct'])),
                                 st.none()))
    return st.lists(st.one_of(*choices), min_size=1, max_size=3)


def build_bad(plan, mutations, now: float, last_valid: float):
    """Apply mutations to a valid message; returns (msg, must_reject)."""
    msg = plan['make'](now)
    must = False
    final = {}      # a later mutation of the same field (or of the stamp) wins
    for kind, a, b in mutations:
        if kind == 'field':
            final[a] = b
    stamps = [m for m in mutations if m[0] == 'stamp']
    mutations = [m for m in mutations if m[0] != 'stamp'] + stamps[-1:]
    for a, value in final.items():
        path, width, rule = plan['fields'][a]
        if width == 'f32' and math.isfinite(value) and abs(value) > 3.4e38:
            value = math.copysign(3.4e38, value)
        if set_path(msg, path, value):
            must |= rule(value)
    for kind, a, _b in sorted(mutations, key=lambda m: m[0] == 'struct'):
        if kind == 'field':
            continue
        if kind == 'stamp':
            apply_stamp(plan['stamp_header'](msg), a, now, last_valid)
            must |= a in plan['stamp']
        else:
            fn, rejected = plan['struct'][a]
            fn(msg)
            must |= rejected
    return msg, must


def sweep(rig: Rig, plans: dict, valid_frame, rejected_total, stats) -> None:
    """Every single corruption once (NaN, ±inf, ±1e308 in every field, every bad stamp, every
    structural corruption), each after a valid frame: deterministic coverage."""
    cases = []
    for topic, plan in sorted(plans.items()):
        for i in range(len(plan['fields'])):
            cases += [(topic, [('field', i, v)]) for v in (NAN, INF, -INF, 1e308, -1e308)]
        cases += [(topic, [('stamp', k, None)]) for k in plan.get('stamp') or ()]
        cases += [(topic, [('struct', k, None)]) for k in sorted(plan.get('struct') or ())]
    last_valid = valid_frame()
    for i, (topic, mutations) in enumerate(cases):
        if i % 4 == 3:
            last_valid = valid_frame()
        msg, must = build_bad(plans[topic], mutations, now_of(rig), last_valid)
        before = rejected_total()
        rig.send(topic, msg)
        stats['sent'] += 1
        if must:
            stats['must_reject'] += 1
            assert rejected_total() > before, f'{topic} {mutations}: bad input not counted'
        rig.check_clean()
    rig.spin(0.01)
    rig.check_clean()


def run_fuzz(rig: Rig, plans: dict, valid_frame, rejected_total, n_examples: int) -> dict:
    """Hypothesis: each example = valid frame, then bad messages on random topics, then a
    valid frame again; checks no exception, no non-finite output and counted rejections."""
    topics = sorted(plans)
    stats = collections.Counter()
    sweep(rig, plans, valid_frame, rejected_total, stats)
    strategy = st.lists(st.sampled_from(topics).flatmap(
        lambda t: st.tuples(st.just(t), mutation_strategy(plans[t]))), min_size=1, max_size=6)

    @settings(max_examples=n_examples, **FUZZ_SETTINGS)
    @given(batch=strategy)
    def one_batch(batch):
        last_valid = valid_frame()
        rig.spin(0.005)
        for topic, mutations in batch:
            msg, must = build_bad(plans[topic], mutations, now_of(rig), last_valid)
            before = rejected_total()
            rig.send(topic, msg)
            after = rejected_total()
            stats['sent'] += 1
            if must:
                stats['must_reject'] += 1
                assert after > before, f'{topic} {mutations}: bad input not counted'
            rig.check_clean()
        valid_frame()
        rig.spin(0.01)
        rig.check_clean()

    one_batch()
    return stats


def total(*dicts) -> int:
    return sum(sum(d.values()) for d in dicts)


# --------------------------------------------------------------------------- apron_estimator

def quat_yaw(yaw):
    return math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)


def apron_plans():
    from geometry_msgs.msg import Point32, TwistStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import ChannelFloat32, Imu, PointCloud, Range

    def imu(t):
        m = Imu()
        stamp(m.header, t)
        m.header.frame_id = 'base_link'
        m.orientation.w, m.orientation.x, m.orientation.y, m.orientation.z = quat_yaw(0.0)
        m.linear_acceleration.z = G
        return m

    def odom(t):
        m = Odometry()
        stamp(m.header, t)
        m.header.frame_id, m.child_frame_id = 'map', 'base_link'
        p = m.pose.pose.position
        p.x, p.y, p.z = 3.0, -1.0, 2.0
        m.pose.pose.orientation.w = 1.0
        return m

    def velocity(t):
        m = TwistStamped()
        stamp(m.header, t)
        m.header.frame_id = 'map'
        return m

    def rng(t):
        m = Range()
        stamp(m.header, t)
        m.header.frame_id = 'lidar_link'
        m.min_range, m.max_range, m.range = 0.05, 40.0, 2.0
        return m

    def blocks(t, n=1):
        m = PointCloud()
        stamp(m.header, t - 0.02)
        m.header.frame_id = 'camera_optical'
        m.points = [Point32(x=160.0, y=100.0, z=0.0) for _ in range(n)]
        m.channels = [ChannelFloat32(name='signature', values=[1.0] * n),
                      ChannelFloat32(name='width', values=[6.0] * n),
                      ChannelFloat32(name='height', values=[6.0] * n)]
        return m

    def drop_channel(m):
        m.channels = m.channels[:2]

    def short_channel(m):
        m.channels[1].values = []

    def oversized(m):
        n = 5000
        m.points = [Point32(x=float(i % 320), y=float(i % 200), z=0.0) for i in range(n)]
        m.channels[0].values = [1.0] * n
        m.channels[1].values = [6.0] * n
        m.channels[2].values = [6.0] * (n - 1)   # and one short: malformed

    def empty_cloud(m):
        m.points = []
        for c in m.channels:
            c.values = []

    def no_orientation(m):
        m.orientation_covariance[0] = -1.0

    def zero_quaternion(m):
        o = m.orientation
        o.w = o.x = o.y = o.z = 0.0

    def hdr(m):
        return m.header

    quat_rule = _nonfinite
    plans = {
        'vehicle/imu': {
            'make': imu, 'stamp_header': hdr, 'stamp': ('old', 'future', 'zero', 'max'),
            'fields': [('orientation.w', 'f64', quat_rule), ('orientation.x', 'f64', quat_rule),
                       ('orientation.z', 'f64', quat_rule),
                       ('linear_acceleration.x', 'f64', _beyond_16g),
                       ('linear_acceleration.z', 'f64', _beyond_16g),
                       ('angular_velocity.x', 'f64', _never),
                       ('orientation_covariance[0]', 'f64', lambda v: v == -1.0),
                       ('linear_acceleration_covariance[4]', 'f64', _never)],
            'struct': {'no_orientation': (no_orientation, True),
                       'zero_quaternion': (zero_quaternion, True)}},
        'vehicle/odom': {
            'make': odom, 'stamp_header': hdr, 'stamp': ('old', 'future', 'zero', 'max'),
            'fields': [('pose.pose.position.x', 'f64', _never),
                       ('pose.pose.position.z', 'f64', _never),
                       ('twist.twist.linear.x', 'f64', _never),
                       ('pose.covariance[0]', 'f64', _never)]},
        'vehicle/velocity': {
            'make': velocity, 'stamp_header': hdr, 'stamp': ('old', 'future', 'zero', 'max'),
            'fields': [('twist.linear.x', 'f64', _never), ('twist.linear.z', 'f64', _never)]},
        'vehicle/range': {
            'make': rng, 'stamp_header': hdr, 'stamp': ('old', 'future', 'zero', 'max'),
            # NaN range: the estimator counts it; ±inf: a counted dropout (REP-117)
            'fields': [('range', 'f32', _nonfinite), ('min_range', 'f32', _never),
                       ('max_range', 'f32', _never), ('field_of_view', 'f32', _never)]},
        'pixy/blocks': {
            'make': blocks, 'stamp_header': hdr, 'stamp': ('old', 'future', 'zero', 'max'),
            'fields': [('points[0].x', 'f32', _nonfinite), ('points[0].y', 'f32', _nonfinite),
                       ('points[0].z', 'f32', _never),
                       ('channels[1].values[0]', 'f32', _nonfinite),
                       ('channels[2].values[0]', 'f32', _nonfinite),
                       ('channels[0].values[0]', 'f32', _never)],
            'struct': {'drop_channel': (drop_channel, True),
                       'short_channel': (short_channel, True),
                       'oversized_malformed': (oversized, True),
                       'empty': (empty_cloud, False)}},
    }
    # a position sample only reaches the estimator as an odom + velocity pair of one stamp
    return plans, {'imu': imu, 'odom': odom, 'velocity': velocity, 'range': rng,
                   'blocks': blocks}


def test_apron_estimator_survives_fuzzed_inputs(ros_context):
    from apron_estimator.node import ApronEstimatorNode
    from deckland_common.messages import apron_state_from_msg
    from deckland_common.ros_node import RELIABLE_QOS
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped, TwistStamped, Vector3Stamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, PointCloud, Range
    from std_msgs.msg import Bool

    from deckland_interfaces.msg import ApronState as ApronStateMsg

    context, _ = ros_context
    ns = f'/fuzz_apron_{next(_NS)}'
    node = ApronEstimatorNode(context=context, namespace=ns)
    q = RELIABLE_QOS
    rig = Rig(context, node, ns,
              inputs={'vehicle/imu': (Imu, q), 'vehicle/odom': (Odometry, q),
                      'vehicle/velocity': (TwistStamped, q), 'vehicle/range': (Range, q),
                      'pixy/blocks': (PointCloud, q)},
              outputs={'apron/state': (ApronStateMsg, q), 'apron/odom': (Odometry, q),
                       'apron/relative': (PointStamped, q),
                       'apron/relative_velocity': (Vector3Stamped, q),
                       'apron/visible': (Bool, q), 'diagnostics': (DiagnosticArray, q)},
              inf_ok=lambda topic, path, v: topic == 'apron/state'
              and path == 'time_since_seen_s')
    try:
        rig.wait_matched()
        plans, make = apron_plans()

        def valid_frame():
            t = now_of(rig)
            for topic, key in (('vehicle/imu', 'imu'), ('vehicle/odom', 'odom'),
                               ('vehicle/velocity', 'velocity'), ('vehicle/range', 'range'),
                               ('pixy/blocks', 'blocks')):
                rig.send(topic, make[key](t))
            return t

        def rejected():
            return total(node.rejected, node.estimator.rejected)

        # a NaN position paired with its velocity (same stamp) reaches the core: counted
        for field in ('x', 'z'):
            valid_frame()
            t = now_of(rig)
            od, vel = make['odom'](t), make['velocity'](t)
            setattr(od.pose.pose.position, field, NAN)
            before = rejected()
            rig.send('vehicle/odom', od)
            rig.send('vehicle/velocity', vel)
            assert rejected() > before
        stats = run_fuzz(rig, plans, valid_frame, rejected, n_examples=30)
        assert stats['must_reject'] >= 20, stats
        assert node.rejected['malformed_cloud'] > 0 and node.rejected['stale_stamp'] > 0
        assert node.rejected['future_stamp'] > 0 and node.rejected['non_finite'] > 0

        # valid input afterwards: the beacon at the image centre is straight below, 2 m down
        rig.clear()

        def converged():
            valid_frame()
            rig.spin(0.02)
            msg = rig.last('apron/state')
            if msg is None:
                return False
            s, _, _ = apron_state_from_msg(msg)
            return (s is not None and s.tracked and s.vertical.valid
                    and abs(s.vertical.height_m - 2.0) < 0.05
                    and max(map(abs, s.rel_position_m)) < 0.02
                    and abs(s.apron_position_m[0] - 3.0) < 0.02
                    and abs(s.apron_position_m[1] + 1.0) < 0.02)
        assert rig.spin_until(converged, 6.0), rig.last('apron/state')
        od = rig.last('apron/odom')
        assert od is not None and od.pose.pose.position.x == pytest.approx(3.0, abs=0.02)
        rig.check_clean()
    finally:
        rig.close()


# --------------------------------------------------------------------------- apron/state

#: the float fields of deckland_interfaces/ApronState the consumers decode, and those each
#: consumer reads (an inf there must be refused; NaN in any decoded field is)
APRON_FIELDS = ('time_since_seen_s', 'rel_position_m[0]', 'rel_position_m[1]',
                'rel_velocity_mps[0]', 'rel_velocity_mps[1]', 'rel_position_cov_m2[0]',
                'rel_position_cov_m2[1]', 'rel_position_cov_m2[3]', 'rel_position_body_m[0]',
                'rel_position_body_m[1]', 'rel_velocity_body_mps[0]',
                'rel_velocity_body_mps[1]', 'apron_position_m[0]', 'apron_position_m[1]',
                'apron_velocity_mps[0]', 'apron_velocity_mps[1]', 'vertical.height_m',
                'vertical.closing_speed_mps', 'vertical.vehicle_altitude_m',
                'vertical.vehicle_vz_mps', 'vertical.surface_height_m',
                'vertical.surface_vz_mps', 'vertical.surface_accel_mps2',
                'vertical.last_rebase_m')
PLANNER_READS = frozenset({'rel_position_m[0]', 'rel_position_m[1]', 'apron_position_m[0]',
                           'apron_position_m[1]', 'apron_velocity_mps[0]',
                           'apron_velocity_mps[1]', 'vertical.height_m',
                           'vertical.closing_speed_mps', 'vertical.surface_height_m',
                           'vertical.last_rebase_m'})
DOB_READS = frozenset({'vertical.height_m', 'vertical.closing_speed_mps',
                       'vertical.vehicle_altitude_m', 'vertical.vehicle_vz_mps',
                       'vertical.surface_accel_mps2'})


def apron_state_plan(reads, height_m=2.0, z_m=2.0):
    from deckland_common.contract import ApronState, VerticalState
    from deckland_common.messages import fill_apron_state

    from deckland_interfaces.msg import ApronState as ApronStateMsg

    def make(t):
        vert = VerticalState(True, height_m, 0.0, z_m, 0.0, z_m - height_m, 0.0, 0.0, 0, 0.0)
        st_ = ApronState(t, False, False, math.inf, (0.0, 0.0), (0.0, 0.0), (0.0, 0.0),
                         (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), vert)
        return fill_apron_state(ApronStateMsg(), st_)

    def rule(path):
        return lambda v: math.isnan(v) or (math.isinf(v) and path in reads)

    def rivals(m):   # extra content nobody decodes yet: ignored, not an error
        from deckland_interfaces.msg import Rival
        m.rivals = [Rival(offset_m=(0.6, 0.0), hits=3)] * 5

    return {'make': make, 'stamp_header': lambda m: m.header,
            'stamp': ('old', 'future', 'zero', 'max'),
            'fields': [(p, 'f64', rule(p)) for p in APRON_FIELDS],
            'struct': {'rivals': (rivals, False)}}


def quaternion_rule(component):
    """Must the node refuse q with this component replaced (|‖q‖ − 1| > 0.05 or non-finite)?"""
    def rule(v):
        w, x = (v, 0.0) if component == 'w' else (1.0, v)
        n = math.sqrt(w * w + x * x) if math.isfinite(v) else math.inf
        return not abs(n - 1.0) <= 0.05
    return rule


def imu_plan(rule_for_accel=_never):
    from sensor_msgs.msg import Imu

    def make(t):
        m = Imu()
        stamp(m.header, t)
        m.header.frame_id = 'base_link'
        m.orientation.w = 1.0
        m.linear_acceleration.z = G
        return m

    def no_orientation(m):
        m.orientation_covariance[0] = -1.0

    return {'make': make, 'stamp_header': lambda m: m.header,
            'stamp': ('old', 'future', 'zero', 'max', 'backwards'),
            'fields': [('orientation.w', 'f64', quaternion_rule('w')),
                       ('orientation.x', 'f64', quaternion_rule('x')),
                       ('orientation.y', 'f64', quaternion_rule('x')),
                       ('linear_acceleration.z', 'f64', rule_for_accel),
                       ('angular_velocity.z', 'f64', _never),
                       ('orientation_covariance[0]', 'f64', lambda v: v == -1.0)],
            'struct': {'no_orientation': (no_orientation, True)}}


def call_trigger(rig, client, timeout_s=3.0):
    from std_srvs.srv import Trigger
    assert rig.spin_until(lambda: client.service_is_ready(), timeout_s)
    future = client.call_async(Trigger.Request())
    assert rig.spin_until(future.done, timeout_s)
    return future.result()


# --------------------------------------------------------------------------- landing_planner

def test_landing_planner_survives_fuzzed_inputs(ros_context):
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, QuaternionStamped, TwistStamped
    from landing_planner.node import LandingPlannerNode
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from std_msgs.msg import Bool, String
    from std_srvs.srv import Trigger

    from deckland_interfaces.msg import ApronState as ApronStateMsg
    from deckland_interfaces.msg import PlannerReference

    context, _ = ros_context
    ns = f'/fuzz_planner_{next(_NS)}'
    node = LandingPlannerNode(context=context, namespace=ns, parameter_overrides=[
        Parameter('landing_area_x_m', value=5.0), Parameter('landing_area_y_m', value=0.0),
        Parameter('xy_ki', value=0.0)])
    q = RELIABLE_QOS
    rig = Rig(context, node, ns,
              inputs={'apron/state': (ApronStateMsg, q), 'vehicle/odom': (Odometry, q),
                      'vehicle/velocity': (TwistStamped, q)},
              outputs={'control/attitude': (QuaternionStamped, q),
                       'planner/reference': (PlannerReference, q),
                       'planner/setpoint': (PoseStamped, q), 'planner/mode': (String, LATCHED_QOS),
                       'control/enabled': (Bool, LATCHED_QOS),
                       'diagnostics': (DiagnosticArray, q)})
    start = rig.helper.create_client(Trigger, 'planner/start_landing')
    try:
        rig.wait_matched()

        def odom(t):
            m = Odometry()
            stamp(m.header, t)
            m.header.frame_id, m.child_frame_id = 'map', 'base_link'
            m.pose.pose.position.z = 2.0
            m.pose.pose.orientation.w = 1.0
            return m

        def velocity(t):
            m = TwistStamped()
            stamp(m.header, t)
            m.header.frame_id = 'map'
            return m

        def wrong_frame(m):
            m.header.frame_id = 'odom'

        stamps = ('old', 'future', 'zero', 'max', 'backwards')
        plans = {
            'apron/state': apron_state_plan(PLANNER_READS),
            'vehicle/odom': {
                'make': odom, 'stamp_header': lambda m: m.header, 'stamp': stamps,
                'fields': [('pose.pose.position.x', 'f64', _nonfinite),
                           ('pose.pose.position.z', 'f64', _nonfinite),
                           ('pose.pose.orientation.w', 'f64', quaternion_rule('w')),
                           ('pose.pose.orientation.z', 'f64', quaternion_rule('x')),
                           ('twist.twist.linear.x', 'f64', _never),
                           ('pose.covariance[35]', 'f64', _never)],
                'struct': {'wrong_frame': (wrong_frame, True)}},
            'vehicle/velocity': {
                'make': velocity, 'stamp_header': lambda m: m.header, 'stamp': stamps,
                'fields': [('twist.linear.x', 'f64', _nonfinite),
                           ('twist.linear.z', 'f64', _nonfinite),
                           ('twist.angular.z', 'f64', _never)],
                'struct': {'wrong_frame': (wrong_frame, True)}},
        }

        def valid_frame():
            t = now_of(rig)
            rig.send('vehicle/odom', odom(t))
            rig.send('vehicle/velocity', velocity(t))
            rig.send('apron/state', plans['apron/state']['make'](t))
            return t

        stats = run_fuzz(rig, plans, valid_frame, lambda: total(node.rejected), n_examples=30)
        assert stats['must_reject'] >= 20, stats
        for key in ('non_finite', 'bad_frame', 'out_of_order', 'future_stamp',
                    'bad_quaternion'):
            assert node.rejected[key] > 0, (key, node.rejected)
        assert rig.out['control/attitude'], 'no command while fed valid frames'

        # valid input afterwards: start landing toward an area 5 m east of a vehicle at rest
        # at the origin: APPROACH, nose down (pitch > 0, within the tilt limit), no roll
        res = call_trigger(rig, start)
        assert res.success, res.message
        rig.clear()
        assert rig.spin_until(lambda: (valid_frame(), rig.spin(0.01),
                                       len(rig.out['control/attitude']) > 20)[-1], 5.0)
        assert node.planner.mode.name == 'APPROACH'
        for msg in rig.out['control/attitude'][-10:]:
            qq = msg.quaternion
            roll = math.atan2(2.0 * (qq.w * qq.x + qq.y * qq.z),
                              1.0 - 2.0 * (qq.x * qq.x + qq.y * qq.y))
            pitch = math.asin(max(-1.0, min(1.0, 2.0 * (qq.w * qq.y - qq.z * qq.x))))
            assert abs(roll) < 1e-6 and 0.0 < pitch <= node.horizontal.params.max_tilt_rad + 1e-9
        ref = rig.out['planner/reference'][-1]
        assert ref.setpoint_m[0] > 0.0 and ref.velocity_ff_mps[0] > 0.0
        rig.check_clean()
    finally:
        rig.helper.destroy_client(start)
        rig.close()


# --------------------------------------------------------------------------- dob_altitude

def test_dob_altitude_survives_fuzzed_inputs(ros_context):
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    from diagnostic_msgs.msg import DiagnosticArray
    from dob_altitude.node import DobAltitudeNode
    from geometry_msgs.msg import WrenchStamped
    from sensor_msgs.msg import Imu
    from std_msgs.msg import Bool

    from deckland_interfaces.msg import AltitudeState, PlannerReference
    from deckland_interfaces.msg import ApronState as ApronStateMsg

    context, _ = ros_context
    ns = f'/fuzz_dob_{next(_NS)}'
    node = DobAltitudeNode(context=context, namespace=ns)
    q = RELIABLE_QOS
    rig = Rig(context, node, ns,
              inputs={'apron/state': (ApronStateMsg, q),
                      'planner/reference': (PlannerReference, q),
                      'vehicle/imu': (Imu, q), 'control/enabled': (Bool, LATCHED_QOS)},
              outputs={'control/thrust': (WrenchStamped, q),
                       'altitude/state': (AltitudeState, q),
                       'diagnostics': (DiagnosticArray, q)})
    try:
        rig.wait_matched()

        def reference(t):
            m = PlannerReference()
            stamp(m.header, t)
            m.header.frame_id = 'map'
            m.vertical_frame = PlannerReference.VERTICAL_RELATIVE
            m.z_d_m = 2.0
            m.thrust_enabled = True
            return m

        def bad_frame(m):
            m.vertical_frame = 7

        stamps = ('old', 'future', 'zero', 'max', 'backwards')
        plans = {
            'apron/state': apron_state_plan(DOB_READS, height_m=1.8),
            'planner/reference': {
                'make': reference, 'stamp_header': lambda m: m.header, 'stamp': stamps,
                'fields': [('z_d_m', 'f64', _nonfinite), ('z_d_dot_mps', 'f64', _nonfinite),
                           ('z_d_ddot_mps2', 'f64', _nonfinite),
                           ('setpoint_m[0]', 'f64', _never), ('yaw_rad', 'f64', _never)],
                'struct': {'bad_frame': (bad_frame, True)}},
            'vehicle/imu': imu_plan(),
        }
        # the apron state's t_s must also strictly increase (a repeat is refused)
        plans['apron/state']['struct']['repeat'] = (lambda m: None, False)

        def valid_frame():
            t = now_of(rig)
            rig.send('vehicle/imu', plans['vehicle/imu']['make'](t))
            rig.send('planner/reference', reference(t))
            rig.send('apron/state', plans['apron/state']['make'](t))
            return t

        rig.send('control/enabled', Bool(data=True))
        stats = run_fuzz(rig, plans, valid_frame, lambda: total(node.rejected), n_examples=30)
        assert stats['must_reject'] >= 20, stats
        for key in ('non_finite', 'out_of_order', 'future_stamp', 'bad_frame',
                    'bad_quaternion'):
            assert node.rejected[key] > 0, (key, node.rejected)
        assert rig.out['control/thrust'], 'no thrust while fed valid frames'

        # Valid input afterwards: hovering 0.2 m below the reference at rest (e_z = -0.2,
        # e_dot = 0, level, free air). The DOB keeps memory: the fuzz's finite-but-absurd
        # inputs (e.g. closing speed or z_d_dot = +-1e308, which the contract accepts) drive
        # d_hat of (18) to its +-2 g clamp, and it relaxes only at ~Gamma K |sigma| ~ 3 m/s^2
        # per second. So "thrust > m g" right after the fuzz depends on how long the fuzz took
        # (this was the flaky failure). What must hold at once is law (16) with the published
        # sigma and d_hat, d_hat within its bound, and the limits.
        from dob_altitude.ground_effect import ground_effect_gain
        cp = node.controller.params
        mg = cp.mass_kg * cp.gravity_mps2
        gbar = ground_effect_gain(cp.rho_bar, cp.prop_radius_m, 1.8 + 0.05,
                                  cp.ge_min_rotor_height_m, cp.ge_max_gain)

        def law_16(sigma, d_hat):
            u = cp.mass_kg / gbar * (-cp.k * sigma + cp.gravity_mps2 - d_hat)   # zeta = 0
            return min(max(u, cp.thrust_min_n), cp.thrust_max_n)

        def commands():
            obs = {(o.header.stamp.sec, o.header.stamp.nanosec): o
                   for o in rig.out['altitude/state']}
            return [(m.wrench.force.z, obs.get((m.header.stamp.sec, m.header.stamp.nanosec)))
                    for m in rig.out['control/thrust']]

        rig.clear()
        assert rig.spin_until(lambda: (valid_frame(), rig.spin(0.01),
                                       len(rig.out['control/thrust']) > 10)[-1], 5.0)
        sigma_expected = -cp.lam * 0.2 / math.sqrt(0.04 + 1.0)                    # (14)
        checked = 0
        for thrust, ob in commands()[-5:]:
            if ob is None:
                continue
            assert ob.e_z_m == pytest.approx(-0.2, abs=1e-6)                      # (7)
            assert ob.sigma == pytest.approx(sigma_expected, rel=1e-9)
            assert abs(ob.d_hat_mps2) <= cp.d_hat_limit_mps2 + 1e-9
            assert thrust == pytest.approx(law_16(ob.sigma, ob.d_hat_mps2), rel=1e-9)
            assert ob.z_m == pytest.approx(1.8) and ob.z_d_m == pytest.approx(2.0)
            assert ob.thrust_n == thrust and ob.controller == ob.CONTROLLER_DOB
            checked += 1
        assert checked >= 3

        # A fresh controller (control/enabled False -> True resets it) starts with d_hat = 0:
        # 0.2 m below the reference at rest, (16) asks for more than m g; the vehicle does not
        # respond (nothing moves in this rig), so d_hat only falls and the thrust only rises
        # (to at most thrust_max_n).
        rig.send('control/enabled', Bool(data=False))
        rig.spin(0.02)
        rig.send('control/enabled', Bool(data=True))
        rig.clear()
        assert rig.spin_until(lambda: (valid_frame(), rig.spin(0.01),
                                       len(rig.out['control/thrust']) > 10)[-1], 5.0)
        cmds = commands()
        assert cmds[0][1] is not None and cmds[0][1].d_hat_mps2 == 0.0  # start-up: d_hat = 0
        assert cmds[0][0] == pytest.approx(law_16(sigma_expected, 0.0), rel=1e-9)
        thrusts = [t for t, _ in cmds]
        for a, b in itertools.pairwise(thrusts):
            assert b >= a - 1e-9
        for t in thrusts:
            assert mg < t <= cp.thrust_max_n
        rig.check_clean()
    finally:
        rig.close()


# --------------------------------------------------------------------------- pixy_driver

PIXY_ERRORS = ('checksum_errors', 'out_of_range', 'resyncs', 'bytes_dropped', 'orphan_blocks',
               'overflow_blocks', 'bad_input')


def _pixy_datagrams():
    """Random bytes, and valid frames cut short, bit-flipped, repeated or glued to garbage."""
    from pixy_driver.protocol import encode_frame

    block = st.tuples(st.integers(1, 7), st.integers(0, 319), st.integers(0, 199),
                      st.integers(1, 320), st.integers(1, 200))
    frame = st.lists(block, min_size=1, max_size=5).map(encode_frame)

    def flip(args):
        data, i, bit = args
        b = bytearray(data)
        k = len(b) - 1 - (i % 10)          # a byte of the last block's five data words
        b[k] ^= 1 << bit
        return ('corrupt', bytes(b))

    return st.one_of(
        st.binary(max_size=600).map(lambda d: ('random', d)),
        st.tuples(frame, st.integers(1, 40)).map(lambda a: ('truncated', a[0][:-a[1]])),
        st.tuples(frame, st.integers(0, 1000), st.integers(0, 7)).map(flip),
        st.tuples(st.binary(min_size=1, max_size=50), frame).map(
            lambda a: ('garbage_prefix', a[0] + a[1])),
        st.sampled_from([('syncs', b'\x55\xaa' * 300), ('zeros', bytes(512)),
                         ('swapped_sync', b'\xaa\x55' * 100), ('huge', b'\xff' * 60_000),
                         ('empty_frame', encode_frame([])), ('one_byte', b'\x55')]))


@pytest.mark.parametrize('datagram_is_frame', [True, False])
def test_pixy_driver_survives_random_datagrams(ros_context, datagram_is_frame):
    from deckland_common.ros_node import RELIABLE_QOS
    from diagnostic_msgs.msg import DiagnosticArray
    from pixy_driver.node import PixyDriverNode
    from pixy_driver.protocol import encode_frame
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud

    context, _ = ros_context
    ns = f'/fuzz_pixy_{next(_NS)}'
    node = PixyDriverNode(context=context, namespace=ns, parameter_overrides=[
        Parameter('transport', value='udp'), Parameter('udp_port', value=0),
        Parameter('udp_datagram_is_frame', value=datagram_is_frame),
        Parameter('diagnostics_period_s', value=0.2)])
    thread_errors = []
    handle = node._handle

    def checked_handle(data):   # the reader thread swallows exceptions: record them
        try:
            handle(data)
        except Exception:
            thread_errors.append(traceback.format_exc())
            raise

    node._handle = checked_handle
    q = RELIABLE_QOS
    rig = Rig(context, node, ns, inputs={},
              outputs={'pixy/blocks': (PointCloud, q), 'pixy/diagnostics': (DiagnosticArray, q)})
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = ('127.0.0.1', node.udp_port_bound)
    stats = collections.Counter()

    def send(data):
        n0 = node.parser.bytes_in
        tx.sendto(data, addr)
        assert rig.spin_until(lambda: node.parser.bytes_in >= n0 + len(data), 2.0)

    def errors():
        s = node.parser.stats()
        return sum(s[k] for k in PIXY_ERRORS)

    try:
        rig.wait_matched()

        @settings(max_examples=60, **FUZZ_SETTINGS)
        @given(batch=st.lists(_pixy_datagrams(), min_size=1, max_size=5))
        def one_batch(batch):
            for kind, data in batch:
                before = errors()
                send(data)
                stats[kind] += 1
                if kind == 'corrupt' and datagram_is_frame:
                    assert errors() > before, 'corrupted block not counted'
            rig.spin(0.005)
            assert not thread_errors, thread_errors[0]
            rig.check_clean()

        one_batch()
        assert stats['corrupt'] > 0 and stats['random'] > 0
        assert node.parser.checksum_errors > 0 and errors() > 0
        for msg in rig.out['pixy/blocks']:    # whatever got through is a well-formed frame
            ch = {c.name: list(c.values) for c in msg.channels}
            assert sorted(ch) == ['height', 'signature', 'width']
            assert all(len(v) == len(msg.points) for v in ch.values())
            assert all(0 <= p.x <= 319 and 0 <= p.y <= 199 for p in msg.points)

        # valid frames afterwards come out exactly (stream mode: a frame ends at the next one)
        rig.clear()
        frame = encode_frame([(1, 160, 100, 12, 10), (2, 5, 7, 3, 4)])
        for _ in range(3):
            send(frame)
        assert rig.spin_until(lambda: len(rig.out['pixy/blocks']) >= 2, 3.0)
        msg = rig.out['pixy/blocks'][-1]
        ch = {c.name: list(c.values) for c in msg.channels}
        got = [(int(s), int(p.x), int(p.y), int(w), int(h)) for p, s, w, h in
               zip(msg.points, ch['signature'], ch['width'], ch['height'], strict=True)]
        assert got == [(1, 160, 100, 12, 10), (2, 5, 7, 3, 4)]
        assert rig.spin_until(lambda: rig.out['pixy/diagnostics'], 2.0)
        diag = {kv.key: kv.value for kv in rig.out['pixy/diagnostics'][-1].status[0].values}
        assert int(diag['checksum_errors']) > 0
        rig.check_clean()
        assert not thread_errors, thread_errors[0]
    finally:
        tx.close()
        rig.close()


# --------------------------------------------------------------------------- deck_simulator

def _free_udp_socket():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', 0))
    s.setblocking(False)
    return s


def test_deck_simulator_survives_bad_modes_and_mavlink_garbage(ros_context):
    from deck_simulator.node import DeckSimulatorNode
    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS
    from nav_msgs.msg import Odometry
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    context, _ = ros_context
    ns = f'/fuzz_sim_{next(_NS)}'
    pixy_sink = _free_udp_socket()         # the simulated Pixy's datagrams land here
    probe = _free_udp_socket()
    mav_port = probe.getsockname()[1]
    probe.close()
    node = DeckSimulatorNode(context=context, namespace=ns, parameter_overrides=[
        Parameter('mavlink_url', value=f'udpin:127.0.0.1:{mav_port}'),
        Parameter('pixy_udp_port', value=pixy_sink.getsockname()[1])])
    rig = Rig(context, node, ns, inputs={'planner/mode': (String, LATCHED_QOS)},
              outputs={'sim/truth/vehicle': (Odometry, RELIABLE_QOS),
                       'sim/truth/apron': (Odometry, RELIABLE_QOS),
                       'sim/outcome': (String, LATCHED_QOS)})
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rig.wait_matched()
        modes = st.one_of(st.text(max_size=40), st.sampled_from(
            ['', '   ', '\n', 'x' * 100_000, 'ΔESCEND', 'search', ' SEARCH ', 'NaN', 'inf']))
        mav = st.one_of(st.binary(max_size=300),
                        st.binary(max_size=300).map(lambda d: b'\xfd' + d),   # MAVLink 2 STX
                        st.binary(max_size=300).map(lambda d: b'\xfe' + d))   # MAVLink 1 STX

        @settings(max_examples=40, **FUZZ_SETTINGS)
        @given(mode=modes, garbage=st.lists(mav, max_size=4))
        def one(mode, garbage):
            before = node.sim.rejected['bad_mode']
            rig.send('planner/mode', String(data=mode))
            if not mode.strip():
                assert node.sim.rejected['bad_mode'] == before + 1
            for data in garbage:
                tx.sendto(data, ('127.0.0.1', mav_port))
            rig.spin(0.01)
            rig.check_clean()
            assert node.thread_errors == 0

        one()
        assert rig.spin_until(lambda: node.emulator.rejected['bad_data'] > 0, 2.0)
        assert node.sim.rejected['bad_mode'] > 0
        # the world still runs and the mode still counts: a search entry and a trigger
        rig.clear()
        searches = node.sim.searches
        rig.send('planner/mode', String(data='HOLD'))
        rig.send('planner/mode', String(data='SEARCH'))
        assert node.sim.searches == searches + 1 and node.sim.trigger_t_s is not None
        assert rig.spin_until(lambda: len(rig.out['sim/truth/vehicle']) > 5, 3.0)
        for text in [m.data for m in rig.out['sim/outcome']]:
            assert 'NaN' not in text and 'Infinity' not in text
            json.loads(text)
        rig.check_clean()
        assert node.thread_errors == 0
    finally:
        tx.close()
        pixy_sink.close()
        rig.close()
