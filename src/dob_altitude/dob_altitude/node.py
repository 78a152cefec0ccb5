"""ROS 2 adapter of the altitude loop: the DOB (paper §3.1, (14)-(19)) or PID core.

Parameters, topics, a watchdog timer and message conversions. Everything between receiving
inputs and publishing ``control/thrust`` is :class:`dob_altitude.loop.AltitudeLoop` (gating,
withholding, resets, frame switches, dt), the same object the in-process runner and the golden
replay step. Event-driven: the loop steps in the ``apron/state`` callback and the thrust goes
out right there; a watchdog (period ``input_timeout_s / 2``) counts staleness and resets the
controller when no apron state arrives at all. Interface tables: the package README.
"""

from __future__ import annotations

import sys

from deckland_common.contract import VehicleDescription, decode_apron_array
from deckland_common.params import ParameterError, ParamSpec, in_range, one_of, positive
from deckland_common.ros_node import (
    LATCHED_QOS,
    RELIABLE_QOS,
    SENSOR_QOS,
    GuardedNode,
    declare_and_validate,
    run_node,
    s_to_stamp,
    stamp_to_s,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Vector3Stamped, WrenchStamped
from rclpy.node import Node
from sensor_msgs.msg import Imu
from std_msgs.msg import Bool, Float64MultiArray
from trajectory_msgs.msg import MultiDOFJointTrajectory

from dob_altitude.adapter import (
    CONTROLLER_KINDS,
    GAIN_PROFILES,
    controller_overrides,
    make_controller,
)
from dob_altitude.loop import AltitudeLoop

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
    positive('mass_kg', VehicleDescription().mass_kg,
             'vehicle mass m (paper Table 2); deckland up passes the vehicle description'),
    ParamSpec('thrust_min_n', 2.66, 'lowest commanded collective thrust (motors keep spinning)',
              lambda v: v >= 0.0, 'must be >= 0 (and below m g / ge_max_gain)'),
    positive('thrust_max_n', 53.17, 'highest commanded collective thrust (must exceed m g)'),
    in_range('rotor_height_offset_m', 0.05, 0.0, 1.0,
             'rotor plane above the body origin: z_p = h + offset in (4)'),
    ParamSpec('surface_accel_feedforward', False,
              "feed the estimated surface acceleration forward ('relative' frame only; "
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

class DobAltitudeNode(GuardedNode, Node):
    """The ``dob_altitude`` node; interface tables in the package README (section Node)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('dob_altitude', **kwargs)
        p = declare_and_validate(self, PARAMS)
        self.cfg = p
        overrides = controller_overrides(p)
        try:
            controller = make_controller(p['controller'], p['gains_profile'], overrides)
        except ValueError as exc:
            raise ParameterError(f'dob_altitude: {exc}') from exc
        self.core = AltitudeLoop(controller, period_s=1.0 / p['rate_hz'],
                                 input_timeout_s=p['input_timeout_s'],
                                 rotor_height_offset_m=p['rotor_height_offset_m'],
                                 surface_accel_ff=p['surface_accel_feedforward'])
        self.attach_guard(self.core, 'publishing no thrust')
        self.controller = controller
        self.counts = self.core.counts
        frame_id = p['base_frame']

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
        self._msg_thrust.header.frame_id = frame_id
        self._msg_observer = Vector3Stamped()
        self._msg_observer.header.frame_id = frame_id
        self.create_timer(p['input_timeout_s'] / 2.0, self._on_watchdog)
        self.create_timer(1.0, self._publish_diagnostics)
        self._steps_at_diag = 0
        self.get_logger().info(
            f"{p['controller']} altitude loop stepped per apron/state, profile "
            f"{p['gains_profile']!r}, overrides {overrides}")

    # --- subscriptions (message → plain numbers → the loop) --------------------------------

    def _on_apron(self, msg: Float64MultiArray) -> None:
        dims = msg.layout.dim
        state, reason, detail = decode_apron_array(dims[0].label if dims else None, msg.data)
        if state is None:
            self._reject(reason, detail)
            return
        out = self.core.on_apron(self._now_s(), state)
        if out is None:
            return
        thrust = self._msg_thrust
        s_to_stamp(state.t_s, thrust.header.stamp)
        thrust.wrench.force.z = out.thrust_n
        self.pub_thrust.publish(thrust)
        if not self.pub_observer.get_subscription_count():
            return      # lazy: Figure 9's σ and d̂ only while something subscribes
        obs = self._msg_observer
        s_to_stamp(state.t_s, obs.header.stamp)
        obs.vector.x = out.sigma
        obs.vector.y = out.d_hat_mps2
        obs.vector.z = out.e_z_m
        self.pub_observer.publish(obs)

    def _on_reference(self, msg: MultiDOFJointTrajectory) -> None:
        pts = msg.points
        if (len(pts) != 1 or not pts[0].transforms or not pts[0].velocities
                or not pts[0].accelerations):
            self._reject('bad_size', 'planner/reference (need one point with a transform, '
                         'a velocity and an acceleration)')
            return
        pt = pts[0]
        self.core.on_reference(self._now_s(), stamp_to_s(msg.header.stamp),
                               msg.joint_names[0] if msg.joint_names else '',
                               pt.transforms[0].translation.z, pt.velocities[0].linear.z,
                               pt.accelerations[0].linear.z)

    def _on_imu(self, msg: Imu) -> None:
        q = msg.orientation
        self.core.on_imu(self._now_s(), stamp_to_s(msg.header.stamp), (q.w, q.x, q.y, q.z),
                         has_orientation=msg.orientation_covariance[0] != -1.0)

    def _on_enabled(self, msg: Bool) -> None:
        enabled = bool(msg.data)
        if enabled != self.core.enabled:
            self.get_logger().info(f'control enabled: {enabled}')
        self.core.on_enabled(enabled)

    def _on_watchdog(self) -> None:
        self.core.watchdog(self._now_s())

    # --- diagnostics -----------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        core = self.core
        steps = core.counts['steps']
        rate = steps - self._steps_at_diag  # the diagnostics timer runs at 1 Hz
        self._steps_at_diag = steps
        status = DiagnosticStatus(name='dob_altitude: altitude loop',
                                  hardware_id=self.cfg['controller'])
        if core.withheld_reason:
            status.level = DiagnosticStatus.WARN
            status.message = f'no thrust published: {core.withheld_reason}'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{rate} steps/s'
        values = {'controller': self.cfg['controller'],
                  'gains_profile': self.cfg['gains_profile'], 'steps_per_s': str(rate)}
        values.update({k: str(v) for k, v in core.counts.items()})
        values.update(self._counter_values())
        values.update({f'core_rejected_{k}': str(v)
                       for k, v in self.controller.rejected.items()})
        values.update({f'core_clamped_{k}': str(v) for k, v in self.controller.clamped.items()})
        out = core.last_output
        if out is not None:
            values.update(thrust_n=f'{out.thrust_n:.3f}', sigma=f'{out.sigma:.4f}',
                          d_hat_mps2=f'{out.d_hat_mps2:.4f}', e_z_m=f'{out.e_z_m:.4f}',
                          saturated=str(out.saturated))
        self._publish_status(self.pub_diag, status, values)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: DobAltitudeNode(), args)


if __name__ == '__main__':
    sys.exit(main())
