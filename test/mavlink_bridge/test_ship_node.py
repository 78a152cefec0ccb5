"""``deck/odom``: the ship-telemetry node over a real UDP MAVLink stream (private rclpy context,
random domain, localhost), and the Odometry encoding both ways (pure)."""

from __future__ import annotations

import math
import socket
import time

from apron_estimator.deck import telemetry_from_odometry
from deck_simulator.ship_link import enu_to_geodetic
from mavlink_bridge.ship import DeckOdom
import pytest
from rostest import free_udp_port, wait_for

ORIGIN = (54.32, 10.15, 0.0)


def test_odometry_encoding_round_trips_velocity_attitude_and_yaw_rate():
    from mavlink_bridge.ship_node import PARAMS, UNKNOWN_VAR, fill_deck_odom
    from nav_msgs.msg import Odometry
    cfg = {s.name: s.default for s in PARAMS}
    rpy = (0.08, -0.05, 2.0)
    rates = (0.03, -0.02, 0.04)
    cp = math.cos(rpy[1])
    yaw_rate = (rates[1] * math.sin(rpy[0]) + rates[2] * math.cos(rpy[0])) / cp
    od = DeckOdom(12.5, (3.0, -4.0, 2.5), (2.0, 0.5, -0.1), True, rpy, rates, yaw_rate)
    m = fill_deck_odom(Odometry(), od, cfg)
    assert m.header.frame_id == 'map' and m.child_frame_id == 'deck'
    assert m.header.stamp.sec == 12 and m.header.stamp.nanosec == 500_000_000
    # twist in the deck frame (REP-105): not the world velocity unless the deck is level
    tw = m.twist.twist
    assert math.hypot(tw.linear.x, tw.linear.y, tw.linear.z) == pytest.approx(
        math.hypot(2.0, 0.5, -0.1))
    assert tw.linear.x != pytest.approx(2.0, abs=0.1)
    o = m.pose.pose.orientation
    vel, valid, rpy2, yr, rates2 = telemetry_from_odometry(
        (o.w, o.x, o.y, o.z), (tw.linear.x, tw.linear.y, tw.linear.z),
        (tw.angular.x, tw.angular.y, tw.angular.z), m.pose.covariance[21])
    assert valid and vel == pytest.approx((2.0, 0.5, -0.1), abs=1e-9)
    assert rpy2 == pytest.approx(rpy, abs=1e-9) and yr == pytest.approx(yaw_rate, abs=1e-9)
    assert rates2 == pytest.approx(rates)
    # without attitude: identity, unknown variance, decoded as not valid
    od2 = DeckOdom(1.0, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), False, (0, 0, 0), (0, 0, 0), 0.0)
    m2 = fill_deck_odom(Odometry(), od2, cfg)
    assert m2.pose.covariance[21] == UNKNOWN_VAR and m2.pose.pose.orientation.w == 1.0
    _, valid2, _, _, _ = telemetry_from_odometry((1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0),
                                                 (0.0, 0.0, 0.0), m2.pose.covariance[21])
    assert not valid2


@pytest.mark.ros
def test_ship_stream_over_udp_becomes_deck_odom_in_enu(ros_context):
    from mavlink_bridge.ship_node import ShipTelemetryNode
    from nav_msgs.msg import Odometry
    from pymavlink.dialects.v20 import common as mavlink2
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    context, executor = ros_context
    port = free_udp_port()
    node = ShipTelemetryNode(context=context, parameter_overrides=[
        Parameter('ship_url', value=f'udpin:127.0.0.1:{port}'),
        Parameter('min_latency_s', value=0.0)])
    helper = Node('ship_odom_test_helper', context=context)
    got: list = []
    helper.create_subscription(Odometry, 'deck/odom', got.append, 10)
    executor.add_node(node)
    executor.add_node(helper)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    class Out:
        def __init__(self, sysid):
            self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=1)

        def write(self, data):
            sock.sendto(data, ('127.0.0.1', port))

    ship, vehicle = Out(17), Out(1)
    lat, lon, alt = enu_to_geodetic(ORIGIN, 30.0, -20.0, 2.5)
    try:
        t0 = time.monotonic()
        k = 0
        # the vehicle's own GLOBAL_POSITION_INT (system 1) must not become the deck
        while time.monotonic() - t0 < 3.0 and len(got) < 5:
            ms = 1000 + 100 * k
            vehicle.mav.global_position_int_send(ms, lat + 10000, lon, alt, alt, 0, 0, 0, 0)
            ship.mav.attitude_send(ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)   # heading north
            ship.mav.global_position_int_send(ms, lat, lon, alt, alt, 150, 0, -10, 0)
            k += 1
            time.sleep(0.1)
        assert wait_for(lambda: len(got) >= 5)
    finally:
        sock.close()
    m = got[-1]
    assert m.header.frame_id == 'map' and m.child_frame_id == 'deck'
    p = m.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((30.0, -20.0, 2.5), abs=0.2)   # + 0.1 s × v
    o = m.pose.pose.orientation
    # deck FLU heading north = ENU yaw +90°: q = (cos 45°, 0, 0, sin 45°)
    assert (o.w, o.z) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)), abs=1e-6)
    tw = m.twist.twist.linear
    # 1.5 m/s north, 0.1 m/s up (vz = −10 cm/s NED) in the deck frame: forward and up
    assert (tw.x, tw.y, tw.z) == pytest.approx((1.5, 0.0, 0.1), abs=1e-6)
    assert node.decoder.rejected['other_system'] >= 1
    assert all(abs(g.pose.pose.position.y + 20.0) < 0.5 for g in got)   # never the vehicle
