"""Shared ROS I/O helpers for ``deckland topic`` and ``deckland bag`` (rclpy + rosbags only).

More in the package README, "Module notes" (`deckland.ros.rosio`).
"""

from __future__ import annotations

import array
from collections.abc import Callable, Iterable
import contextlib
import functools
import importlib
import time
from typing import Any

#: QoS keyword accepted by ``--qos``.
QOS_MODES = ('auto', 'sensor', 'reliable')

#: rosbag2's (Jazzy) "infinite" duration: RMW_DURATION_INFINITE = INT64_MAX ns as sec/nsec.
_INFINITE_SEC = 9223372036
_INFINITE_NSEC = 854775807


def normalize_topic(name: str) -> str:
    """Fully qualified topic name (a leading ``/``), as the graph API reports it."""
    name = name.strip()
    return name if name.startswith('/') else '/' + name


def split_type(type_str: str) -> tuple[str, str, str]:
    """``'pkg/msg/Name'`` or ``'pkg/Name'`` -> ``('pkg', 'msg', 'Name')``; ValueError otherwise."""
    parts = [p for p in type_str.strip().split('/') if p]
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(p.replace('_', '').isalnum() for p in parts):
        raise ValueError(f'not a ROS message type string: {type_str!r}')
    return parts[0], parts[1], parts[2]


@functools.lru_cache(maxsize=256)
def import_message_type(type_str: str) -> type:
    """The generated Python class for a type string (no generic type support in rclpy).

    Raises ``ValueError`` naming the type when the package or class is not installed.
    """
    pkg, sub, name = split_type(type_str)
    try:
        module = importlib.import_module(f'{pkg}.{sub}')
        cls = getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f'message type {type_str!r} is not installed here ({exc})') from None
    return cls


def message_type_name(cls: type) -> str:
    """Inverse of :func:`import_message_type` (class -> ``pkg/msg/Name``)."""
    module = cls.__module__.split('.')
    return f'{module[0]}/{module[1]}/{cls.__name__}'


# --------------------------------------------------------------------------------- QoS rules


def match_publishers(reliabilities: Iterable[str], durabilities: Iterable[str]) -> tuple[str, str]:
    """Subscriber (reliability, durability) compatible with every publisher, pure.

    Inputs are lower-case names (``'reliable'``, ``'best_effort'``, ``'transient_local'``,
    ``'volatile'``). A reliable subscription does not match a best-effort publisher, so one
    best-effort publisher makes the subscription best effort. A transient-local subscription
    does not match a volatile publisher, so it is transient local only if all publishers are
    (and there is at least one). With no publishers: reliable, volatile.
    """
    rel = list(reliabilities)
    dur = list(durabilities)
    reliability = 'best_effort' if any(r == 'best_effort' for r in rel) else 'reliable'
    durability = 'transient_local' if dur and all(d == 'transient_local' for d in dur) \
        else 'volatile'
    return reliability, durability


def _policy_name(policy: Any) -> str:
    return str(getattr(policy, 'name', policy)).lower()


def _keep_last(reliability: str, durability: str, depth: int) -> Any:
    """A KEEP_LAST profile from policy names ('best_effort' | 'reliable',
    'transient_local' | 'volatile')."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=(ReliabilityPolicy.BEST_EFFORT if reliability == 'best_effort'
                     else ReliabilityPolicy.RELIABLE),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if durability == 'transient_local'
                    else DurabilityPolicy.VOLATILE))


def subscription_qos(publisher_qos: Iterable[Any], mode: str = 'auto', depth: int = 10) -> Any:
    """rclpy ``QoSProfile`` for subscribing to a topic offered with ``publisher_qos``.

    ``mode``: ``'auto'`` matches the publishers (:func:`match_publishers`), ``'sensor'`` is
    ``qos_profile_sensor_data`` (best effort, volatile), ``'reliable'`` forces reliable/volatile.
    """
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_sensor_data,
    )

    if mode not in QOS_MODES:
        raise ValueError(f'qos mode must be one of {QOS_MODES}, got {mode!r}')
    if mode == 'sensor':
        return qos_profile_sensor_data
    if mode == 'reliable':
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
    pubs = list(publisher_qos)
    reliability, durability = match_publishers(
        (_policy_name(q.reliability) for q in pubs), (_policy_name(q.durability) for q in pubs))
    return _keep_last(reliability, durability, depth)


def _duration_to_qostime(duration: Any) -> Any:
    from rosbags.interfaces import QosTime

    ns = int(getattr(duration, 'nanoseconds', 0))
    if ns <= 0 or ns >= 2**62:
        # rmw reports "infinite"/"unspecified" as 0 or a huge value; rosbag2 writes the
        # infinite sentinel for both.
        return QosTime(_INFINITE_SEC, _INFINITE_NSEC)
    return QosTime(ns // 10**9, ns % 10**9)


def qos_to_rosbags(profile: Any) -> Any:
    """rclpy ``QoSProfile`` (an offered publisher profile) -> rosbags ``Qos`` record."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
    )

    def enum(cls: Any, policy: Any) -> Any:
        return cls.__members__.get(_policy_name(policy).upper(), cls.UNKNOWN)

    return Qos(
        history=enum(QosHistory, profile.history),
        depth=int(profile.depth),
        reliability=enum(QosReliability, profile.reliability),
        durability=enum(QosDurability, profile.durability),
        deadline=_duration_to_qostime(profile.deadline),
        lifespan=_duration_to_qostime(profile.lifespan),
        liveliness=enum(QosLiveliness, profile.liveliness),
        liveliness_lease_duration=_duration_to_qostime(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def default_offered_qos(transient_local: bool = False) -> Any:
    """A rosbags ``Qos`` for a reliable keep-last(10) publisher (used when none is known)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    inf = QosTime(_INFINITE_SEC, _INFINITE_NSEC)
    return Qos(QosHistory.KEEP_LAST, 10 if not transient_local else 1, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               inf, inf, QosLiveliness.AUTOMATIC, inf, False)


def offered_qos_yaml(profiles: list[Any]) -> str:
    """rosbag2 storage version 9 text of a list of rosbags ``Qos`` (MCAP channel metadata)."""
    from rosbags.rosbag2.metadata import dump_qos_v9
    import yaml

    return yaml.safe_dump(dump_qos_v9(list(profiles)), default_flow_style=False,
                          sort_keys=False).strip()


def publisher_qos_from_offered(offered: list[Any], depth: int = 10) -> Any:
    """rclpy ``QoSProfile`` for republishing a topic recorded with ``offered`` rosbags QoS.

    Reliable unless a recorded publisher was best effort; transient local only if every
    recorded publisher was (so late joiners still get latched state such as ``planner/mode``).
    """
    reliability, durability = match_publishers(
        (q.reliability.name.lower() for q in offered),
        (q.durability.name.lower() for q in offered))
    depth = max([depth, *(int(q.depth) for q in offered if int(q.depth) > 0)])
    return _keep_last(reliability, durability, depth)


# ------------------------------------------------------------------------------- typestore


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """The rosbags typestore for Jazzy plus deckland_interfaces (message definitions and
    RIHS01 hashes)."""
    from deckland.ros import msgtypes

    return msgtypes.typestore()


def message_definition(type_str: str) -> tuple[str, str]:
    """(``ros2msg`` definition text, ``RIHS01_...`` hash) or ``('', '')`` if unknown."""
    store = typestore()
    if type_str not in store.types:
        return '', ''
    text, _ = store.generate_msgdef(type_str, ros_version=2)
    return text, store.hash_rihs01(type_str)


# -------------------------------------------------------------------------------- messages


def message_to_dict(msg: Any) -> dict[str, Any]:
    """A generated ROS message -> ordered nested dict of plain Python values.

    Sequences and arrays (``array.array``, numpy arrays, tuples) become lists, nested
    messages become dicts, ``bytes`` become lists of ints; field order is the IDL order.
    """
    out: dict[str, Any] = {}
    for field in msg.get_fields_and_field_types():
        out[field] = _plain(getattr(msg, field))
    return out


def _plain(value: Any) -> Any:
    if hasattr(value, 'get_fields_and_field_types'):
        return message_to_dict(value)
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (list, tuple, array.array)):
        return [_plain(v) for v in value]
    if hasattr(value, 'tolist'):  # numpy arrays and scalars
        return _plain(value.tolist())
    return value


# ------------------------------------------------------------------------------- the session


class RosSession:
    """One node on one executor, in a private context unless ``context`` is given.

    With ``context=None`` a fresh ``rclpy.Context`` is initialised without rclpy's signal
    handlers (the command decides what SIGINT/SIGTERM do) and shut down by :meth:`close`.
    A borrowed context is left running. ``spin_*`` helpers run callbacks in the calling
    thread; :meth:`spin_in_thread` runs them in a background thread instead. ``executor``:
    ``'single'`` (rclpy's SingleThreadedExecutor) or ``'events'`` (its EventsExecutor, as
    the nodes spin: a fraction of the CPU per message, for a session that forwards streams).
    """

    def __init__(self, node_name: str, context: Any = None, executor: str = 'single') -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        if executor not in ('single', 'events'):
            raise ValueError(f"executor must be 'single' or 'events', got {executor!r}")

        self._own_context = context is None
        if context is None:
            context = rclpy.Context()
            rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
        self.context = context
        self.node = rclpy.create_node(node_name, context=context,
                                      start_parameter_services=False)
        if executor == 'events':
            from rclpy.experimental import EventsExecutor
            self.executor: Any = EventsExecutor(context=context)
        else:
            self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._thread = None
        self._closed = False

    def ok(self) -> bool:
        return not self._closed and self.context.ok()

    def spin_once(self, timeout_s: float = 0.1) -> None:
        self.executor.spin_once(timeout_sec=timeout_s)

    def spin_until(self, done: Callable[[], bool], timeout_s: float | None = None,
                   step_s: float = 0.05) -> bool:
        """Spin until ``done()`` is true (True) or ``timeout_s`` elapses (False)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.ok():
            if done():
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False
            self.spin_once(step_s)
        return done()

    def spin_in_thread(self) -> None:
        import threading

        def run() -> None:
            while self.ok():
                try:
                    self.executor.spin_once(timeout_sec=0.05)
                except Exception:
                    if not self.ok():
                        return
                    raise

        self._thread = threading.Thread(target=run, name=f'{self.node.get_name()}-spin',
                                        daemon=True)
        self._thread.start()

    def topic_types(self) -> dict[str, list[str]]:
        return dict(self.node.get_topic_names_and_types())

    def wait_for_topic(self, topic: str, timeout_s: float | None) -> str | None:
        """The type of ``topic`` once it has a publisher (or is known), ``None`` on timeout."""
        topic = normalize_topic(topic)
        found: list[str] = []

        def check() -> bool:
            types = self.topic_types().get(topic)
            if types and self.node.get_publishers_info_by_topic(topic):
                found.append(types[0])
                return True
            return False

        if self._thread is None:
            self.spin_until(check, timeout_s)
        else:
            deadline = None if timeout_s is None else time.monotonic() + timeout_s
            while self.ok() and not check():
                if deadline is not None and time.monotonic() >= deadline:
                    break
                time.sleep(0.05)
        return found[0] if found else None

    def publisher_qos(self, topic: str) -> list[Any]:
        return [info.qos_profile
                for info in self.node.get_publishers_info_by_topic(normalize_topic(topic))]

    def close(self, linger_s: float = 0.0, ack_timeout_s: float = 1.0) -> None:
        """Destroy the node (and the context, if the session made it). With ``linger_s`` > 0
        the node's last messages get to leave first: each reliable publisher waits for its
        acknowledgements (``ack_timeout_s`` at most), then everything waits ``linger_s`` more
        (best-effort data has no acknowledgement: a writer deleted right after its last write
        lost that write in about one run in three here, 2026-12-08)."""
        if self._closed:
            return
        self._closed = True
        if linger_s > 0.0:
            from rclpy.duration import Duration
            for pub in list(self.node.publishers):
                with contextlib.suppress(Exception):   # best effort: returns at once
                    pub.wait_for_all_acked(Duration(seconds=ack_timeout_s))
            time.sleep(linger_s)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        try:
            self.executor.remove_node(self.node)
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            if self._own_context:
                self.context.try_shutdown()

    def __enter__(self) -> RosSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def install_stop_signals(callback: Callable[[], None]) -> Callable[[], None]:
    """Route SIGINT and SIGTERM to ``callback`` (main thread only); returns a restorer."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = {}

    def handler(signum: int, frame: Any) -> None:
        callback()

    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, handler)

    def restore() -> None:
        for sig, old in previous.items():
            signal.signal(sig, old)

    return restore
