"""``deckland topic``: ``list``, ``echo`` and ``hz`` on rclpy alone (no ros2cli here).

Each command runs one node in its own rclpy context, waits for the topic to appear
(``--timeout``), subscribes with QoS matched to the publishers (:mod:`deckland.ros.rosio`) and
exits cleanly on ``--count``/``--duration``, SIGINT or SIGTERM.

The pure parts (YAML-ish rendering, CSV flattening, the rate statistics of :class:`RateMeter`)
have no ROS dependency and are unit-tested on their own.
"""

from __future__ import annotations

import argparse
from collections import deque
from collections.abc import Callable
import csv
from dataclasses import dataclass
import io
import math
import sys
import threading
import time
from typing import Any, TextIO

import yaml

from deckland.ros import rosio

# ============================================================================== pure helpers

#: libyaml's emitter when present (about 10x faster than the pure-Python one).
_DUMPER = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


def to_yaml(data: dict[str, Any]) -> str:
    """``ros2 topic echo`` style text of a message dict (block style, IDL field order)."""
    return yaml.dump(data, Dumper=_DUMPER, sort_keys=False, default_flow_style=False,
                     allow_unicode=True, width=1 << 30).rstrip('\n')


def flatten(data: Any, prefix: str = '') -> list[tuple[str, Any]]:
    """Flatten a message dict to ``(path, value)`` pairs: nested fields joined by ``.``,
    sequence items as ``name[i]``. An empty sequence is one column holding ``''``."""
    out: list[tuple[str, Any]] = []
    if isinstance(data, dict):
        for key, value in data.items():
            out.extend(flatten(value, f'{prefix}.{key}' if prefix else key))
    elif isinstance(data, list):
        if not data:
            out.append((prefix, ''))
        for i, value in enumerate(data):
            out.extend(flatten(value, f'{prefix}[{i}]'))
    else:
        out.append((prefix, data))
    return out


def csv_line(values: list[Any]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator='').writerow(
        [repr(v) if isinstance(v, float) else v for v in values])
    return buf.getvalue()


@dataclass(frozen=True, slots=True)
class HzStats:
    """Rate over the window: ``rate_hz`` = 1 / mean period, min/max/std of the period."""

    rate_hz: float
    min_s: float
    max_s: float
    std_s: float
    window: int      # number of periods in the window

    def format(self) -> str:
        return (f'average rate: {self.rate_hz:.3f}\n'
                f'\tmin: {self.min_s:.3f}s max: {self.max_s:.3f}s '
                f'std dev: {self.std_s:.5f}s window: {self.window}')


class RateMeter:
    """Sliding-window message rate from arrival times (seconds, any origin), like
    ``ros2 topic hz``: the last ``window`` periods between consecutive arrivals.

    Non-finite or out-of-order stamps are rejected and counted in ``rejected``.
    """

    def __init__(self, window: int = 10000) -> None:
        if window < 1:
            raise ValueError(f'window must be >= 1, got {window!r}')
        self.window = window
        self._periods: deque[float] = deque(maxlen=window)
        self._last: float | None = None
        self.count = 0
        self.rejected = {'nan': 0, 'out_of_order': 0}

    def add(self, t_s: float) -> None:
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return
        if self._last is not None:
            if t_s < self._last:
                self.rejected['out_of_order'] += 1
                return
            self._periods.append(t_s - self._last)
        self._last = t_s
        self.count += 1

    def stats(self) -> HzStats | None:
        """``None`` until two messages arrived (or if all periods are zero)."""
        n = len(self._periods)
        if n == 0:
            return None
        mean = math.fsum(self._periods) / n
        if mean <= 0:
            return None
        var = math.fsum((p - mean) ** 2 for p in self._periods) / n
        return HzStats(1.0 / mean, min(self._periods), max(self._periods), math.sqrt(var), n)


# ================================================================================ ROS plumbing


def _run(args: argparse.Namespace, body: Callable[[rosio.RosSession, threading.Event], int],
         node_name: str) -> int:
    """Run ``body(session, stop)`` in a private context with SIGINT/SIGTERM -> stop."""
    stop = threading.Event()
    restore = rosio.install_stop_signals(stop.set)
    session = rosio.RosSession(node_name, getattr(args, 'context', None))
    try:
        return body(session, stop)
    except KeyboardInterrupt:
        return 0
    finally:
        session.close()
        restore()


def _subscribe(session: rosio.RosSession, stop: threading.Event, args: argparse.Namespace,
               callback: Callable[..., None], raw: bool, err: TextIO) -> Any:
    """Wait for the topic, then subscribe to it with matched QoS; None on timeout/stop."""
    topic = rosio.normalize_topic(args.topic)
    deadline = None if args.timeout is None else time.monotonic() + args.timeout
    msgtype = None
    while msgtype is None and not stop.is_set():
        remaining = None if deadline is None else deadline - time.monotonic()
        if remaining is not None and remaining <= 0:
            break
        msgtype = session.wait_for_topic(topic, 0.2 if remaining is None else min(0.2,
                                                                                  remaining))
    if msgtype is None:
        if not stop.is_set():
            print(f'topic {topic} did not appear within {args.timeout} s', file=err)
        return None
    try:
        cls = rosio.import_message_type(msgtype)
    except ValueError as exc:
        print(str(exc), file=err)
        return None
    qos = rosio.subscription_qos(session.publisher_qos(topic), getattr(args, 'qos', 'auto'))
    return session.node.create_subscription(cls, topic, callback, qos, raw=raw)


def _spin(session: rosio.RosSession, stop: threading.Event, done: Callable[[], bool],
          deadline: float | None = None, tick: Callable[[], None] | None = None) -> None:
    while not stop.is_set() and session.ok() and not done():
        if deadline is not None and time.monotonic() >= deadline:
            return
        session.spin_once(0.05)
        if tick is not None:
            tick()


# ==================================================================================== commands


def cmd_list(args: argparse.Namespace) -> int:
    out: TextIO = getattr(args, 'out', None) or sys.stdout

    def body(session: rosio.RosSession, stop: threading.Event) -> int:
        # Discovery needs a moment after start-up; gather for ``--spin-time``.
        end = time.monotonic() + args.spin_time
        while time.monotonic() < end and not stop.is_set():
            session.spin_once(0.05)
        for name, types in sorted(session.topic_types().items()):
            print(f'{name} [{", ".join(types)}]' if args.show_types else name, file=out)
        return 0

    return _run(args, body, 'deckland_topic_list')


def cmd_echo(args: argparse.Namespace) -> int:
    out: TextIO = getattr(args, 'out', None) or sys.stdout
    err: TextIO = getattr(args, 'err', None) or sys.stderr
    state = {'n': 0, 'header': None}

    def on_msg(msg: Any) -> None:
        if args.count is not None and state['n'] >= args.count:
            return
        data = rosio.message_to_dict(msg)
        if args.csv:
            pairs = flatten(data)
            if state['header'] is None:
                state['header'] = [p for p, _ in pairs]
                print(csv_line(state['header']), file=out)
            print(csv_line([v for _, v in pairs]), file=out)
        else:
            print(to_yaml(data), file=out)
            print('---', file=out)
        out.flush()
        state['n'] += 1

    def body(session: rosio.RosSession, stop: threading.Event) -> int:
        sub = _subscribe(session, stop, args, on_msg, raw=False, err=err)
        if sub is None:
            return 0 if stop.is_set() else 1
        deadline = None if args.duration is None else time.monotonic() + args.duration
        _spin(session, stop, lambda: args.count is not None and state['n'] >= args.count,
              deadline)
        if args.count is not None and state['n'] < args.count and not stop.is_set():
            print(f"received {state['n']} of {args.count} messages on "
                  f'{rosio.normalize_topic(args.topic)} within {args.duration} s', file=err)
            return 1
        return 0

    return _run(args, body, 'deckland_topic_echo')


def cmd_hz(args: argparse.Namespace) -> int:
    out: TextIO = getattr(args, 'out', None) or sys.stdout
    err: TextIO = getattr(args, 'err', None) or sys.stderr
    meter = RateMeter(args.window)
    state = {'last_print': time.monotonic(), 'printed_count': -1}

    def on_msg(data: bytes, info: dict[str, Any]) -> None:
        # rmw's reception stamp: free of Python callback latency and GIL jitter.
        stamp_ns = int(info.get('received_timestamp', 0)) or time.time_ns()
        if args.count is None or meter.count < args.count:
            meter.add(stamp_ns * 1e-9)

    def report() -> None:
        if meter.count == state['printed_count'] and meter.count:
            return
        state['printed_count'] = meter.count
        stats = meter.stats()
        print(stats.format() if stats else 'no new messages', file=out)
        out.flush()

    def tick() -> None:
        now = time.monotonic()
        if now - state['last_print'] >= 1.0:
            state['last_print'] = now
            report()

    def body(session: rosio.RosSession, stop: threading.Event) -> int:
        sub = _subscribe(session, stop, args, on_msg, raw=True, err=err)
        if sub is None:
            return 0 if stop.is_set() else 1
        state['last_print'] = time.monotonic()
        deadline = None if args.duration is None else time.monotonic() + args.duration
        _spin(session, stop, lambda: args.count is not None and meter.count >= args.count,
              deadline, tick)
        report()
        return 0

    args.stats = meter  # for callers that want the numbers, not the text
    return _run(args, body, 'deckland_topic_hz')


# ========================================================================================= CLI


def register(sub: Any) -> None:
    """Add ``topic`` with ``list``, ``echo`` and ``hz`` to ``sub``."""
    topic = sub.add_parser('topic', help='list, echo and measure ROS 2 topics')
    tsub = topic.add_subparsers(dest='topic_command', metavar='VERB')
    tsub.required = True

    lst = tsub.add_parser('list', help='topics in the graph')
    lst.add_argument('-t', '--show-types', action='store_true', help='show the types too')
    lst.add_argument('--spin-time', type=float, default=1.0, metavar='S',
                     help='discovery time before listing (default: %(default)s)')
    lst.set_defaults(func=cmd_list)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument('topic', metavar='TOPIC')
        p.add_argument('--timeout', type=float, default=10.0, metavar='S',
                       help='wait at most S seconds for the topic to appear (default: '
                            '%(default)s)')
        p.add_argument('--count', type=int, default=None, metavar='N',
                       help='stop after N messages')
        p.add_argument('--duration', type=float, default=None, metavar='S',
                       help='stop after S seconds')
        p.add_argument('--qos', choices=rosio.QOS_MODES, default='auto',
                       help='auto: match the publishers (default); sensor: best effort; '
                            'reliable')

    echo = tsub.add_parser('echo', help='print messages (YAML-ish, or --csv)')
    common(echo)
    echo.add_argument('--csv', action='store_true',
                      help='a header row of field paths, then one row per message')
    echo.set_defaults(func=cmd_echo)

    hz = tsub.add_parser('hz', help='average rate and period statistics of a topic')
    common(hz)
    hz.add_argument('--window', type=int, default=10000, metavar='N',
                    help='periods in the sliding window (default: %(default)s)')
    hz.set_defaults(func=cmd_hz)


def main(argv: list[str] | None = None) -> int:
    """``python -m deckland.ros.topic VERB ...`` (same as ``deckland topic VERB ...``)."""
    parser = argparse.ArgumentParser(prog='deckland')
    register(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['topic', *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)


if __name__ == '__main__':
    sys.exit(main())
