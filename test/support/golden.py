"""Golden-bag regression (test tooling): record a reference ``paper`` landing, replay, compare.

``python test/support/golden.py record DIR`` (``make golden``) flies one landing with the real node
graph and writes a small rosbag2 MCAP bag plus ``DIR/golden.yaml``; regenerating it is
deliberate. :func:`replay_cores` feeds the recorded inputs in bag order through the nodes'
loop cores (``apron_estimator.loop``, ``landing_planner.loop``, ``dob_altitude.loop``), no
rclpy; :func:`replay_nodes` plays them into the three nodes over DDS. :func:`compare` matches
outputs by stamp against :data:`CORE_TOLERANCES` / :data:`NODE_TOLERANCES`. Tolerances and the
reasons behind them: ``src/deckland/README-golden.md``.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
import math
import os
from pathlib import Path
import random
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

from deckland_common.contract import VehicleDescription
from deckland_common.messages import apron_state_from_msg, vertical_frame_name
from deckland_common.stats import percentile
import yaml

#: Inputs of the three nodes (the replay feeds these) and the landing trigger's witness.
INPUT_TOPICS = ('/pixy/blocks', '/vehicle/imu', '/vehicle/odom', '/vehicle/velocity',
                '/vehicle/range', '/vehicle/landed', '/planner/mode')
#: Recorded outputs the replays compare against.
OUTPUT_TOPICS = ('/apron/state', '/planner/reference', '/control/attitude', '/control/thrust',
                 '/altitude/state', '/control/enabled')
#: The outputs of a bag recorded before the typed interfaces (``altitude/observer``).
LEGACY_OUTPUT_TOPICS = tuple('/altitude/observer' if t == '/altitude/state' else t
                             for t in OUTPUT_TOPICS)
#: Topics played into the nodes by :func:`replay_nodes` (``planner/mode`` is the planner's
#: own output: the trigger is a service call instead).
PLAY_TOPICS = ('/pixy/blocks', '/vehicle/imu', '/vehicle/odom', '/vehicle/velocity',
               '/vehicle/range', '/vehicle/landed')
META_NAME = 'golden.yaml'
META_VERSION = 1
DEFAULT_SCENARIO = 'paper'
DEFAULT_SEED = 7
#: ``apron_estimator`` ``clock`` of the recording (see :func:`record`)
GOLDEN_ESTIMATOR_CLOCK = 'imu'
MAX_BAG_BYTES = 3 * 1024 * 1024

#: Node-level parameters the replay mirrors (defaults of the nodes' PARAMS; the test
#: ``system/test_golden_cores.py::test_node_defaults_mirrored`` checks them against the nodes).
NODE_DEFAULTS: dict[str, dict[str, Any]] = {
    'apron_estimator': {'rate_hz': 100.0, 'input_timeout_s': 0.5, 'gravity_mps2': 9.81,
                        'position_pair_tolerance_s': 0.005},
    'landing_planner': {'rate_hz': 100.0, 'input_timeout_s': 0.3, 'map_frame': 'map',
                        'landing_area_x_m': 0.0, 'landing_area_y_m': 0.0},
    'dob_altitude': {'controller': 'dob', 'gains_profile': 'default',
                     'mass_kg': VehicleDescription().mass_kg,
                     'thrust_min_n': 2.66, 'thrust_max_n': 53.17,
                     'rotor_height_offset_m': 0.05, 'surface_accel_feedforward': False,
                     'rate_hz': 100.0, 'input_timeout_s': 0.2},
}


# ======================================================================== tolerances


@dataclass(frozen=True, slots=True)
class Tolerances:
    """Allowed differences replay − recorded (README-golden.md explains every number).

    The first number of each pair bounds the ``quantile`` (0.99) of the absolute error over
    all matched samples,
    ``*_max`` the worst sample (a rare ordering race may move one sample further);
    ``min_matched`` is the fraction of recorded samples that must find a replayed one.
    """

    apron_pos_m: tuple[float, float]        # rel/apron positions (p99, max)
    apron_vel_mps: tuple[float, float]      # rel/apron velocities
    height_m: tuple[float, float]           # vertical heights / altitudes
    vspeed_mps: tuple[float, float]         # vertical speeds
    ref_z_m: tuple[float, float]            # z_d
    ref_z_dot_mps: tuple[float, float]      # ż_d, and the feed-forward velocities
    ref_xy_m: tuple[float, float]           # horizontal setpoint
    attitude_rad: tuple[float, float]       # roll/pitch/yaw command
    thrust_n: tuple[float, float]           # u_z
    observer: tuple[float, float]           # σ and d̂ (e_z uses ref_z_m)
    min_matched: float
    stamp_s: float = 0.0                    # match window of stamps (node replay only)
    quantile: float = 0.99                  # the quantile the first bound applies to


#: Pure replay: the same code on the same inputs. What is left comes from timing the bag does
#: not record exactly: which lidar/odometry sample the estimator had when it published (the
#: alignment picks the IMU/camera trigger, not the samples in between), the planner's clock
#: (its ``now`` is approximated by the recorder's receive time: the reference generator and
#: the horizontal PID see dt jitter of a few ms, and a mode change may move by one tick).
#: Measured on the shipped bag: README-golden.md, "Tolerances".
CORE_TOLERANCES = Tolerances(
    apron_pos_m=(2e-3, 0.15), apron_vel_mps=(1e-2, 0.4), height_m=(1e-3, 0.05),
    vspeed_mps=(2e-2, 0.2), ref_z_m=(3e-3, 1e-2), ref_z_dot_mps=(5e-3, 2e-2),
    ref_xy_m=(1e-2, 3e-2), attitude_rad=(1e-2, 0.12), thrust_n=(5e-2, 0.3),
    observer=(1e-2, 5e-2), min_matched=0.99)

#: Node replay through DDS at rate 1.0: every output is stamped with the node's wall clock,
#: so samples pair only to the nearest stamp (± 10 ms) and each node handles its inputs in
#: whatever order and bunching the executor delivers them; the planner's mode changes may
#: move by a few ticks. Only the 90th percentile is bounded: the worst samples sit where one
#: tick of timing moves a step (the surface re-base at the deck edge moves h and e_z by the
#: deck's height and the thrust by tens of newtons for a tick or two). The bounds catch a
#: wrong sign, a lost stage or a grossly changed gain, not a subtle one (the pure replay's
#: job).
_INF = math.inf
NODE_TOLERANCES = Tolerances(
    apron_pos_m=(0.1, _INF), apron_vel_mps=(0.3, _INF), height_m=(5e-2, _INF),
    vspeed_mps=(0.3, _INF), ref_z_m=(5e-2, _INF), ref_z_dot_mps=(0.1, _INF),
    ref_xy_m=(0.15, _INF), attitude_rad=(8e-2, _INF), thrust_n=(8.0, _INF),
    observer=(4.0, _INF), min_matched=0.4, stamp_s=0.02, quantile=0.9)


# ================================================================= reading (pure, rosbags)


@dataclass(frozen=True, slots=True)
class Event:
    """One bag message decoded to plain numbers: ``kind`` and a tuple of fields."""

    t_ns: int          # bag (receive) time
    kind: str
    data: tuple


def _stamp(h: Any) -> float:
    return h.stamp.sec + h.stamp.nanosec * 1e-9


def _decode(topic: str, m: Any) -> tuple[str, tuple] | None:
    """rosbags message → (kind, fields); the field order is what the replays read."""
    if topic == '/vehicle/imu':
        o, a = m.orientation, m.linear_acceleration
        return 'imu', (_stamp(m.header), (o.w, o.x, o.y, o.z),
                       float(m.orientation_covariance[0]), (a.x, a.y, a.z))
    if topic == '/vehicle/odom':
        p, q = m.pose.pose.position, m.pose.pose.orientation
        return 'odom', (_stamp(m.header), m.header.frame_id, (p.x, p.y, p.z),
                        (q.w, q.x, q.y, q.z))
    if topic == '/vehicle/velocity':
        v = m.twist.linear
        return 'velocity', (_stamp(m.header), m.header.frame_id, (v.x, v.y, v.z))
    if topic == '/vehicle/range':
        return 'range', (_stamp(m.header), float(m.range), float(m.min_range),
                         float(m.max_range))
    if topic == '/pixy/blocks':
        return 'blocks', (_stamp(m.header), [p.x for p in m.points], [p.y for p in m.points],
                          {c.name: [float(v) for v in c.values] for c in m.channels})
    if topic == '/vehicle/landed':
        return 'landed', (bool(m.data),)
    if topic == '/planner/mode':
        return 'mode', (str(m.data),)
    if topic == '/control/enabled':
        return 'enabled', (bool(m.data),)
    if topic in _LEGACY:
        legacy = _decode_legacy(topic, m)
        if legacy is not None:
            return legacy
    if topic == '/apron/state':
        st, _, detail = apron_state_from_msg(m)
        if st is None:
            raise ValueError(f'golden: undecodable {detail}')
        # the v1 array for the comparisons, and the whole state (deck source, acceleration,
        # attitude: fields the v1 array has no room for) for the planner the replay steps
        return 'apron', (tuple(st.to_array()), '', st)
    if topic == '/planner/reference':
        sp, ff = m.setpoint_m, m.velocity_ff_mps
        return 'reference', (_stamp(m.header), vertical_frame_name(m.vertical_frame),
                             (float(sp[0]), float(sp[1]), m.z_d_m),
                             (float(ff[0]), float(ff[1]), m.z_d_dot_mps), m.z_d_ddot_mps2,
                             m.yaw_rad)
    if topic == '/control/attitude':
        q = m.quaternion
        return 'attitude', (_stamp(m.header), (q.w, q.x, q.y, q.z))
    if topic == '/control/thrust':
        return 'thrust', (_stamp(m.header), float(m.wrench.force.z))
    if topic == '/altitude/state':
        return 'observer', (_stamp(m.header), (m.sigma, m.d_hat_mps2, m.e_z_m))
    return None


def _decode_legacy(topic: str, m: Any) -> tuple[str, tuple] | None:
    """Outputs of a bag recorded before the typed interfaces (Float64MultiArray apron state,
    MultiDOFJointTrajectory reference, Vector3Stamped observer), in the same shapes."""
    from deckland_common.frames import quaternion_to_euler

    if topic == '/altitude/observer':
        v = m.vector
        return 'observer', (_stamp(m.header), (v.x, v.y, v.z))
    if not hasattr(m, 'layout') and not hasattr(m, 'points'):
        return None                     # the typed message: the caller decodes it
    if topic == '/apron/state':
        label = m.layout.dim[0].label if len(m.layout.dim) else ''
        return 'apron', (tuple(float(x) for x in m.data), label)
    pt = m.points[0]
    tr, r = pt.transforms[0].translation, pt.transforms[0].rotation
    v, a = pt.velocities[0].linear, pt.accelerations[0].linear
    name = m.joint_names[0] if len(m.joint_names) else ''
    return 'reference', (_stamp(m.header), name, (tr.x, tr.y, tr.z), (v.x, v.y, v.z), a.z,
                         quaternion_to_euler(r.w, r.x, r.y, r.z)[2])


#: topics whose pre-interfaces encoding :func:`_decode_legacy` still reads (a golden bag
#: recorded before the switch replays until ``make golden`` re-records it)
_LEGACY = ('/altitude/observer', '/apron/state', '/planner/reference')


@dataclass
class Golden:
    """A golden bag read into memory: metadata and every event in bag order."""

    path: Path
    meta: dict[str, Any]
    events: list[Event]

    def of(self, kind: str) -> list[Event]:
        return [e for e in self.events if e.kind == kind]


def load(bag_dir: str | os.PathLike[str]) -> Golden:
    """Read ``DIR/golden.yaml`` and decode every message of the bag (rosbags, no rclpy)."""

    bag = Path(bag_dir)
    meta_path = bag / META_NAME
    if not meta_path.is_file():
        raise FileNotFoundError(f'{meta_path} missing: not a golden bag (make golden)')
    meta = yaml.safe_load(meta_path.read_text())
    if not isinstance(meta, dict) or meta.get('version') != META_VERSION:
        raise ValueError(f'{meta_path}: unsupported golden metadata version')
    return Golden(bag, meta, load_events(bag))


def load_events(bag_dir: str | os.PathLike[str]) -> list[Event]:
    """Every message of a bag the replays know, decoded, in bag order."""
    from rosbags.highlevel import AnyReader

    events = []
    with AnyReader([Path(bag_dir)]) as reader:
        for conn, t_ns, raw in reader.messages():
            decoded = _decode(conn.topic, reader.deserialize(raw, conn.msgtype))
            if decoded is not None:
                events.append(Event(t_ns, decoded[0], decoded[1]))
    return events


# ===================================================================== pure core replay


def node_params(meta: dict[str, Any], node: str) -> dict[str, Any]:
    """The effective parameters of ``node`` in the recording: defaults + recorded overrides."""
    values = dict(NODE_DEFAULTS[node])
    values.update((meta.get('parameters') or {}).get(node) or {})
    return values


def make_cores(meta: dict[str, Any]) -> tuple[Any, Any, Any, Any]:
    """(estimator, planner, horizontal controller, altitude controller) as the nodes build them.

    The estimator and the planner use their core defaults (the nodes' PARAMS are generated
    from them) plus the recorded overrides; the altitude controller is built by
    :func:`dob_altitude.adapter.make_controller` with the node's override rule.
    """
    from apron_estimator.estimator import ApronEstimator, EstimatorParams
    from dob_altitude.adapter import controller_overrides, make_controller
    from landing_planner.horizontal import HorizontalController, HorizontalParams
    from landing_planner.planner import LandingPlanner, PlannerParams

    pp = node_params(meta, 'landing_planner')
    dp = node_params(meta, 'dob_altitude')
    planner = LandingPlanner(PlannerParams(
        landing_area_m=(float(pp['landing_area_x_m']), float(pp['landing_area_y_m']))))
    controller = make_controller(dp['controller'], dp['gains_profile'],
                                 controller_overrides(dp))
    return (ApronEstimator(EstimatorParams()), planner, HorizontalController(HorizontalParams()),
            controller)


@dataclass
class Replay:
    """What a replay produced, keyed by the stamp the node would put on the message."""

    apron: dict[float, tuple[float, ...]] = field(default_factory=dict)
    reference: dict[float, tuple] = field(default_factory=dict)
    attitude: dict[float, tuple[float, float, float]] = field(default_factory=dict)
    thrust: dict[float, float] = field(default_factory=dict)
    observer: dict[float, tuple[float, float, float]] = field(default_factory=dict)
    modes: list[tuple[float, str]] = field(default_factory=list)
    rejected: dict[str, int] = field(default_factory=dict)
    notes: dict[str, int] = field(default_factory=dict)


def _count(d: dict[str, int], key: str, n: int = 1) -> None:
    if n:
        d[key] = d.get(key, 0) + n


def _feed_estimator(loop: Any, now: float, e: Event) -> None:
    """One decoded input event into the estimator node's loop core (as the node unpacks it)."""
    k, d = e.kind, e.data
    if k == 'imu':
        loop.on_imu(now, d[0], d[1], d[3], has_orientation=d[2] != -1.0)
    elif k == 'odom':
        loop.on_position(now, d[0], d[2])
    elif k == 'velocity':
        loop.on_velocity(now, d[0], d[2])
    elif k == 'range':
        loop.on_range(now, d[0], d[1], d[2], d[3])
    elif k == 'blocks':
        loop.on_blocks(now, d[0], d[1], d[2], d[3])


def _estimator_loop(est: Any, meta: dict[str, Any]) -> Any:
    from apron_estimator.loop import EstimatorLoop

    p = node_params(meta, 'apron_estimator')
    return EstimatorLoop(est, input_timeout_s=p['input_timeout_s'],
                         gravity_mps2=p['gravity_mps2'],
                         position_pair_tolerance_s=p['position_pair_tolerance_s'],
                         imu_min_spacing_s=0.5 / p['rate_hz'])


def _loop_rejections(out: Replay, prefix: str, loop: Any) -> None:
    for reason, n in loop.rejected.items():
        _count(out.rejected, f'{prefix}_{reason}', n)


_EST_KINDS = ('imu', 'odom', 'velocity', 'range', 'blocks')
#: Scale of each apron_state_v1 field in the alignment distance (m, m/s); flags weigh 100.
_ALIGN_SCALE = {5: 0.01, 6: 0.01, 7: 0.05, 8: 0.05, 20: 0.01, 21: 0.05, 22: 0.01, 23: 0.05,
                24: 0.01, 25: 0.05, 26: 0.5}
#: Most candidate positions tried per output (bounds the cost of a long backlog).
MAX_CANDIDATES = 8
#: An input that reached the recorder this much after the node's clock said ``t_s`` may
#: still have been handled before that state (the two processes receive independently).
ARRIVAL_SLACK_S = 0.002


def _align_distance(a: Sequence[float], b: Sequence[float]) -> float:
    d = sum(abs(a[i] - b[i]) / s for i, s in _ALIGN_SCALE.items())
    return d + 100.0 * sum((a[i] > 0.5) != (b[i] > 0.5) for i in (2, 3, 19))


def replay_estimator(golden: Golden, out: Replay | None = None, make: Any = None) -> Replay:
    """The estimator stage: recorded sensor inputs → ``apron/state`` at each recorded ``t_s``.

    The node handles its inputs in arrival order (≈ the bag's order) but may lag behind (a
    backlog under load), so the position in the input stream at which it published a state is
    reconstructed, never assumed from the bag time alone:

    * the state's own ``camera_stamp_s`` names the last camera frame the node had processed:
      that frame was fed, the next one was not;
    * an input that reached the recorder after the state's ``t_s`` (+ 2 ms) was not fed;
    * positions never go back, and a state is published right after an IMU message or a
      camera frame (the node's two triggers).

    Among the (≤ 8) positions left, the one whose predicted state is closest to the recorded
    one is taken (copies of the estimator are stepped for the alternatives). This picks *when*
    the node published, out of a few causal orderings; it cannot absorb a change of the
    estimator itself, which moves every candidate (README-golden.md, decision 2).
    """
    import copy

    out = out if out is not None else Replay()
    est, _, _, _ = (make or make_cores)(golden.meta)
    feed = _estimator_loop(est, golden.meta)
    inputs = [e for e in golden.events if e.kind in _EST_KINDS]
    frame_pos = {e.data[0]: i for i, e in enumerate(inputs) if e.kind == 'blocks'}
    frames = sorted(frame_pos.values())
    arrival = [e.t_ns * 1e-9 for e in inputs]
    pos = 0                     # inputs[:pos] have been fed to ``feed``

    def advance(f: Any, start: int, stop: int) -> None:
        for j in range(start, stop):
            _feed_estimator(f, arrival[j], inputs[j])

    import bisect
    for e in golden.events:
        if e.kind != 'apron':
            continue
        data = e.data[0]
        t, cam = data[0], data[1]
        lo = pos
        if math.isfinite(cam) and cam in frame_pos:
            fp = frame_pos[cam]
            lo = max(lo, fp + 1)
            k = bisect.bisect_right(frames, fp)
            hi = frames[k] if k < len(frames) else len(inputs)
        else:
            hi = frames[0] if frames else len(inputs)
        hi = min(hi, bisect.bisect_right(arrival, t + ARRIVAL_SLACK_S))
        hi = max(hi, lo)
        cands = [p for p in range(lo + 1, hi + 1) if inputs[p - 1].kind in ('imu', 'blocks')]
        cands = cands[:MAX_CANDIDATES]
        advance(feed, pos, lo)
        pos = lo
        best = feed.estimator.state(t).to_array()
        best_d = _align_distance(best, data)
        best_feed, best_pos = feed, lo
        f, fpos = feed, lo
        for p in cands:
            if best_d == 0.0:
                break
            f = copy.deepcopy(f) if f is feed else f
            advance(f, fpos, p)
            fpos = p
            st = f.estimator.state(t).to_array()
            d = _align_distance(st, data)
            if d < best_d:
                best, best_d = st, d
                best_feed, best_pos = copy.deepcopy(f), p
        if best_feed is not feed:
            _count(out.notes, 'estimator_later_position')
            feed, pos = best_feed, best_pos
        out.apron[t] = tuple(best)
    _loop_rejections(out, 'estimator', feed)
    return out


def _used_reference(loop: Any, st: Any, refs: list[tuple[float, tuple]],
                    ref_stamps: list[float], observed: dict[float, tuple]) -> tuple[Any, str]:
    """The reference the altitude node used for ``st``, and a note ('' = the latest one).

    The planner steps on the same apron state, so the node usually has the previous state's
    reference, but which one it had depends on the two nodes' timing. The recorded ``e_z``
    (= h − z_d, (7), relative frame) tells exactly: among the references stamped within 50 ms
    before ``st`` the one with that z_d is taken; if none fits to 1e-9 m (or e_z was not
    recorded), the latest one received, as the node would.
    """
    import bisect

    from deckland_common.contract import VERTICAL_RELATIVE, VerticalReference

    ref = loop.reference
    obs = observed.get(st.t_s)
    if obs is None or ref is None or ref.frame != VERTICAL_RELATIVE:
        return None, ''
    want = st.vertical.height_m - obs[2]
    if abs(ref.z_d_m - want) <= 1e-9:
        return None, ''
    lo = bisect.bisect_left(ref_stamps, st.t_s - 0.05)
    hi = bisect.bisect_right(ref_stamps, st.t_s)
    for stamp, d in refs[lo:hi]:
        if abs(d[2][2] - want) <= 1e-9:
            return (VerticalReference(d[2][2], d[3][2], d[4], ref.frame, stamp),
                    'dob_reference_not_latest_in_bag')
    return None, 'dob_reference_unidentified'


def replay_cores(golden: Golden, make: Any = None) -> Replay:
    """Replay the golden inputs through the nodes' loop cores, as the three nodes ran them.

    Events are taken in bag (receive) order; the bag time of an event stands for the node
    clock's ``now`` when it was handled. Each stage is fed what its node received:

    * the estimator gets the sensor topics (:func:`replay_estimator`);
    * the planner and the altitude loops step on each *recorded* ``apron/state`` (so a
      difference in one stage does not hide or smear one in the next); the altitude loop
      with the recorded ``planner/reference`` it used (:func:`_used_reference`);
    * ``start_landing`` is called at the bag time of the first ``planner/mode`` leaving IDLE,
      and the planner's watchdog ticks (apron state stale: a recorded reference whose stamp is
      no apron ``t_s``) are stepped on ``ApronState.untracked(stamp)`` at that stamp.

    ``make(meta)`` replaces :func:`make_cores` (tests build deliberately changed cores).
    """
    from deckland_common.contract import ApronState
    from deckland_common.frames import euler_to_quaternion, quaternion_to_euler
    from dob_altitude.loop import AltitudeLoop
    from landing_planner.loop import PlannerLoop

    out = Replay()
    replay_estimator(golden, out, make)
    _, planner, horizontal, ctrl = (make or make_cores)(golden.meta)
    pp = node_params(golden.meta, 'landing_planner')
    dp = node_params(golden.meta, 'dob_altitude')
    ploop = PlannerLoop(planner, horizontal, period_s=1.0 / pp['rate_hz'],
                        input_timeout_s=pp['input_timeout_s'], map_frame=pp['map_frame'])
    aloop = AltitudeLoop(ctrl, period_s=1.0 / dp['rate_hz'],
                         input_timeout_s=dp['input_timeout_s'],
                         rotor_height_offset_m=dp['rotor_height_offset_m'],
                         surface_accel_ff=dp['surface_accel_feedforward'])
    refs = sorted((e.data[0], e.data) for e in golden.events if e.kind == 'reference')
    ref_stamps = [r[0] for r in refs]
    observed = {e.data[0]: e.data[1] for e in golden.events if e.kind == 'observer'}
    apron_stamps = {e.data[0][0] for e in golden.events if e.kind == 'apron'}
    mode = planner.mode

    def track_mode(now: float) -> None:
        nonlocal mode
        if planner.mode is not mode:
            mode = planner.mode
            out.modes.append((now, mode.name))

    def record(tick: Any) -> None:
        if tick is None or not tick.publish_reference:
            return
        o, s = tick.output, tick.stamp_s
        q = euler_to_quaternion(0.0, 0.0, o.yaw_rad)   # the yaw as the message carries it
        out.reference[s] = (o.vertical_mode, (o.setpoint_m[0], o.setpoint_m[1], o.z_d_m),
                            (o.velocity_ff_mps[0], o.velocity_ff_mps[1], o.z_d_dot_mps),
                            o.z_d_ddot_mps2, quaternion_to_euler(*q)[2])
        if tick.publish_attitude and tick.command is not None:
            out.attitude[s] = (tick.command[0], tick.command[1], o.yaw_rad)

    started = False
    for e in golden.events:
        now = e.t_ns * 1e-9
        k, d = e.kind, e.data
        if k == 'odom':
            ploop.on_odom(now, d[0], d[1], d[2], d[3])
        elif k == 'velocity':
            ploop.on_velocity(now, d[0], d[2], d[1])
        elif k == 'landed':
            ploop.on_landed(d[0])
        elif k == 'imu':
            aloop.on_imu(now, d[0], d[1], has_orientation=d[2] != -1.0)
        elif k == 'mode':
            if not started and d[0] not in ('IDLE', 'LANDED'):
                started = True
                ok, _ = ploop.start_landing(now)
                _count(out.notes, 'start_landing_ok' if ok else 'start_landing_refused')
                track_mode(now)
        elif k == 'enabled':
            aloop.on_enabled(d[0])
        elif k == 'reference':
            stamp = d[0]
            if stamp not in apron_stamps and stamp not in out.reference:
                record(ploop.step(stamp, ApronState.untracked(stamp)))   # the node's watchdog
                track_mode(stamp)
                _count(out.notes, 'planner_watchdog_steps')
            aloop.on_reference(now, stamp, d[1], d[2][2], d[3][2], d[4])
        elif k == 'apron':
            st = d[2] if len(d) > 2 else ApronState.from_array(d[0])
            record(ploop.on_apron(now, st))
            track_mode(now)
            used, note = _used_reference(aloop, st, refs, ref_stamps, observed)
            steps = aloop.counts['steps']
            o = aloop.on_apron(now, st, reference=used)
            if note and aloop.counts['steps'] > steps:
                _count(out.notes, note)
            if o is not None:
                out.thrust[st.t_s] = o.thrust_n
                out.observer[st.t_s] = (o.sigma, o.d_hat_mps2, o.e_z_m)
    _loop_rejections(out, 'planner', ploop)
    _count(out.notes, 'planner_clock_not_advancing', ploop.withheld['clock_not_advancing'])
    _count(out.notes, 'planner_vehicle_stale', ploop.withheld['vehicle_stale'])
    _count(out.notes, 'dob_withheld', sum(aloop.withheld[r] for r in
                                          ('disabled', 'stale', 'invalid_vertical')))
    return out


# ========================================================================== comparison


@dataclass
class Check:
    """One compared quantity: errors over the matched samples and the verdict."""

    name: str
    n: int
    p99: float
    max: float
    tol: tuple[float, float]
    worst_at: float = math.nan

    @property
    def ok(self) -> bool:
        return self.p99 <= self.tol[0] and self.max <= self.tol[1]

    def __str__(self) -> str:
        flag = 'ok  ' if self.ok else 'FAIL'
        return (f'{flag} {self.name:<26} n={self.n:<5d} q={self.p99:.3g} max={self.max:.3g} '
                f'(tol {self.tol[0]:g}/{self.tol[1]:g}) worst at t={self.worst_at:.3f}')


@dataclass
class Report:
    checks: list[Check]
    matched: dict[str, tuple[int, int]]     # topic → (matched, recorded)
    min_matched: float
    notes: dict[str, Any] = field(default_factory=dict)

    @property
    def failures(self) -> list[str]:
        bad = [str(c) for c in self.checks if not c.ok]
        for topic, (m, n) in self.matched.items():
            if n == 0 or m < self.min_matched * n:
                bad.append(f'FAIL {topic}: matched {m} of {n} recorded samples '
                           f'(need {self.min_matched:.0%})')
        return bad

    @property
    def ok(self) -> bool:
        return not self.failures

    def __str__(self) -> str:
        lines = [str(c) for c in self.checks]
        lines += [f'{"ok  " if m >= self.min_matched * n and n else "FAIL"} {t}: '
                  f'{m}/{n} matched' for t, (m, n) in self.matched.items()]
        lines += [f'note {k}: {v}' for k, v in self.notes.items()]
        return '\n'.join(lines)


#: apron_state_v1 indices compared, by tolerance group (t_s is the key; epoch compared as is).
_APRON_GROUPS = {
    'apron_pos_m': (5, 6, 11, 12, 15, 16),
    'apron_vel_mps': (7, 8, 13, 14, 17, 18),
    'height_m': (20, 22, 24, 28),
    'vspeed_mps': (21, 23, 25),
}
_APRON_FLAGS = (2, 3, 19, 27)   # tracked, visible, vertical_valid, surface_epoch


def _match(recorded: dict[float, Any], replayed: dict[float, Any],
           window_s: float) -> list[tuple[float, Any, Any]]:
    """Pairs (stamp, recorded, replayed): equal stamps, or the nearest within ``window_s``."""
    if window_s <= 0.0:
        return [(t, v, replayed[t]) for t, v in recorded.items() if t in replayed]
    keys = sorted(replayed)
    out = []
    import bisect
    for t, v in recorded.items():
        i = bisect.bisect_left(keys, t)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(keys) and abs(keys[j] - t) <= window_s and (
                    best is None or abs(keys[j] - t) < abs(best - t)):
                best = keys[j]
        if best is not None:
            out.append((t, v, replayed[best]))
    return out


def _check(name: str, pairs: Iterable[tuple[float, float, float]],
           tol: tuple[float, float], q: float = 0.99) -> Check:
    errs, worst, worst_t = [], -1.0, math.nan
    for t, a, b in pairs:
        err = abs(a - b) if math.isfinite(a) or math.isfinite(b) else 0.0
        if a == b:
            err = 0.0
        if not math.isfinite(err):
            err = math.inf
        errs.append(err)
        if err > worst:
            worst, worst_t = err, t
    return Check(name, len(errs), percentile(errs, 100.0 * q) if errs else 0.0,
                 max(errs, default=0.0), tol, worst_t)


def recorded_outputs(golden: Golden) -> Replay:
    """The recorded outputs in the same shape as :class:`Replay` (keyed by stamp)."""
    from deckland_common.frames import quaternion_to_euler

    rec = Replay()
    for e in golden.events:
        d = e.data
        if e.kind == 'apron':
            rec.apron[d[0][0]] = d[0]
        elif e.kind == 'reference':
            rec.reference[d[0]] = (d[1], d[2], d[3], d[4], d[5])
        elif e.kind == 'attitude':
            rec.attitude[d[0]] = quaternion_to_euler(*d[1])
        elif e.kind == 'thrust':
            rec.thrust[d[0]] = d[1]
        elif e.kind == 'observer':
            rec.observer[d[0]] = d[1]
        elif e.kind == 'mode':
            rec.modes.append((e.t_ns * 1e-9, d[0]))
    return rec


def compare(recorded: Replay, replayed: Replay, tol: Tolerances, *,
            time_offset_s: float = 0.0) -> Report:
    """Compare ``replayed`` with ``recorded`` (stamps of ``replayed`` minus ``time_offset_s``)."""
    from deckland_common.frames import wrap_pi

    def shift(d: dict[float, Any]) -> dict[float, Any]:
        return d if time_offset_s == 0.0 else {t - time_offset_s: v for t, v in d.items()}

    def chk(name: str, pairs: Iterable[tuple[float, float, float]],
            bounds: tuple[float, float]) -> Check:
        return _check(name, pairs, bounds, tol.quantile)

    checks: list[Check] = []
    matched: dict[str, tuple[int, int]] = {}
    w = tol.stamp_s

    ap_all = _match(recorded.apron, shift(replayed.apron), w)
    matched['apron/state'] = (len(ap_all), len(recorded.apron))
    # values compared where tracked/visible/valid agree (disagreements: the flags check)
    ap = [(t, a, b) for t, a, b in ap_all
          if not any((a[i] > 0.5) != (b[i] > 0.5) for i in _APRON_FLAGS[:3])]
    for group, idx in _APRON_GROUPS.items():
        checks.append(chk(f'apron {group}', ((t, a[i], b[i]) for t, a, b in ap for i in idx
                                                if a[2] > 0.5 or i >= 19), getattr(tol, group)))
    n_flag = sum(1 for t, a, b in ap_all if any((a[i] > 0.5) != (b[i] > 0.5)
                                                for i in _APRON_FLAGS[:3]) or a[27] != b[27])
    pct = 100.0 * n_flag / max(1, len(ap_all))
    checks.append(Check('apron flags (disagree %)', len(ap_all), pct, pct,
                        (1.0, 1.0) if w == 0.0 else (5.0, 5.0)))

    rp = _match(recorded.reference, shift(replayed.reference), w)
    matched['planner/reference'] = (len(rp), len(recorded.reference))
    checks.append(chk('reference z_d', ((t, a[1][2], b[1][2]) for t, a, b in rp),
                         tol.ref_z_m))
    checks.append(chk('reference z_d_dot', ((t, a[2][2], b[2][2]) for t, a, b in rp),
                         tol.ref_z_dot_mps))
    checks.append(chk('reference z_d_ddot', ((t, a[3], b[3]) for t, a, b in rp),
                         (tol.ref_z_dot_mps[0] * 10, tol.ref_z_dot_mps[1] * 10)))
    checks.append(chk('reference setpoint xy', ((t, a[1][i], b[1][i]) for t, a, b in rp
                                                   for i in (0, 1)), tol.ref_xy_m))
    checks.append(chk('reference ff xy', ((t, a[2][i], b[2][i]) for t, a, b in rp
                                             for i in (0, 1)), tol.ref_z_dot_mps))
    checks.append(chk('reference yaw', ((t, 0.0, wrap_pi(a[4] - b[4])) for t, a, b in rp),
                         tol.attitude_rad))

    at = _match(recorded.attitude, shift(replayed.attitude), w)
    matched['control/attitude'] = (len(at), len(recorded.attitude))
    checks.append(chk('attitude roll/pitch', ((t, a[i], b[i]) for t, a, b in at
                                                 for i in (0, 1)), tol.attitude_rad))
    checks.append(chk('attitude yaw', ((t, 0.0, wrap_pi(a[2] - b[2])) for t, a, b in at),
                         tol.attitude_rad))

    th = _match(recorded.thrust, shift(replayed.thrust), w)
    matched['control/thrust'] = (len(th), len(recorded.thrust))
    checks.append(chk('thrust u_z', th, tol.thrust_n))
    ob = _match(recorded.observer, shift(replayed.observer), w)
    matched['altitude/state'] = (len(ob), len(recorded.observer))
    checks.append(chk('observer sigma, d_hat', ((t, a[i], b[i]) for t, a, b in ob
                                                   for i in (0, 1)), tol.observer))
    checks.append(chk('observer e_z', ((t, a[2], b[2]) for t, a, b in ob), tol.ref_z_m))
    notes = dict(replayed.notes)
    notes.update({f'rejected {k}': v for k, v in replayed.rejected.items()})
    notes['modes recorded'] = ' '.join(m for _, m in recorded.modes)
    notes['modes replayed'] = ' '.join(m for _, m in replayed.modes)
    return Report(checks, matched, tol.min_matched, notes)


def mode_sequence(modes: Sequence[tuple[float, str]]) -> list[str]:
    """Mode names without repeats (``planner/mode`` is latched: IDLE may appear twice)."""
    out: list[str] = []
    for _, m in modes:
        if not out or out[-1] != m:
            out.append(m)
    return out


# ================================================================ recording (ROS, make golden)


def _isolate_ros_domain() -> None:
    """A private DDS domain on loopback unless the caller chose one (before rclpy loads)."""
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(101, 200)))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


class ReplayMismatchError(RuntimeError):
    """A recording whose pure replay is outside ``CORE_TOLERANCES`` (README-golden.md,
    decision 7); ``report`` says where."""

    def __init__(self, report: Report) -> None:
        super().__init__('the recording does not replay within CORE_TOLERANCES: '
                         + '; '.join(report.failures))
        self.report = report


def record_verified(out_dir: str | os.PathLike[str], scenario: str = DEFAULT_SCENARIO,
                    seed: int = DEFAULT_SEED, attempts: int = 10,
                    log: Any = sys.stderr) -> Path:
    """:func:`record` until a recording replays (at most ``attempts`` landings)."""
    for attempt in range(1, attempts + 1):
        try:
            return record(out_dir, scenario, seed, log=log, verify=True)
        except ReplayMismatchError as exc:
            print(f'golden record: attempt {attempt} of {attempts}: {exc}', file=log)
            if attempt == attempts:
                raise
    raise AssertionError('unreachable')


def record(out_dir: str | os.PathLike[str], scenario: str = DEFAULT_SCENARIO,
           seed: int = DEFAULT_SEED, *, timeout_s: float = 60.0, log: Any = sys.stderr,
           verify: bool = False) -> Path:
    """Fly one landing with the real graph and write the trimmed golden bag into ``out_dir``.

    ``verify``: install it only if its pure replay is within ``CORE_TOLERANCES`` (else
    :class:`ReplayMismatchError`; the old bag stays).

    The recorder (explicit topic list, on the monitor's context) is subscribed before the
    nodes start, so the bag holds every input from the first one; the landing is triggered
    as ``deckland up`` does (offboard, then ``planner/start_landing`` 1 s after every topic
    flows). ``out_dir`` is replaced only if it is empty or an earlier golden bag.
    """
    _isolate_ros_domain()
    from deckland.graph.orchestrator import Orchestrator, load_graph
    from deckland.graph.up import (
        MissionMonitor,
        UdpReservations,
        default_graph_path,
        graph_substitutions,
    )
    from deckland.ros.bag import Recorder

    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not (out / META_NAME).exists():
        raise ValueError(f'{out} is not empty and not a golden bag; not overwriting')
    args = argparse.Namespace(scenario=scenario, seed=seed, hardware=False, mavlink=None,
                              pixy_port=None, area=(0.0, 0.0))
    udp = UdpReservations()   # the listening sockets, bound now and inherited by the nodes
    graph = load_graph(default_graph_path(), graph_substitutions(args, udp), False)
    overrides = {n.name: dict(n.parameters) for n in graph['nodes'] if n.name in NODE_DEFAULTS}
    # The estimator is clocked by its inputs (clock: imu) for the recording: each apron/state
    # then follows a recorded input, so the pure replay can tell exactly which inputs it had.
    # The default loop clock publishes at wall-clock ticks between inputs, and the bag's
    # arrival times (the recorder's, not the estimator's) cannot pin that input prefix down
    # to the millimetre (tried: apron position q = 8 mm against the 2 mm tolerance). The
    # cores are the same either way. Written down, so replay_nodes clocks the node the same.
    overrides.setdefault('apron_estimator', {})['clock'] = GOLDEN_ESTIMATOR_CLOCK
    work = Path(tempfile.mkdtemp(prefix='deckland-golden-'))
    raw = work / 'raw'
    monitor = MissionMonitor(graph['wait_for_topics'])
    recorder = Recorder(raw, topics=[*INPUT_TOPICS, *OUTPUT_TOPICS, '/sim/outcome'],
                        context=monitor.context, discovery_period_s=0.05, depth=1000)
    sim = [n for n in graph['nodes'] if n.sim_only]
    orch = Orchestrator([n for n in graph['nodes'] if not n.sim_only], out=log,
                        stop_timeout_s=5.0, pass_fds=udp.fds())
    orch_sim = Orchestrator(sim, out=log, stop_timeout_s=5.0, pass_fds=udp.fds())
    outcome = None
    try:
        recorder.start()
        orch.start()
        # every subscription in place before the simulator makes data flow: the bag then
        # holds each node's inputs from the very first message
        _wait_subscribed(monitor.node, recorder, 30.0)
        orch_sim.start()
        silent = monitor.wait_flowing(40.0)
        if silent:
            raise RuntimeError(f'start-up failed: silent topics {silent}')
        time.sleep(1.0)
        monitor.trigger('bridge/offboard')
        ok, msg = monitor.trigger('planner/start_landing')
        if not ok:
            raise RuntimeError(f'start_landing refused: {msg}')
        deadline = time.monotonic() + timeout_s
        while monitor.outcome is None and time.monotonic() < deadline:
            orch.check()
            time.sleep(0.05)
        outcome = monitor.outcome
        time.sleep(0.2)
    finally:
        orch_sim.stop()
        orch.stop()
        orch_sim.close()
        orch.close()
        udp.close()
        recorder.stop()
        monitor.close()
    if outcome is None or not outcome.get('success'):
        shutil.rmtree(work, ignore_errors=True)
        raise RuntimeError(f'the reference landing did not succeed: {outcome}')
    trimmed = work / 'golden'
    window = trim(raw, trimmed)
    meta: dict[str, Any] = {'version': META_VERSION, 'scenario': scenario, 'seed': seed,
            'recorded_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
            'window_ns': list(window), 'outcome': outcome, 'parameters': overrides,
            'note': 'regenerate deliberately with `make golden`; never written by tests'}
    (trimmed / META_NAME).write_text(yaml.safe_dump(meta, sort_keys=False))
    size = sum(p.stat().st_size for p in trimmed.iterdir())
    if size > MAX_BAG_BYTES:
        raise RuntimeError(f'golden bag is {size} bytes (> {MAX_BAG_BYTES}); not installed')
    if verify:
        gold = load(trimmed)
        report = compare(recorded_outputs(gold), replay_cores(gold), CORE_TOLERANCES)
        if not report.ok:
            shutil.rmtree(work, ignore_errors=True)
            raise ReplayMismatchError(report)
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(trimmed, out)
    shutil.rmtree(work, ignore_errors=True)
    return out


#: Subscribers each topic has once the graph (without the simulator) and the recorder are up.
_SUBSCRIBERS = {'/vehicle/imu': 3, '/vehicle/odom': 3, '/vehicle/velocity': 3,
                '/vehicle/range': 2, '/pixy/blocks': 2, '/apron/state': 3,
                '/planner/reference': 2}


def _wait_subscribed(node: Any, recorder: Any, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (set(INPUT_TOPICS) - {'/planner/mode'} <= set(recorder.subscribed)
                and all(node.count_subscribers(t) >= n for t, n in _SUBSCRIBERS.items())):
            time.sleep(0.5)   # endpoint matching settles
            return
        time.sleep(0.05)
    raise RuntimeError(f'subscriptions not in place after {timeout_s} s '
                       f'(recorder has {recorder.subscribed})')


def trim(raw_dir: Path, out_dir: Path) -> tuple[int, int]:
    """Copy the replay's topics from ``raw_dir`` into a new bag, first input to outcome.

    The window starts at the first input message and ends 0.2 s after ``sim/outcome`` (the
    touchdown). Latched topics keep their messages from before the window (stamped at its
    start). Offered QoS profiles are copied explicitly. Returns the window (ns).
    """
    from deckland.ros.bag import BagWriter
    from rosbags.highlevel import AnyReader

    keep = set(INPUT_TOPICS) | set(OUTPUT_TOPICS)
    latched = {'/vehicle/landed', '/planner/mode', '/control/enabled'}
    with AnyReader([raw_dir]) as reader:
        first = min((t for c, t, _ in reader.messages()
                     if c.topic in INPUT_TOPICS and c.topic not in latched), default=None)
        ends = [t for c, t, _ in reader.messages() if c.topic == '/sim/outcome']
        if first is None or not ends:
            raise RuntimeError(f'{raw_dir}: no inputs or no outcome recorded')
        end = ends[0] + 200_000_000
        writer = BagWriter(out_dir)
        try:
            for c in reader.connections:
                if c.topic in keep:
                    writer.add_topic(c.topic, c.msgtype, list(c.ext.offered_qos_profiles))
            for c, t, data in reader.messages():
                if c.topic not in keep or t > end:
                    continue
                if t < first:
                    if c.topic not in latched:
                        continue
                    t = first
                writer.write(c.topic, t, data)
        finally:
            writer.close()
    return first, end


# ============================================================== node replay (ROS, bag play)


def shifted_copy(bag_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str],
                 offset_ns: int, topics: Iterable[str] = PLAY_TOPICS, gate: bool = False) -> int:
    """Copy ``topics`` into a new bag with every time moved by ``offset_ns``; returns count.

    The nodes reject stale stamps against their own (wall) clock, so a bag recorded earlier
    must be re-stamped to be played into them. Every played topic starts with a
    ``std_msgs/Header`` except ``vehicle/landed``: its CDR stamp (bytes 4-11 after the 4-byte
    encapsulation header: int32 sec, uint32 nanosec, little endian) is rewritten in place,
    nothing else is touched. Bag times move by the same offset. ``gate`` adds one
    ``std_msgs/Bool`` on :data:`GATE_TOPIC` at the first message's time: a player started with
    ``--wait-subscribers`` then starts the moment something subscribes to it.
    """
    from deckland.ros.bag import BagWriter
    from rosbags.highlevel import AnyReader

    wanted = set(topics)
    n = 0
    writer = BagWriter(out_dir)
    try:
        with AnyReader([Path(bag_dir)]) as reader:
            conns = [c for c in reader.connections if c.topic in wanted]
            for c in conns:
                writer.add_topic(c.topic, c.msgtype, list(c.ext.offered_qos_profiles))
            if gate:
                from deckland.ros import rosio

                writer.add_topic(GATE_TOPIC, 'std_msgs/msg/Bool', [rosio.default_offered_qos()])
                writer.write(GATE_TOPIC, reader.start_time + offset_ns, b'\x00\x01\x00\x00\x01')
            for c, t, raw in reader.messages(connections=conns):
                data = bytearray(raw)
                if c.topic != '/vehicle/landed':
                    if data[1] != 1:
                        raise ValueError(f'{c.topic}: not little-endian CDR')
                    sec = int.from_bytes(data[4:8], 'little', signed=True)
                    nsec = int.from_bytes(data[8:12], 'little')
                    stamp = sec * 1_000_000_000 + nsec + offset_ns
                    data[4:8] = (stamp // 1_000_000_000).to_bytes(4, 'little', signed=True)
                    data[8:12] = (stamp % 1_000_000_000).to_bytes(4, 'little')
                writer.write(c.topic, t + offset_ns, bytes(data))
                n += 1
    finally:
        writer.close()
    return n


#: Topic only the replay's collector subscribes to: opening it starts the player.
GATE_TOPIC = '/golden/gate'

#: Subscriptions of the three nodes to the played topics (estimator, planner, dob).
_NODE_SUBSCRIBERS = {'vehicle/imu': 3, 'vehicle/odom': 2, 'vehicle/velocity': 2,
                     'vehicle/range': 1, 'pixy/blocks': 1, 'vehicle/landed': 1,
                     'apron/state': 3}


def replay_nodes(bag_dir: str | os.PathLike[str], context: Any, executor: Any, *,
                 lead_s: float = 4.0, tail_s: float = 0.5,
                 log: Any = None) -> tuple[Replay, float]:
    """Run the three nodes in ``context``, play the golden inputs into them, collect outputs.

    The estimator, planner and altitude nodes run as their own processes (as in the real
    graph, ``deckland.graph.orchestrator``; in-process they would share one GIL with the player and
    fall behind) with the recorded parameters, in this process's ROS domain; the collector
    node is added to ``executor`` (which must be spinning). The inputs are re-stamped to start
    ``lead_s`` from now (:func:`shifted_copy`) and played with :func:`deckland.ros.bag.play` at
    rate 1.0; ``planner/start_landing`` is called through its service at the recorded trigger
    time. Returns the outputs (stamps as published) and the offset (s) to subtract to compare
    them with the recording (:func:`compare` ``time_offset_s``).
    """

    import io

    from deckland.graph.orchestrator import NodeSpec, Orchestrator

    golden = load(bag_dir)
    params = {name: dict(v or {}) for name, v in (golden.meta.get('parameters') or {}).items()}
    # A bag recorded before the estimator had a `clock` parameter was clocked by vehicle/imu
    # and camera frames; replay it that way (its apron/state stamps are the IMU arrivals).
    params.setdefault('apron_estimator', {}).setdefault('clock', 'imu')
    orch = Orchestrator([NodeSpec(name, name, parameters=dict(params.get(name) or {}))
                         for name in NODE_DEFAULTS], out=log or io.StringIO(),
                        stop_timeout_s=3.0)
    orch.start()
    try:
        return _replay_into(golden, bag_dir, context, executor, orch, lead_s, tail_s)
    finally:
        orch.stop()


def _replay_into(golden: Golden, bag_dir: Any, context: Any, executor: Any, orch: Any,
                 lead_s: float, tail_s: float) -> tuple[Replay, float]:
    import threading

    from deckland_common.ros_node import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    import rclpy
    from sensor_msgs.msg import Imu
    from std_msgs.msg import Bool, String
    from std_srvs.srv import Trigger

    from deckland_interfaces.msg import AltitudeState, ApronState, PlannerReference


    helper = rclpy.create_node('golden_collector', context=context)
    executor.add_node(helper)
    got: list[tuple[str, Any]] = []
    lock = threading.Lock()

    def sub(cls: type, topic: str, qos: Any = RELIABLE_QOS) -> None:
        def cb(msg: Any, _topic: str = topic) -> None:
            with lock:
                got.append((_topic, msg))
        helper.create_subscription(cls, topic.lstrip('/'), cb, qos)

    sub(ApronState, '/apron/state')
    sub(PlannerReference, '/planner/reference')
    sub(QuaternionStamped, '/control/attitude')
    sub(WrenchStamped, '/control/thrust')
    sub(AltitudeState, '/altitude/state')
    sub(String, '/planner/mode', LATCHED_QOS)
    arrivals: list[tuple[float, float]] = []   # (wall s, stamp s) of played IMU messages

    def on_imu(msg: Any) -> None:
        arrivals.append((time.time(), msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9))
    helper.create_subscription(Imu, 'vehicle/imu', on_imu, SENSOR_QOS)
    client = helper.create_client(Trigger, 'planner/start_landing')
    if not client.wait_for_service(timeout_sec=20.0):
        raise RuntimeError('planner/start_landing not available')
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and not (
            all(helper.count_publishers(t) >= 1 for t in ('apron/state', 'planner/reference',
                                                          'control/thrust'))
            and all(helper.count_subscribers(t) >= n for t, n in _NODE_SUBSCRIBERS.items())):
        orch.check()
        time.sleep(0.05)
    time.sleep(0.3)

    first_ns = golden.meta['window_ns'][0]
    triggers = [e.t_ns for e in golden.events
                if e.kind == 'mode' and e.data[0] not in ('IDLE', 'LANDED')]
    work = Path(tempfile.mkdtemp(prefix='deckland-golden-play-'))
    try:
        start_wall = time.time() + lead_s
        offset_ns = int(start_wall * 1e9) - first_ns
        shifted_copy(bag_dir, work / 'play', offset_ns, gate=True)
        offset_s = offset_ns * 1e-9
        stop = threading.Event()

        def trigger() -> None:
            """planner/start_landing at the recorded trigger time (the service, as up.py)."""
            if not triggers:
                return
            wait = triggers[0] * 1e-9 + offset_s - time.time()
            if wait > 0 and stop.wait(wait):
                return
            future = client.call_async(Trigger.Request())
            end = time.monotonic() + 5.0
            while not future.done() and time.monotonic() < end:
                time.sleep(0.005)

        # the player runs in its own process (``deckland bag play``: its own interpreter, so
        # the collector here cannot starve it) and waits for the gate's subscriber
        player = subprocess.Popen(
            [sys.executable, '-m', 'deckland.ros.bag', 'play', str(work / 'play'),
             '--rate', '1.0', '--wait-subscribers', str(lead_s + 20.0)],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + lead_s + 15.0
            while (helper.count_publishers(GATE_TOPIC) < 1 and time.monotonic() < deadline
                   and player.poll() is None):
                time.sleep(0.02)
            late = time.time() - start_wall
            if late > 0:   # the player took longer to start than planned: restamp later
                raise RuntimeError(f'player started {late:.2f} s late; raise lead_s')
            time.sleep(max(0.0, start_wall - time.time()))
            helper.create_subscription(Bool, GATE_TOPIC, lambda _m: None, RELIABLE_QOS)
            trig = threading.Thread(target=trigger, daemon=True)
            trig.start()
            duration = (golden.meta['window_ns'][1] - first_ns) * 1e-9
            player.wait(timeout=duration + 20.0)
            time.sleep(tail_s)
            stop.set()
            trig.join(timeout=6.0)
        finally:
            if player.poll() is None:
                player.terminate()
                player.wait(timeout=5.0)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    # the gate opens after DDS matching: measure how late the inputs really were (IMU
    # receive time − stamp, against the same in the recording) and compare with that offset
    rec_lat = sorted(e.t_ns * 1e-9 - e.data[0] for e in golden.events if e.kind == 'imu')
    play_lat = sorted(w - st for w, st in arrivals)
    late_s = 0.0
    if rec_lat and play_lat:
        late_s = play_lat[len(play_lat) // 2] - rec_lat[len(rec_lat) // 2]
    out = Replay()
    out.notes['play_late_ms'] = round(late_s * 1e3, 1)
    with lock:
        items = list(got)
    for topic, msg in items:
        kind, d = _decode(topic, msg)
        if kind == 'apron':
            out.apron[d[0][0]] = d[0]
        elif kind == 'reference':
            out.reference[d[0]] = (d[1], d[2], d[3], d[4], d[5])
        elif kind == 'attitude':
            from deckland_common.frames import quaternion_to_euler
            out.attitude[d[0]] = quaternion_to_euler(*d[1])
        elif kind == 'thrust':
            out.thrust[d[0]] = d[1]
        elif kind == 'observer':
            out.observer[d[0]] = d[1]
        elif kind == 'mode':
            out.modes.append((0.0, d[0]))
    return out, offset_s + late_s


# ======================================================================================= CLI


def main(argv: list[str] | None = None) -> int:
    """``python test/support/golden.py record DIR`` | ``check DIR`` (pure replay report)."""
    parser = argparse.ArgumentParser(prog='python test/support/golden.py',
                                     description='golden-bag regression (make golden)')
    sub = parser.add_subparsers(dest='verb', required=True)
    rec = sub.add_parser('record', help='fly the reference landing and (re)write DIR')
    rec.add_argument('dir')
    rec.add_argument('--scenario', default=DEFAULT_SCENARIO)
    rec.add_argument('--seed', type=int, default=DEFAULT_SEED)
    rec.add_argument('--attempts', type=int, default=10,
                     help='landings flown at most until one replays (README-golden.md)')
    chk = sub.add_parser('check', help='replay DIR through the pure cores and compare')
    chk.add_argument('dir')
    args = parser.parse_args(argv)
    if args.verb == 'record':
        try:
            out = record_verified(args.dir, args.scenario, args.seed, args.attempts)
        except (RuntimeError, ValueError, OSError) as exc:
            print(f'golden record: {exc}', file=sys.stderr)
            return 1
        size = sum(p.stat().st_size for p in out.iterdir())
        print(f'golden bag written to {out} ({size / 1024:.0f} KiB)')
        return 0
    golden = load(args.dir)
    report = compare(recorded_outputs(golden), replay_cores(golden), CORE_TOLERANCES)
    print(report)
    return 0 if report.ok else 1


if __name__ == '__main__':
    sys.exit(main())
