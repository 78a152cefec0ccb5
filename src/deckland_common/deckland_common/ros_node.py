"""Thin rclpy helpers shared by every deckland node: parameters, QoS, stamps, the
guarded-input mixin and ``main()``.

Nodes stay adapters: declare the :class:`~deckland_common.params.ParamSpec` rows, convert
messages to the pure cores' plain inputs and back, and publish. Nothing algorithmic lives here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
import math
import os
import sys
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from deckland_common.checks import InputGuard
from deckland_common.params import ParameterError, ParamSpec, validate

#: High-rate sensor streams (camera blocks, lidar, IMU): best effort, keep last 5.
SENSOR_QOS = qos_profile_sensor_data
#: Commands and estimates: reliable, keep last 10.
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST)
#: Latched state (mode, scenario, outcome): reliable + transient local, depth 1.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declare_and_validate(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare each spec with its description, read the values, validate them all.

    Raises :class:`ParameterError` on the first bad value (also for a value of the wrong
    type, which rclpy refuses while declaring: the message names the node).
    """
    specs = list(specs)
    values = {}
    for spec in specs:
        descriptor = ParameterDescriptor(description=spec.description + (
            f' ({spec.rule})' if spec.rule else ''))
        try:
            values[spec.name] = node.declare_parameter(spec.name, spec.default,
                                                       descriptor).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise ParameterError(f'{node.get_name()}: {exc}') from exc
    return validate(values, specs)


def stamp_to_s(stamp) -> float:
    """builtin_interfaces/Time → seconds (float)."""
    return stamp.sec + stamp.nanosec * 1e-9


def s_to_stamp(t_s: float, stamp) -> Any:
    """Fill a builtin_interfaces/Time in place from seconds; returns it."""
    sec = math.floor(t_s)
    stamp.sec = int(sec)
    stamp.nanosec = min(round((t_s - sec) * 1e9), 999_999_999)
    return stamp


def all_finite(*values: float) -> bool:
    """True when every value is a finite float (the gate in front of every core)."""
    return all(math.isfinite(v) for v in values)


class GuardedNode:
    """Mixin for a node whose pure loop core counts what it rejects and withholds.

    :meth:`attach_guard` shares the core's ``rejected`` / ``withheld`` dicts with the node
    (the node's own message-level rejections, :meth:`_reject`, count in the same dict) and
    routes the core's hooks to throttled warnings; :meth:`_now_s` is the node clock in
    seconds and :meth:`_counter_values` the diagnostics rows of both counters. Mix into an
    ``rclpy.node.Node`` subclass.
    """

    rejected: dict[str, int]
    withheld: dict[str, int]
    get_clock: Callable[[], Any]     # provided by rclpy.node.Node
    get_logger: Callable[[], Any]
    _withheld_text = 'publishing nothing'

    def attach_guard(self, guard: InputGuard, withheld_text: str) -> None:
        self.rejected = guard.rejected
        self.withheld = guard.withheld
        self._withheld_text = withheld_text
        guard.on_reject = self._log_reject
        guard.on_withhold = self._log_withheld

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _log_reject(self, reason: str, what: str) -> None:
        self.get_logger().warn(
            f'rejected {what}: {reason} ({self.rejected.get(reason, 0)} so far)',
            throttle_duration_sec=2.0)

    def _log_withheld(self, reason: str) -> None:
        self.get_logger().warn(f'{self._withheld_text}: {reason}',
                               throttle_duration_sec=2.0)

    def _reject(self, reason: str, what: str) -> None:
        """Count and log a message the node refuses before its core sees it."""
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        self._log_reject(reason, what)

    def _counter_values(self) -> dict[str, str]:
        """``rejected_<reason>`` and ``withheld_<reason>`` diagnostics values."""
        values = {f'rejected_{k}': str(v) for k, v in self.rejected.items()}
        values.update({f'withheld_{k}': str(v) for k, v in self.withheld.items()})
        return values

    def _publish_status(self, publisher: Any, status: DiagnosticStatus,
                        values: dict[str, str]) -> None:
        """``status`` with ``values`` as one DiagnosticArray on ``publisher``, stamped now."""
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        publisher.publish(msg)


#: Environment variable choosing the executor of :func:`run_node`: ``events`` (default) or
#: ``single`` (rclpy's SingleThreadedExecutor, the fallback).
EXECUTOR_ENV = 'DECKLAND_EXECUTOR'
EXECUTORS = ('events', 'single')
#: Longest wait of one ``spin_once`` of the events executor (s); only bounds how fast a
#: shutdown that did not wake the executor is noticed.
SPIN_ONCE_TIMEOUT_S = 0.5


def executor_kind(environ: dict | None = None) -> str:
    """The executor named by ``$DECKLAND_EXECUTOR`` (default ``events``).

    Raises :class:`ParameterError` for any other value (the node then exits with status 2).
    """
    env = os.environ if environ is None else environ
    kind = env.get(EXECUTOR_ENV, '').strip().lower() or 'events'
    if kind not in EXECUTORS:
        raise ParameterError(f'environment {EXECUTOR_ENV}={env.get(EXECUTOR_ENV)!r}: must be '
                             f'one of {EXECUTORS}')
    return kind


def spin(node: Node, kind: str = 'events') -> None:
    """Spin ``node`` until its context shuts down.

    ``events``: ``rclpy.experimental.EventsExecutor`` (C++ event queue, no per-wake wait-set
    rebuild: about a third of the CPU of the SingleThreadedExecutor for the same callbacks).
    Its blocking ``spin()`` never runs timers in this rclpy (7.1.5: the timer thread starves
    while ``spin()`` blocks; checked with a 100 Hz timer that never fired), so it is driven by
    ``spin_once`` in a loop, which runs timers, subscriptions, services and accepts
    publications from other threads. ``single``: ``rclpy.spin`` (SingleThreadedExecutor).
    """
    if kind == 'single':
        rclpy.spin(node)
        return
    from rclpy.experimental import EventsExecutor
    context = node.context
    executor = EventsExecutor(context=context)
    executor.add_node(node)
    try:
        while context.ok():
            executor.spin_once(timeout_sec=SPIN_ONCE_TIMEOUT_S)
    finally:
        executor.shutdown(timeout_sec=1.0)


def run_node(factory: Callable[..., Node], args: list[str] | None = None) -> int:
    """Standard Jazzy ``main()`` body: init, build, spin, clean shutdown.

    The executor is :func:`spin`'s ``events`` unless ``$DECKLAND_EXECUTOR=single``. A
    :class:`ParameterError` while building the node (or a bad ``$DECKLAND_EXECUTOR``) is
    printed as a clear message and the process exits with status 2 (never a silent default).
    """
    rclpy.init(args=args)
    node = None
    try:
        kind = executor_kind()
        node = factory()
        spin(node, kind)
    except ParameterError as exc:
        print(f'[FATAL] {exc}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
