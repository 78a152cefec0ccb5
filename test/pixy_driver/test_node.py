"""The pixy_driver node in-process: UDP in, sensor_msgs/PointCloud and diagnostics out."""

import socket
import threading
import time

from pixy_driver.protocol import encode_frame
import pytest

pytestmark = pytest.mark.ros


def wait_for(predicate, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


class Inbox:
    """Collects messages of one topic on a subscriber node in the test's context."""

    def __init__(self, context, executor, msg_type, topic):
        from deckland_common.ros_node import RELIABLE_QOS
        import rclpy

        self.node = rclpy.create_node(f'pixy_test_{topic.replace("/", "_")}', context=context)
        self.msgs = []
        self._lock = threading.Lock()
        self.sub = self.node.create_subscription(msg_type, topic, self._cb, RELIABLE_QOS)
        executor.add_node(self.node)

    def _cb(self, msg):
        with self._lock:
            self.msgs.append(msg)

    def snapshot(self):
        with self._lock:
            return list(self.msgs)


def start_driver(context, executor, **params):
    from pixy_driver.node import PixyDriverNode
    from rclpy.parameter import Parameter

    overrides = [Parameter('transport', value='udp'), Parameter('udp_port', value=0),
                 Parameter('diagnostics_period_s', value=0.2)]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    node = PixyDriverNode(context=context, parameter_overrides=overrides)
    executor.add_node(node)
    assert node.udp_port_bound
    return node


def cloud_blocks(msg):
    ch = {c.name: list(c.values) for c in msg.channels}
    return [(int(s), int(p.x), int(p.y), int(w), int(h), p.z) for p, s, w, h in
            zip(msg.points, ch['signature'], ch['width'], ch['height'], strict=True)]


def test_udp_frames_become_point_clouds(ros_context):
    from sensor_msgs.msg import PointCloud

    context, executor = ros_context
    driver = start_driver(context, executor, latency_s=0.25)
    inbox = Inbox(context, executor, PointCloud, 'pixy/blocks')
    assert wait_for(lambda: driver._pub.get_subscription_count() >= 1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = ('127.0.0.1', driver.udp_port_bound)
    try:
        t_before = driver.get_clock().now().nanoseconds * 1e-9
        tx.sendto(encode_frame([(1, 160, 100, 12, 10), (2, 5, 7, 3, 4)]), addr)
        assert wait_for(lambda: len(inbox.snapshot()) == 1)
        t_after = driver.get_clock().now().nanoseconds * 1e-9
        tx.sendto(bytes(range(256)) * 3, addr)  # garbage datagram: ignored, counted
        tx.sendto(b'\x55\xaa' + encode_frame([(3, 1, 2, 3, 4)])[2:-1], addr)  # truncated
        tx.sendto(encode_frame([(0o12, 300, 150, 20, 10, -30)]), addr)  # colour code
        tx.sendto(encode_frame([]), addr)  # empty frame
        assert wait_for(lambda: len(inbox.snapshot()) == 4)
    finally:
        tx.close()
    msgs = inbox.snapshot()
    first = msgs[0]
    assert first.header.frame_id == 'camera_optical'
    assert [c.name for c in first.channels] == ['signature', 'width', 'height']
    assert cloud_blocks(first) == [(1, 160, 100, 12, 10, 0.0), (2, 5, 7, 3, 4, 0.0)]
    stamp = first.header.stamp.sec + first.header.stamp.nanosec * 1e-9
    # stamp = arrival - latency_s, arrival within the send/receive window
    assert t_before - 0.25 - 1e-3 <= stamp <= t_after - 0.25 + 1e-3
    assert cloud_blocks(msgs[1]) == []  # the truncated datagram's frame had no whole block
    assert cloud_blocks(msgs[2]) == [(0o12, 300, 150, 20, 10, 0.0)]
    assert msgs[3].points == [] and all(len(c.values) == 0 for c in msgs[3].channels)
    assert driver.parser.bytes_dropped >= 768
    assert driver._thread.is_alive()


def test_stream_mode_latency_and_diagnostics(ros_context):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from sensor_msgs.msg import PointCloud

    context, executor = ros_context
    driver = start_driver(context, executor, udp_datagram_is_frame=False, stale_timeout_s=0.3)
    inbox = Inbox(context, executor, PointCloud, 'pixy/blocks')
    diag = Inbox(context, executor, DiagnosticArray, 'pixy/diagnostics')
    assert wait_for(lambda: driver._pub.get_subscription_count() >= 1)
    a = encode_frame([(1, 10, 20, 5, 5)])
    bad = encode_frame([(2, 30, 40, 6, 6)])
    bad = bad[:4] + bytes([bad[4] ^ 0xFF]) + bad[5:]  # checksum error
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = ('127.0.0.1', driver.udp_port_bound)
    try:
        tx.sendto(a[:5], addr)  # a frame split over two datagrams
        tx.sendto(a[5:], addr)
        time.sleep(0.3)
        assert inbox.snapshot() == []  # complete only once the next frame starts
        tx.sendto(bad, addr)
        assert wait_for(lambda: len(inbox.snapshot()) == 1)
        tx.sendto(encode_frame([(3, 1, 1, 1, 1)], end_marker=True), addr)
        assert wait_for(lambda: len(inbox.snapshot()) == 3)
    finally:
        tx.close()
    msgs = inbox.snapshot()
    assert cloud_blocks(msgs[0]) == [(1, 10, 20, 5, 5, 0.0)]
    assert cloud_blocks(msgs[1]) == []  # its only block failed the checksum
    assert cloud_blocks(msgs[2]) == [(3, 1, 1, 1, 1, 0.0)]

    def latest_status():
        got = diag.snapshot()
        return got[-1].status[0] if got else None

    def latest_values():
        status = latest_status()
        return {} if status is None else {kv.key: kv.value for kv in status.values}

    assert wait_for(lambda: latest_values().get('checksum_errors') == '1')
    values = latest_values()
    assert {'frames_per_s', 'checksum_errors', 'resyncs', 'bytes_dropped'} <= values.keys()
    # no frames since: WARN after stale_timeout_s
    assert wait_for(lambda: latest_status().level == DiagnosticStatus.WARN, timeout_s=3.0)
    assert 'no frame' in latest_status().message


def test_bad_parameters_raise_clear_errors(ros_context):
    from deckland_common.params import ParameterError
    from pixy_driver.node import PixyDriverNode
    from rclpy.parameter import Parameter

    context, _ = ros_context
    cases = [('transport', 'usb'), ('udp_port', 70000), ('baud_rate', 12345),
             ('udp_bind_address', 'not-an-ip'), ('latency_s', -0.1), ('frame_id', '')]
    for name, value in cases:
        with pytest.raises(ParameterError, match=name):
            PixyDriverNode(context=context, parameter_overrides=[Parameter(name, value=value)])


def test_clean_shutdown_joins_thread_and_closes_socket(ros_context):
    context, executor = ros_context
    driver = start_driver(context, executor)
    sock, thread = driver._io, driver._thread
    executor.remove_node(driver)
    driver.destroy_node()
    assert not thread.is_alive()
    assert sock.fileno() == -1
    driver.destroy_node()  # idempotent


def test_serial_port_missing_reports_error_and_keeps_running(ros_context):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from pixy_driver.node import PixyDriverNode
    from rclpy.parameter import Parameter

    context, executor = ros_context
    driver = PixyDriverNode(context=context, parameter_overrides=[
        Parameter('transport', value='serial'),
        Parameter('serial_port', value='/dev/pixy_does_not_exist'),
        Parameter('diagnostics_period_s', value=0.2), Parameter('reopen_period_s', value=0.1)])
    executor.add_node(driver)
    diag = Inbox(context, executor, DiagnosticArray, 'pixy/diagnostics')
    assert wait_for(lambda: diag.snapshot() != [])
    status = diag.snapshot()[-1].status[0]
    assert status.level == DiagnosticStatus.ERROR and 'port not open' in status.message
    assert driver._thread.is_alive()
