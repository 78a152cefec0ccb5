"""Byte transports for the emulated autopilot's MAVLink side (no rclpy).

:class:`UdpTransport` is a non-blocking UDP socket (PX4 SITL style: answer whoever last sent a
valid packet); :class:`MemoryLink` is an in-memory pair for tests. Every transport has
``send(data)``, ``receive() -> [(data, addr)]``, ``set_peer(addr)`` and ``close()``;
:func:`make_mavlink_link` opens the socket a ``mavlink_url`` names.
"""

from __future__ import annotations

import ipaddress
import re
import socket

_URL_RE = re.compile(r'^(udpin|udpout|udp):([^:]+):(\d{1,5})$')


def parse_mavlink_url(url: str) -> tuple[str, str, int]:
    """``'udpin:HOST:PORT'`` / ``'udp:HOST:PORT'`` (listen there) or ``'udpout:HOST:PORT'``
    (send there) → ``(mode, host, port)`` with mode ``'in'`` or ``'out'``; ValueError if bad.

    pymavlink's syntax seen from the autopilot: the bridge's default ``udpin:127.0.0.1:14540``
    pairs with our default ``udpout:127.0.0.1:14540`` (PX4 SITL sends to 14540), the bridge's
    ``udpout:H:P`` (``deckland up``) with our ``udpin:H:P``.
    """
    m = _URL_RE.match(url.strip())
    if m is None:
        raise ValueError(f"expected 'udpin:HOST:PORT' or 'udpout:HOST:PORT', got {url!r}")
    kind, host, port_s = m.groups()
    port = int(port_s)
    if host != 'localhost':
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise ValueError(f'host must be an IPv4 literal or localhost, got {host!r}') \
                from None
    mode = 'out' if kind == 'udpout' else 'in'
    if not (0 <= port <= 65535) or (mode == 'out' and port == 0):
        raise ValueError(f'bad UDP port {port} in {url!r}')
    return mode, ('127.0.0.1' if host == 'localhost' else host), port


def is_mavlink_url(value: str) -> bool:
    """``value`` is a ``mavlink_url`` :func:`parse_mavlink_url` accepts."""
    try:
        parse_mavlink_url(value)
    except ValueError:
        return False
    return True


def is_ipv4(value: str) -> bool:
    try:
        ipaddress.IPv4Address(value)
    except ValueError:
        return False
    return True


class UdpTransport:
    """Non-blocking UDP socket bound to ``bind``, sending to ``remote``.

    ``remote`` may be None until a peer is known (``udpin`` before the companion's first
    packet): sends are then dropped and counted in ``dropped_no_peer`` instead of spraying a
    guessed port. The emulator calls :meth:`set_peer` with the source of every valid packet.
    """

    def __init__(self, bind: tuple[str, int], remote: tuple[str, int] | None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind(bind)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.remote = remote
        self.send_errors = 0
        self.dropped_no_peer = 0

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def send(self, data: bytes) -> None:
        if self.remote is None:
            self.dropped_no_peer += 1
            return
        try:
            self.sock.sendto(data, self.remote)
        except OSError:
            self.send_errors += 1   # nobody listening (ECONNREFUSED), socket closed, ...

    def receive(self) -> list[tuple[bytes, object]]:
        out = []
        for _ in range(1000):
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                if self.sock.fileno() < 0:
                    break
                continue   # a late ICMP error (port unreachable) surfaces on recv: skip it
            out.append((data, addr))
        return out

    def set_peer(self, addr: object) -> None:
        self.remote = addr

    def close(self) -> None:
        self.sock.close()


def make_mavlink_link(url: str) -> UdpTransport:
    """The emulator's socket for ``mavlink_url`` (see :func:`parse_mavlink_url`)."""
    mode, host, port = parse_mavlink_url(url)
    if mode == 'in':
        return UdpTransport((host, port), None)
    bind_host = '127.0.0.1' if ipaddress.IPv4Address(host).is_loopback else '0.0.0.0'
    return UdpTransport((bind_host, 0), (host, port))


class MemoryLink:
    """Two in-memory endpoints ``a`` and ``b``: bytes sent on one are received on the other."""

    class End:
        def __init__(self) -> None:
            self.inbox: list[bytes] = []
            self.peer: MemoryLink.End | None = None

        def send(self, data: bytes) -> None:
            self.peer.inbox.append(bytes(data))

        def write(self, data: bytes) -> None:  # pymavlink file-like writer
            self.send(data)

        def receive(self) -> list[tuple[bytes, object]]:
            out, self.inbox = self.inbox, []
            return [(d, None) for d in out]

        def set_peer(self, addr: object) -> None:
            pass

        def close(self) -> None:
            pass

    def __init__(self) -> None:
        self.a, self.b = MemoryLink.End(), MemoryLink.End()
        self.a.peer, self.b.peer = self.b, self.a


__all__ = ['MemoryLink', 'UdpTransport', 'is_ipv4', 'is_mavlink_url', 'make_mavlink_link',
           'parse_mavlink_url']
