"""ROS 2 adapter: read a Pixy v1 byte stream (serial or UDP), publish one PointCloud per frame.

Thin by design: the protocol lives in :mod:`pixy_driver.protocol`, stamping by arrival in
:mod:`pixy_driver.arrival`. A background thread reads with a short timeout, feeds the parser and
publishes; a timer publishes diagnostics. Topics, parameters and wiring: see the README.
"""

from __future__ import annotations

import contextlib
import ipaddress
import math
import os
import socket
import threading

from deckland_common.params import (
    ParameterError,
    ParamSpec,
    in_range,
    one_of,
    positive,
)
from deckland_common.ros_node import RELIABLE_QOS, declare_and_validate, run_node, s_to_stamp
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point32
from rclpy.node import Node
from sensor_msgs.msg import ChannelFloat32, PointCloud

from pixy_driver.arrival import ArrivalLog
from pixy_driver.protocol import ParserParams, PixyFrame, PixyParser

STANDARD_BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400)


def _is_ip_literal(value: str) -> bool:
    try:
        ipaddress.ip_address(value)
    except ValueError:
        return False
    return True


PARAMS = [
    one_of('transport', 'serial', ('serial', 'udp'),
           'where the Pixy byte stream comes from: a serial port or UDP datagrams'),
    ParamSpec('serial_port', '/dev/ttyACM0', 'serial device of the Pixy UART (transport serial)',
              lambda v: v.strip() != '', 'must not be empty'),
    ParamSpec('baud_rate', 19200, 'serial baud rate; the Pixy default is 19200 (PixyMon: '
              'Interface, UART baudrate)', lambda v: v in STANDARD_BAUD_RATES,
              f'must be one of {list(STANDARD_BAUD_RATES)}'),
    ParamSpec('udp_bind_address', '127.0.0.1', 'local address to bind (transport udp); '
              'loopback unless configured', _is_ip_literal, 'must be an IPv4/IPv6 literal'),
    in_range('udp_port', 14600, 0, 65535, 'local UDP port (0: the OS picks one)'),
    in_range('udp_fd', -1, -1, 65535, 'an inherited UDP socket already bound (deckland up '
             'binds it before starting the graph so the port cannot be taken meanwhile); '
             '-1: bind udp_bind_address:udp_port here'),
    ParamSpec('udp_datagram_is_frame', True, 'UDP: each datagram holds exactly one frame, '
              'publish it at once (no one-frame latency)'),
    ParamSpec('frame_id', 'camera_optical', 'header.frame_id of pixy/blocks',
              lambda v: v.strip() != '', 'must not be empty'),
    in_range('latency_s', 0.0, 0.0, 1.0,
             'exposure-to-arrival latency subtracted from the arrival time for the stamp'),
    in_range('max_blocks_per_frame', 130, 1, 10_000, 'blocks kept per frame'),
    positive('diagnostics_period_s', 1.0, 'period of pixy/diagnostics'),
    positive('stale_timeout_s', 1.0, 'diagnostics turn WARN when no frame for longer'),
    in_range('read_timeout_s', 0.05, 0.001, 1.0,
             'blocking read timeout of the reader thread (bounds shutdown time)'),
    positive('reopen_period_s', 1.0, 'retry period when the port cannot be opened'),
]


def frame_to_cloud(frame: PixyFrame, stamp_s: float, frame_id: str) -> PointCloud:
    """PixyFrame -> sensor_msgs/PointCloud per docs/interfaces.md.

    One point per block (x = x_px, y = y_px, z = 0) and channels signature, width, height.
    """
    msg = PointCloud()
    msg.header.frame_id = frame_id
    s_to_stamp(max(stamp_s, 0.0), msg.header.stamp)
    blocks = frame.blocks
    msg.points = [Point32(x=b.x_px, y=b.y_px, z=0.0) for b in blocks]
    msg.channels = [
        ChannelFloat32(name='signature', values=[float(b.signature) for b in blocks]),
        ChannelFloat32(name='width', values=[b.width_px for b in blocks]),
        ChannelFloat32(name='height', values=[b.height_px for b in blocks]),
    ]
    return msg


def _drain(sock: socket.socket) -> int:
    """Discard every datagram waiting in ``sock``; returns how many."""
    sock.setblocking(False)
    n = 0
    with contextlib.suppress(BlockingIOError, InterruptedError):
        while True:
            sock.recv(65536)
            n += 1
    return n


class PixyDriverNode(Node):
    """Publishes ``pixy/blocks`` (PointCloud) and ``pixy/diagnostics`` (DiagnosticArray)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('pixy_driver', **kwargs)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._io = None
        try:
            p = declare_and_validate(self, PARAMS)
        except ParameterError:
            self.destroy_node()
            raise
        self._p = p
        self._datagram = p['transport'] == 'udp' and p['udp_datagram_is_frame']
        self.parser = PixyParser(ParserParams(max_blocks_per_frame=p['max_blocks_per_frame']))
        self._arrivals = ArrivalLog()
        self._io_error = ''
        self.udp_port_bound: int | None = None
        self.frames_published = 0
        self._last_frame_s: float | None = None
        self._start_s = self._now_s()
        self._diag_last = (self._start_s, 0)
        if p['transport'] == 'udp':
            self._hardware_id = f"udp://{p['udp_bind_address']}:{p['udp_port']}"
        else:
            self._hardware_id = f"{p['serial_port']}@{p['baud_rate']}"

        self._pub = self.create_publisher(PointCloud, 'pixy/blocks', RELIABLE_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, 'pixy/diagnostics', RELIABLE_QOS)
        self._timer = self.create_timer(p['diagnostics_period_s'], self._publish_diagnostics)
        if self._open():   # a failure is logged there, reported in diagnostics and readiness
            self.get_logger().info(f'reading Pixy frames from {self._hardware_id}')
        self._thread = threading.Thread(target=self._run, name='pixy_reader', daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ io
    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def device_problem(self) -> str:
        """Why the device is not open (empty when it is): readiness and diagnostics."""
        if self._io is not None:
            return ''
        return f'cannot open {self._hardware_id}: {self._io_error}'

    def _open(self) -> bool:
        p = self._p
        try:
            if p['transport'] == 'udp' and p['udp_fd'] >= 0:
                sock = socket.socket(fileno=os.dup(p['udp_fd']))
                if sock.type != socket.SOCK_DGRAM:
                    sock.close()
                    raise OSError(f"udp_fd {p['udp_fd']} is not a UDP socket")
                _drain(sock)   # datagrams queued while no driver read them are stale
                sock.settimeout(p['read_timeout_s'])
                self.udp_port_bound = sock.getsockname()[1]
                self._hardware_id = f"udp://{p['udp_bind_address']}:{self.udp_port_bound}"
                self._io = sock
            elif p['transport'] == 'udp':
                family = (socket.AF_INET6 if ':' in p['udp_bind_address'] else socket.AF_INET)
                sock = socket.socket(family, socket.SOCK_DGRAM)
                try:
                    sock.bind((p['udp_bind_address'], p['udp_port']))
                    sock.settimeout(p['read_timeout_s'])
                except OSError:
                    sock.close()
                    raise
                self.udp_port_bound = sock.getsockname()[1]
                self._io = sock
            else:
                import serial  # pyserial; only needed for the serial transport

                self._io = serial.Serial(p['serial_port'], baudrate=p['baud_rate'],
                                         timeout=p['read_timeout_s'])
        except Exception as exc:
            if str(exc) != self._io_error:
                self.get_logger().error(f'cannot open {self._hardware_id}: {exc}')
            self._io_error = str(exc)
            self._io = None
            return False
        self._io_error = ''
        return True

    def _close(self) -> None:
        io, self._io = self._io, None
        if io is not None:
            with contextlib.suppress(Exception):
                io.close()

    def _read(self) -> bytes:
        io = self._io
        if isinstance(io, socket.socket):
            try:
                data, _ = io.recvfrom(65536)
            except TimeoutError:
                return b''
            return data
        return io.read(max(1, io.in_waiting))

    def _run(self) -> None:
        """Reader thread: read, parse, stamp, publish; never dies on bad bytes."""
        p = self._p
        while not self._stop.is_set():
            if self._io is None and not self._open():
                self._stop.wait(p['reopen_period_s'])
                continue
            try:
                data = self._read()
            except Exception as exc:
                if self._stop.is_set():
                    break
                self._io_error = str(exc)
                self.get_logger().error(f'read from {self._hardware_id} failed: {exc}')
                self._close()
                continue
            if not data:
                continue
            try:
                self._handle(data)
            except Exception as exc:
                if self._stop.is_set() or not self.context.ok():
                    break
                self.get_logger().error(f'publishing a Pixy frame failed: {exc}')

    def _handle(self, data: bytes) -> None:
        now_s = self._now_s()
        parser = self.parser
        frames = parser.feed_datagram(data) if self._datagram else parser.feed(data)
        self._arrivals.record(parser.bytes_in, now_s)
        for frame in frames:
            arrival_s = self._arrivals.time_of(frame.end_offset)
            if arrival_s is None or not math.isfinite(arrival_s):
                arrival_s = now_s
            stamp_s = arrival_s - self._p['latency_s']
            self._pub.publish(frame_to_cloud(frame, stamp_s, self._p['frame_id']))
            self.frames_published += 1
            self._last_frame_s = now_s

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        now_s = self._now_s()
        t0, n0 = self._diag_last
        frames = self.frames_published
        rate = (frames - n0) / (now_s - t0) if now_s > t0 else 0.0
        self._diag_last = (now_s, frames)
        since = now_s - (self._last_frame_s if self._last_frame_s is not None
                         else self._start_s)
        status = DiagnosticStatus(name='pixy_driver: Pixy camera', hardware_id=self._hardware_id)
        if self._io is None:
            status.level = DiagnosticStatus.ERROR
            status.message = f'port not open: {self.device_problem()}'
        elif since > self._p['stale_timeout_s']:
            status.level = DiagnosticStatus.WARN
            status.message = f'no frame for {since:.1f} s'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{rate:.1f} frames/s'
        values = {'frames_per_s': f'{rate:.2f}', 'time_since_frame_s': f'{since:.3f}',
                  **{k: str(v) for k, v in self.parser.stats().items()}}
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        s_to_stamp(max(now_s, 0.0), msg.header.stamp)
        self._diag_pub.publish(msg)

    # ------------------------------------------------------------------ shutdown
    def destroy_node(self) -> None:
        """Stop and join the reader thread, close the port, then destroy the node."""
        stop = getattr(self, '_stop', None)
        if stop is not None:
            stop.set()
        thread = getattr(self, '_thread', None)
        if thread is not None and thread.is_alive():
            thread.join(timeout=5.0)
        self._close()
        if not getattr(self, '_destroyed', False):
            self._destroyed = True
            super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``pixy_driver_node``."""
    return run_node(PixyDriverNode, args)


if __name__ == '__main__':  # pragma: no cover
    raise SystemExit(main())


__all__ = ['PARAMS', 'PixyDriverNode', 'frame_to_cloud', 'main']
