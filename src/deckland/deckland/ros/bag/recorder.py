"""The recorder: subscribes (rclpy) to the chosen topics with QoS matched to their publishers
and writes what arrives through :class:`~deckland.ros.bag.writer.BagWriter`."""

from __future__ import annotations

from collections.abc import Iterable
import contextlib
import fcntl
import os
from pathlib import Path
import time
from typing import Any

from deckland.ros import rosio
from deckland.ros.bag.writer import DEFAULT_EXCLUDES, LOCK_NAME, BagWriter


class Recorder:
    """Records topics into a rosbag2 MCAP bag with raw (CDR) subscriptions.

    ``topics``: names to record (subscribed as soon as each appears); ``all_topics``: every
    topic, including ones that appear later (discovery every ``discovery_period_s``).
    Subscriptions match the publishers' QoS (:func:`rosio.subscription_qos`). ``context``:
    an initialised rclpy context to create the node in (e.g. ``deckland up``'s); by default a
    private one. :meth:`start` spins in a background thread; :meth:`stop` finishes the bag.
    """

    def __init__(self, out_dir: str | os.PathLike[str], topics: list[str] | None = None,
                 all_topics: bool = False, context: Any = None, *,
                 discovery_period_s: float = 1.0, flush_period_s: float = 0.25,
                 metadata_period_s: float = 1.0, depth: int = 100,
                 exclude: Iterable[str] = DEFAULT_EXCLUDES,
                 node_name: str = 'deckland_recorder') -> None:
        if not topics and not all_topics:
            raise ValueError('Recorder needs topics or all_topics=True')
        for name, value in (('discovery_period_s', discovery_period_s),
                            ('flush_period_s', flush_period_s),
                            ('metadata_period_s', metadata_period_s)):
            if not value > 0:
                raise ValueError(f'{name} must be > 0, got {value!r}')
        if depth < 1:
            raise ValueError(f'depth must be >= 1, got {depth!r}')
        self.out_dir = Path(out_dir)
        self.topics = [rosio.normalize_topic(t) for t in (topics or [])]
        self.all_topics = all_topics
        self.exclude = {rosio.normalize_topic(t) for t in exclude}
        self.discovery_period_s = discovery_period_s
        self.flush_period_s = flush_period_s
        self.metadata_period_s = metadata_period_s
        self.depth = depth
        self._context = context
        self._node_name = node_name
        self._session: rosio.RosSession | None = None
        self._writer: BagWriter | None = None
        self._lock_file: Any = None
        self._subscriptions: dict[str, Any] = {}
        self.skipped: dict[str, str] = {}
        self._timers: list[Any] = []

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic so far."""
        if self._writer is None:
            return {}
        return {t: c.count for t, c in self._writer.channels.items()}

    @property
    def subscribed(self) -> list[str]:
        return sorted(self._subscriptions)

    def start(self) -> Recorder:
        if self._session is not None:
            raise RuntimeError('Recorder already started')
        self._writer = BagWriter(self.out_dir)
        self._lock_file = open(self.out_dir / LOCK_NAME, 'w')  # noqa: SIM115
        fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._lock_file.write(f'{os.getpid()}\n')
        self._lock_file.flush()
        self._session = rosio.RosSession(self._node_name, self._context)
        node = self._session.node
        self._discover()
        self._timers = [node.create_timer(self.discovery_period_s, self._discover),
                        node.create_timer(self.flush_period_s, self._writer.flush),
                        node.create_timer(self.metadata_period_s, self._writer.update_metadata)]
        self._session.spin_in_thread()
        return self

    def wait_for_subscriptions(self, n: int, timeout_s: float = 5.0) -> bool:
        """Block until ``n`` topics are subscribed (handy in tests and launchers)."""
        deadline = time.monotonic() + timeout_s
        while len(self._subscriptions) < n:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def stop(self) -> None:
        """Finish the bag (footer, index, metadata.yaml) and release the node and lock."""
        session, self._session = self._session, None
        if session is not None:
            session.close()
        if self._writer is not None:
            self._writer.close()
        if self._lock_file is not None:
            with contextlib.suppress(OSError):
                (self.out_dir / LOCK_NAME).unlink()
            self._lock_file.close()
            self._lock_file = None

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _discover(self) -> None:
        session, writer = self._session, self._writer
        if session is None or writer is None:
            return
        available = session.topic_types()
        wanted = (sorted(t for t in available if t not in self.exclude) if self.all_topics
                  else self.topics)
        for topic in wanted:
            if topic in self._subscriptions or topic in self.skipped:
                continue
            types = available.get(topic)
            pub_qos = session.publisher_qos(topic) if types else []
            if not types or not pub_qos:
                continue  # not published (yet)
            msgtype = types[0]
            try:
                cls = rosio.import_message_type(msgtype)
            except ValueError as exc:
                self.skipped[topic] = str(exc)
                session.node.get_logger().warning(f'not recording {topic}: {exc}')
                continue
            writer.add_topic(topic, msgtype, [rosio.qos_to_rosbags(q) for q in pub_qos])
            qos = rosio.subscription_qos(pub_qos, 'auto', depth=self.depth)

            def callback(data: bytes, info: Any, _topic: str = topic) -> None:
                received = int(info.get('received_timestamp', 0)) or time.time_ns()
                writer.write(_topic, received, data, int(info.get('source_timestamp', 0))
                             or received, int(info.get('publication_sequence_number', 0)))

            self._subscriptions[topic] = session.node.create_subscription(
                cls, topic, callback, qos, raw=True)
