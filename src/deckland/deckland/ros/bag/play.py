"""Playing a bag back: republish with its recorded timing and QoS, or iterate its messages
in time order."""

from __future__ import annotations

from collections.abc import Iterator
import os
from pathlib import Path
import threading
import time
from typing import Any

from deckland.ros import rosio
from deckland.ros.bag.repair import ensure_readable

#: how long the player stays after its last message before deleting its publishers
#: (:meth:`deckland.ros.rosio.RosSession.close`: reliable ones wait for their acks first)
LINGER_S = 0.1


def play(bag_dir: str | os.PathLike[str], rate: float = 1.0, topics: list[str] | None = None,
         context: Any = None, *, loop: bool = False, start_offset_s: float = 0.0,
         delay_s: float = 0.0, wait_for_subscribers_s: float = 0.0,
         stop_event: threading.Event | None = None, log: Any = None) -> int:
    """Republish a bag's raw CDR data with the recorded timing; returns messages published.

    Timing is relative to the first message played (after ``start_offset_s``), scaled by
    ``1/rate``; publishers use the QoS of the recorded offered profiles
    (:func:`rosio.publisher_qos_from_offered`). ``wait_for_subscribers_s`` waits up to that
    long for every publisher to be matched before the first message (discovery takes a few
    hundred ms). ``stop_event`` ends playback early (also between loops).
    """
    from rosbags.highlevel import AnyReader

    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate!r}')
    if start_offset_s < 0:
        raise ValueError(f'start_offset_s must be >= 0, got {start_offset_s!r}')
    bag = Path(bag_dir)
    if not ensure_readable(bag, log):
        raise RuntimeError(f'{bag} is still being recorded; play it when it is finished')
    stop = stop_event or threading.Event()
    wanted = {rosio.normalize_topic(t) for t in topics} if topics else None
    published = 0
    session = rosio.RosSession('deckland_player', context)
    try:
        with AnyReader([bag]) as reader:
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            publishers: dict[str, Any] = {}
            for c in conns:
                if c.topic in publishers:
                    continue
                try:
                    cls = rosio.import_message_type(c.msgtype)
                except ValueError as exc:
                    if log is not None:
                        print(f'skipping {c.topic}: {exc}', file=log)
                    continue
                offered = [q for cc in conns if cc.topic == c.topic
                           for q in cc.ext.offered_qos_profiles]
                publishers[c.topic] = session.node.create_publisher(
                    cls, c.topic, rosio.publisher_qos_from_offered(offered))
            if not publishers:
                return 0
            deadline = time.monotonic() + wait_for_subscribers_s
            while (wait_for_subscribers_s > 0 and time.monotonic() < deadline
                   and not stop.is_set()
                   and any(p.get_subscription_count() == 0 for p in publishers.values())):
                stop.wait(0.02)
            if delay_s > 0:
                stop.wait(delay_s)
            conns = [c for c in conns if c.topic in publishers]
            first_ns = reader.start_time + int(start_offset_s * 1e9)
            while not stop.is_set():
                t0_wall = time.monotonic()
                t0_bag = None
                for conn, t_ns, data in reader.messages(connections=conns, start=first_ns):
                    if t0_bag is None:
                        t0_bag = t_ns
                    due = t0_wall + (t_ns - t0_bag) / 1e9 / rate
                    wait = due - time.monotonic()
                    if wait > 0 and stop.wait(wait):
                        break
                    if stop.is_set():
                        break
                    publishers[conn.topic].publish(bytes(data))
                    published += 1
                if not loop or t0_bag is None:
                    break
    finally:
        session.close(linger_s=LINGER_S if published else 0.0)
    return published



def iter_messages(bag_dir: str | os.PathLike[str],
                  topics: list[str] | None = None) -> Iterator[tuple[str, str, int, bytes]]:
    """``(topic, msgtype, t_ns, cdr)`` in time order (reindexing an unfinished bag first)."""
    from rosbags.highlevel import AnyReader

    bag = Path(bag_dir)
    ensure_readable(bag)
    wanted = {rosio.normalize_topic(t) for t in topics} if topics else None
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for conn, t_ns, data in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t_ns, bytes(data)
