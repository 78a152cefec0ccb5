"""ROS 2 adapter of the landing planner and the horizontal position loop.

Parameters, topics, services, a watchdog timer and message conversions. Everything between
receiving inputs and publishing commands is :class:`landing_planner.loop.PlannerLoop` (input
gating, one planner + horizontal-loop tick per accepted ``apron/state``, dt, the stale-apron
fallback, withholding), the same object the in-process runner and the golden replay step.
Event-driven: the tick runs in the ``apron/state`` callback and ``control/attitude`` /
``planner/reference`` go out right there, stamped with the apron state's ``t_s`` (never
decreasing); a watchdog at ``rate_hz`` ticks on the core's safe fallback only while
``apron/state`` is stale. Interface tables: the package README.
"""

from __future__ import annotations

import sys

from deckland_common.contract import VERTICAL_RELATIVE, ApronState, decode_apron_array
from deckland_common.frames import euler_to_quaternion
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
from geometry_msgs.msg import PoseStamped, QuaternionStamped, Transform, Twist, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from std_msgs.msg import Bool, Float64MultiArray, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint

from landing_planner.horizontal import HorizontalController
from landing_planner.loop import PlannerLoop, PlannerTick
from landing_planner.node_params import PARAMS, params_from
from landing_planner.planner import LandingPlanner

__all__ = ['PARAMS', 'LandingPlannerNode', 'main', 'params_from']

# --- node ------------------------------------------------------------------------------------


class LandingPlannerNode(GuardedNode, Node):
    """The ``landing_planner`` node; interface tables in the package README (section Node)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('landing_planner', **kwargs)
        p = declare_and_validate(self, PARAMS)
        self.cfg = p
        planner_params, horizontal_params = params_from(p)
        self.core = PlannerLoop(LandingPlanner(planner_params),
                                HorizontalController(horizontal_params),
                                period_s=1.0 / p['rate_hz'],
                                input_timeout_s=p['input_timeout_s'], map_frame=p['map_frame'])
        self.attach_guard(self.core, 'publishing no commands')
        self.planner, self.horizontal = self.core.planner, self.core.horizontal
        self.counts = self.core.counts
        self._map = p['map_frame']
        self._mode_published = None
        self._enabled_published: bool | None = None
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
        self.create_timer(self.core.period_s, self._on_watchdog)
        self.create_timer(1.0, self._publish_diagnostics)
        self._publish_mode()
        self.get_logger().info(
            f"landing planner stepped per apron/state (watchdog {p['rate_hz']:g} Hz), "
            'landing area '
            f"({p['landing_area_x_m']:.2f}, {p['landing_area_y_m']:.2f}) m, profile "
            f"{p['descent_profile']!r}")

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

    # --- subscriptions (message → plain numbers → the loop) --------------------------------

    def _on_apron(self, msg: Float64MultiArray) -> None:
        dims = msg.layout.dim
        st, reason, detail = decode_apron_array(dims[0].label if dims else None, msg.data)
        if st is None:
            self._reject(reason, detail)
            return
        self._publish(self.core.on_apron(self._now_s(), st))

    def _on_odom(self, msg: Odometry) -> None:
        pos, q = msg.pose.pose.position, msg.pose.pose.orientation
        self.core.on_odom(self._now_s(), stamp_to_s(msg.header.stamp), msg.header.frame_id,
                          (pos.x, pos.y, pos.z), (q.w, q.x, q.y, q.z))

    def _on_velocity(self, msg: TwistStamped) -> None:
        v = msg.twist.linear
        self.core.on_velocity(self._now_s(), stamp_to_s(msg.header.stamp), (v.x, v.y, v.z),
                              msg.header.frame_id)

    def _on_landed(self, msg: Bool) -> None:
        self.core.on_landed(bool(msg.data))

    def _on_watchdog(self) -> None:
        self._publish(self.core.watchdog(self._now_s()))

    # --- services (std_srvs/Trigger → the core's (ok, message)) ----------------------------

    def _service(self, fn, name: str, response):
        ok, message = fn(self._now_s())
        response.success, response.message = bool(ok), str(message)
        self.get_logger().info(f'{name}: {"ok" if ok else "refused"}: {message}')
        self._publish_mode()
        return response

    def _srv_start(self, request, response):
        return self._service(self.core.start_landing, 'start_landing', response)

    def _srv_abort(self, request, response):
        return self._service(self.core.abort, 'abort', response)

    def _srv_takeoff(self, request, response):
        return self._service(self.core.takeoff, 'takeoff', response)

    # --- publishers ------------------------------------------------------------------------

    def _publish(self, tick: PlannerTick | None) -> None:
        """Publish what a tick says: mode and enabled on change, reference, attitude."""
        if tick is None:
            return
        out = tick.output
        self._publish_mode()
        self._publish_enabled(out.thrust_enabled)
        if tick.publish_reference:
            self._publish_reference(out, tick.apron, tick.stamp_s)
        if tick.publish_attitude and tick.command is not None:
            att = self._msg_att
            s_to_stamp(tick.stamp_s, att.header.stamp)
            q = att.quaternion
            q.w, q.x, q.y, q.z = euler_to_quaternion(tick.command[0], tick.command[1],
                                                     out.yaw_rad)
            self.pub_attitude.publish(att)

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
        core = self.core
        steps = core.counts['steps']
        rate = steps - self._steps_at_diag  # the diagnostics timer runs at 1 Hz
        self._steps_at_diag = steps
        status = DiagnosticStatus(name='landing_planner: mission and horizontal loop',
                                  hardware_id=self._map)
        reason = core.withheld_reason
        if reason and reason != 'thrust_disabled':
            status.level = DiagnosticStatus.WARN
            status.message = f'no commands published: {reason}'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{self.planner.mode.name}, {rate} steps/s'

        values = {'mode': self.planner.mode.name, 'reason': self.planner.reason,
                  'searches': str(self.planner.searches), 'steps_per_s': str(rate),
                  **core.diagnostic_values(now)}
        self._publish_status(self.pub_diag, status, values)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: LandingPlannerNode(), args)


if __name__ == '__main__':
    sys.exit(main())
