"""ROS 2 adapter of the ship-telemetry decode: the ship's own MAVLink link → ``deck/odom``.

A second, small bridge beside ``mavlink_bridge_node``: it listens on the ship's link
(``ship_url``, a pymavlink connection string), decodes with :mod:`mavlink_bridge.ship` (system
id filter, ENU, clock, stale / out-of-order) and publishes nav_msgs/Odometry ``deck/odom``
(frame ``map``, child ``deck``; twist in the deck frame, REP-105) for each accepted sample.
Topic and parameter tables: the package README, section "Ship telemetry".
"""

from __future__ import annotations

import math
import sys
from typing import Any

from deckland_common.frames import euler_to_quaternion, mat_t_vec, rot_body_to_world
from deckland_common.params import ParamSpec, in_range, non_negative, positive
from deckland_common.ros_node import RELIABLE_QOS, declare_and_validate, run_node, s_to_stamp
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.node import Node

from mavlink_bridge.ship import DeckOdom, DeckOdomAssembler, ShipDecodeParams, ShipTelemetryDecoder

#: Variance published for what the sample does not carry (m², rad², ...).
UNKNOWN_VAR = 1.0e4

PARAMS = (
    ParamSpec('ship_url', 'udpin:0.0.0.0:14570', 'pymavlink connection of the ship link',
              lambda v: bool(v.strip()), 'must not be empty'),
    in_range('ship_sysid', 17, 1, 255, 'MAVLink system id of the ship (FOLL_SYSID)'),
    in_range('origin_lat_deg', 54.32, -85.0, 85.0, 'latitude of the map origin, deg'),
    in_range('origin_lon_deg', 10.15, -180.0, 180.0, 'longitude of the map origin, deg'),
    ParamSpec('origin_alt_m', 0.0, 'altitude (AMSL) of the map origin, m'),
    positive('max_age_s', 1.0, 'a sample older than this on arrival is stale, s'),
    non_negative('min_latency_s', 0.1, "the link's fastest one-way delay (nominal), s"),
    positive('attitude_max_age_s', 0.5, 'attitude older than this is not published, s'),
    positive('poll_hz', 200.0, 'how often the link is read, Hz'),
    non_negative('position_var_m2', 1.0, 'published position variance (GNSS), m^2'),
    non_negative('velocity_var_m2ps2', 0.01, 'published velocity variance, m^2/s^2'),
    non_negative('attitude_var_rad2', 1.0e-5, 'published attitude variance when known, rad^2'),
    ParamSpec('map_frame', 'map', 'frame_id of deck/odom (ENU)'),
    ParamSpec('deck_frame', 'deck', 'child_frame_id of deck/odom (deck FLU)'),
)


def fill_deck_odom(msg: Any, odom: DeckOdom, cfg: dict) -> Any:
    """nav_msgs/Odometry from a :class:`DeckOdom` (twist in the deck frame); returns it."""
    s_to_stamp(odom.t_s, msg.header.stamp)
    msg.header.frame_id = cfg['map_frame']
    msg.child_frame_id = cfg['deck_frame']
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = odom.position_m
    rpy = odom.rpy_rad if odom.attitude_valid else (0.0, 0.0, 0.0)
    q = euler_to_quaternion(*rpy)
    p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z = q
    v = mat_t_vec(rot_body_to_world(*rpy), odom.velocity_mps)   # world → deck axes
    t = msg.twist.twist
    t.linear.x, t.linear.y, t.linear.z = v
    t.angular.x, t.angular.y, t.angular.z = odom.rates_flu_radps
    att_var = cfg['attitude_var_rad2'] if odom.attitude_valid else UNKNOWN_VAR
    pc = [0.0] * 36
    tc = [0.0] * 36
    for i in range(3):
        pc[7 * i] = cfg['position_var_m2']
        pc[7 * (i + 3)] = att_var
        tc[7 * i] = cfg['velocity_var_m2ps2']
        tc[7 * (i + 3)] = att_var
    msg.pose.covariance = pc
    msg.twist.covariance = tc
    return msg


class ShipTelemetryNode(Node):
    """The ``ship_telemetry`` node: the ship's MAVLink link in, ``deck/odom`` out."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('ship_telemetry', **kwargs)
        cfg = declare_and_validate(self, PARAMS)
        self.cfg = cfg
        self.decoder = ShipTelemetryDecoder(ShipDecodeParams(
            ship_sysid=cfg['ship_sysid'], origin_lat_deg=cfg['origin_lat_deg'],
            origin_lon_deg=cfg['origin_lon_deg'], origin_alt_m=cfg['origin_alt_m'],
            max_age_s=cfg['max_age_s'], min_latency_s=cfg['min_latency_s']))
        self.assembler = DeckOdomAssembler(cfg['attitude_max_age_s'])
        from pymavlink import mavutil
        self.conn = mavutil.mavlink_connection(cfg['ship_url'], source_system=255,
                                               source_component=191)
        self.pub = self.create_publisher(Odometry, 'deck/odom', RELIABLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, 'diagnostics', RELIABLE_QOS)
        self._msg = Odometry()
        self.published = 0
        self.create_timer(1.0 / cfg['poll_hz'], self._poll)
        self.create_timer(1.0, self._diagnostics)
        self.get_logger().info(f"ship telemetry from system {cfg['ship_sysid']} on "
                               f"{cfg['ship_url']} -> deck/odom")

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _poll(self) -> None:
        for _ in range(100):
            try:
                m = self.conn.recv_match(blocking=False)
            except (OSError, ValueError) as exc:   # a malformed datagram must not end the node
                self.get_logger().warning(f'ship link: {exc}', throttle_duration_sec=5.0)
                return
            if m is None:
                return
            if m.get_type() == 'BAD_DATA':
                continue
            sample = self.decoder.on_message(self._now_s(), m.get_srcSystem(), m)
            odom = self.assembler.on_sample(sample) if sample is not None else None
            if odom is not None and all(math.isfinite(x) for x in odom.position_m):
                self.pub.publish(fill_deck_odom(self._msg, odom, self.cfg))
                self.published += 1

    def _diagnostics(self) -> None:
        st = DiagnosticStatus(name='ship_telemetry', hardware_id=self.cfg['ship_url'])
        st.level = DiagnosticStatus.OK if self.published else DiagnosticStatus.WARN
        st.message = f'{self.published} deck/odom published'
        off = self.decoder.clock_offset_s
        values = {'published': str(self.published), 'accepted': str(self.decoder.accepted),
                  'clock_offset_s': 'unknown' if off is None else f'{off:.3f}'}
        values.update({f'rejected_{k}': str(v) for k, v in self.decoder.rejected.items()})
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray(status=[st])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def destroy_node(self) -> None:
        try:
            self.conn.close()
        finally:
            super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(ShipTelemetryNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
