"""ROS 2 adapter of the apron estimator (paper §2.3-2.4, (27)-(35); see the package README).

Thin: parameters, topics, message unpacking and a 1 Hz diagnostics timer. The algorithm is
:class:`apron_estimator.estimator.ApronEstimator`, fed exactly as the in-process runner
(`deckland.runner`) feeds it; the pure conversions are in :mod:`apron_estimator.inputs`.

Inputs (each message's ``header.stamp`` is its ``t_s``, in the node clock's domain):

* ``vehicle/imu`` → ``on_attitude`` (orientation → Z-Y-X Euler) and ``on_accel``
  (specific force FLU rotated to ENU, gravity removed);
* ``vehicle/odom`` (pose position) + ``vehicle/velocity`` (ENU twist) of the same stamp →
  ``on_local_position``;
* ``vehicle/range`` → ``on_lidar`` (±inf / outside [min_range, max_range] → None);
* ``pixy/blocks`` → ``on_camera`` (stamp = exposure time set by the driver).

When ``state(now)`` is published (``clock`` parameter; planner and altitude loop step on each
``apron/state``, so this is the clock of the whole control chain):

* ``loop`` (default): a thread ticks at ``rate_hz`` on absolute deadlines, phase-locked to the
  camera (:class:`deckland_common.loop_clock.PhaseLockedLoop`): each processed ``pixy/blocks``
  frame nudges the phase (at most ``loop_max_slew_s``) so that ticks fall ``loop_lead_s``
  after the frames; a frame that would wait longer than ``loop_max_wait_s`` for its tick (while
  locking, or a late frame) is published at once as well. Regular 100 Hz output with a fresh
  frame every other tick after a wait of ``loop_lead_s``.
* ``imu``: event-driven, as before the loop existed (and for replays with recorded timing):
  on each accepted ``vehicle/imu`` message unless the previous IMU-triggered publication is
  less than ``0.5 / rate_hz`` old, and at once after each accepted ``pixy/blocks`` frame.

Each publication is ``apron/state`` (``apron_state_v1``), ``apron/visible``, ``apron/odom``
(while tracked, unless ``odom_when_untracked``) and ``apron/relative`` /
``apron/relative_velocity`` (while tracked), all for the same ``now``; ``t_s`` strictly
increases. If the attitude or the local position is stale (older than ``input_timeout_s``, or
never received) nothing is published (counted in ``withheld``), so downstream nodes see
``apron/state`` go stale and withhold their commands; when every input stops, nothing triggers
a publication at all and the 1 Hz diagnostics report the reason.
"""

from __future__ import annotations

from array import array
from dataclasses import MISSING, fields
import functools
import math
import re
import sys
import threading
import time

from deckland_common.frames import quaternion_to_euler
from deckland_common.loop_clock import PhaseLockedLoop, PhaseLockParams
from deckland_common.params import ParameterError, ParamSpec, in_range, one_of, positive
from deckland_common.ros_node import (
    RELIABLE_QOS,
    SENSOR_QOS,
    declare_and_validate,
    run_node,
    s_to_stamp,
    stamp_to_s,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, TwistStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from sensor_msgs.msg import Imu, PointCloud, Range
from std_msgs.msg import Bool, Float64MultiArray, MultiArrayDimension

from apron_estimator.camera import CameraParams
from apron_estimator.estimator import ApronEstimator, EstimatorParams
from apron_estimator.horizontal import HorizontalParams
from apron_estimator.inputs import (
    LocalPositionPairer,
    blocks_from_cloud,
    lidar_range,
    normalised_quaternion,
    world_accel_from_specific_force,
)
from apron_estimator.types import APRON_STATE_LAYOUT, APRON_STATE_V1_LEN
from apron_estimator.vertical import VerticalParams

#: Variance (m², m²/s², rad²) published for a quantity that is not known.
UNKNOWN_VAR = 1.0e4

#: Largest plausible IMU specific force per axis (m/s²): 16 g, the full scale of the Pixhawk
#: IMUs. A larger (finite) reading cannot come from the sensor; fed to the core it wrecks the
#: horizontal filter's acceleration integrals for good (tests/test_fuzz_nodes.py).
MAX_SPECIFIC_FORCE_MPS2 = 16.0 * 9.80665

#: Parameter prefix of each nested dataclass of EstimatorParams.
SECTIONS = (('camera', CameraParams), ('horizontal', HorizontalParams),
            ('vertical', VerticalParams))

#: Meaning of every estimator parameter (ROS name → description); defaults come from the
#: dataclasses so they never drift apart.
ESTIMATOR_DESCRIPTIONS = {
    'camera.fov_x_deg': 'full horizontal field of view of the Pixy; α_x = fov/2 in (27) '
                        '(Table 2: 60)',
    'camera.fov_y_deg': 'full vertical field of view; α_y = fov/2 in (28) (Table 2: 47)',
    'camera.width_px': 'image width; x_max = width/2 in (29)',
    'camera.height_px': 'image height; y_max = height/2 in (30)',
    'camera.cx_px': 'principal point x (image x right)',
    'camera.cy_px': 'principal point y (image y down)',
    'camera.mount_x_m': 'camera position from the body origin, FLU x (forward)',
    'camera.mount_y_m': 'camera position from the body origin, FLU y (left)',
    'camera.mount_z_m': 'camera position from the body origin, FLU z (up)',
    'camera.mount_roll_rad': 'extra camera rotation vs the default down-looking mount, roll',
    'camera.mount_pitch_rad': 'extra camera rotation vs the default mount, pitch',
    'camera.mount_yaw_rad': 'extra camera rotation vs the default mount, yaw',
    'camera.min_ray_down_cos': 'rays flatter than acos(this) from straight down give no fix',
    'camera.paper_exact': 'use (29)-(30) with the raw lidar range, no tilt compensation, '
                          'yaw-only (35)',
    'horizontal.accel_psd_m2ps3': 'q of the relative-position KF: Q = diag(0, q dt) per axis '
                                  '(31)',
    'horizontal.sigma0_m': 'camera measurement sigma at zero height (R of (33))',
    'horizontal.sigma_per_m': 'camera measurement sigma growth per metre of height',
    'horizontal.nis_gate': '2-D chi-square gate on the normalised innovation',
    'horizontal.acquire_hits': 'consistent detections before the apron is tracked',
    'horizontal.lost_timeout_s': 'no accepted detection for this long = track lost',
    'horizontal.init_vel_sigma_mps': 'relative velocity sigma at (re-)initialisation',
    'horizontal.use_accel_input': 'drive the KF with u = -vehicle acceleration (beyond the '
                                  'paper)',
    'horizontal.accel_history_s': 'acceleration history kept (>= lost_timeout_s)',
    'horizontal.rival_gate_m': 'false blobs: a detection this close (m) to a rival is that rival',
    'horizontal.rival_confirm_hits': 'false blobs: detections before a rival makes the target '
                                     'ambiguous',
    'horizontal.rival_timeout_s': 'false blobs: an unresolved rival unseen this long (s) is '
                                  'dropped',
    'horizontal.rejected_rival_timeout_s': 'false blobs: a rejected rival is remembered this '
                                           'long (s)',
    'horizontal.ambiguity_min_sep_m': 'false blobs: rivals closer (m) than this to the track do '
                                      'not matter',
    'horizontal.verify_radius_m': 'false blobs: lidar spot this close (m) to a hypothesis → '
                                  'surface sample',
    'horizontal.verify_dwell_s': 'false blobs: hover this long (s) before sampling',
    'horizontal.deck_rise_m': "false blobs: the beacon's surface is higher by at least this (m)",
    'horizontal.max_rivals': 'false blobs: rival hypotheses kept at most',
    'vertical.sigma_lidar_m': 'lidar sigma',
    'vertical.sigma_altitude_m': 'local position z sigma (GPS/EKF)',
    'vertical.sigma_vz_mps': 'local velocity z sigma',
    'vertical.use_vz': 'fuse the local vertical velocity',
    'vertical.vehicle_accel_psd_m2ps3': 'process noise of the vehicle acceleration input',
    'vertical.surface_accel_sigma_mps2': 'stationary sigma of the deck acceleration (Singer)',
    'vertical.surface_tau_s': 'Singer time constant of the deck acceleration',
    'vertical.surface_model': "'accel' (z_s, v_s, a_s) or 'velocity' (z_s, v_s)",
    'vertical.jump_threshold_m': 'minimum lidar innovation of a surface jump (re-base)',
    'vertical.jump_sigma': 'or this many innovation sigmas, if larger',
    'vertical.jump_confirm': 'consecutive consistent samples to re-base the surface',
    'vertical.jump_consistency_m': 'max spread of the innovations of a jump run',
    'vertical.jump_window_s': 'max age of a pending jump run',
    'vertical.rebase_vs_sigma_mps': 'surface velocity sigma after a re-base',
    'vertical.altitude_gate': 'NIS gate of the altitude / vz updates',
    'vertical.lidar_timeout_s': 'vertical state invalid after this long without a used lidar '
                                'sample',
    'vertical.range_min_m': 'shortest accepted lidar range',
    'vertical.range_max_m': 'longest accepted lidar range',
    'vertical.max_tilt_rad': 'no lidar fusion beyond this roll/pitch',
    'vertical.late_tolerance_s': 'samples this much older than the filter are applied now; '
                                 'older ones are out of order',
    'beacon_signature': 'Pixy signature of the beacon (0 = any)',
    'attitude_history_s': 'attitude history kept for exposure-stamp look-ups',
    'max_attitude_gap_s': 'camera frame rejected without an attitude sample this close',
    'height_fallback_timeout_s': 'raw lidar height usable this long when the filter is invalid',
    'visible_timeout_s': "'visible' also needs a camera frame this recent",
    'max_position_extrapolation_s': 'cap of the vehicle position extrapolation for '
                                    'apron_position',
}


def _estimator_specs() -> list[ParamSpec]:
    """One ParamSpec per EstimatorParams field, flattened as ``section.field`` / ``field``."""
    specs = []
    rows = [(f'{prefix}.{f.name}', f.default) for prefix, cls in SECTIONS
            for f in fields(cls)]
    rows += [(f.name, f.default) for f in fields(EstimatorParams) if f.default is not MISSING]
    for name, default in rows:
        desc = ESTIMATOR_DESCRIPTIONS.get(name, 'estimator field (see the package README)')
        desc += ' (core default; the core validates)'
        if name == 'vertical.surface_model':
            specs.append(one_of(name, default, ('accel', 'velocity'), desc))
        else:
            specs.append(ParamSpec(name, default, desc))
    return specs


def _nonempty(name: str, default: str, description: str) -> ParamSpec:
    return ParamSpec(name, default, description, lambda v: bool(v.strip()), 'must not be empty')


NODE_PARAMS = [
    ParamSpec('rate_hz', 100.0,
              'control rate: the loop rate (clock=loop), or the IMU thinning rate (clock=imu: '
              'an IMU message publishes unless the previous IMU-triggered publication is less '
              'than 0.5/rate_hz old)',
              lambda v: 1.0 <= v <= 1000.0, 'must be in [1, 1000]'),
    one_of('clock', 'loop', ('loop', 'imu'),
           "what publishes apron/state: 'loop' = a rate_hz loop phase-locked to the camera "
           "frames; 'imu' = each vehicle/imu message and each camera frame (event-driven)"),
    in_range('loop_lead_s', 0.001, 0.0, 0.004,
             'clock=loop: wanted time from a processed camera frame to the next tick'),
    in_range('loop_max_slew_s', 0.0002, 0.0, 0.001,
             'clock=loop: largest phase correction per camera frame (period change)'),
    in_range('loop_max_wait_s', 0.003, 0.0, 0.009,
             'clock=loop: a frame further than this before its tick is published at once; '
             'must be >= loop_lead_s'),
    positive('input_timeout_s', 0.5,
             'inputs older (or newer) than this vs the node clock are rejected; no output '
             'while vehicle/imu or the local position is this stale'),
    positive('gravity_mps2', 9.81, 'g removed from the rotated IMU specific force'),
    in_range('position_pair_tolerance_s', 0.005, 0.0, 0.1,
             'max stamp difference of a vehicle/odom + vehicle/velocity pair'),
    ParamSpec('odom_when_untracked', False,
              'also publish apron/odom while not tracked (position = vehicle + 0, variance '
              f'{UNKNOWN_VAR:g}); off because LANDING_TARGET consumers ignore covariance'),
    _nonempty('map_frame', 'map', 'header.frame_id of apron/odom (world, ENU)'),
    _nonempty('apron_frame', 'apron', 'child_frame_id of apron/odom'),
    _nonempty('relative_frame', 'base_link',
              'frame_id of apron/relative(_velocity): heading-aligned FLU axes (Figure 8)'),
]

PARAMS = _estimator_specs() + NODE_PARAMS

_CLASS_PREFIX = {'CameraParams': 'camera.', 'HorizontalParams': 'horizontal.',
                 'VerticalParams': 'vertical.', 'EstimatorParams': ''}


def estimator_params_from(values: dict) -> EstimatorParams:
    """Build EstimatorParams from validated flat values; ParameterError names the parameter."""
    try:
        nested = {prefix: cls(**{f.name: values[f'{prefix}.{f.name}'] for f in fields(cls)})
                  for prefix, cls in SECTIONS}
        top = {f.name: values[f.name] for f in fields(EstimatorParams)
               if f.default is not MISSING}
        return EstimatorParams(**nested, **top)
    except ValueError as exc:
        text = str(exc)
        m = re.match(r'(\w+)\.(\w+)', text)
        name = (_CLASS_PREFIX.get(m.group(1), '') + m.group(2)) if m else '?'
        raise ParameterError(f'parameter {name!r}: {text}') from exc


def _locked(method):
    """Run a callback under the node's lock (the loop thread steps the same estimator)."""
    @functools.wraps(method)
    def wrapper(self, *args):
        with self._lock:
            return method(self, *args)
    return wrapper


class ApronEstimatorNode(Node):
    """The ``apron_estimator`` node; interface tables in the package README (section Node)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('apron_estimator', **kwargs)
        try:
            p = declare_and_validate(self, PARAMS)
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise ParameterError(f'apron_estimator: {exc}') from exc
        self.cfg = p
        self.estimator = ApronEstimator(estimator_params_from(p))
        self.pairer = LocalPositionPairer(p['position_pair_tolerance_s'])
        self._timeout_s = p['input_timeout_s']
        self._g = p['gravity_mps2']
        self._imu_min_spacing_s = 0.5 / p['rate_hz']
        self._odom_when_untracked = p['odom_when_untracked']
        self._clock = self.get_clock()
        vp = self.estimator.params.vertical
        # world surface height/velocity uncertainty (see README, Node: apron/odom covariance)
        self._surface_var = vp.sigma_altitude_m ** 2 + vp.sigma_lidar_m ** 2
        self._surface_v_var = vp.sigma_vz_mps ** 2

        #: last accepted stamp per input stream (None = never)
        self.last_stamp: dict[str, float | None] = {
            'imu': None, 'odom': None, 'velocity': None, 'range': None, 'camera': None}
        #: messages refused by the node (never reach the estimator or an output)
        self.rejected: dict[str, int] = {
            'stale_stamp': 0, 'future_stamp': 0, 'malformed_cloud': 0, 'no_orientation': 0,
            'bad_quaternion': 0, 'non_finite': 0, 'out_of_order': 0, 'implausible': 0}
        #: timer ticks that published nothing, by reason
        self.withheld: dict[str, int] = {'no_attitude': 0, 'no_position': 0,
                                         'non_finite_output': 0, 'clock_not_advancing': 0}
        #: publications by trigger; IMU messages not publishing (closer than 0.5/rate_hz)
        self.triggers: dict[str, int] = {'imu': 0, 'camera': 0, 'imu_thinned': 0, 'loop': 0}
        self.published = 0
        self._t_published = -math.inf      # t_s of the last published state
        self._t_imu_published = -math.inf  # node time of the last IMU-triggered publication
        self._published_at_diag = 0
        self._withheld_reason = 'starting'
        self.last_state = None

        self.pub_state = self.create_publisher(Float64MultiArray, 'apron/state', RELIABLE_QOS)
        self.pub_odom = self.create_publisher(Odometry, 'apron/odom', RELIABLE_QOS)
        self.pub_rel = self.create_publisher(PointStamped, 'apron/relative', RELIABLE_QOS)
        self.pub_rel_vel = self.create_publisher(Vector3Stamped, 'apron/relative_velocity',
                                                 RELIABLE_QOS)
        self.pub_visible = self.create_publisher(Bool, 'apron/visible', RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, 'diagnostics', RELIABLE_QOS)
        self.create_subscription(PointCloud, 'pixy/blocks', self._on_blocks, SENSOR_QOS)
        self.create_subscription(Imu, 'vehicle/imu', self._on_imu, SENSOR_QOS)
        self.create_subscription(Odometry, 'vehicle/odom', self._on_odom, SENSOR_QOS)
        self.create_subscription(TwistStamped, 'vehicle/velocity', self._on_velocity,
                                 SENSOR_QOS)
        self.create_subscription(Range, 'vehicle/range', self._on_range, SENSOR_QOS)
        self._build_messages(p)
        self.create_timer(1.0, self._publish_diagnostics)
        # the estimator is not thread-safe: callbacks and the loop thread take this lock
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.loop: PhaseLockedLoop | None = None
        self._loop_thread: threading.Thread | None = None
        self.loop_errors = 0
        if p['clock'] == 'loop':
            try:
                lp = PhaseLockParams(period_s=1.0 / p['rate_hz'], lead_s=p['loop_lead_s'],
                                     max_slew_s=p['loop_max_slew_s'],
                                     max_wait_s=p['loop_max_wait_s'])
            except ValueError as exc:
                raise ParameterError(f'apron_estimator: loop parameters: {exc}') from exc
            self.loop = PhaseLockedLoop(lp, time.monotonic())
            self._loop_thread = threading.Thread(target=self._run_loop, daemon=True,
                                                 name='apron_estimator_loop')
            self._loop_thread.start()
            how = f"a {p['rate_hz']:g} Hz loop phase-locked to pixy/blocks"
        else:
            how = f"vehicle/imu (<= {p['rate_hz']:g} Hz) and pixy/blocks"
        self.get_logger().info(
            f"apron estimator clocked by {how}, FOV {p['camera.fov_x_deg']:g}x"
            f"{p['camera.fov_y_deg']:g} deg, paper_exact={p['camera.paper_exact']}")

    # --- helpers ---------------------------------------------------------------------------

    def _now_s(self) -> float:
        return self._clock.now().nanoseconds * 1e-9

    def _build_messages(self, p: dict) -> None:
        """Output messages built once and refilled per publication (publish serialises)."""
        st = Float64MultiArray()
        st.layout.dim = [MultiArrayDimension(label=APRON_STATE_LAYOUT, size=APRON_STATE_V1_LEN,
                                             stride=APRON_STATE_V1_LEN)]
        self._msg_state = st
        self._msg_visible = Bool()
        od = Odometry()
        od.header.frame_id = p['map_frame']
        od.child_frame_id = p['apron_frame']
        od.pose.pose.orientation.w = 1.0  # apron axes = map axes (its heading is not observed)
        self._msg_odom = od
        rel = PointStamped()
        rel.header.frame_id = p['relative_frame']
        self._msg_rel = rel
        vel = Vector3Stamped()
        vel.header.frame_id = p['relative_frame']
        self._msg_rel_vel = vel

    def _reject(self, reason: str, what: str) -> None:
        self.rejected[reason] += 1
        self.get_logger().warn(f'rejected {what}: {reason} ({self.rejected[reason]} so far)',
                               throttle_duration_sec=2.0)

    def _stamp(self, header, what: str) -> float | None:
        """header.stamp in seconds, or None (counted) if stale or in the future."""
        t = stamp_to_s(header.stamp)
        now = self._now_s()
        if now - t > self._timeout_s:
            self._reject('stale_stamp', what)
            return None
        if t - now > self._timeout_s:
            self._reject('future_stamp', what)
            return None
        return t

    # --- subscriptions ---------------------------------------------------------------------

    @_locked
    def _on_imu(self, msg: Imu) -> None:
        t = self._stamp(msg.header, 'vehicle/imu')
        if t is None:
            return
        if msg.orientation_covariance[0] == -1.0:  # REP-145: no orientation estimate
            self._reject('no_orientation', 'vehicle/imu')
            return
        o = msg.orientation
        q = normalised_quaternion(o.w, o.x, o.y, o.z)
        if q is None:
            self._reject('bad_quaternion' if all(map(math.isfinite, (o.w, o.x, o.y, o.z)))
                         else 'non_finite', 'vehicle/imu orientation')
            return
        roll, pitch, yaw = quaternion_to_euler(*q)
        self.estimator.on_attitude(t, roll, pitch, yaw)
        self.last_stamp['imu'] = t
        a = msg.linear_acceleration
        acc = world_accel_from_specific_force(q, (a.x, a.y, a.z), self._g)
        if acc is None:
            self._reject('non_finite', 'vehicle/imu linear_acceleration')
        elif max(abs(a.x), abs(a.y), abs(a.z)) > MAX_SPECIFIC_FORCE_MPS2:
            self._reject('implausible', 'vehicle/imu linear_acceleration (beyond 16 g)')
        else:
            self.estimator.on_accel(t, acc)
        if self.loop is not None:
            return                  # clock=loop: the loop thread publishes
        # the attitude was accepted: this message is a tick of the control clock
        now = self._now_s()
        if now - self._t_imu_published < self._imu_min_spacing_s:
            self.triggers['imu_thinned'] += 1
            return
        if self._publish(now):
            self._t_imu_published = now
            self.triggers['imu'] += 1

    @_locked
    def _on_odom(self, msg: Odometry) -> None:
        t = self._stamp(msg.header, 'vehicle/odom')
        if t is None:
            return
        p = msg.pose.pose.position
        self.last_stamp['odom'] = t
        self._feed_position(self.pairer.on_position(t, (p.x, p.y, p.z)), t, 'vehicle/odom')

    @_locked
    def _on_velocity(self, msg: TwistStamped) -> None:
        t = self._stamp(msg.header, 'vehicle/velocity')
        if t is None:
            return
        v = msg.twist.linear
        self.last_stamp['velocity'] = t
        self._feed_position(self.pairer.on_velocity(t, (v.x, v.y, v.z)), t,
                            'vehicle/velocity')

    def _feed_position(self, pair, t: float, what: str) -> None:
        if pair is not None:
            self.estimator.on_local_position(pair.t_s, pair.position_m, pair.velocity_mps)
        elif t < self.pairer.last_t_s:
            self._reject('out_of_order', what)

    @_locked
    def _on_range(self, msg: Range) -> None:
        t = self._stamp(msg.header, 'vehicle/range')
        if t is None:
            return
        self.last_stamp['range'] = t
        self.estimator.on_lidar(t, lidar_range(msg.range, msg.min_range, msg.max_range))

    @_locked
    def _on_blocks(self, msg: PointCloud) -> None:
        t = self._stamp(msg.header, 'pixy/blocks')
        if t is None:
            return
        pts = msg.points
        blocks = blocks_from_cloud([pt.x for pt in pts], [pt.y for pt in pts],
                                   {c.name: c.values for c in msg.channels})
        if blocks is None:
            self._reject('malformed_cloud', 'pixy/blocks (channels inconsistent with points)')
            return
        self.last_stamp['camera'] = t
        self.estimator.on_camera(t, blocks)
        if self.loop is not None and not self.loop.on_event(time.monotonic()):
            return                  # the next loop tick, at most loop_max_wait_s away, has it
        if self._publish(self._now_s()):  # the processed frame goes out at once
            self.triggers['camera'] += 1

    # --- the loop (clock=loop) -------------------------------------------------------------

    def _run_loop(self) -> None:
        """Loop thread: sleep to each deadline of :attr:`loop`, then publish ``state(now)``."""
        loop, stop = self.loop, self._stop
        while not stop.is_set():
            delay = loop.wait_s(time.monotonic())
            if delay > 0.0:
                if stop.wait(delay):
                    break
                continue            # re-check: a camera frame may have moved the deadline
            try:
                with self._lock:
                    loop.tick(time.monotonic())
                    if self.context.ok() and self._publish(self._now_s()):
                        self.triggers['loop'] += 1
            except Exception as exc:  # never let one bad tick stop the loop
                if stop.is_set() or not self.context.ok():
                    break
                self.loop_errors += 1
                self.get_logger().error(f'loop tick failed: {exc!r}',
                                        throttle_duration_sec=2.0)

    def destroy_node(self) -> None:
        self._stop.set()
        th = self._loop_thread
        if th is not None and th.is_alive() and th is not threading.current_thread():
            th.join(timeout=1.0)
        return super().destroy_node()

    # --- output ----------------------------------------------------------------------------

    def _withhold_reason(self, now: float) -> str:
        t_att = self.last_stamp['imu']
        if t_att is None or now - t_att > self._timeout_s:
            return 'no_attitude'
        t_pos = self.pairer.last_t_s
        if not math.isfinite(t_pos) or now - t_pos > self._timeout_s:
            return 'no_position'
        return ''

    def _publish(self, now: float) -> bool:
        """Publish ``state(now)`` and the derived outputs; False (counted) if withheld."""
        reason = self._withhold_reason(now)
        if not reason and now <= self._t_published:
            reason = 'clock_not_advancing'   # downstream rejects repeated or older t_s
        if not reason:
            st = self.estimator.state(now)
            data = st.to_array()
            if any(map(math.isnan, data)):  # defensive: the core never does this
                reason = 'non_finite_output'
        if reason:
            self.withheld[reason] += 1
            if reason != self._withheld_reason:
                self.get_logger().warn(f'publishing no apron state: {reason}',
                                       throttle_duration_sec=2.0)
            self._withheld_reason = reason
            return False
        self._withheld_reason = ''
        self.last_state = st
        self._t_published = now
        self.published += 1

        msg = self._msg_state
        msg.data = array('d', data)
        self.pub_state.publish(msg)
        # Lazy: the derived topics (viewers, figures, LANDING_TARGET) are built and published
        # only while something subscribes; the control chain reads apron/state alone.
        if self.pub_visible.get_subscription_count():
            vis = self._msg_visible
            vis.data = st.visible
            self.pub_visible.publish(vis)
        if (st.tracked or self._odom_when_untracked) and self.pub_odom.get_subscription_count():
            self.pub_odom.publish(self._odom(st, now))
        if st.tracked and (self.pub_rel.get_subscription_count()
                           or self.pub_rel_vel.get_subscription_count()):
            rel = self._msg_rel
            s_to_stamp(now, rel.header.stamp)
            rel.point.x, rel.point.y = st.rel_position_body_m
            rel.point.z = -st.vertical.height_m if st.vertical.valid else 0.0
            vel = self._msg_rel_vel
            s_to_stamp(now, vel.header.stamp)
            vel.vector.x, vel.vector.y = st.rel_velocity_body_mps
            vel.vector.z = st.vertical.closing_speed_mps if st.vertical.valid else 0.0
            self.pub_rel.publish(rel)
            self.pub_rel_vel.publish(vel)
        return True

    def _odom(self, st, now: float) -> Odometry:
        """apron/odom: (apron x, y, surface height), (apron vx, vy, surface vz) in map."""
        v = st.vertical
        od = self._msg_odom
        s_to_stamp(now, od.header.stamp)
        pos = od.pose.pose.position
        pos.x, pos.y = st.apron_position_m
        pos.z = v.surface_height_m if v.valid else 0.0
        lin = od.twist.twist.linear
        lin.x, lin.y = st.apron_velocity_mps
        lin.z = v.surface_vz_mps if v.valid else 0.0
        if st.tracked:
            var_x, var_y = st.rel_position_var_m2
            var_vx, var_vy = self._rel_velocity_var(now)
        else:
            var_x = var_y = var_vx = var_vy = UNKNOWN_VAR
        var_z, var_vz = ((self._surface_var, self._surface_v_var) if v.valid
                         else (UNKNOWN_VAR, UNKNOWN_VAR))
        pc = od.pose.covariance
        pc[0], pc[7], pc[14] = var_x, var_y, var_z
        pc[21] = pc[28] = pc[35] = UNKNOWN_VAR
        tc = od.twist.covariance
        tc[0], tc[7], tc[14] = var_vx, var_vy, var_vz
        tc[21] = tc[28] = tc[35] = UNKNOWN_VAR
        return od

    def _rel_velocity_var(self, now: float) -> tuple[float, float]:
        """Relative-velocity variances predicted to now: c + q·dt of (31)-(32)."""
        h = self.estimator.horizontal
        kf = h.kf
        dt = max(0.0, now - h.t_filter) if h.t_filter is not None else 0.0
        q = h.params.accel_psd_m2ps3
        return kf.cx + q * dt, kf.cy + q * dt

    # --- diagnostics -----------------------------------------------------------------------

    @_locked
    def _publish_diagnostics(self) -> None:
        now = self._now_s()
        rate = self.published - self._published_at_diag  # the timer runs at 1 Hz
        self._published_at_diag = self.published
        if not rate:  # nothing triggered a publication (all inputs stopped?): say why
            self._withheld_reason = self._withhold_reason(now) or self._withheld_reason
        status = DiagnosticStatus(name='apron_estimator: apron state', hardware_id='pixy')
        st = self.last_state
        if self._withheld_reason:
            status.level = DiagnosticStatus.WARN
            status.message = f'no apron state published: {self._withheld_reason}'
        else:
            status.level = DiagnosticStatus.OK
            tracked = st is not None and st.tracked
            status.message = f"{rate} states/s, {'tracked' if tracked else 'not tracked'}"
        values = {'states_per_s': str(rate), 'published': str(self.published)}
        for name, t in self.last_stamp.items():
            values[f'age_{name}_s'] = 'inf' if t is None else f'{now - t:.3f}'
        values.update({f'rejected_{k}': str(v) for k, v in self.rejected.items()})
        values.update({f'withheld_{k}': str(v) for k, v in self.withheld.items()})
        values.update({f'trigger_{k}': str(v) for k, v in self.triggers.items()})
        if self.loop is not None:
            values.update(loop_ticks=str(self.loop.ticks), loop_skipped=str(self.loop.skipped),
                          loop_overruns=str(self.loop.overruns),
                          loop_errors=str(self.loop_errors))
        values.update({f'core_rejected_{k}': str(v)
                       for k, v in self.estimator.rejected.items()})
        if st is not None:
            values.update(tracked=str(st.tracked), visible=str(st.visible),
                          time_since_seen_s=f'{st.time_since_seen_s:.3f}',
                          vertical_valid=str(st.vertical.valid),
                          height_m=f'{st.vertical.height_m:.3f}',
                          surface_epoch=str(st.vertical.surface_epoch))
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        s_to_stamp(now, msg.header.stamp)
        self.pub_diag.publish(msg)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: ApronEstimatorNode(), args)


if __name__ == '__main__':
    sys.exit(main())
