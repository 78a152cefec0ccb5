"""``deckland bag`` command line: ``record``, ``play``, ``info`` and ``reindex``."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from typing import Any

from deckland.ros import rosio
from deckland.ros.bag.info import bag_info, format_info
from deckland.ros.bag.play import play
from deckland.ros.bag.recorder import Recorder
from deckland.ros.bag.repair import reindex
from deckland.ros.bag.writer import DEFAULT_EXCLUDES


def register(sub: Any) -> None:
    """Add ``bag`` with ``record``, ``play``, ``info`` and ``reindex`` to ``sub``."""
    bag = sub.add_parser('bag', help='record, play and inspect rosbag2 MCAP bags')
    bsub = bag.add_subparsers(dest='bag_command', metavar='VERB')
    bsub.required = True

    rec = bsub.add_parser('record', help='record topics into DIR (rosbag2, MCAP)')
    rec.add_argument('topics', nargs='*', metavar='TOPIC')
    rec.add_argument('-o', '--output', required=True, metavar='DIR', help='bag directory')
    rec.add_argument('-a', '--all', action='store_true',
                     help='record every topic, also ones that appear later')
    rec.add_argument('--duration', type=float, default=None, metavar='S',
                     help='stop after S seconds')
    rec.add_argument('--exclude', nargs='*', default=list(DEFAULT_EXCLUDES), metavar='TOPIC',
                     help='topics --all leaves out (default: %(default)s)')
    rec.set_defaults(func=_cmd_record)

    ply = bsub.add_parser('play', help='republish a bag with its recorded timing')
    ply.add_argument('bag', metavar='DIR')
    ply.add_argument('-r', '--rate', type=float, default=1.0)
    ply.add_argument('--topics', nargs='*', default=None, metavar='TOPIC')
    ply.add_argument('-l', '--loop', action='store_true')
    ply.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                     help='skip the first S seconds of the bag')
    ply.add_argument('--delay', type=float, default=0.0, metavar='S',
                     help='sleep S seconds before playing')
    ply.add_argument('--wait-subscribers', type=float, default=0.0, metavar='S',
                     help='wait up to S seconds until every topic has a subscriber')
    ply.set_defaults(func=_cmd_play)

    inf = bsub.add_parser('info', help='topics, types, counts, duration and size of a bag')
    inf.add_argument('bag', metavar='DIR')
    inf.add_argument('--no-recover', action='store_true',
                     help='do not reindex an unfinished bag, scan it read-only')
    inf.set_defaults(func=_cmd_info)

    rix = bsub.add_parser('reindex', help='repair a bag whose recorder was killed')
    rix.add_argument('bag', metavar='DIR')
    rix.set_defaults(func=_cmd_reindex)


def _cmd_record(args: argparse.Namespace) -> int:
    if not args.topics and not args.all:
        print('bag record: give TOPIC ... or --all', file=sys.stderr)
        return 2
    if args.duration is not None and not args.duration > 0:
        print('bag record: --duration must be > 0', file=sys.stderr)
        return 2
    stop = threading.Event()
    restore = rosio.install_stop_signals(stop.set)
    try:
        recorder = Recorder(args.output, topics=args.topics or None, all_topics=args.all,
                            exclude=args.exclude)
        recorder.start()
    except (FileExistsError, ValueError, OSError) as exc:
        restore()
        print(f'bag record: {exc}', file=sys.stderr)
        return 1
    print(f'recording to {args.output} '
          f'({"all topics" if args.all else ", ".join(recorder.topics)})', file=sys.stderr)
    try:
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set():
            timeout = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if timeout <= 0:
                break
            stop.wait(timeout)
    except KeyboardInterrupt:
        pass
    finally:
        recorder.stop()
        restore()
    total = sum(recorder.counts.values())
    print(f'recorded {total} messages on {len(recorder.counts)} topics to {args.output}',
          file=sys.stderr)
    return 0


def _cmd_play(args: argparse.Namespace) -> int:
    stop = threading.Event()
    restore = rosio.install_stop_signals(stop.set)
    try:
        n = play(args.bag, rate=args.rate, topics=args.topics, loop=args.loop,
                 start_offset_s=args.start_offset, delay_s=args.delay,
                 wait_for_subscribers_s=args.wait_subscribers, stop_event=stop,
                 log=sys.stderr)
    except (FileNotFoundError, RuntimeError, ValueError) as exc:
        print(f'bag play: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        restore()
    print(f'published {n} messages', file=sys.stderr)
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    try:
        info = bag_info(args.bag, recover=not args.no_recover)
    except (FileNotFoundError, RuntimeError, OSError) as exc:
        print(f'bag info: {exc}', file=sys.stderr)
        return 1
    print(format_info(info))
    return 0


def _cmd_reindex(args: argparse.Namespace) -> int:
    try:
        counts = reindex(args.bag)
    except (FileNotFoundError, RuntimeError, OSError) as exc:
        print(f'bag reindex: {exc}', file=sys.stderr)
        return 1
    print(f'reindexed {args.bag}: {sum(counts.values())} messages on {len(counts)} topics')
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m deckland.ros.bag VERB ...`` (same as ``deckland bag VERB ...``)."""
    parser = argparse.ArgumentParser(prog='deckland')
    register(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['bag', *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)
