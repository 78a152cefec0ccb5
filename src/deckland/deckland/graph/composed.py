"""Composed mode: several graph nodes in one process, on one context and one executor.

ROS 2's composition idea in rclpy. :func:`compose` turns the graph's node list into the
simulator (left as its own process: it stands in for the hardware) plus one
:class:`ComposedSpec` process holding every other node; the orchestrator starts it like any
node. Inside, :func:`main` builds each node from its package's node class with the very
``--ros-args`` the per-process mode passes on its command line (name, parameters,
remappings, params file), so topics, parameters and remappings are the same. Each node
reports ready on its own; a crash of the process takes all of its nodes (the price of
composition, reported by name).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import importlib
import json
import sys
from typing import Any

from deckland.graph.orchestrator import NodeSpec, launcher_code

#: name of the composed process in the orchestrator's log and report
COMPOSED_NAME = 'stack'


@dataclass
class ComposedSpec(NodeSpec):
    """One process running ``components`` (NodeSpecs) together; never respawned."""

    components: list[NodeSpec] = field(default_factory=list)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.components:
            raise ValueError(f'node {self.name!r}: components must not be empty')

    def command(self, python: str = sys.executable) -> list[str]:
        """argv: this module's :func:`main` with one JSON argument (data, no shell)."""
        code = launcher_code('deckland.graph.composed', 'main(sys.argv[1:])')
        return [python, '-c', code, json.dumps(component_table(self.components))]


def ros_args(spec: NodeSpec) -> list[str]:
    """The ``--ros-args ...`` part of ``spec``'s per-process command line."""
    argv = spec.command()
    return argv[argv.index('--ros-args'):]


def component_table(specs: list[NodeSpec]) -> list[dict[str, Any]]:
    return [{'name': s.name, 'package': s.package, 'module': s.module, 'ros_args': ros_args(s)}
            for s in specs]


def compose(nodes: list[NodeSpec], name: str = COMPOSED_NAME) -> list[NodeSpec]:
    """The graph's nodes for ``--composed``: sim-only nodes apart, the rest in one process."""
    alone = [n for n in nodes if n.sim_only]
    together = [n for n in nodes if not n.sim_only]
    if not together:
        return alone
    return [*alone, ComposedSpec(name=name, package='deckland', module='graph.composed',
                                 components=together)]


def node_class(package: str, module: str) -> type:
    """The rclpy ``Node`` subclass defined in ``<package>.<module>`` (exactly one)."""
    from rclpy.node import Node

    mod = importlib.import_module(f'{package}.{module}')
    found = [c for c in vars(mod).values() if isinstance(c, type) and issubclass(c, Node)
             and c is not Node and c.__module__ == mod.__name__]
    if len(found) != 1:
        raise ValueError(f'{package}.{module}: expected one Node subclass, found '
                         f'{[c.__name__ for c in found]}')
    return found[0]


def main(argv: list[str]) -> int:
    """Build every component on one private context, report each ready, spin them together.

    Shutdown as :func:`deckland_common.ros_node.run_node`: a signal ends the spin, the
    executor stops, the nodes are destroyed (threads joined) in reverse order, then the
    context. A component that cannot be built ends the process (status 2, its message).
    """
    from deckland_common.params import ParameterError
    from deckland_common.ros_node import executor_kind, notify_ready, spin_nodes, stop_on_signals
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    table = json.loads(argv[0])
    stop = stop_on_signals()
    context = rclpy.Context()
    rclpy.init(context=context, args=[], signal_handler_options=SignalHandlerOptions.NO)
    nodes: list[Any] = []
    try:
        kind = executor_kind()
        for row in table:
            try:
                cls = node_class(row['package'], row['module'])
                node = cls(context=context, cli_args=row['ros_args'],
                           use_global_arguments=False)
            except ParameterError as exc:
                print(f"[FATAL] {row['name']}: {exc}", file=sys.stderr)
                return 2
            nodes.append(node)
            notify_ready(node)
        spin_nodes(nodes, kind, stop)
    except KeyboardInterrupt:
        pass
    finally:
        for node in reversed(nodes):
            node.destroy_node()
        context.try_shutdown()
    return 0
