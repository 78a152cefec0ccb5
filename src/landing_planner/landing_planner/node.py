"""ROS 2 adapter of the landing planner and the horizontal position loop.

Thin: parameters, topics, services, a watchdog timer and message conversions. The algorithm is
the pure
core — :class:`~landing_planner.planner.LandingPlanner` (paper section 3.3, Steps 1-16) and
:class:`~landing_planner.horizontal.HorizontalController` (inverse of the translational rows of
model (2)) — wired exactly as :func:`deckland.runner.run_landing` wires them: every tick
``planner.step`` first, then ``HorizontalController.step`` on the planner's setpoint and
feed-forward with the *measured* position, velocity and yaw; the command is (roll, pitch) from
the horizontal loop and yaw from the planner.

Event-driven tick: the node steps *in the ``apron/state`` callback*, once per new accepted
apron state (the estimator publishes one per autopilot IMU message, ~100 Hz, and one per
processed camera frame), and publishes ``control/attitude`` and ``planner/reference`` right
there. A watchdog timer (every ``1/rate_hz`` s) steps only while ``apron/state`` is stale, so
the mission logic keeps running on the core's fallback. Per tick (node clock ``now``):

1. Nothing is stepped before the first vehicle state (odom + velocity) arrives.
2. Planner time is the node clock: ``t_s = now``, ``dt_s`` = time since the last step (the
   nominal period ``1/rate_hz`` after a pause longer than ``input_timeout_s``; a tick whose
   clock did not advance is skipped).
3. ``apron/state`` older than ``input_timeout_s`` (or never received): the watchdog steps
   with the core's safe fallback ``ApronState.untracked(now)`` (not tracked, vertical state
   invalid): the planner then pauses and, after its ``invalid_timeout_s``, goes to HOLD
   (FALLBACK when low in DESCEND/FINAL).
4. A stale vehicle state is fed as a non-finite ``VehicleState`` (the core's only
   "vehicle invalid" path; it counts it in ``planner.rejected['nan']``), so the planner's safe
   mode runs; ``control/attitude``, ``planner/reference`` and ``planner/setpoint`` are then
   withheld (the bridge stops streaming and the autopilot's offboard-loss failsafe acts).
5. ``control/attitude`` is also withheld while the planner disables thrust (LANDED, IDLE on
   the ground); ``control/enabled`` carries that flag (latched, published on change).

Stamps: every command is stamped with the ``t_s`` of the apron state it was computed from
(the fallback's ``t_s`` = ``now`` when the apron state is stale), like the dob_altitude node,
so a consumer measures end-to-end latency as (its clock − header.stamp). Stamps never go
backwards (clamped to the last one published), because the bridge and the altitude node
reject out-of-order commands.
"""

from __future__ import annotations

from dataclasses import fields
import math
import sys

from apron_estimator.types import ApronState, decode_apron_array
from deckland_common.checks import stamp_verdict
from deckland_common.frames import euler_to_quaternion, quaternion_to_euler
from deckland_common.params import ParameterError, ParamSpec, one_of, positive
from deckland_common.ros_node import (
    LATCHED_QOS,
    RELIABLE_QOS,
    SENSOR_QOS,
    all_finite,
    declare_and_validate,
    run_node,
    s_to_stamp,
    stamp_to_s,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, QuaternionStamped, Transform, Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from std_msgs.msg import Bool, Float64MultiArray, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint

from landing_planner.horizontal import HorizontalController, HorizontalParams
from landing_planner.planner import DESCENT_PROFILES, LandingPlanner, PlannerParams
from landing_planner.types import VERTICAL_RELATIVE, Mode, VehicleState

# --- parameters ------------------------------------------------------------------------------

#: Meaning of every PlannerParams field exposed as a ROS parameter (same name).
PLANNER_DESCRIPTIONS: dict[str, str] = {
    'max_xy_dist_m': 'accept a target only this close (m) to the landing area',
    'acceptance_radius_m': 'horizontally close (m) to the target: may descend (paper 4.2)',
    'acceptance_hold_s': 'stay within the acceptance radius this long (s) before descending',
    'acceptance_hysteresis': 'leave acceptance_radius x this → pause the descent and re-align',
    'align_speed_mps': 'slew limit (m/s) of the setpoint toward the target',
    'approach_height_m': 'height (m) above the surface below for the approach (paper 4.2)',
    'approach_speed_mps': 'horizontal speed (m/s) of the GPS approach leg (Step 2)',
    'approach_accel_mps2': 'acceleration limit (m/s^2) of the approach/search path',
    'approach_jerk_mps3': 'jerk limit (m/s^3) of the approach/search path',
    'arrival_radius_m': 'vehicle this close (m) to the landing area = arrived',
    'arrival_wait_s': 'at the area this long (s) without a target → search (Step 3)',
    'vertical_speed_mps': 'climb/descent speed (m/s) to approach, search and hold heights',
    'vertical_accel_mps2': 'acceleration limit (m/s^2) of the vertical reference',
    'vertical_jerk_mps3': 'jerk limit (m/s^3) of the vertical reference',
    'descent_speed_mps': 'descent speed (m/s) relative to the deck (Step 6)',
    'final_approach_height_m': 'height (m) where the final approach starts (Step 9)',
    'final_speed_mps': 'final descent speed (m/s) relative to the deck (Step 10)',
    'final_press_m': 'final reference this far (m) below the contact height',
    'final_leash_m': 'final descent: the height reference at most this far (m) below the '
                     'measured height (bounds the catch-up speed of the altitude law)',
    'search_height_m': 'search height (m) above the surface below (Step 12)',
    'search_speed_mps': 'horizontal speed (m/s) of the search pattern',
    'search_radius_m': 'half side (m) of the square search pattern',
    'search_hold_s': 'hover (s) at the pattern centre before flying the square',
    'search_timeout_s': 'duration (s) of one search attempt',
    'max_searches': 'search attempts before the fallback landing (Steps 11, 14)',
    'target_lost_timeout_s': 'target unseen this long (s) = lost (Step 8)',
    'fallback_speed_mps': 'fallback descent speed (m/s) above the final-approach height',
    'gear_height_m': 'body origin above the bottom of the landing gear (m)',
    'landed_height_tol_m': 'landed: height within this (m) of gear_height_m',
    'landed_speed_tol_mps': 'landed: closing speed magnitude below this (m/s)',
    'landed_hold_s': 'landed: the conditions held this long (s) (Step 15)',
    'max_target_sigma_m': 'no descent while the target position σ (m) exceeds this (an '
                          'unresolved rival IR blob inflates it)',
    'landed_press_m': 'landed: the height reference already this far (m) below the measured '
                      'height (< final_press_m)',
    'invalid_timeout_s': 'invalid vehicle/vertical state this long (s) → safe mode',
    'descent_profile': "'deck_relative' (paper) or 'constant_rate' (world-rate baseline)",
    'constant_rate_mps': "world descent rate (m/s) of the 'constant_rate' profile",
}

#: ROS parameter name → HorizontalParams field, with its meaning.
HORIZONTAL_FIELDS: dict[str, tuple[str, str]] = {
    'xy_kp': ('kp', 'horizontal PID k_p (m/s^2 per m)'),
    'xy_kd': ('kd', 'horizontal PID k_d (m/s^2 per m/s of velocity error)'),
    'xy_ki': ('ki', 'horizontal PID k_i (m/s^2 per m s)'),
    'xy_precise_kp': ('precise_kp', 'k_p over the deck (DESCEND/FINAL)'),
    'xy_precise_kd': ('precise_kd', 'k_d over the deck (DESCEND/FINAL)'),
    'xy_precise_ki': ('precise_ki', 'k_i over the deck (DESCEND/FINAL)'),
    'xy_max_accel_mps2': ('max_accel_mps2', 'horizontal acceleration command limit (m/s^2)'),
    'max_tilt_rad': ('max_tilt_rad', 'tilt limit of the attitude command (rad)'),
    'xy_max_integral_accel_mps2': ('max_integral_accel_mps2',
                                   'clamp of the integral term per axis (m/s^2)'),
    'xy_integral_zone_m': ('integral_zone_m',
                           'integrate only while the position error is below this (m)'),
    'gravity_mps2': ('gravity_mps2', 'gravity used to turn acceleration into tilt (m/s^2)'),
}

_H_RULES = {
    'kp': (lambda v: v > 0, 'must be > 0'), 'kd': (lambda v: v >= 0, 'must be >= 0'),
    'ki': (lambda v: v >= 0, 'must be >= 0'),
    'precise_kp': (lambda v: v > 0, 'must be > 0'),
    'precise_kd': (lambda v: v >= 0, 'must be >= 0'),
    'precise_ki': (lambda v: v >= 0, 'must be >= 0'),
    'max_accel_mps2': (lambda v: v > 0, 'must be > 0'),
    'max_tilt_rad': (lambda v: 0 < v < math.radians(60.0), 'must be in (0, 1.0472) (60 deg)'),
    'max_integral_accel_mps2': (lambda v: v >= 0, 'must be >= 0'),
    'integral_zone_m': (lambda v: v > 0, 'must be > 0'),
    'gravity_mps2': (lambda v: v > 0, 'must be > 0'),
}


def _planner_specs() -> list[ParamSpec]:
    defaults = PlannerParams()
    specs = [
        ParamSpec('landing_area_x_m', float(defaults.landing_area_m[0]),
                  'landing area (expected apron position), ENU x / east (m)'),
        ParamSpec('landing_area_y_m', float(defaults.landing_area_m[1]),
                  'landing area (expected apron position), ENU y / north (m)'),
    ]
    for f in fields(PlannerParams):
        if f.name == 'landing_area_m':
            continue
        default = getattr(defaults, f.name)
        text = PLANNER_DESCRIPTIONS.get(f.name, f'PlannerParams.{f.name} (landing_planner '
                                        'README)')
        if f.name == 'descent_profile':
            specs.append(one_of(f.name, default, DESCENT_PROFILES, text))
        elif f.name == 'max_searches':
            specs.append(ParamSpec(f.name, int(default), text, lambda v: v >= 0,
                                   'must be >= 0'))
        elif f.name == 'acceptance_hysteresis':
            specs.append(ParamSpec(f.name, float(default), text, lambda v: v >= 1.0,
                                   'must be >= 1'))
        else:
            specs.append(positive(f.name, float(default), text))
    return specs


def _horizontal_specs() -> list[ParamSpec]:
    defaults = HorizontalParams()
    out = []
    for name, (field_name, text) in HORIZONTAL_FIELDS.items():
        check, rule = _H_RULES[field_name]
        out.append(ParamSpec(name, float(getattr(defaults, field_name)), text, check, rule))
    return out


PARAMS: list[ParamSpec] = [
    *_planner_specs(),
    *_horizontal_specs(),
    ParamSpec('rate_hz', 100.0,
              'nominal loop rate (Hz): the loop steps per apron/state; at this rate the '
              'watchdog steps while apron/state is stale, 1/rate_hz is the dt after a pause',
              lambda v: 1.0 <= v <= 1000.0, 'must be in [1, 1000]'),
    positive('input_timeout_s', 0.3,
             'apron/state or vehicle state older than this (s) = stale'),
    ParamSpec('map_frame', 'map', 'world frame id (ENU): required on vehicle/odom and '
              'vehicle/velocity, used on every output', lambda v: bool(v.strip()),
              'must not be empty'),
]


def params_from(values: dict) -> tuple[PlannerParams, HorizontalParams]:
    """Build the core parameter objects from validated ROS parameter values.

    The cores' own cross-field checks (e.g. the height ordering) raise ``ValueError``; it is
    turned into a :class:`ParameterError` naming the node.
    """
    kw = {f.name: values[f.name] for f in fields(PlannerParams)
          if f.name != 'landing_area_m' and f.name in values}
    kw['landing_area_m'] = (values['landing_area_x_m'], values['landing_area_y_m'])
    hkw = {field_name: values[name] for name, (field_name, _) in HORIZONTAL_FIELDS.items()}
    try:
        return PlannerParams(**kw), HorizontalParams(**hkw)
    except ValueError as exc:
        raise ParameterError(f'landing_planner: {exc}') from exc


# --- node ------------------------------------------------------------------------------------

_NAN3 = (math.nan, math.nan, math.nan)


class LandingPlannerNode(Node):
    """The ``landing_planner`` node; interface tables in the package README (section Node)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('landing_planner', **kwargs)
        try:
            p = declare_and_validate(self, PARAMS)
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise ParameterError(f'landing_planner: {exc}') from exc
        self.cfg = p
        planner_params, horizontal_params = params_from(p)
        self.planner = LandingPlanner(planner_params)
        self.horizontal = HorizontalController(horizontal_params)
        self._period_s = 1.0 / p['rate_hz']
        self._timeout_s = p['input_timeout_s']
        self._map = p['map_frame']
        self._clock = self.get_clock()

        self._apron: ApronState | None = None
        # vehicle: odom (stamp, position, roll, pitch, yaw) and velocity (stamp, v)
        self._odom: tuple[float, tuple[float, float, float], float, float, float] | None = None
        self._vel: tuple[float, tuple[float, float, float]] | None = None
        self._landed = False
        self._t_step: float | None = None      # node time of the last planner step
        self._last_stamp = -math.inf           # last stamp published on a command
        self._mode_published: Mode | None = None
        self._enabled_published: bool | None = None
        self._withheld_reason = 'starting'
        self.last_output = None
        self.last_command: tuple[float, float] | None = None
        #: refused messages, by reason (never reach the cores or an output)
        self.rejected: dict[str, int] = {
            'non_finite': 0, 'bad_size': 0, 'bad_layout': 0, 'bad_frame': 0,
            'bad_quaternion': 0, 'out_of_order': 0, 'stale_stamp': 0, 'future_stamp': 0}
        #: ticks that published no command, by reason
        self.withheld: dict[str, int] = {
            'no_vehicle': 0, 'vehicle_stale': 0, 'thrust_disabled': 0, 'non_finite_output': 0,
            'clock_not_advancing': 0}
        #: planner steps, ticks with a stale apron state (fallback fed), commands published
        self.counts: dict[str, int] = {'steps': 0, 'apron_fallback': 0, 'attitude': 0,
                                       'reference': 0}
        self._steps_at_diag = 0

        self.pub_attitude = self.create_publisher(QuaternionStamped, 'control/attitude',
                                                  RELIABLE_QOS)
        self.pub_reference = self.create_publisher(MultiDOFJointTrajectory, 'planner/reference',
                                                   RELIABLE_QOS)
        self.pub_setpoint = self.create_publisher(PoseStamped, 'planner/setpoint', RELIABLE_QOS)
        self.pub_mode = self.create_publisher(String, 'planner/mode', LATCHED_QOS)
        self.pub_enabled = self.create_publisher(Bool, 'control/enabled', LATCHED_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, 'diagnostics', RELIABLE_QOS)
        self.create_subscription(Float64MultiArray, 'apron/state', self._on_apron, SENSOR_QOS)
        self.create_subscription(Odometry, 'vehicle/odom', self._on_odom, SENSOR_QOS)
        self.create_subscription(TwistStamped, 'vehicle/velocity', self._on_velocity,
                                 SENSOR_QOS)
        self.create_subscription(Bool, 'vehicle/landed', self._on_landed, LATCHED_QOS)
        self.create_service(Trigger, 'planner/start_landing', self._srv_start)
        self.create_service(Trigger, 'planner/abort', self._srv_abort)
        self.create_service(Trigger, 'planner/takeoff', self._srv_takeoff)
        self._build_messages()
        self.create_timer(self._period_s, self._on_watchdog)
        self.create_timer(1.0, self._publish_diagnostics)
        self._publish_mode()
        self.get_logger().info(
            f"landing planner stepped per apron/state (watchdog {p['rate_hz']:g} Hz), "
            'landing area '
            f"({p['landing_area_x_m']:.2f}, {p['landing_area_y_m']:.2f}) m, profile "
            f"{p['descent_profile']!r}")

    # --- helpers ---------------------------------------------------------------------------

    def _now_s(self) -> float:
        return self._clock.now().nanoseconds * 1e-9

    def _build_messages(self) -> None:
        """Command messages built once and refilled per tick (publish serialises them)."""
        att = QuaternionStamped()
        att.header.frame_id = self._map
        self._msg_att = att
        self._tf, self._vel_ff, self._acc = Transform(), Twist(), Twist()
        ref = MultiDOFJointTrajectory()
        ref.header.frame_id = self._map
        ref.joint_names = ['']
        ref.points = [MultiDOFJointTrajectoryPoint(transforms=[self._tf],
                                                   velocities=[self._vel_ff],
                                                   accelerations=[self._acc])]
        self._msg_ref = ref
        pose = PoseStamped()
        pose.header.frame_id = self._map
        self._msg_pose = pose

    def _reject(self, reason: str, what: str) -> None:
        self.rejected[reason] += 1
        self.get_logger().warn(f'rejected {what}: {reason} ({self.rejected[reason]} so far)',
                               throttle_duration_sec=2.0)

    def _stamp_ok(self, stamp_s: float, last_s: float | None, what: str) -> bool:
        """Finite, not older than the last accepted one, not stale, not in the future."""
        reason = stamp_verdict(stamp_s, last_s, self._now_s(), self._timeout_s)
        if reason is None:
            return True
        self._reject(reason, what)
        return False

    def _age(self, stamp_s: float | None, now: float) -> float:
        return math.inf if stamp_s is None else now - stamp_s

    # --- subscriptions ---------------------------------------------------------------------

    def _on_apron(self, msg: Float64MultiArray) -> None:
        dims = msg.layout.dim
        st, reason, detail = decode_apron_array(dims[0].label if dims else None, msg.data)
        if st is None:
            self._reject(reason, detail)
            return
        v = st.vertical
        # everything the planner reads must be finite (time_since_seen_s and camera_stamp_s
        # may legitimately be ±inf and are not used)
        if not all_finite(st.t_s, *st.rel_position_m, *st.apron_position_m,
                          *st.apron_velocity_mps, v.height_m, v.closing_speed_mps,
                          v.surface_height_m, v.last_rebase_m):
            self._reject('non_finite', 'apron/state')
            return
        if not self._stamp_ok(st.t_s, self._apron.t_s if self._apron else None, 'apron/state'):
            return
        self._apron = st
        self._step(self._now_s(), st)   # event-driven: the commands go out in this callback

    def _on_odom(self, msg: Odometry) -> None:
        if msg.header.frame_id != self._map:
            self._reject('bad_frame', f'vehicle/odom (frame {msg.header.frame_id!r}, '
                         f'expected {self._map!r})')
            return
        pos = msg.pose.pose.position
        q = msg.pose.pose.orientation
        if not all_finite(pos.x, pos.y, pos.z, q.w, q.x, q.y, q.z):
            self._reject('non_finite', 'vehicle/odom')
            return
        n = math.sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z)
        if abs(n - 1.0) > 0.05:
            self._reject('bad_quaternion', f'vehicle/odom (norm {n:.3f})')
            return
        stamp = stamp_to_s(msg.header.stamp)
        if not self._stamp_ok(stamp, self._odom[0] if self._odom else None, 'vehicle/odom'):
            return
        roll, pitch, yaw = quaternion_to_euler(q.w / n, q.x / n, q.y / n, q.z / n)
        self._odom = (stamp, (pos.x, pos.y, pos.z), roll, pitch, yaw)

    def _on_velocity(self, msg: TwistStamped) -> None:
        if msg.header.frame_id != self._map:
            self._reject('bad_frame', f'vehicle/velocity (frame {msg.header.frame_id!r}, '
                         f'expected {self._map!r})')
            return
        v = msg.twist.linear
        if not all_finite(v.x, v.y, v.z):
            self._reject('non_finite', 'vehicle/velocity')
            return
        stamp = stamp_to_s(msg.header.stamp)
        if not self._stamp_ok(stamp, self._vel[0] if self._vel else None, 'vehicle/velocity'):
            return
        self._vel = (stamp, (v.x, v.y, v.z))

    def _on_landed(self, msg: Bool) -> None:
        self._landed = bool(msg.data)

    # --- services (std_srvs/Trigger → the core's (ok, message)) ----------------------------

    def _service(self, fn, name: str, response):
        ok, message = fn(self._now_s())
        response.success, response.message = bool(ok), str(message)
        self.get_logger().info(f'{name}: {"ok" if ok else "refused"}: {message}')
        self._publish_mode()
        return response

    def _srv_start(self, request, response):
        return self._service(self.planner.start_landing, 'start_landing', response)

    def _srv_abort(self, request, response):
        return self._service(self.planner.abort, 'abort', response)

    def _srv_takeoff(self, request, response):
        return self._service(self.planner.takeoff, 'takeoff', response)

    # --- loop ------------------------------------------------------------------------------

    def _vehicle(self, now: float) -> VehicleState | None:
        """The vehicle state if both parts are fresh, else None."""
        if self._odom is None or self._vel is None:
            return None
        stamp, pos, roll, pitch, yaw = self._odom
        v_stamp, vel = self._vel
        if now - stamp > self._timeout_s or now - v_stamp > self._timeout_s:
            return None
        return VehicleState(t_s=stamp, position_m=pos, velocity_mps=vel, roll_rad=roll,
                            pitch_rad=pitch, yaw_rad=yaw, landed=self._landed)

    def _withhold(self, reason: str) -> None:
        self.withheld[reason] += 1
        if reason != self._withheld_reason:
            self.get_logger().warn(f'publishing no commands: {reason}',
                                   throttle_duration_sec=2.0)
        self._withheld_reason = reason

    def _on_watchdog(self) -> None:
        """Step on the core's fallback while apron/state is stale (or never received)."""
        now = self._now_s()
        apron = self._apron
        if apron is not None and now - apron.t_s <= self._timeout_s:
            return                          # the chain is alive: apron/state drives the steps
        if self._odom is not None and self._vel is not None:
            self.counts['apron_fallback'] += 1
        self._step(now, ApronState.untracked(now))   # the core's safe fallback (module doc)

    def _step(self, now: float, apron: ApronState) -> None:
        """One planner + horizontal-loop tick on ``apron``; publish the commands."""
        if self._odom is None or self._vel is None:
            self._withhold('no_vehicle')   # nothing known yet: the planner is not stepped
            return
        if self._t_step is not None and now <= self._t_step:
            self._withhold('clock_not_advancing')
            return
        dt = now - self._t_step if self._t_step is not None else self._period_s
        if dt > self._timeout_s:
            dt = self._period_s            # after a pause: restart at the nominal period
        self._t_step = now

        vehicle = self._vehicle(now)
        fed = vehicle if vehicle is not None else VehicleState(
            t_s=now, position_m=_NAN3, velocity_mps=_NAN3, roll_rad=math.nan,
            pitch_rad=math.nan, yaw_rad=math.nan, landed=self._landed)

        # --- the same order as deckland.runner: planner, then the horizontal loop ----------
        out = self.planner.step(now, dt, fed, apron)
        self.counts['steps'] += 1
        self.last_output = out
        self._publish_mode()
        self._publish_enabled(out.thrust_enabled)
        if vehicle is None:
            self._withhold('vehicle_stale')
            return
        pos, vel = vehicle.position_m, vehicle.velocity_mps
        roll, pitch = self.horizontal.step(out.setpoint_m, out.velocity_ff_mps,
                                           (pos[0], pos[1]), (vel[0], vel[1]),
                                           vehicle.yaw_rad, dt, precise=out.precise_xy)
        if not all_finite(roll, pitch, out.yaw_rad, *out.setpoint_m, *out.velocity_ff_mps,
                          out.z_d_m, out.z_d_dot_mps, out.z_d_ddot_mps2):
            self._withhold('non_finite_output')   # defensive: the cores never do this
            return
        stamp_s = max(apron.t_s, self._last_stamp)
        self._last_stamp = stamp_s
        self._publish_reference(out, apron, stamp_s)
        if not out.thrust_enabled:
            self._withhold('thrust_disabled')
            return
        self._withheld_reason = ''
        self.last_command = (roll, pitch)
        att = self._msg_att
        s_to_stamp(stamp_s, att.header.stamp)
        q = att.quaternion
        q.w, q.x, q.y, q.z = euler_to_quaternion(roll, pitch, out.yaw_rad)
        self.pub_attitude.publish(att)
        self.counts['attitude'] += 1

    # --- publishers ------------------------------------------------------------------------

    def _publish_reference(self, out, apron: ApronState, stamp_s: float) -> None:
        sx, sy = out.setpoint_m
        fx, fy = out.velocity_ff_mps
        qw, qx, qy, qz = euler_to_quaternion(0.0, 0.0, out.yaw_rad)
        tf = self._tf
        tf.translation.x, tf.translation.y, tf.translation.z = sx, sy, out.z_d_m
        tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z = qw, qx, qy, qz
        vel = self._vel_ff.linear
        vel.x, vel.y, vel.z = fx, fy, out.z_d_dot_mps
        self._acc.linear.z = out.z_d_ddot_mps2
        ref = self._msg_ref
        s_to_stamp(stamp_s, ref.header.stamp)
        if ref.joint_names[0] != out.vertical_mode:
            ref.joint_names = [out.vertical_mode]
        self.pub_reference.publish(ref)
        self.counts['reference'] += 1

        # viewers: the setpoint as a map pose (a height above the surface is shifted by the
        # estimated surface height when it is known). Lazy: nothing in the control chain
        # reads it, so it is built and published only while something subscribes.
        if not self.pub_setpoint.get_subscription_count():
            return
        z = out.z_d_m
        if out.vertical_mode == VERTICAL_RELATIVE and apron.vertical.valid:
            z += apron.vertical.surface_height_m
        pose = self._msg_pose
        s_to_stamp(stamp_s, pose.header.stamp)
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = sx, sy, z
        o = pose.pose.orientation
        o.w, o.x, o.y, o.z = qw, qx, qy, qz
        self.pub_setpoint.publish(pose)

    def _publish_mode(self) -> None:
        mode = self.planner.mode
        if mode is self._mode_published:
            return
        if self._mode_published is not None:
            self.get_logger().info(f'mode {self._mode_published.name} → {mode.name}: '
                                   f'{self.planner.reason}')
        self._mode_published = mode
        self.pub_mode.publish(String(data=mode.name))

    def _publish_enabled(self, enabled: bool) -> None:
        if enabled is self._enabled_published:
            return
        self._enabled_published = enabled
        self.get_logger().info(f'control enabled: {enabled}')
        self.pub_enabled.publish(Bool(data=enabled))

    def _publish_diagnostics(self) -> None:
        now = self._now_s()
        steps = self.counts['steps']
        rate = steps - self._steps_at_diag  # the diagnostics timer runs at 1 Hz
        self._steps_at_diag = steps
        status = DiagnosticStatus(name='landing_planner: mission and horizontal loop',
                                  hardware_id=self._map)
        if self._withheld_reason and self._withheld_reason != 'thrust_disabled':
            status.level = DiagnosticStatus.WARN
            status.message = f'no commands published: {self._withheld_reason}'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{self.planner.mode.name}, {rate} steps/s'
        apron_age = self._age(self._apron.t_s if self._apron else None, now)
        odom_age = self._age(self._odom[0] if self._odom else None, now)
        vel_age = self._age(self._vel[0] if self._vel else None, now)
        values = {'mode': self.planner.mode.name, 'reason': self.planner.reason,
                  'searches': str(self.planner.searches), 'steps_per_s': str(rate),
                  'apron_age_s': f'{apron_age:.3f}', 'odom_age_s': f'{odom_age:.3f}',
                  'velocity_age_s': f'{vel_age:.3f}', 'landed': str(self._landed)}
        values.update({k: str(v) for k, v in self.counts.items()})
        values.update({f'rejected_{k}': str(v) for k, v in self.rejected.items()})
        values.update({f'withheld_{k}': str(v) for k, v in self.withheld.items()})
        values.update({f'planner_rejected_{k}': str(v)
                       for k, v in self.planner.rejected.items()})
        values.update({f'horizontal_rejected_{k}': str(v)
                       for k, v in self.horizontal.rejected.items()})
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: LandingPlannerNode(), args)


if __name__ == '__main__':
    sys.exit(main())
