"""A MAVLink TCP client that survives its peer going away (pymavlink transport, no rclpy).

pymavlink's ``mavtcp`` without ``autoreconnect`` prints "EOF on TCP socket" and returns on
every read once the peer has closed — a reader thread then spins at 100 % of a core writing
that line (1.8 M lines a minute against ArduPilot SITL, issue 17) — and with it, it blocks in
``connect`` retries inside the read. :class:`ReconnectingTcp` closes the dead socket, reads
nothing while disconnected (``select`` sleeps), tries one short connect every
``reconnect_period_s`` and reports each change of state once in :attr:`events`.
"""

from __future__ import annotations

import contextlib
import errno
import math
import socket
import time

from pymavlink import mavutil


class ReconnectingTcp(mavutil.mavtcp):
    """``tcp:HOST:PORT`` for :func:`pymavlink.mavutil.mavlink_connection` callers.

    ``device`` is ``HOST:PORT``. The first connect is tried at once and never raises: a peer
    that is not there yet is tried again every ``reconnect_period_s`` (each attempt waits at
    most ``connect_timeout_s``). :attr:`events` collects human-readable state changes for the
    caller to log (``'connected'``, ``'lost (EOF)'``, ``'connect failed: …'`` — the latter only
    for the first failure after a loss); :attr:`stats` counts them.
    """

    def __init__(self, device: str, source_system: int = 255, source_component: int = 0,
                 reconnect_period_s: float = 1.0, connect_timeout_s: float = 0.5) -> None:
        host, sep, port = device.rpartition(':')
        if not sep or not host or not port.isdigit():
            raise ValueError(f'TCP device {device!r}: must be HOST:PORT')
        for name, v in (('reconnect_period_s', reconnect_period_s),
                        ('connect_timeout_s', connect_timeout_s)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f'ReconnectingTcp.{name} = {v!r}: must be a finite number > 0')
        self.destination_addr = (host, int(port))
        self.autoreconnect = False
        self.retries = 0
        self.reconnect_delay = reconnect_period_s
        self.reconnect_period_s = float(reconnect_period_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.port: socket.socket | None = None
        self.events: list[str] = []
        self.stats = {'connects': 0, 'disconnects': 0, 'connect_failures': 0,
                      'dropped_writes': 0}
        self._next_try_s = -math.inf
        self._failed_since_loss = False
        mavutil.mavfile.__init__(self, None, 'tcp:' + device, source_system=source_system,
                                 source_component=source_component)
        self._try_connect()

    @property
    def connected(self) -> bool:
        return self.port is not None

    def _try_connect(self) -> bool:
        now = time.monotonic()
        if self.port is not None:
            return True
        if now < self._next_try_s:
            return False
        self._next_try_s = now + self.reconnect_period_s
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.settimeout(self.connect_timeout_s)
        try:
            sock.connect(self.destination_addr)
        except OSError as exc:
            sock.close()
            self.stats['connect_failures'] += 1
            if not self._failed_since_loss:
                self._failed_since_loss = True
                self.events.append(f'connect to {self.destination_addr[0]}:'
                                   f'{self.destination_addr[1]} failed ({exc}); retrying every '
                                   f'{self.reconnect_period_s:g} s')
            return False
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        mavutil.set_close_on_exec(sock.fileno())
        self.port = sock
        self.fd = sock.fileno()
        self._reset_parser()
        self._failed_since_loss = False
        self.stats['connects'] += 1
        self.events.append(f'connected to {self.destination_addr[0]}:{self.destination_addr[1]}')
        return True

    def _reset_parser(self) -> None:
        """Forget a partial packet of the previous connection."""
        m = self.mav
        m.buf = bytearray()
        m.buf_index = 0
        m.expected_length = mavutil.mavlink.HEADER_LEN_V1 + 2
        m.have_prefix_error = False

    def _drop(self, why: str) -> None:
        if self.port is None:
            return
        with contextlib.suppress(OSError):
            self.port.close()
        self.port = None
        self.fd = None
        self.stats['disconnects'] += 1
        self._next_try_s = time.monotonic() + self.reconnect_period_s
        self.events.append(f'TCP link lost ({why}); reconnecting every '
                           f'{self.reconnect_period_s:g} s')

    # --- pymavlink hooks ----------------------------------------------------------------

    def handle_eof(self) -> None:
        self._drop('EOF')

    def handle_disconnect(self) -> None:
        self._drop('connection reset')

    def reconnect(self) -> None:
        self._try_connect()

    def select(self, timeout: float) -> bool:
        if self.port is None:
            # nothing to read: sleep until the next connect attempt is due (never spin)
            wait = max(0.0, min(timeout, self._next_try_s - time.monotonic()))
            time.sleep(max(wait, 0.001))
            self._try_connect()
            return False
        return super().select(timeout)

    def recv(self, n: int | None = None) -> bytes:
        if self.port is None and not self._try_connect():
            return b''
        assert self.port is not None
        if n is None:
            n = self.mav.bytes_needed()
        try:
            data = self.port.recv(n)
        except BlockingIOError:
            return b''
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                return b''
            self._drop(f'read error: {exc}')
            return b''
        if not data:
            self._drop('EOF')
        return data

    def write(self, buf: bytes) -> None:
        if self.port is None and not self._try_connect():
            self.stats['dropped_writes'] += 1
            return
        assert self.port is not None
        try:
            self.port.send(buf)
        except BlockingIOError:
            self.stats['dropped_writes'] += 1     # a full send buffer: the peer is stuck
        except OSError as exc:
            self._drop(f'write error: {exc}')

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
            self.port = None
            self.fd = None
