"""``deckland up``: start the node graph, fly the mission, stop everything, report.

More in the package README, "Module notes" (`deckland.graph.up`).
"""

from __future__ import annotations

import argparse
import contextlib
from importlib import resources
import json
import pathlib
import shutil
import signal
import socket
import sys
import threading
import time
from typing import Any

from deckland.graph.mission_report import (
    EXIT_CODES,
    KillSchedule,
    bridge_modes,
    finish_report,
    firmware_modes,
    parse_outcome,
    summary_lines,
)
from deckland.graph.orchestrator import Orchestrator, describe_status, load_graph, members

RUN_MARKERS = ('report.json', 'metadata.yaml')
#: recorded hover before the landing trigger (s)
PRE_TRIGGER_S = 1.0


class UdpReservations:
    """Loopback UDP sockets bound before the graph starts and handed to the nodes by fd.

    The node that listens (pixy_driver, the simulator's MAVLink ``udpin``, the bench tap)
    inherits the already-bound socket (``udp_fd`` / ``mavlink_fd``) instead of binding a port
    picked earlier, so no other process can take the port in between; the orchestrator keeps
    its copy until the end, so a respawned node gets the same port back.
    """

    def __init__(self) -> None:
        self.sockets: list[socket.socket] = []

    def bind(self, port: int = 0) -> tuple[int, int]:
        """A new socket on 127.0.0.1 (``port`` 0: the OS picks one): ``(port, fd)``."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(('127.0.0.1', port))
        self.sockets.append(sock)
        return sock.getsockname()[1], sock.fileno()

    def fds(self) -> tuple[int, ...]:
        return tuple(s.fileno() for s in self.sockets if s.fileno() >= 0)

    def close(self) -> None:
        for sock in self.sockets:
            sock.close()


def default_graph_path() -> str:
    return str(resources.files('deckland') / 'data' / 'graph.yaml')


class MissionMonitor:
    """The orchestrator's own ROS node: waits for topics, triggers services, reads outcome.

    ``context`` is a private rclpy context without rclpy's signal handlers (``deckland up``
    owns SIGINT/SIGTERM); the bag recorder borrows it.
    """

    def __init__(self, wait_topics: list[str], expect: dict[str, Any] | None = None):
        from deckland_common.ros_node import LATCHED_QOS
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String

        self.context = rclpy.Context()
        rclpy.init(context=self.context, args=[],
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('deckland_up', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.counts = dict.fromkeys(wait_topics, 0)
        self.outcome: dict | None = None
        #: identity of the simulation this run started ({'scenario', 'seed'}): an outcome
        #: from another graph on the same ROS domain is ignored, not taken as ours
        self.expect = dict(expect or {})
        self.foreign_outcomes = 0
        self.mode = ''
        self.vehicle_modes: list[tuple[float, str]] = []   # (monotonic s, autopilot mode)
        self._subs: dict[str, Any] = {}
        self.node.create_subscription(String, 'sim/outcome', self._on_outcome, LATCHED_QOS)
        self.node.create_subscription(String, 'planner/mode', self._on_mode, LATCHED_QOS)
        self.node.create_subscription(String, 'vehicle/mode', self._on_vehicle_mode,
                                      LATCHED_QOS)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        with contextlib.suppress(Exception):
            self.executor.spin()

    def _subscribe_new(self) -> None:
        """Count messages on each watched topic as soon as it appears (any type, raw)."""
        from deckland_common.ros_node import SENSOR_QOS

        from deckland.ros.rosio import import_message_type

        missing = [t for t in self.counts if t not in self._subs]
        if not missing:
            return
        available = {n.lstrip('/'): types for n, types in self.node.get_topic_names_and_types()}
        for topic in missing:
            types = available.get(topic.lstrip('/'))
            if not types:
                continue
            try:
                cls = import_message_type(types[0])
            except ValueError:
                continue

            def on_msg(_raw, topic=topic):
                self.counts[topic] += 1

            self._subs[topic] = self.node.create_subscription(cls, topic, on_msg, SENSOR_QOS,
                                                              raw=True)

    def _on_outcome(self, msg) -> None:
        outcome, why = parse_outcome(msg.data, self.expect)
        if why == 'foreign':
            self.foreign_outcomes += 1   # another graph shares this ROS domain
            return
        self.outcome = outcome

    def _on_mode(self, msg) -> None:
        self.mode = msg.data

    def _on_vehicle_mode(self, msg) -> None:
        if not self.vehicle_modes or self.vehicle_modes[-1][1] != msg.data:
            self.vehicle_modes.append((time.monotonic(), msg.data))

    def wait_flowing(self, timeout_s: float, abort=None, skip=()) -> list[str]:
        """Wait until every watched topic (but those in ``skip``) has delivered messages;
        return the silent ones.

        ``abort()`` (optional) is polled every 0.1 s; when it returns true the wait ends early.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            self._subscribe_new()
            silent = [t for t, n in self.counts.items() if n < 3 and t not in skip]
            if not silent or (abort is not None and abort()) or time.monotonic() >= deadline:
                return silent
            time.sleep(0.1)

    def stop_counting(self) -> None:
        """Drop the counting subscriptions (once the topics flow they only cost CPU: ~400
        messages/s through this process)."""
        for sub in self._subs.values():
            self.node.destroy_subscription(sub)
        self._subs = {}
        self.counts = {}

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


def vehicle_of(args, scenario) -> Any:
    """The vehicle description the stack is given (one source for the altitude controller and
    the bridge): the scenario's in simulation, ``--mass-kg`` / ``--hover-thrust-norm`` /
    ``--thrust-expo`` on hardware (defaults: the paper's vehicle)."""
    from deckland_common.contract import VehicleDescription

    if scenario is not None:
        from deckland.batch.runner import vehicle_description
        return vehicle_description(scenario)
    d = VehicleDescription()
    given = {'mass_kg': getattr(args, 'mass_kg', None),
             'hover_thrust_norm': getattr(args, 'hover_thrust_norm', None),
             'thrust_expo': getattr(args, 'thrust_expo', None)}
    return VehicleDescription(**{k: (getattr(d, k) if v is None else float(v))
                                 for k, v in given.items()})


def graph_substitutions(args, udp: UdpReservations) -> dict[str, Any]:
    """The graph YAML's ``{placeholder}`` values for ``args`` (any object with ``scenario``,
    ``seed``, ``hardware``, ``mavlink``, ``pixy_port`` and ``area``): loopback UDP sockets
    bound now in ``udp`` (simulation; their fds go to the listening nodes), the scenario's
    camera latency, landing area and vehicle (simulation) or the given ones (hardware,
    :func:`vehicle_of`). Shared by ``deckland up`` and ``deckland bench``."""
    from deck_simulator.scenario import load_scenario

    hardware = bool(args.hardware)
    scenario = None if hardware else load_scenario(args.scenario)
    vehicle = vehicle_of(args, scenario)
    (mav_port, mav_fd), (pixy_port, pixy_fd) = ((0, -1), (0, -1)) if hardware else (
        udp.bind(), udp.bind())
    # the bridge enters OFFBOARD only with a safe offboard-loss action: Land or Hold, and
    # Return where the scenario deliberately configures it (a return to the OFFBOARD point)
    returns = scenario is not None and scenario.faults and any(
        getattr(f, 'action', 'land') == 'return' for f in scenario.faults)
    return {
        'offboard_loss_actions': 'land,hold,return' if returns else 'land,hold',
        'mass_kg': vehicle.mass_kg, 'gravity_mps2': vehicle.gravity_mps2,
        'hover_thrust_norm': vehicle.hover_thrust_norm, 'thrust_expo': vehicle.thrust_expo,
        'scenario': args.scenario, 'seed': args.seed,
        'mavlink_url': args.mavlink or f'udpout:127.0.0.1:{mav_port}',
        'sim_mavlink_url': f'udpin:127.0.0.1:{mav_port}',
        'sim_mavlink_fd': mav_fd,
        'pixy_udp_fd': pixy_fd,
        'pixy_transport': 'serial' if hardware else 'udp',
        'pixy_port': args.pixy_port or '/dev/ttyACM0',
        'pixy_udp_port': pixy_port,
        'pixy_latency_s': (float(scenario.sensors.true_camera.timing.assumed_latency_s)
                           if scenario else 0.036),
        'landing_area_x_m': float(scenario.apron.position_m[0]) if scenario else args.area[0],
        'landing_area_y_m': float(scenario.apron.position_m[1]) if scenario else args.area[1],
    }


# --- helpers -------------------------------------------------------------------------------

def prepare_record_dir(path: str) -> pathlib.Path:
    """The bag/report directory: new, empty, or a previous run (moved to ``DIR.prev``).

    A non-empty directory that does not look like a previous run (no ``report.json`` or
    ``metadata.yaml``) is refused (ValueError): ``deckland up`` never deletes foreign data.
    """
    out = pathlib.Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f'--record {out}: exists and is not a directory')
    if out.is_dir() and any(out.iterdir()):
        if not any((out / m).exists() for m in RUN_MARKERS):
            raise ValueError(f'--record {out}: not empty and not a previous run; '
                             'choose another directory')
        prev = out.with_name(out.name + '.prev')
        if prev.exists():
            if not (prev.is_dir() and any((prev / m).exists() for m in RUN_MARKERS)):
                raise ValueError(f'--record {out}: {prev} is in the way')
            shutil.rmtree(prev)
        out.rename(prev)
    return out


def node_kill_faults(scenario) -> list[Any]:
    """The scenario's ``node_kill`` faults (deck_simulator.faults.NodeKill), by start time."""
    if scenario is None:
        return []
    return sorted((f for f in scenario.faults if f.type == 'node_kill'), key=lambda f: f.start_s)


# --- the command ---------------------------------------------------------------------------

def _cmd_up(args: argparse.Namespace) -> int:
    from deck_simulator.scenario import load_scenario

    def fail(msg: str) -> int:
        print(f'deckland up: {msg}', file=sys.stderr)
        return 2

    hardware = bool(args.hardware)
    if hardware and not (args.mavlink and args.pixy_port):
        return fail('--hardware needs --mavlink URL and --pixy-port DEV')
    from deckland.sitl import sitl_autopilot
    backend = sitl_autopilot(getattr(args, 'autopilot', 'emulator'))
    if backend is not None and (hardware or args.mavlink):
        return fail(f'--autopilot {backend.name} is a simulation (no --hardware, no --mavlink)')
    if not hardware and any(getattr(args, k, None) is not None
                            for k in ('mass_kg', 'hover_thrust_norm', 'thrust_expo')):
        return fail('--mass-kg, --hover-thrust-norm and --thrust-expo are for --hardware '
                    "(in simulation the scenario's vehicle is flown)")
    if not (args.timeout > 0 and args.startup_timeout > 0):
        return fail('--timeout and --startup-timeout must be > 0')
    udp = UdpReservations()
    try:
        scenario = None if hardware else load_scenario(args.scenario)
        subs = graph_substitutions(args, udp)   # a bad --mass-kg etc.: ValueError naming it
        graph = load_graph(args.graph or default_graph_path(), subs, hardware)
        record = prepare_record_dir(args.record) if args.record else None
    except (ValueError, OSError) as exc:
        udp.close()
        return fail(str(exc))
    try:
        return _run_up(args, hardware, scenario, graph, record, udp, backend)
    finally:
        udp.close()


def _run_up(args: argparse.Namespace, hardware: bool, scenario, graph: dict[str, Any],
            record: pathlib.Path | None, udp: UdpReservations, backend: Any) -> int:
    def fail(msg: str) -> int:
        print(f'deckland up: {msg}', file=sys.stderr)
        return 2

    nodes = graph['nodes']
    px4 = None
    if backend is not None:   # a firmware in the loop (deckland.sitl.SITL_AUTOPILOTS)
        from deckland.sitl import SitlNotFoundError
        try:
            px4 = backend.load('mission')(scenario, keep_ulog=args.keep_ulog)
        except (SitlNotFoundError, ValueError) as exc:
            return fail(str(exc))
    names = {n.name for n in nodes}
    kills = node_kill_faults(scenario)
    for f in kills:
        if f.node not in names:
            return fail(f'node_kill fault names {f.node!r}, which is not in the graph')
    if args.params:
        for spec in nodes:
            spec.params_file = args.params
    if getattr(args, 'composed', False):
        from deckland.graph.composed import compose
        nodes = compose(nodes)
    orch = Orchestrator(nodes, stop_timeout_s=5.0, pass_fds=udp.fds())

    stop_requested = threading.Event()
    received: list[int] = []

    def on_signal(signum, _frame):
        received.append(signum)
        stop_requested.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    recorder = None
    monitor = None
    view = None
    result_code = 1
    report: dict[str, Any] = {}
    t_trigger: float | None = None
    t_outcome: float | None = None
    injected: list[dict[str, Any]] = []
    try:
        if px4 is not None:
            problem = _start_px4(px4, nodes, orch)
            if problem:
                report = {'success': False, 'reason': f'start-up failed: {problem}'}
                result_code = 3
                raise _EndRunError
        orch.start()
        expect = {} if scenario is None else {'scenario': scenario.name, 'seed': args.seed}
        monitor = MissionMonitor(graph.get('wait_for_topics', []), expect=expect)
        if args.foxglove is not None:
            view = _start_view(args, scenario, monitor, orch)

        def startup_abort() -> bool:
            orch.check()
            return stop_requested.is_set() or any(
                e.action in ('not respawned', 'gave up') for e in orch.exits)

        t_start = time.monotonic()
        not_ready = orch.wait_ready(args.startup_timeout, abort=startup_abort)
        silent: list[str] = []
        if not not_ready and not stop_requested.is_set():
            t_flow = t_start
            if px4 is not None:
                ok, msg = px4.wait_up(args.startup_timeout, abort=startup_abort)
                if not ok:
                    report = {'success': False, 'reason': f'start-up failed: {msg}'}
                    result_code = 3
                    orch.log(report['reason'])
                    raise _EndRunError
                orch.log(f'{backend.name} up after {px4.times["up_s"]:.1f} s')
                t_flow = time.monotonic()   # PX4's boot is not the topics' time
            # on the ground the planner disables the thrust: the command topics flow once in
            # the air (PX4's take-off, below)
            silent = monitor.wait_flowing(
                args.startup_timeout - (time.monotonic() - t_flow), abort=startup_abort,
                skip=() if px4 is None else px4.GROUND_SILENT)
        if stop_requested.is_set():
            raise _EndRunError
        if not_ready or silent or orch.crashed:
            dead = ', '.join(f'{n} ({describe_status(c)})' for n, c in orch.crashed)
            problems = orch.device_problems()
            orch.log('start-up failed: ' + '; '.join(x for x in (
                f'not ready {not_ready}' if not_ready else '',
                f'silent topics {silent}' if silent else '',
                f'exited: {dead}' if dead else '',
                f'device problems {problems}' if problems else '') if x))
            report = {'success': False, 'reason': 'start-up failed', 'silent_topics': silent,
                      'not_ready': not_ready}
            result_code = 3
            raise _EndRunError
        wait_topics = graph.get('wait_for_topics', [])
        if px4 is not None:   # the bag covers PX4's take-off
            if record is not None:
                recorder = _start_recorder(record, monitor, [
                    t for t in wait_topics if t not in px4.GROUND_SILENT], orch)
            ok, msg = px4.operator_take_off(monitor, orch.log, stop_requested.is_set)
            if ok:
                silent = monitor.wait_flowing(10.0, abort=startup_abort)
                ok, msg = not silent, f'silent topics in the air {silent}'
            if not ok:
                report = {'success': False, 'reason': f'start-up failed: {msg}'}
                result_code = 3
                orch.log(report['reason'])
                raise _EndRunError
        orch.log(f'all nodes ready, all topics flowing after {time.monotonic() - t_start:.2f} s')
        monitor.stop_counting()
        if record is not None and recorder is None:
            recorder = _start_recorder(record, monitor, wait_topics, orch)
        if stop_requested.is_set():
            raise _EndRunError
        ok, msg = monitor.trigger('bridge/offboard')
        orch.log(f'offboard: {ok} {msg}')
        if px4 is not None and not px4.wait_mode(px4.OFFBOARD_MODE, 5.0,
                                                 stop_requested.is_set):
            report = {'success': False, 'reason': f'{backend.name} did not enter '
                      f'{px4.OFFBOARD_MODE} ({msg}; mode {px4.mode})'}
            result_code = 4
            orch.log(report['reason'])
            raise _EndRunError
        ok, msg = monitor.trigger('planner/start_landing')
        t_trigger = time.monotonic()
        orch.log(f'start_landing: {ok} {msg}')
        if not ok:
            report = {'success': False, 'reason': f'start_landing refused: {msg}'}
            result_code = 4
            raise _EndRunError
        schedule = KillSchedule(kills)
        deadline = t_trigger + args.timeout
        while time.monotonic() < deadline and not stop_requested.is_set():
            now = time.monotonic() - t_trigger
            to_kill, to_release = schedule.due(now)
            for f in to_kill:
                killed = orch.kill(f.node)
                injected.append({'type': 'node_kill', 'node': f.node, 'at_s': round(now, 3),
                                 'planned_s': f.start_s, 'killed': killed,
                                 'nodes_lost': members(orch.by_name[f.node].spec)})
            for node in to_release:
                orch.release(node)
            orch.check()
            if monitor.outcome is not None:
                break
            if hardware and monitor.mode == 'LANDED':
                break
            time.sleep(0.05)
        if stop_requested.is_set():
            raise _EndRunError
        if monitor.outcome is not None:
            t_outcome = time.monotonic()
            if px4 is not None:   # PX4's land detector disarms it (or its failsafe lands)
                disarmed = px4.wait_disarmed(PX4_DISARM_WAIT_S, stop_requested.is_set)
                orch.log(f'{px4.NAME} {"disarmed" if disarmed else "still armed"} '
                         f'{time.monotonic() - t_outcome:.1f} s after the touchdown')
            report = dict(monitor.outcome)
            result_code = 0 if report.get('success') else 1
            orch.log(f'outcome: {json.dumps(report)}')
        elif hardware and monitor.mode == 'LANDED':
            report = {'success': True, 'reason': 'planner LANDED', 'final_mode': 'LANDED'}
            result_code = 0
        else:
            report = {'success': False, 'reason': f'timeout after {args.timeout:.0f} s',
                      'final_mode': monitor.mode}
            orch.log(report['reason'])
    except _EndRunError:
        pass
    finally:
        if stop_requested.is_set():
            sig = received[0] if received else signal.SIGINT
            result_code = 128 + int(sig)
            report = {'success': False, 'reason': 'interrupted',
                      'interrupted': signal.Signals(sig).name, **{
                          k: v for k, v in report.items() if k not in ('success', 'reason')}}
            orch.log(f'interrupted by {signal.Signals(sig).name}; stopping')
        took = orch.stop()
        orch.check()
        orch.close()
        orch.log(f'stopped all nodes in {took:.2f} s')
        px4_report = None
        if px4 is not None:
            px4_report = px4.report(t_trigger)
            px4.stop()
            orch.log(f'{px4.NAME} stopped, its working directory removed'
                     + (f'; ULog kept in {args.keep_ulog}' if args.keep_ulog else ''))
        if recorder is not None:
            with contextlib.suppress(Exception):
                recorder.stop()
        if view is not None:
            with contextlib.suppress(Exception):
                view.stop()
        modes = [] if monitor is None else bridge_modes(monitor.vehicle_modes, t_trigger)
        if monitor is not None:
            monitor.close()
        if px4_report is not None:
            modes = firmware_modes(px4_report['modes'], t_trigger, t_outcome)
        for s, h in old.items():
            signal.signal(s, h)
        report = _finish_report(report, args, hardware, orch, injected, modes,
                                record if recorder is not None else None, result_code)
        if record is not None and recorder is None:
            report['bag'] = {'path': str(record), 'messages': 0,
                             'not_started': 'the run ended before recording began'}
        if px4_report is not None:
            report['autopilot'] = backend.name
            report[backend.report_key] = px4_report
        if record is not None:
            with contextlib.suppress(OSError):
                record.mkdir(parents=True, exist_ok=True)
                (record / 'report.json').write_text(json.dumps(report, indent=2) + '\n')
        if getattr(args, 'report', None):
            with contextlib.suppress(OSError):
                pathlib.Path(args.report).write_text(json.dumps(report, indent=2) + '\n')
        print('\n'.join(summary_lines(report, result_code, str(record) if record else None)),
              flush=True)
    return result_code


class _EndRunError(Exception):
    """Leave the mission early (start-up failure, refused trigger, SIGINT/SIGTERM)."""


#: after the touchdown, how long PX4 gets to disarm (land detector: COM_DISARM_LAND 2 s)
PX4_DISARM_WAIT_S = 20.0


def _start_px4(px4, nodes, orch: Orchestrator) -> str:
    """PX4 SITL in a fresh directory, the graph pointed at its instance's ports; '' or why
    PX4 could not be started."""
    from deckland.sitl import SitlStartError
    try:
        px4.start()
    except (SitlStartError, OSError) as exc:
        orch.log(f'{px4.NAME} did not start: {exc}')
        return f'{px4.NAME} did not start: {exc}'
    # composed: the simulator and the bridge are components (their commands are built at
    # start, so their parameters can still change here)
    px4.configure_graph([c for n in nodes for c in (getattr(n, 'components', None) or [n])])
    orch.log(px4.describe())
    return ''


def _start_view(args: Any, scenario: Any, monitor: MissionMonitor, orch: Orchestrator) -> Any:
    """The live Foxglove view (``--foxglove``) on the monitor's context."""
    from deckland.graph.viz import LiveView

    pad = None if scenario is None else tuple(scenario.apron.size_m)
    view = LiveView(host=args.foxglove_host, port=args.foxglove, pad_size_m=pad,
                    context=monitor.context).start()
    orch.log(f'Foxglove: open connection ws://{args.foxglove_host}:{view.port}')
    return view


def _start_recorder(record: pathlib.Path, monitor: MissionMonitor, wait_topics: list[str],
                    orch: Orchestrator):
    """The in-process recorder on the monitor's context, subscribed before the trigger."""
    from deckland.ros.bag import Recorder

    recorder = Recorder(record, all_topics=True, context=monitor.context)
    recorder.start()
    deadline = time.monotonic() + 10.0
    wanted = [t.lstrip('/') for t in wait_topics]
    while time.monotonic() < deadline:
        counts = {t.lstrip('/'): n for t, n in recorder.counts.items()}
        if all(counts.get(t, 0) > 0 for t in wanted):
            break
        time.sleep(0.05)
    else:
        orch.log('recorder: not every watched topic recorded yet; triggering anyway')
    time.sleep(PRE_TRIGGER_S)   # a little of the hover before the trigger, for the plots
    orch.log(f'recording {len(recorder.subscribed)} topics to {record}')
    return recorder


def _finish_report(report: dict[str, Any], args, hardware: bool, orch: Orchestrator,
                   injected: list, modes: list, record: pathlib.Path | None,
                   code: int) -> dict[str, Any]:
    """The run's facts from the orchestrator and the bag, folded in by ``finish_report``."""
    bag = None
    if record is not None:
        try:
            from deckland.ros.bag import bag_info
            info = bag_info(record)
            bag = {'path': str(record), 'messages': info.message_count,
                   'topics': len(info.topics), 'duration_s': round(info.duration_s, 3)}
        except Exception as exc:   # reported, never fatal at the end of a run
            bag = {'path': str(record), 'error': str(exc)}
    return finish_report(
        report, scenario=None if hardware else args.scenario,
        seed=None if hardware else args.seed, composed=bool(getattr(args, 'composed', False)),
        modes=modes, injected=injected, device_problems=orch.device_problems(),
        crashed=[e.as_dict() for e in orch.exits if not e.injected], code=code, bag=bag)


def register(sub) -> None:
    p = sub.add_parser('up', help='start the node graph and fly the mission (default: simulated)',
                       epilog='exit status: ' + '; '.join(f'{k} {v}' for k, v in
                                                          EXIT_CODES.items()))
    p.add_argument('--scenario', default='paper', help='built-in name or YAML file (simulation)')
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--hardware', action='store_true', help='fly real hardware (no simulator)')
    p.add_argument('--mavlink', help="autopilot connection, e.g. '/dev/ttyACM0' or 'udpout:..'")
    p.add_argument('--pixy-port', help='Pixy serial device (hardware)')
    p.add_argument('--area', type=float, nargs=2, default=(0.0, 0.0), metavar=('X', 'Y'),
                   help='landing-area position in map (hardware)')
    p.add_argument('--mass-kg', type=float,
                   help="vehicle mass (hardware; default the paper's 2.71 kg)")
    p.add_argument('--hover-thrust-norm', type=float,
                   help='normalised thrust that hovers, PX4 MPC_THR_HOVER (hardware; default 0.5)')
    p.add_argument('--thrust-expo', type=float,
                   help='thrust-curve expo e, PX4 THR_MDL_FAC (hardware; default 0)')
    p.add_argument('--params', help='ROS 2 parameters YAML passed to every node')
    p.add_argument('--graph', help='graph YAML (default: the packaged graph)')
    p.add_argument('--composed', action='store_true',
                   help='run the stack nodes in one process on one executor (the simulator '
                   'stays apart); default: one process per node')
    p.add_argument('--record', help='record a bag (and report.json) into this directory')
    p.add_argument('--foxglove', type=int, nargs='?', const=8765, default=None, metavar='PORT',
                   help='serve a live Foxglove view on this WebSocket port (default 8765)')
    p.add_argument('--foxglove-host', default='127.0.0.1',
                   help='bind address of the Foxglove view (default 127.0.0.1, loopback)')
    p.add_argument('--timeout', type=float, default=120.0, help='mission timeout [s]')
    p.add_argument('--startup-timeout', type=float, default=40.0)
    from deckland.sitl import SITL_AUTOPILOTS
    p.add_argument('--autopilot', choices=('emulator', *SITL_AUTOPILOTS), default='emulator',
                   help='what flies the simulated vehicle: the emulated PX4 (default) or a '
                   'firmware in the loop: ' + '; '.join(
                       f'{a.name}: {a.help}' for a in SITL_AUTOPILOTS.values()))
    p.add_argument('--report', metavar='FILE',
                   help='write report.json here too (no bag needed; deckland campaign '
                   '--autopilot px4-sitl reads it)')
    p.add_argument('--keep-ulog', metavar='DIR',
                   help="px4-sitl: keep PX4's ULog and its log in DIR (default: not logged)")
    p.set_defaults(func=_cmd_up)
