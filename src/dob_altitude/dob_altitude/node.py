"""ROS 2 adapter of the altitude loop: the DOB (paper §3.1, (14)-(19)) or PID core.

Thin: parameters, topics, a watchdog timer and message conversions. The controller comes from
:func:`dob_altitude.adapter.make_controller` and its input from
:func:`dob_altitude.adapter.altitude_input` — the same wiring the in-process runner uses.

Event-driven loop: the controller steps *in the ``apron/state`` callback*, once per new
accepted apron state (the estimator publishes one per autopilot IMU message, ~100 Hz, and one
per processed camera frame), and ``control/thrust`` is published right there — no timer wait.

1. Withhold (publish nothing, count the reason, reset the controller so it restarts bumpless
   when inputs return) if ``control/enabled`` is False, or any of ``apron/state``,
   ``planner/reference``, ``vehicle/imu`` was never received or its stamp is older than
   ``input_timeout_s``, or the vertical estimate is not valid. A watchdog timer (period
   ``input_timeout_s / 2``) applies the same test when no apron state arrives at all, so the
   staleness is counted and the controller reset even when nothing triggers a step.
   Downstream the bridge then stops streaming and the autopilot's offboard-loss failsafe takes
   over; a NaN is never published.
2. The step uses dt = the difference of the ``ApronState.t_s`` stamps of the two samples (the
   interval over which σ of (14) changed; the first step after a reset uses 1/rate_hz, which
   the cores ignore) and the *latest* ``planner/reference``. The planner steps on the same
   apron state, so its reference for that state usually arrives after this step: the
   reference used is then the previous one (one apron state, ≤ ~10 ms, old). Accepted: the
   reference is a smooth jerk-limited trajectory, and waiting for it would add a hop of
   latency to every command (README, Node: ordering).
3. Publish ``control/thrust`` (force.z = u_z, N) and ``altitude/observer`` (σ, d̂, e_z), both
   stamped with the ``t_s`` of the apron state used, so a consumer measures end-to-end latency
   as (its clock − header.stamp) and the bench maps each setpoint to its camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import sys

from apron_estimator.types import ApronState, decode_apron_array
from deckland_common.checks import stamp_verdict
from deckland_common.frames import quaternion_to_euler
from deckland_common.params import ParameterError, ParamSpec, in_range, one_of, positive
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
from geometry_msgs.msg import Vector3Stamped, WrenchStamped
from rclpy.node import Node
from sensor_msgs.msg import Imu
from std_msgs.msg import Bool, Float64MultiArray
from trajectory_msgs.msg import MultiDOFJointTrajectory

from dob_altitude.adapter import (
    CONTROLLER_KINDS,
    GAIN_PROFILES,
    altitude_input,
    make_controller,
    parse_vertical_frame,
)

#: A gain parameter below zero means "the value of gains_profile".
PROFILE_VALUE = -1.0


def _gain(name: str, meaning: str) -> ParamSpec:
    return ParamSpec(name, PROFILE_VALUE, f'{meaning}; negative = the gains_profile value')


PARAMS = [
    one_of('controller', 'dob', CONTROLLER_KINDS,
           "altitude law: 'dob' (paper (16)-(19)) or 'pid' (baseline matched to the DOB)"),
    one_of('gains_profile', 'default', GAIN_PROFILES,
           "gain set: 'paper' = Table 4 (K, Λ, Γ), 'default' = shipped"),
    _gain('k', 'DOB K of (15)-(16), > 0'),
    _gain('lam', 'DOB Λ of (14)-(17), > 0'),
    _gain('gamma_obs', 'DOB observer gain Γ of (18)-(19), > 0'),
    _gain('kp', 'PID K_p (m/s² per m), >= 0'),
    _gain('ki', 'PID K_i (m/s² per m·s), >= 0'),
    _gain('kd', 'PID K_d (m/s² per m/s), >= 0'),
    positive('mass_kg', 2.71, 'vehicle mass m (paper Table 2)'),
    ParamSpec('thrust_min_n', 2.66, 'lowest commanded collective thrust (motors keep spinning)',
              lambda v: v >= 0.0, 'must be >= 0 (and below m g / ge_max_gain)'),
    positive('thrust_max_n', 53.17, 'highest commanded collective thrust (must exceed m g)'),
    in_range('rotor_height_offset_m', 0.05, 0.0, 1.0,
             'rotor plane above the body origin: z_p = h + offset in (4)'),
    ParamSpec('surface_accel_feedforward', False,
              "feed the estimated surface acceleration forward ('surface' frame only; "
              'beyond the paper)'),
    ParamSpec('rate_hz', 100.0,
              'nominal control rate (paper: 100 Hz); the loop steps per apron/state, '
              '1/rate_hz is only the dt of the first step after a reset',
              lambda v: 1.0 <= v <= 1000.0, 'must be in [1, 1000]'),
    positive('input_timeout_s', 0.2,
             'max age of apron/state, planner/reference and vehicle/imu stamps; older = stale'),
    ParamSpec('base_frame', 'base_link', 'frame_id of control/thrust and altitude/observer',
              lambda v: bool(v.strip()), 'must not be empty'),
]

_GAINS = {'dob': ('k', 'lam', 'gamma_obs'), 'pid': ('kp', 'ki', 'kd')}


@dataclass(frozen=True, slots=True)
class _Reference:
    z_d_m: float
    z_d_dot_mps: float
    z_d_ddot_mps2: float
    frame: str
    stamp_s: float


class DobAltitudeNode(Node):
    """The ``dob_altitude`` node; interface tables in the package README (section Node)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('dob_altitude', **kwargs)
        p = declare_and_validate(self, PARAMS)
        self.cfg = p
        overrides = {name: p[name] for name in _GAINS[p['controller']] if p[name] >= 0.0}
        overrides.update(mass_kg=p['mass_kg'], thrust_min_n=p['thrust_min_n'],
                         thrust_max_n=p['thrust_max_n'])
        try:
            self.controller = make_controller(p['controller'], p['gains_profile'], overrides)
        except ValueError as exc:
            raise ParameterError(f'dob_altitude: {exc}') from exc
        self._period_s = 1.0 / p['rate_hz']
        self._timeout_s = p['input_timeout_s']
        self._offset_m = p['rotor_height_offset_m']
        self._ff = p['surface_accel_feedforward']
        self._frame_id = p['base_frame']
        self._clock = self.get_clock()

        self._apron: ApronState | None = None
        self._ref: _Reference | None = None
        self._att: tuple[float, float, float] | None = None  # roll, pitch, stamp_s
        self._enabled = True
        self._need_reset = True
        self._last_t_s = 0.0  # t_s of the apron state of the last step
        self._frame_used = ''
        self._withheld_reason = 'starting'
        self.last_output = None
        #: refused messages, by reason (never reach the controller or an output)
        self.rejected: dict[str, int] = {
            'non_finite': 0, 'bad_size': 0, 'bad_layout': 0, 'out_of_order': 0,
            'stale_stamp': 0, 'future_stamp': 0, 'bad_frame': 0, 'bad_quaternion': 0}
        #: apron states (and watchdog checks without one) that published nothing, by reason
        self.withheld: dict[str, int] = {
            'disabled': 0, 'stale': 0, 'invalid_vertical': 0, 'non_finite_output': 0}
        #: controller steps, resets, frame switches
        self.counts: dict[str, int] = {'steps': 0, 'resets': 0, 'frame_switches': 0}

        self.pub_thrust = self.create_publisher(WrenchStamped, 'control/thrust', RELIABLE_QOS)
        self.pub_observer = self.create_publisher(Vector3Stamped, 'altitude/observer',
                                                  RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, 'diagnostics', RELIABLE_QOS)
        self.create_subscription(Float64MultiArray, 'apron/state', self._on_apron, SENSOR_QOS)
        self.create_subscription(MultiDOFJointTrajectory, 'planner/reference',
                                 self._on_reference, RELIABLE_QOS)
        self.create_subscription(Imu, 'vehicle/imu', self._on_imu, SENSOR_QOS)
        self.create_subscription(Bool, 'control/enabled', self._on_enabled, LATCHED_QOS)
        self._msg_thrust = WrenchStamped()
        self._msg_thrust.header.frame_id = self._frame_id
        self._msg_observer = Vector3Stamped()
        self._msg_observer.header.frame_id = self._frame_id
        self.create_timer(self._timeout_s / 2.0, self._on_watchdog)
        self.create_timer(1.0, self._publish_diagnostics)
        self._steps_at_diag = 0
        self.get_logger().info(
            f"{p['controller']} altitude loop stepped per apron/state, profile "
            f"{p['gains_profile']!r}, overrides {overrides}")

    # --- helpers ---------------------------------------------------------------------------

    def _now_s(self) -> float:
        return self._clock.now().nanoseconds * 1e-9

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

    # --- subscriptions ---------------------------------------------------------------------

    def _on_apron(self, msg: Float64MultiArray) -> None:
        dims = msg.layout.dim
        state, reason, detail = decode_apron_array(dims[0].label if dims else None, msg.data)
        if state is None:
            self._reject(reason, detail)
            return
        v = state.vertical
        if not all_finite(state.t_s, v.height_m, v.closing_speed_mps, v.vehicle_altitude_m,
                          v.vehicle_vz_mps, v.surface_accel_mps2):
            self._reject('non_finite', 'apron/state')
            return
        last = self._apron.t_s if self._apron is not None else None
        if last is not None and state.t_s == last:
            self._reject('out_of_order', 'apron/state (repeated t_s)')
            return
        if not self._stamp_ok(state.t_s, last, 'apron/state'):
            return
        self._apron = state
        self._step()   # event-driven: the command goes out in this callback

    def _on_reference(self, msg: MultiDOFJointTrajectory) -> None:
        pts = msg.points
        if (len(pts) != 1 or not pts[0].transforms or not pts[0].velocities
                or not pts[0].accelerations):
            self._reject('bad_size', 'planner/reference (need one point with a transform, '
                         'a velocity and an acceleration)')
            return
        pt = pts[0]
        z_d = pt.transforms[0].translation.z
        z_d_dot = pt.velocities[0].linear.z
        z_d_ddot = pt.accelerations[0].linear.z
        if not all_finite(z_d, z_d_dot, z_d_ddot):
            self._reject('non_finite', 'planner/reference')
            return
        frame = parse_vertical_frame(msg.joint_names[0] if msg.joint_names else '')
        if frame is None:
            self._reject('bad_frame', f'planner/reference (joint name {msg.joint_names[0]!r})')
            return
        stamp = stamp_to_s(msg.header.stamp)
        if not self._stamp_ok(stamp, self._ref.stamp_s if self._ref else None,
                              'planner/reference'):
            return
        self._ref = _Reference(z_d, z_d_dot, z_d_ddot, frame, stamp)

    def _on_imu(self, msg: Imu) -> None:
        q = msg.orientation
        if msg.orientation_covariance[0] == -1.0:  # REP-145: no orientation estimate
            self._reject('bad_quaternion', 'vehicle/imu (no orientation)')
            return
        if not all_finite(q.w, q.x, q.y, q.z):
            self._reject('non_finite', 'vehicle/imu')
            return
        n = math.sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z)
        if abs(n - 1.0) > 0.05:
            self._reject('bad_quaternion', f'vehicle/imu (norm {n:.3f})')
            return
        stamp = stamp_to_s(msg.header.stamp)
        if not self._stamp_ok(stamp, self._att[2] if self._att else None, 'vehicle/imu'):
            return
        roll, pitch, _ = quaternion_to_euler(q.w / n, q.x / n, q.y / n, q.z / n)
        self._att = (roll, pitch, stamp)

    def _on_enabled(self, msg: Bool) -> None:
        enabled = bool(msg.data)
        if enabled != self._enabled:
            self.get_logger().info(f'control enabled: {enabled}')
        self._enabled = enabled
        if not enabled:
            self._reset()

    # --- loop ------------------------------------------------------------------------------

    def _reset(self) -> None:
        if not self._need_reset:
            self.counts['resets'] += 1
        self.controller.reset()
        self._need_reset = True

    def _withhold_reason(self, now: float) -> str:
        if not self._enabled:
            return 'disabled'
        for stamp in (self._apron.t_s if self._apron else None,
                      self._ref.stamp_s if self._ref else None,
                      self._att[2] if self._att else None):
            if stamp is None or now - stamp > self._timeout_s:
                return 'stale'
        if not self._apron.vertical.valid:
            return 'invalid_vertical'
        return ''

    def _withhold(self, reason: str) -> None:
        self.withheld[reason] += 1
        if reason != self._withheld_reason:
            self.get_logger().warn(f'publishing no thrust: {reason}',
                                   throttle_duration_sec=2.0)
        self._withheld_reason = reason
        self._reset()

    def _on_watchdog(self) -> None:
        """Staleness without any apron state arriving: count it and reset the controller."""
        reason = self._withhold_reason(self._now_s())
        if reason:
            self._withhold(reason)

    def _step(self) -> None:
        """One controller step on the apron state just accepted; publish its command."""
        reason = self._withhold_reason(self._now_s())
        if reason:
            self._withhold(reason)
            return
        st, ref, att = self._apron, self._ref, self._att
        dt = st.t_s - self._last_t_s
        if ref.frame != self._frame_used and not self._need_reset:
            self.counts['frame_switches'] += 1
            self._reset()
        if self._need_reset or not 0.0 < dt <= self._timeout_s:
            self.controller.reset()  # bumpless (re)start: the cores initialise on this sample
            dt = self._period_s
        inp = altitude_input(st.vertical, ref.z_d_m, ref.z_d_dot_mps, ref.z_d_ddot_mps2,
                             ref.frame, att[0], att[1], self._offset_m, self._ff)
        out = self.controller.step(inp, dt)
        self.counts['steps'] += 1
        if not all_finite(out.thrust_n, out.sigma, out.d_hat_mps2, out.e_z_m):
            self.withheld['non_finite_output'] += 1  # defensive: the cores never do this
            self._reset()
            return
        self._need_reset = False
        self._withheld_reason = ''
        self._last_t_s = st.t_s
        self._frame_used = ref.frame
        self.last_output = out

        thrust = self._msg_thrust
        s_to_stamp(st.t_s, thrust.header.stamp)
        thrust.wrench.force.z = out.thrust_n
        self.pub_thrust.publish(thrust)
        if not self.pub_observer.get_subscription_count():
            return      # lazy: Figure 9's σ and d̂ only while something subscribes
        obs = self._msg_observer
        s_to_stamp(st.t_s, obs.header.stamp)
        obs.vector.x = out.sigma
        obs.vector.y = out.d_hat_mps2
        obs.vector.z = out.e_z_m
        self.pub_observer.publish(obs)

    # --- diagnostics -----------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        steps = self.counts['steps']
        rate = steps - self._steps_at_diag  # the diagnostics timer runs at 1 Hz
        self._steps_at_diag = steps
        status = DiagnosticStatus(name='dob_altitude: altitude loop',
                                  hardware_id=self.cfg['controller'])
        if self._withheld_reason:
            status.level = DiagnosticStatus.WARN
            status.message = f'no thrust published: {self._withheld_reason}'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{rate} steps/s'
        values = {'controller': self.cfg['controller'],
                  'gains_profile': self.cfg['gains_profile'], 'steps_per_s': str(rate)}
        values.update({k: str(v) for k, v in self.counts.items()})
        values.update({f'rejected_{k}': str(v) for k, v in self.rejected.items()})
        values.update({f'withheld_{k}': str(v) for k, v in self.withheld.items()})
        values.update({f'core_rejected_{k}': str(v)
                       for k, v in self.controller.rejected.items()})
        values.update({f'core_clamped_{k}': str(v) for k, v in self.controller.clamped.items()})
        out = self.last_output
        if out is not None:
            values.update(thrust_n=f'{out.thrust_n:.3f}', sigma=f'{out.sigma:.4f}',
                          d_hat_mps2=f'{out.d_hat_mps2:.4f}', e_z_m=f'{out.e_z_m:.4f}',
                          saturated=str(out.saturated))
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: DobAltitudeNode(), args)


if __name__ == '__main__':
    sys.exit(main())
