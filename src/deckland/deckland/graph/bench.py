"""``deckland bench latency``: end-to-end latency, loop jitter and CPU of the simulated graph.

More in the package README, "Module notes" (`deckland.graph.bench`).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence
import contextlib
from dataclasses import dataclass, field
import itertools
import json
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import types
from typing import Any

from deckland_common.stats import percentile

MS_MASK = 0xFFFFFFFF
SET_ATTITUDE_TARGET_ID = 82
MAVLINK1_STX = 0xFE
MAVLINK2_STX = 0xFD
MAVLINK2_SIGNED = 0x01
#: control loop period of the graph (dob_altitude / landing_planner ``rate_hz`` = 100)
LOOP_PERIOD_S = 0.010
#: gaps longer than this between setpoints are stream interruptions, not jitter samples
MAX_GAP_S = 0.1
#: targets reported against (never asserted)
TARGETS = {'stack_latency_p99_ms': 10.0, 'loop_jitter_p99_ms': 2.0,
           'cpu_total_without_sim_percent': 50.0}
SIM_NODE = 'deck_simulator'


# --- statistics ------------------------------------------------------------------------------

def summarize_ms(values_s: Sequence[float]) -> dict[str, float | int | None]:
    """``{'p50', 'p99', 'max', 'n'}`` in milliseconds of samples given in seconds (None when
    empty, so the JSON stays strict)."""
    if not values_s:
        return {'p50': None, 'p99': None, 'max': None, 'n': 0}
    return {'p50': percentile(values_s, 50.0) * 1e3, 'p99': percentile(values_s, 99.0) * 1e3,
            'max': max(values_s) * 1e3, 'n': len(values_s)}


def loop_jitter(arrivals_s: Sequence[float], period_s: float = LOOP_PERIOD_S,
                max_gap_s: float = MAX_GAP_S) -> tuple[list[float], int]:
    """Lateness of the setpoint stream against the control period, and the stream gaps.

    For consecutive arrivals (sorted first) the jitter sample is ``max(0, Δt − period)``: how
    late the next setpoint came relative to the 100 Hz schedule the autopilot expects. The
    event-driven chain sends a second setpoint of the same instant when a camera frame lands
    between IMU ticks (0.5–2 ms after the IMU-triggered one); such an *early* extra setpoint is
    not jitter, but with ``|Δt − period|`` it would count as ~9 ms. Gaps longer than
    ``max_gap_s`` are stream interruptions, counted apart and not as jitter.
    """
    ts = sorted(arrivals_s)
    out: list[float] = []
    gaps = 0
    for a, b in itertools.pairwise(ts):
        dt = b - a
        if dt > max_gap_s:
            gaps += 1
        else:
            out.append(dt - period_s if dt > period_s else 0.0)
    return out, gaps


# --- /proc -----------------------------------------------------------------------------------

def parse_proc_stat(text: str) -> tuple[int, int]:
    """``(utime, stime)`` in clock ticks from the text of ``/proc/<pid>/stat``.

    proc(5): field 2 ``comm`` is in parentheses and may itself contain spaces and ``)``, so
    the fields are counted after the *last* ``)``: field 3 (state) first, utime = field 14,
    stime = field 15. ValueError for anything else.
    """
    end = text.rfind(')')
    if end < 0:
        raise ValueError('not a /proc/<pid>/stat line: no ")" after comm')
    rest = text[end + 1:].split()
    if len(rest) < 13:
        raise ValueError(f'not a /proc/<pid>/stat line: {len(rest)} fields after comm')
    return int(rest[11]), int(rest[12])


def read_cpu_ticks(pid: int) -> int | None:
    """utime + stime of a process (threads included), or None if it is gone."""
    try:
        with open(f'/proc/{pid}/stat') as fh:
            u, s = parse_proc_stat(fh.read())
    except (OSError, ValueError):
        return None
    return u + s


def cpu_percent(ticks0: int | None, ticks1: int | None, wall_s: float,
                clk_tck: int) -> float | None:
    """CPU use between two tick readings in % of one core (None if a reading is missing)."""
    if ticks0 is None or ticks1 is None or wall_s <= 0.0 or clk_tck <= 0:
        return None
    return 100.0 * (ticks1 - ticks0) / clk_tck / wall_s


# --- MAVLink on the wire ---------------------------------------------------------------------

def iter_mavlink_frames(data: bytes) -> Iterable[tuple[int, bytes]]:
    """``(msgid, payload)`` of every complete MAVLink 1/2 frame in a datagram.

    Bytes before a start marker and truncated frames are skipped; the CRC is not checked (the
    tap observes what the bridge, a pymavlink sender, put on the wire). MAVLink 2 payloads may
    be truncated of trailing zero bytes; callers pad them.
    """
    i, n = 0, len(data)
    while i < n:
        stx = data[i]
        if stx == MAVLINK2_STX and i + 10 <= n:
            plen, incompat = data[i + 1], data[i + 2]
            msgid = data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16)
            end = i + 10 + plen + 2 + (13 if incompat & MAVLINK2_SIGNED else 0)
            if end <= n:
                yield msgid, bytes(data[i + 10:i + 10 + plen])
                i = end
                continue
        elif stx == MAVLINK1_STX and i + 6 <= n:
            plen, msgid = data[i + 1], data[i + 5]
            end = i + 6 + plen + 2
            if end <= n:
                yield msgid, bytes(data[i + 6:i + 6 + plen])
                i = end
                continue
        i += 1


def set_attitude_target_boot_ms(data: bytes) -> list[int]:
    """``time_boot_ms`` (the first payload field, uint32 LE) of each SET_ATTITUDE_TARGET."""
    out = []
    for msgid, payload in iter_mavlink_frames(data):
        if msgid == SET_ATTITUDE_TARGET_ID:
            out.append(struct.unpack_from('<I', payload.ljust(4, b'\0'))[0])
    return out


def stamp_ms(t_s: float) -> int:
    """A stamp as the bridge puts it into ``time_boot_ms``: round(ms) mod 2^32."""
    return round(t_s * 1000.0) & MS_MASK


# --- the stamp chain -------------------------------------------------------------------------

@dataclass
class ChainMatch:
    """Result of :func:`match_chain` (seconds)."""

    first_use_latency_s: list[float] = field(default_factory=list)  # per camera frame
    data_age_s: list[float] = field(default_factory=list)           # per setpoint
    #: per camera frame, its first setpoint split at the apron state it went through:
    #: (state t_s − frame stamp, setpoint arrival − state t_s)
    stages_s: list[tuple[float, float]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)


def match_chain(setpoints: Sequence[tuple[float, int]],
                apron_states: Sequence[tuple[float, float]],
                frame_stamps: Sequence[float],
                window_s: tuple[float, float] = (-math.inf, math.inf),
                stamp_tol_s: float = 2e-6) -> ChainMatch:
    """Map each setpoint ``(arrival_s, time_boot_ms)`` to the camera frame it was based on.

    ``time_boot_ms`` selects the apron state whose ``stamp_ms(t_s)`` equals it (±1 ms for the
    rounding of two float paths; states are 10 ms apart so this is unambiguous) and that
    state's ``camera_stamp_s`` must equal a ``pixy/blocks`` stamp (within ``stamp_tol_s``).
    Only setpoints arriving inside ``window_s`` count, and only frames stamped inside it.
    Per frame the *first* setpoint that used it gives the e2e latency; every setpoint gives a
    data age (arrival − the stamp of the frame it used). Unmatched links are counted.
    """
    by_ms: dict[int, tuple[float, float]] = {}
    for t_s, cam_s in apron_states:
        if math.isfinite(t_s):
            by_ms[stamp_ms(t_s)] = (t_s, cam_s)
    frames = sorted(s for s in frame_stamps if math.isfinite(s))
    counts = {'setpoints': 0, 'no_apron_state': 0, 'no_camera_yet': 0, 'frame_not_seen': 0,
              'before_window_frame': 0, 'matched': 0}
    first_use: dict[float, tuple[float, float]] = {}   # frame -> (arrival, state t_s)
    ages: list[float] = []
    lo, hi = window_s
    for arrival, boot_ms in sorted(setpoints):
        if not lo <= arrival <= hi:
            continue
        counts['setpoints'] += 1
        state = by_ms.get(boot_ms)
        if state is None:
            state = by_ms.get((boot_ms - 1) & MS_MASK) or by_ms.get((boot_ms + 1) & MS_MASK)
        if state is None:
            counts['no_apron_state'] += 1
            continue
        cam_s = state[1]
        if not math.isfinite(cam_s):
            counts['no_camera_yet'] += 1
            continue
        frame = _nearest(frames, cam_s)
        if frame is None or abs(frame - cam_s) > stamp_tol_s:
            counts['frame_not_seen'] += 1
            continue
        counts['matched'] += 1
        ages.append(arrival - frame)
        if frame < lo:
            counts['before_window_frame'] += 1
            continue
        if frame not in first_use or arrival < first_use[frame][0]:
            first_use[frame] = (arrival, state[0])
    frames_used = sorted(first_use)
    latencies = [first_use[f][0] - f for f in frames_used]
    stages = [(first_use[f][1] - f, first_use[f][0] - first_use[f][1]) for f in frames_used]
    counts['frames_in_window'] = sum(1 for f in frames if lo <= f <= hi)
    counts['frames_used'] = len(latencies)
    return ChainMatch(latencies, ages, stages, counts)


def _nearest(sorted_xs: Sequence[float], x: float) -> float | None:
    import bisect
    i = bisect.bisect_left(sorted_xs, x)
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(sorted_xs) and (best is None or abs(sorted_xs[j] - x) < abs(best - x)):
            best = sorted_xs[j]
    return best


# --- report ----------------------------------------------------------------------------------

def build_report(chain: ChainMatch, jitter_s: Sequence[float], gaps: int,
                 cpu: dict[str, float | None], camera_latency_s: float, duration_s: float,
                 extra: dict | None = None) -> dict:
    """The JSON report (see README-bench.md for every key)."""
    stack = [x - camera_latency_s for x in chain.first_use_latency_s]
    nodes = {k: v for k, v in cpu.items() if v is not None}
    total = sum(v for k, v in nodes.items() if k != SIM_NODE)
    e2e = summarize_ms(chain.first_use_latency_s)
    st = summarize_ms(stack)
    jit = summarize_ms(jitter_s)
    report = {
        'e2e_latency_ms': e2e,
        'stack_latency_ms': st,
        'camera_latency_ms': camera_latency_s * 1e3,
        'data_age_ms': summarize_ms(chain.data_age_s),
        'stage_latency_ms': {
            'pixy_publish_to_apron_state': summarize_ms(
                [a - camera_latency_s for a, _ in chain.stages_s]),
            'apron_state_to_mavlink': summarize_ms([b for _, b in chain.stages_s]),
        },
        'loop_jitter_ms': jit,
        'loop_period_ms': LOOP_PERIOD_S * 1e3,
        'stream_gaps': gaps,
        'cpu_percent': {**nodes, 'total_without_sim': total},
        'duration_s': duration_s,
        'samples': len(chain.first_use_latency_s),
        'counts': dict(chain.counts),
        'targets': {
            'stack_latency_p99_ms': _target(st['p99'], TARGETS['stack_latency_p99_ms']),
            'loop_jitter_p99_ms': _target(jit['p99'], TARGETS['loop_jitter_p99_ms']),
            'cpu_total_without_sim_percent': _target(
                total, TARGETS['cpu_total_without_sim_percent']),
        },
    }
    if extra:
        report.update(extra)
    return report


def _target(value: float | None, limit: float) -> dict:
    return {'value': value, 'limit': limit, 'met': value is not None and value <= limit}


def format_table(report: dict) -> str:
    """A short human-readable table of the report."""
    def f(x, unit=''):
        return '   n/a' if x is None else f'{x:6.2f}{unit}'

    lines = [f"{'figure':<34}{'p50':>9}{'p99':>9}   target"]
    t = report['targets']
    for key, label, tgt in (
            ('e2e_latency_ms', 'e2e latency (exposure->MAVLink) ms', ''),
            ('stack_latency_ms', 'stack latency (pixy pub->MAVLink) ms',
             _fmt_target(t['stack_latency_p99_ms'])),
            ('data_age_ms', 'camera data age per setpoint ms', ''),
            ('loop_jitter_ms', 'loop jitter (lateness) ms', _fmt_target(t['loop_jitter_p99_ms']))):
        v = report[key]
        lines.append(f'{label:<34}{f(v["p50"]):>9}{f(v["p99"]):>9}   {tgt}')
        if key == 'stack_latency_ms':
            for name, v in report.get('stage_latency_ms', {}).items():
                lines.append(f'  {name:<32}{f(v["p50"]):>9}{f(v["p99"]):>9}')
    lines.append(f"{'CPU % of one core':<34}")
    for name, v in report['cpu_percent'].items():
        tgt = _fmt_target(t['cpu_total_without_sim_percent']) if name == 'total_without_sim' \
            else ''
        lines.append(f'  {name:<32}{f(v):>9}{"":>9}   {tgt}')
    fv = report.get('foxglove_view')
    if fv:
        lines.append(f"  {'foxglove_view (deckland viz)':<32}{f(fv['cpu_percent']):>9}{'':>9}   "
                     f"{fv['client_channels']} channels, {fv['client_messages_per_s']} msg/s "
                     'to the client')
    lines.append(f"window {report['duration_s']:.1f} s, {report['samples']} frames matched, "
                 f"{report['counts'].get('setpoints', 0)} setpoints, "
                 f"{report['stream_gaps']} stream gaps")
    return '\n'.join(lines)


def _fmt_target(t: dict) -> str:
    return f"<= {t['limit']:g}: {'met' if t['met'] else 'NOT met'}"


# --- the MAVLink tap (its own process) -------------------------------------------------------

def tap_main(argv: Sequence[str]) -> int:
    """``LISTEN_FD SIM_PORT OUT_FILE``: relay UDP between the bridge and the simulator on
    127.0.0.1 (listening on the inherited, already bound socket LISTEN_FD), record
    ``arrival_s time_boot_ms`` of each SET_ATTITUDE_TARGET; write them to OUT_FILE on
    SIGINT/SIGTERM."""
    listen_fd, sim_port, out_path = int(argv[0]), int(argv[1]), argv[2]
    sim_addr = ('127.0.0.1', sim_port)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    sock = socket.socket(fileno=listen_fd)
    sock.settimeout(0.1)
    bridge_addr = None
    records: list[tuple[float, int]] = []
    relayed = errors = 0
    while not stop.is_set():
        try:
            data, addr = sock.recvfrom(65535)
        except TimeoutError:
            continue
        except OSError:
            errors += 1   # e.g. a late ICMP port-unreachable
            continue
        t = time.time()
        try:
            if addr == sim_addr:
                if bridge_addr is not None:
                    sock.sendto(data, bridge_addr)
            else:
                bridge_addr = addr
                sock.sendto(data, sim_addr)
                for ms in set_attitude_target_boot_ms(data):
                    records.append((t, ms))
            relayed += 1
        except OSError:
            errors += 1
    sock.close()
    with open(out_path, 'w') as fh:
        fh.write(f'# relayed {relayed} errors {errors}\n')
        fh.writelines(f'{t:.6f} {ms}\n' for t, ms in records)
    return 0


def read_tap_file(path: str) -> list[tuple[float, int]]:
    out = []
    with open(path) as fh:
        for line in fh:
            if line.startswith('#') or not line.strip():
                continue
            t, ms = line.split()
            out.append((float(t), int(ms)))
    return out


# --- ROS recorder ----------------------------------------------------------------------------

class StreamRecorder:
    """Subscriptions on the monitor's node recording the stamp chain (wall arrival times)."""

    def __init__(self, node):
        from deckland_common.ros_node import SENSOR_QOS, stamp_to_s
        from sensor_msgs.msg import PointCloud

        from deckland_interfaces.msg import ApronState
        self.frames: list[float] = []
        self.apron: list[tuple[float, float]] = []

        def on_blocks(msg):
            self.frames.append(stamp_to_s(msg.header.stamp))

        def on_apron(msg):
            cam = msg.camera_stamp   # zero: no camera frame behind it yet
            self.apron.append((stamp_to_s(msg.header.stamp),
                               stamp_to_s(cam) if cam.sec or cam.nanosec else -math.inf))

        self._subs = [
            node.create_subscription(PointCloud, 'pixy/blocks', on_blocks, SENSOR_QOS),
            node.create_subscription(ApronState, 'apron/state', on_apron, SENSOR_QOS),
        ]


# --- the Foxglove view under test (--foxglove) --------------------------------------------------

class ViewClient:
    """A ``foxglove.sdk.v1`` WebSocket client subscribing to every channel the view advertises
    (as the Foxglove app does with the layout open) and counting what it receives."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.channels: dict[int, str] = {}
        self.messages = 0
        self.bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name='view-client')

    def start(self) -> ViewClient:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        import websocket

        ws = None
        while ws is None and not self._stop.is_set():
            try:
                ws = websocket.create_connection(f'ws://127.0.0.1:{self.port}', timeout=1.0,
                                                 subprotocols=['foxglove.sdk.v1'])
            except OSError:
                time.sleep(0.3)
        if ws is None:
            return
        try:
            while not self._stop.is_set():
                try:
                    op, data = ws.recv_data()
                except websocket.WebSocketTimeoutException:
                    continue
                if op == websocket.ABNF.OPCODE_BINARY:
                    self.messages += 1
                    self.bytes += len(data)
                elif op == websocket.ABNF.OPCODE_TEXT:
                    msg = json.loads(data)
                    if msg.get('op') == 'advertise':
                        new = [c for c in msg['channels'] if c['id'] not in self.channels]
                        self.channels.update({c['id']: c['topic'] for c in new})
                        ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
                            {'id': c['id'], 'channelId': c['id']} for c in new]}))
        except (OSError, websocket.WebSocketException):
            return
        finally:
            ws.close()


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def _start_view(port: int, scenario: str, log: Any) -> subprocess.Popen:
    """``deckland viz --port PORT`` as its own process (its CPU measured apart)."""
    return subprocess.Popen(
        [sys.executable, '-c', 'import sys; from deckland.cli import main; '
         'sys.exit(main(sys.argv[1:]))', 'viz', '--port', str(port), '--scenario', scenario],
        stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


# --- the command -----------------------------------------------------------------------------

def _url_port(url: str) -> int:
    return int(url.rsplit(':', 1)[1])


def run_latency_bench(args: argparse.Namespace, out=sys.stdout) -> tuple[int, dict]:
    """Start the graph with the tap, measure for ``args.duration`` s, return (status, report)."""
    from deckland.graph.up import UdpReservations

    udp = UdpReservations()
    try:
        return _run_latency_bench(args, udp, out)
    finally:
        udp.close()


def _run_latency_bench(args: argparse.Namespace, udp, out) -> tuple[int, dict]:
    from deckland.graph.orchestrator import Orchestrator, load_graph
    from deckland.graph.up import MissionMonitor, default_graph_path, graph_substitutions

    subs = graph_substitutions(types.SimpleNamespace(
        scenario=args.scenario, seed=args.seed, hardware=False, mavlink=None, pixy_port=None,
        area=(0.0, 0.0)), udp)
    px4 = _px4_for_bench(args)
    # bridge -> tap -> simulator; with PX4 the tap sits on PX4's onboard link (it listens
    # where PX4 sends, 14540 + i, and relays to PX4's 14580 + i)
    try:
        tap_port, tap_fd = (udp.bind() if px4 is None
                            else udp.bind(px4.ports['onboard_remote']))
    except OSError:
        if px4 is not None:
            px4.stop()
        raise
    sim_port = (_url_port(subs['sim_mavlink_url']) if px4 is None
                else px4.ports['onboard_local'])
    subs['mavlink_url'] = f'udpout:127.0.0.1:{tap_port}'
    graph = load_graph(args.graph or default_graph_path(), subs, hardware=False)
    if px4 is not None:
        px4.configure_graph(graph['nodes'])
        for spec in graph['nodes']:
            if spec.name == 'mavlink_bridge':
                spec.parameters['connection'] = subs['mavlink_url']
    workdir = tempfile.mkdtemp(prefix='deckland_bench_')
    log_path = args.log or os.path.join(workdir, 'graph.log')
    tap_out = os.path.join(workdir, 'tap.txt')
    clk_tck = os.sysconf('SC_CLK_TCK')
    status, report = 1, {}
    with open(log_path, 'w') as log:
        nodes = graph['nodes']
        if getattr(args, 'composed', False):
            from deckland.graph.composed import compose
            nodes = compose(nodes)
        orch = Orchestrator(nodes, out=log, stop_timeout_s=5.0, pass_fds=udp.fds())
        tap = subprocess.Popen(
            [sys.executable, '-c', 'import sys; from deckland.graph.bench import tap_main; '
             'sys.exit(tap_main(sys.argv[1:]))', str(tap_fd), str(sim_port), tap_out],
            stdin=subprocess.DEVNULL, start_new_session=True, pass_fds=(tap_fd,))
        monitor = None
        view = client = None
        try:
            orch.start()
            if args.foxglove:
                port = free_tcp_port()
                view = _start_view(port, args.scenario, log)
                client = ViewClient(port).start()
            monitor = MissionMonitor(graph.get('wait_for_topics', []))
            recorder = StreamRecorder(monitor.node)
            t_start = time.monotonic()
            not_ready = orch.wait_ready(args.startup_timeout)
            silent: list[str] = []
            if not not_ready:
                silent = _px4_up(px4, monitor, args, out) if px4 is not None else []
                silent = silent or monitor.wait_flowing(
                    args.startup_timeout - (time.monotonic() - t_start) if px4 is None
                    else args.startup_timeout)
            if not_ready or silent:
                out.write(f'start-up failed after {time.monotonic() - t_start:.0f} s: not '
                          f'ready {not_ready}, silent topics {silent}, device problems '
                          f'{orch.device_problems()} (log: {log_path})\n')
                return 3, {}
            startup_s = time.monotonic() - t_start
            pids = {p.spec.name: p.proc.pid for p in orch.procs}
            if view is not None:
                time.sleep(2.0)     # the view discovers the topics (1 s period), the client
                pids['foxglove_view'] = view.pid   # subscribes: measure the steady state
            msgs0 = client.messages if client is not None else 0
            land_after = (max(0.0, args.duration - 15.0) if args.land_after is None
                          else args.land_after)
            load0 = os.getloadavg()
            t0_wall, t0 = time.time(), time.monotonic()
            ticks0 = {n: read_cpu_ticks(pid) for n, pid in pids.items()}
            tap0 = read_cpu_ticks(tap.pid)
            px4_cpu0 = px4.cpu_s() if px4 is not None else 0.0
            triggered, outcome_at = False, None
            while time.monotonic() - t0 < args.duration:
                orch.check()
                if not triggered and time.monotonic() - t0 >= land_after:
                    triggered = True
                    monitor.trigger('bridge/offboard')
                    ok, msg = monitor.trigger('planner/start_landing')
                    if not ok:
                        out.write(f'start_landing failed: {msg}\n')
                if monitor.outcome is not None and outcome_at is None:
                    outcome_at = time.monotonic()
                if outcome_at is not None and time.monotonic() - outcome_at > 0.5:
                    break   # landed: the stream stops, the loop is no longer busy
                time.sleep(0.02)
            t1_wall, wall = time.time(), time.monotonic() - t0
            ticks1 = {n: read_cpu_ticks(pid) for n, pid in pids.items()}
            tap1 = read_cpu_ticks(tap.pid)
            px4_cpu = (round(100.0 * (px4.cpu_s() - px4_cpu0) / wall, 1)
                       if px4 is not None else None)
            msgs1 = client.messages if client is not None else 0
            crashed = list(orch.crashed)
            outcome = monitor.outcome
        finally:
            if client is not None:
                client.stop()
            if view is not None:
                view.send_signal(signal.SIGINT)
                try:
                    view.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    view.kill()
            if monitor is not None:
                monitor.close()
            orch.stop()
            orch.close()
            if px4 is not None:
                px4.stop()
            tap.send_signal(signal.SIGTERM)
            try:
                tap.wait(timeout=3.0)
            except subprocess.TimeoutExpired:
                tap.kill()
    setpoints = read_tap_file(tap_out) if os.path.exists(tap_out) else []
    window = (t0_wall, t1_wall)
    chain = match_chain(setpoints, recorder.apron, recorder.frames, window)
    jitter, gaps = loop_jitter([t for t, _ in setpoints if t0_wall <= t <= t1_wall])
    cpu = {n: cpu_percent(ticks0[n], ticks1[n], wall, clk_tck) for n in pids}
    view_cpu = cpu.pop('foxglove_view', None)
    extra = {
        'foxglove_view': None if not args.foxglove else {
            'cpu_percent': view_cpu, 'client_channels': len(client.channels) if client else 0,
            'client_messages_per_s': round((msgs1 - msgs0) / wall, 1) if wall > 0 else None},
        'scenario': args.scenario, 'seed': args.seed,
        'composed': bool(getattr(args, 'composed', False)),
        'instrumentation_cpu_percent': {'mavlink_tap': cpu_percent(tap0, tap1, wall, clk_tck)},
        'landing': None if outcome is None else {
            k: outcome.get(k) for k in ('success', 'reason', 'time_to_land_s')},
        'crashed_nodes': [{'node': n, 'status': c} for n, c in crashed],
        'startup_s': round(startup_s, 3),
        'autopilot': getattr(args, 'autopilot', 'emulator'),
        'autopilot_cpu_percent': px4_cpu,
        'log': log_path,
        'machine': {'cpus': os.cpu_count(), 'loadavg_1min_before': load0[0],
                    'loadavg_1min_after': os.getloadavg()[0]},
    }
    report = build_report(chain, jitter, gaps, cpu, float(subs['pixy_latency_s']), wall, extra)
    # CPU per setpoint: comparable between runs that streamed at different rates (overload)
    n_sp = report['counts'].get('setpoints', 0)
    report['setpoints_per_s'] = n_sp / wall if wall > 0 else 0.0
    report['cpu_ms_per_setpoint_without_sim'] = (
        report['cpu_percent']['total_without_sim'] * 10.0 * wall / n_sp if n_sp else None)
    ok = report['samples'] > 0 and not crashed
    status = 0 if ok else 1
    return status, report


def _px4_for_bench(args: argparse.Namespace):
    """``--autopilot NAME``: the firmware started for the bench (deckland.sitl registry)."""
    from deckland.sitl import sitl_autopilot
    backend = sitl_autopilot(getattr(args, 'autopilot', 'emulator'))
    if backend is None:
        return None
    from deck_simulator.scenario import load_scenario

    px4 = backend.load('mission')(load_scenario(args.scenario))
    px4.start()
    return px4


def _px4_up(px4, monitor, args: argparse.Namespace, out) -> list[str]:
    """PX4 up, the ground topics, the operator's take-off: the graph then flies as with the
    emulator (the window starts in PX4's loiter). Returns what did not come up."""
    def log(text: str) -> None:
        out.write(f'{text}\n')

    ok, msg = px4.wait_up(args.startup_timeout)
    silent = [] if ok else [msg]
    silent = silent or monitor.wait_flowing(args.startup_timeout, skip=px4.GROUND_SILENT)
    if not silent:
        ok, msg = px4.operator_take_off(monitor, log)
        silent = [] if ok else [msg]
    return silent


def _cmd_latency(args: argparse.Namespace) -> int:
    if not (args.duration > 0.0 and math.isfinite(args.duration)):
        print('deckland bench latency: --duration must be a positive number of seconds',
              file=sys.stderr)
        return 2
    from deckland.sitl import SitlNotFoundError, SitlStartError
    try:
        status, report = run_latency_bench(args)
    except (SitlNotFoundError, SitlStartError) as exc:
        print(f'deckland bench latency: {exc}', file=sys.stderr)
        return 2
    if not report:
        return status
    text = json.dumps(report, indent=2, allow_nan=False) + '\n'
    if args.out:
        with open(args.out, 'w') as fh:
            fh.write(text)
    print(format_table(report))
    if report['duration_s'] < 0.9 * args.duration:
        landing = report.get('landing') or {}
        print(f"note: the window ended after {report['duration_s']:.1f} s of "
              f"{args.duration:g} s: the simulator reported an outcome "
              f"({landing.get('reason')}); the loop was no longer busy")
    if args.out:
        print(f'wrote {args.out}')
    if status:
        print('no frame could be traced to a setpoint or a node crashed; see '
              f"{report.get('log')}", file=sys.stderr)
    return status


def register(sub) -> None:
    p = sub.add_parser('bench', help='measure the running graph (latency, jitter, CPU)')
    bsub = p.add_subparsers(dest='bench_command', metavar='BENCH')
    bsub.required = True
    lat = bsub.add_parser(
        'latency', help='camera-to-MAVLink latency, 100 Hz loop jitter and CPU per node '
        '(simulated graph, landing triggered)')
    lat.add_argument('--scenario', default='paper', help='built-in name or YAML file')
    lat.add_argument('--seed', type=int, default=1)
    lat.add_argument('--duration', type=float, default=20.0, help='measurement window [s]')
    lat.add_argument('--land-after', type=float, default=None,
                     help='trigger the landing this long into the window [s] (default: '
                     'max(0, duration - 15) so the landing fills the end of the window)')
    lat.add_argument('--out', help='write the JSON report here')
    lat.add_argument('--graph', help='graph YAML (default: the packaged graph)')
    lat.add_argument('--log', help='node output log (default: a file in a temp directory)')
    lat.add_argument('--startup-timeout', type=float, default=40.0)
    lat.add_argument('--composed', action='store_true',
                     help='the stack nodes in one process (as deckland up --composed)')
    from deckland.sitl import SITL_AUTOPILOTS
    lat.add_argument('--autopilot', choices=('emulator', *SITL_AUTOPILOTS), default='emulator',
                     help='a firmware (e.g. px4-sitl) flies the simulated vehicle (it takes '
                     'off first; its CPU in autopilot_cpu_percent)')
    lat.add_argument('--foxglove', action='store_true',
                     help='also run `deckland viz` with a client subscribed to every channel; '
                     "its CPU is reported apart (foxglove_view), the nodes' as usual")
    lat.set_defaults(func=_cmd_latency)


def main(argv: list[str] | None = None) -> int:
    """``python -m deckland.graph.bench latency ...`` (the same as ``deckland bench latency``)."""
    parser = argparse.ArgumentParser(prog='deckland')
    sub = parser.add_subparsers(dest='command')
    register(sub)
    args = parser.parse_args(['bench', *(sys.argv[1:] if argv is None else argv)])
    with contextlib.suppress(KeyboardInterrupt):
        return int(args.func(args) or 0)
    return 130


if __name__ == '__main__':
    sys.exit(main())
