"""``deckland up``: start the node graph, fly the mission, stop everything, report.

Simulation (default): the deck_simulator node stands in for the Pixhawk (MAVLink over UDP) and
the Pixy (block bytes over UDP); the exit status is the landing's result and
``DIR/report.json`` holds the same outcome fields as a campaign run. Hardware
(``--hardware --mavlink URL --pixy-port DEV``): the same graph without the simulator.
"""

from __future__ import annotations

import argparse
import contextlib
from importlib import resources
import json
import pathlib
import signal
import socket
import subprocess
import sys
import threading
import time

from deckland.orchestrator import Orchestrator, load_graph


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def default_graph_path() -> str:
    return str(resources.files('deckland') / 'data' / 'graph.yaml')


class MissionMonitor:
    """The orchestrator's own ROS node: waits for topics, triggers services, reads outcome."""

    def __init__(self, wait_topics: list[str]):
        from deckland_common.ros_node import LATCHED_QOS
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        self.context = rclpy.Context()
        rclpy.init(context=self.context, args=[])
        self.node = rclpy.create_node('deckland_up', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.counts = dict.fromkeys(wait_topics, 0)
        self.outcome: dict | None = None
        self.mode = ''
        self._subs = []
        for topic in wait_topics:
            self._subs.append(self._raw_counter(topic))
        self.node.create_subscription(String, 'sim/outcome', self._on_outcome, LATCHED_QOS)
        self.node.create_subscription(String, 'planner/mode', self._on_mode, LATCHED_QOS)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        with contextlib.suppress(Exception):
            self.executor.spin()

    def _raw_counter(self, topic: str):
        """Count messages on a topic without knowing its type in advance."""
        from deckland_common.ros_node import SENSOR_QOS

        from deckland.rosio import import_message_type

        def on_msg(_raw, topic=topic):
            self.counts[topic] += 1

        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            for name, types in self.node.get_topic_names_and_types():
                if name.lstrip('/') == topic.lstrip('/') and types:
                    cls = import_message_type(types[0])
                    return self.node.create_subscription(cls, topic, on_msg, SENSOR_QOS, raw=True)
            time.sleep(0.1)
        raise TimeoutError(f'topic {topic} never appeared')

    def _on_outcome(self, msg) -> None:
        try:
            self.outcome = json.loads(msg.data)
        except ValueError:
            self.outcome = {'reason': f'unparsable outcome: {msg.data[:80]}'}

    def _on_mode(self, msg) -> None:
        self.mode = msg.data

    def wait_flowing(self, timeout_s: float) -> list[str]:
        """Wait until every watched topic has delivered messages; return the silent ones."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            silent = [t for t, n in self.counts.items() if n < 3]
            if not silent:
                return []
            time.sleep(0.1)
        return [t for t, n in self.counts.items() if n < 3]

    def trigger(self, service: str, timeout_s: float = 5.0) -> tuple[bool, str]:
        from std_srvs.srv import Trigger
        client = self.node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=timeout_s):
            return False, f'service {service} not available'
        future = client.call_async(Trigger.Request())
        deadline = time.monotonic() + timeout_s
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.02)
        if not future.done():
            return False, f'service {service} timed out'
        res = future.result()
        return bool(res.success), res.message

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()
        self._thread.join(timeout=2.0)


def _cmd_up(args: argparse.Namespace) -> int:
    from deck_simulator.scenario import load_scenario

    hardware = bool(args.hardware)
    scenario = None if hardware else load_scenario(args.scenario)
    mav_port, pixy_port = free_udp_port(), free_udp_port()
    subs = {
        'scenario': args.scenario, 'seed': args.seed,
        'mavlink_url': args.mavlink or f'udpout:127.0.0.1:{mav_port}',
        'sim_mavlink_url': f'udpin:127.0.0.1:{mav_port}',
        'pixy_transport': 'serial' if hardware else 'udp',
        'pixy_port': args.pixy_port or '/dev/ttyACM0',
        'pixy_udp_port': pixy_port,
        'pixy_latency_s': float(scenario.sensors.camera.latency_s) if scenario else 0.02,
        'landing_area_x_m': float(scenario.apron.position_m[0]) if scenario else args.area[0],
        'landing_area_y_m': float(scenario.apron.position_m[1]) if scenario else args.area[1],
    }
    graph = load_graph(args.graph or default_graph_path(), subs, hardware)
    nodes = graph['nodes']
    if args.params:
        for spec in nodes:
            spec.params_file = args.params
    orch = Orchestrator(nodes, stop_timeout_s=5.0)

    stop_requested = threading.Event()

    def on_signal(signum, _frame):
        stop_requested.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    recorder = None
    monitor = None
    result_code = 1
    report: dict = {}
    try:
        orch.start()
        monitor = MissionMonitor(graph.get('wait_for_topics', []))
        silent = monitor.wait_flowing(args.startup_timeout)
        if silent:
            orch.log(f'topics not flowing after {args.startup_timeout:.0f} s: {silent}')
            return 3
        orch.log('all topics flowing')
        if args.record:
            recorder = subprocess.Popen(
                [sys.executable, '-m', 'deckland.cli', 'bag', 'record', '-o', args.record,
                 '--all'], start_new_session=True)
            time.sleep(1.0)
        ok, msg = monitor.trigger('bridge/offboard')
        orch.log(f'offboard: {ok} {msg}')
        ok, msg = monitor.trigger('planner/start_landing')
        orch.log(f'start_landing: {ok} {msg}')
        if not ok:
            return 4
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline and not stop_requested.is_set():
            orch.check()
            if monitor.outcome is not None:
                break
            if hardware and monitor.mode == 'LANDED':
                break
            time.sleep(0.1)
        if stop_requested.is_set():
            orch.log('interrupted')
            result_code = 130
        elif monitor.outcome is not None:
            report = dict(monitor.outcome)
            result_code = 0 if report.get('success') else 1
            orch.log(f'outcome: {json.dumps(report)}')
        elif hardware and monitor.mode == 'LANDED':
            result_code = 0
        else:
            report = {'success': False, 'reason': f'timeout after {args.timeout:.0f} s',
                      'final_mode': monitor.mode}
            orch.log(report['reason'])
        if orch.crashed:
            report['crashed_nodes'] = [{'node': n, 'status': c} for n, c in orch.crashed]
    finally:
        if monitor is not None:
            monitor.close()
        if recorder is not None and recorder.poll() is None:
            recorder.send_signal(signal.SIGINT)
            try:
                recorder.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                recorder.kill()
        took = orch.stop()
        orch.log(f'stopped all nodes in {took:.2f} s')
        for s, h in old.items():
            signal.signal(s, h)
    if args.record and not hardware:
        out = pathlib.Path(args.record)
        out.mkdir(parents=True, exist_ok=True)
        report.setdefault('scenario', args.scenario)
        report.setdefault('seed', args.seed)
        (out / 'report.json').write_text(json.dumps(report, indent=2) + '\n')
        orch.log(f'wrote {out / "report.json"}')
    return result_code


def register(sub) -> None:
    p = sub.add_parser('up', help='start the node graph and fly the mission (default: simulated)')
    p.add_argument('--scenario', default='paper', help='built-in name or YAML file (simulation)')
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--hardware', action='store_true', help='fly real hardware (no simulator)')
    p.add_argument('--mavlink', help="autopilot connection, e.g. '/dev/ttyACM0' or 'udpout:..'")
    p.add_argument('--pixy-port', help='Pixy serial device (hardware)')
    p.add_argument('--area', type=float, nargs=2, default=(0.0, 0.0), metavar=('X', 'Y'),
                   help='landing-area position in map (hardware)')
    p.add_argument('--params', help='ROS 2 parameters YAML passed to every node')
    p.add_argument('--graph', help='graph YAML (default: the packaged graph)')
    p.add_argument('--record', help='record a bag (and report.json) into this directory')
    p.add_argument('--timeout', type=float, default=120.0, help='mission timeout [s]')
    p.add_argument('--startup-timeout', type=float, default=40.0)
    p.set_defaults(func=_cmd_up)
