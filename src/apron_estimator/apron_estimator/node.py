"""ROS 2 adapter of the apron estimator (paper §2.3-2.4, (27)-(35); see the package README).

Parameters, topics, message unpacking, the loop thread and a 1 Hz diagnostics timer.
Everything between receiving inputs and publishing ``apron/state`` is
:class:`apron_estimator.loop.EstimatorLoop` (stamp gating, plausibility, pairing,
withholding), the same object the in-process runner and the golden replay feed. What
publishes (``clock``): ``loop`` (default) a ``rate_hz`` thread on absolute deadlines,
phase-locked to the processed camera frames (:class:`deckland_common.loop_clock.PhaseLockedLoop`;
a frame further than ``loop_max_wait_s`` from its tick is published at once); ``imu`` each
accepted ``vehicle/imu`` message (thinned to 0.5 / rate_hz) and each camera frame.
"""

from __future__ import annotations

import functools
import sys
import threading
import time

from deckland_common.loop_clock import PhaseLockedLoop, PhaseLockParams
from deckland_common.messages import fill_apron_state, fill_rivals
from deckland_common.params import ParameterError
from deckland_common.ros_node import (
    RELIABLE_QOS,
    SENSOR_QOS,
    GuardedNode,
    declare_and_validate,
    run_node,
    s_to_stamp,
    stamp_to_s,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, TwistStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Imu, PointCloud, Range
from std_msgs.msg import Bool

from apron_estimator.deck import telemetry_from_odometry
from apron_estimator.estimator import ApronEstimator
from apron_estimator.loop import UNKNOWN_VAR, EstimatorLoop
from apron_estimator.node_params import (
    DECK_DESCRIPTIONS,
    ESTIMATOR_DESCRIPTIONS,
    NODE_PARAMS,
    PARAMS,
    SECTIONS,
    deck_params_from,
    estimator_params_from,
)
from deckland_interfaces.msg import ApronState as ApronStateMsg
from deckland_interfaces.msg import Rival

__all__ = ['DECK_DESCRIPTIONS', 'ESTIMATOR_DESCRIPTIONS', 'NODE_PARAMS', 'PARAMS', 'SECTIONS',
           'ApronEstimatorNode', 'deck_params_from', 'estimator_params_from', 'main']


def _locked(method):
    """Run a callback under the node's lock (the loop thread steps the same estimator)."""
    @functools.wraps(method)
    def wrapper(self, *args):
        with self._lock:
            return method(self, *args)
    return wrapper


class ApronEstimatorNode(GuardedNode, Node):
    """The ``apron_estimator`` node; interface tables in the package README (section Node)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('apron_estimator', **kwargs)
        p = declare_and_validate(self, PARAMS)
        self.cfg = p
        self.core = EstimatorLoop(ApronEstimator(estimator_params_from(p)),
                                  deck=deck_params_from(p),
                                  input_timeout_s=p['input_timeout_s'],
                                  gravity_mps2=p['gravity_mps2'],
                                  position_pair_tolerance_s=p['position_pair_tolerance_s'],
                                  imu_min_spacing_s=0.5 / p['rate_hz'])
        self.attach_guard(self.core, 'publishing no apron state')
        self.estimator = self.core.estimator
        self.triggers = self.core.triggers
        self._odom_when_untracked = p['odom_when_untracked']
        self._published_at_diag = 0

        self.pub_state = self.create_publisher(ApronStateMsg, 'apron/state', RELIABLE_QOS)
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
        # the ship's telemetry (mavlink_bridge ship_telemetry node), when there is one
        self.create_subscription(Odometry, 'deck/odom', self._on_deck_odom, RELIABLE_QOS)
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

    def _build_messages(self, p: dict) -> None:
        """Output messages built once and refilled per publication (publish serialises)."""
        self._msg_state = ApronStateMsg()
        self._map_frame = p['map_frame']
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

    # --- subscriptions (message → plain numbers → the loop) --------------------------------

    @_locked
    def _on_imu(self, msg: Imu) -> None:
        o, a = msg.orientation, msg.linear_acceleration
        if not self.core.on_imu(self._now_s(), stamp_to_s(msg.header.stamp),
                                (o.w, o.x, o.y, o.z), (a.x, a.y, a.z),
                                has_orientation=msg.orientation_covariance[0] != -1.0):
            return
        if self.loop is None:   # clock=imu: an accepted attitude is a tick of the chain
            now = self._now_s()
            self._send(self.core.publish_on_imu(now), now)

    @_locked
    def _on_odom(self, msg: Odometry) -> None:
        p = msg.pose.pose.position
        self.core.on_position(self._now_s(), stamp_to_s(msg.header.stamp), (p.x, p.y, p.z))

    @_locked
    def _on_deck_odom(self, msg: Odometry) -> None:
        pp, o = msg.pose.pose.position, msg.pose.pose.orientation
        tw = msg.twist.twist
        vel, valid, rpy, yaw_rate, rates = telemetry_from_odometry(
            (o.w, o.x, o.y, o.z), (tw.linear.x, tw.linear.y, tw.linear.z),
            (tw.angular.x, tw.angular.y, tw.angular.z), msg.pose.covariance[21])
        self.core.on_deck_odom(self._now_s(), stamp_to_s(msg.header.stamp),
                               (pp.x, pp.y, pp.z), vel, valid, rpy, yaw_rate, rates)

    @_locked
    def _on_velocity(self, msg: TwistStamped) -> None:
        v = msg.twist.linear
        self.core.on_velocity(self._now_s(), stamp_to_s(msg.header.stamp), (v.x, v.y, v.z))

    @_locked
    def _on_range(self, msg: Range) -> None:
        self.core.on_range(self._now_s(), stamp_to_s(msg.header.stamp), msg.range,
                           msg.min_range, msg.max_range)

    @_locked
    def _on_blocks(self, msg: PointCloud) -> None:
        pts = msg.points
        if not self.core.on_blocks(self._now_s(), stamp_to_s(msg.header.stamp),
                                   [pt.x for pt in pts], [pt.y for pt in pts],
                                   {c.name: c.values for c in msg.channels}):
            return
        if self.loop is not None and not self.loop.on_event(time.monotonic()):
            return                  # the next loop tick, at most loop_max_wait_s away, has it
        now = self._now_s()         # the processed frame goes out at once
        self._send(self.core.publish(now, 'camera'), now)

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
                    if self.context.ok():
                        now = self._now_s()
                        self._send(self.core.publish(now, 'loop'), now)
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

    def _send(self, st, now: float) -> None:
        """Publish a state the loop released and the outputs derived from it."""
        if st is None:
            return
        msg = fill_apron_state(self._msg_state, st, self._map_frame)
        tracker = self.estimator.horizontal
        msg.ambiguous = tracker.ambiguous
        if tracker.rivals or msg.rivals:
            fill_rivals(msg, tracker.rivals, st.t_s, tracker.params.rival_confirm_hits, Rival)
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
        var_x, var_y, var_z, var_vx, var_vy, var_vz = self.core.odom_variances(st, now)
        pc, tc = od.pose.covariance, od.twist.covariance
        pc[0], pc[7], pc[14] = var_x, var_y, var_z
        tc[0], tc[7], tc[14] = var_vx, var_vy, var_vz
        pc[21] = pc[28] = pc[35] = tc[21] = tc[28] = tc[35] = UNKNOWN_VAR
        return od

    # --- diagnostics -----------------------------------------------------------------------

    @_locked
    def _publish_diagnostics(self) -> None:
        now = self._now_s()
        core = self.core
        rate = core.published - self._published_at_diag  # the timer runs at 1 Hz
        self._published_at_diag = core.published
        if not rate:  # nothing triggered a publication (all inputs stopped?): say why
            core.withheld_reason = core.withhold_reason(now) or core.withheld_reason
        status = DiagnosticStatus(name='apron_estimator: apron state', hardware_id='pixy')
        st = core.last_state
        if core.withheld_reason:
            status.level = DiagnosticStatus.WARN
            status.message = f'no apron state published: {core.withheld_reason}'
        else:
            status.level = DiagnosticStatus.OK
            tracked = st is not None and st.tracked
            status.message = f"{rate} states/s, {'tracked' if tracked else 'not tracked'}"
        values = {'states_per_s': str(rate), **core.diagnostic_values(now)}
        if self.loop is not None:
            values.update(loop_ticks=str(self.loop.ticks), loop_skipped=str(self.loop.skipped),
                          loop_overruns=str(self.loop.overruns),
                          loop_errors=str(self.loop_errors))
        self._publish_status(self.pub_diag, status, values)


def main(args: list[str] | None = None) -> int:
    return run_node(lambda: ApronEstimatorNode(), args)


if __name__ == '__main__':
    sys.exit(main())
