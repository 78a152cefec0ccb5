"""Live Foxglove view of the node graph (``deckland viz``, ``deckland up --foxglove``).

:class:`LiveView` runs a foxglove-sdk WebSocket server (loopback by default) beside a node of
its own: every topic of the graph is forwarded as it arrives, CDR bytes untouched, on a
channel with its ``ros2msg`` schema (:func:`deckland.ros.rosio.message_definition`), and a
``SceneUpdate`` (:mod:`deckland.graph.vizscene`) goes out on :data:`SCENE_TOPIC` at ``rate_hz``.
``deckland viz --snapshot`` renders a recorded bag's scene with the pure
:func:`deckland.graph.vizscene.scene_from_bag` and :func:`~deckland.graph.vizscene.render_png`.
How to open it in Foxglove: ``src/deckland/README-viz.md``.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from typing import Any

from deckland.graph.vizscene import (
    Item,
    SceneState,
    apply_latest,
    build_scene,
    pad_size_of,
    relative_name,
    render_png,
    scene_from_bag,
)
from deckland.ros import rosio

DEFAULT_HOST = '127.0.0.1'
DEFAULT_PORT = 8765
SCENE_TOPIC = '/deckland/scene'
DEFAULT_RATE_HZ = 25.0
EXCLUDES = ('/rosout', '/parameter_events')

# --- foxglove conversion -------------------------------------------------------------------

def scene_update(items: list[Item], t_s: float) -> Any:
    """The foxglove ``SceneUpdate`` of ``items`` (one entity per item group, frame ``map``)."""
    from foxglove.messages import (
        ArrowPrimitive,
        Color,
        CubePrimitive,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        TextPrimitive,
        Timestamp,
        Vector3,
    )

    def pose(it: Item) -> Any:
        w, x, y, z = it.orientation
        return Pose(position=Vector3(x=it.position[0], y=it.position[1], z=it.position[2]),
                    orientation=Quaternion(x=x, y=y, z=z, w=w))

    def color(it: Item) -> Any:
        r, g, b, a = it.color
        return Color(r=r, g=g, b=b, a=a)

    groups: dict[str, dict[str, list[Any]]] = {}
    for it in items:
        g = groups.setdefault(it.entity, {'cubes': [], 'spheres': [], 'lines': [],
                                          'arrows': [], 'texts': []})
        size = Vector3(x=it.size[0], y=it.size[1], z=it.size[2])
        if it.kind == 'cube':
            g['cubes'].append(CubePrimitive(pose=pose(it), size=size, color=color(it)))
        elif it.kind == 'sphere':
            g['spheres'].append(SpherePrimitive(pose=pose(it), size=size, color=color(it)))
        elif it.kind == 'line':
            g['lines'].append(LinePrimitive(
                type=LinePrimitiveLineType.LineLoop, thickness=0.02, color=color(it),
                points=[Point3(x=p[0], y=p[1], z=p[2]) for p in it.points]))
        elif it.kind == 'arrow':
            g['arrows'].append(ArrowPrimitive(
                pose=pose(it), shaft_length=it.size[0] * 0.75, shaft_diameter=it.size[1],
                head_length=it.size[0] * 0.25, head_diameter=it.size[1] * 2.5,
                color=color(it)))
        elif it.kind == 'text':
            g['texts'].append(TextPrimitive(pose=pose(it), billboard=True, font_size=14.0,
                                            scale_invariant=True, color=color(it),
                                            text=it.text))
    sec = math.floor(t_s)
    stamp = Timestamp(int(sec), min(round((t_s - sec) * 1e9), 999_999_999))
    return SceneUpdate(entities=[SceneEntity(timestamp=stamp, frame_id='map', id=name, **g)
                                 for name, g in groups.items()])


# --- the live view -------------------------------------------------------------------------

class LiveView:
    """Foxglove WebSocket server forwarding the graph's topics, plus the 3-D scene.

    ``context``: an initialised rclpy context (``deckland up``'s); by default a private one.
    ``port`` 0 picks a free port (:attr:`port` says which). :meth:`start` spins the view's
    node in a background thread; :meth:`stop` closes the server and the node.
    """

    def __init__(self, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 rate_hz: float = DEFAULT_RATE_HZ, pad_size_m: tuple[float, float] | None = None,
                 context: Any = None, discovery_period_s: float = 1.0,
                 node_name: str = 'deckland_viz') -> None:
        if not (0 <= port <= 65535):
            raise ValueError(f'port must be in [0, 65535], got {port!r}')
        if not (1.0 <= rate_hz <= 60.0):
            raise ValueError(f'rate_hz must be in [1, 60], got {rate_hz!r}')
        if not host.strip():
            raise ValueError('host must not be empty')
        self.host, self.requested_port, self.rate_hz = host, port, rate_hz
        self.scene = SceneState() if pad_size_m is None else SceneState(pad_size_m=pad_size_m)
        self._context = context
        self._node_name = node_name
        self._discovery_period_s = discovery_period_s
        self._session: rosio.RosSession | None = None
        self._server: Any = None
        self._fox: Any = None
        self._scene_channel: Any = None
        self.channels: dict[str, Any] = {}
        self._subs: dict[str, Any] = {}
        self.skipped: dict[str, str] = {}
        self.forwarded: dict[str, int] = {}
        self.scene_updates = 0
        # latest raw message of each scene input (callbacks and the scene timer share the
        # view's single-threaded executor: no lock)
        self._latest: dict[str, tuple[type, bytes]] = {}
        # the last message of each latched (transient local) topic, logged again every
        # second: a client connecting after a mode change still sees the mode
        self._latched: dict[str, bytes] = {}

    @property
    def port(self) -> int:
        return int(self._server.port) if self._server is not None else self.requested_port

    def start(self) -> LiveView:
        import foxglove
        from foxglove.channels import SceneUpdateChannel

        self._fox = foxglove.Context()
        self._server = foxglove.start_server(name='deckland', host=self.host,
                                             port=self.requested_port, context=self._fox)
        self._scene_channel = SceneUpdateChannel(SCENE_TOPIC, context=self._fox)
        self._session = rosio.RosSession(self._node_name, self._context, executor='events')
        node = self._session.node
        self._discover()
        node.create_timer(self._discovery_period_s, self._discover)
        node.create_timer(1.0 / self.rate_hz, self._publish_scene)
        node.create_timer(1.0, self._relog_latched)
        self._session.spin_in_thread()
        return self

    def stop(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()
        if self._server is not None:
            self._server.stop()
            self._server = None

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- forwarding --------------------------------------------------------------------------

    def _discover(self) -> None:
        import foxglove

        session = self._session
        if session is None:
            return
        for topic, types in sorted(session.topic_types().items()):
            if topic in self._subs or topic in self.skipped or topic in EXCLUDES:
                continue
            pub_qos = session.publisher_qos(topic)
            if not types or not pub_qos:
                continue
            msgtype = types[0]
            text, _ = rosio.message_definition(msgtype)
            try:
                cls = rosio.import_message_type(msgtype)
            except ValueError as exc:
                text, self.skipped[topic] = '', str(exc)
            if not text:
                self.skipped.setdefault(topic, f'no definition of {msgtype}')
                continue
            schema = foxglove.Schema(name=msgtype, encoding='ros2msg',
                                     data=text.encode('utf-8'))
            channel = foxglove.Channel(topic, schema=schema, message_encoding='cdr',
                                       context=self._fox)
            self.channels[topic] = channel
            self.forwarded[topic] = 0
            qos = rosio.subscription_qos(pub_qos, 'auto')
            latched = any(rosio._policy_name(q.durability) == 'transient_local'
                          for q in pub_qos)
            self._subs[topic] = session.node.create_subscription(
                cls, topic, self._forwarder(topic, channel, cls, latched), qos, raw=True)

    def _forwarder(self, topic: str, channel: Any, cls: type, latched: bool) -> Any:
        rel = relative_name(topic)
        forwarded, latest, last = self.forwarded, self._latest, self._latched

        def callback(data: bytes) -> None:
            forwarded[topic] += 1
            channel.log(data, log_time=time.time_ns())
            if rel is not None:
                latest[rel] = (cls, data)
            if latched:
                last[topic] = data
        return callback

    def _relog_latched(self) -> None:
        now = time.time_ns()
        for topic, data in self._latched.items():
            self.channels[topic].log(data, log_time=now)

    def _publish_scene(self) -> None:
        from rclpy.serialization import deserialize_message

        latest = dict(self._latest)
        self._latest.clear()
        apply_latest(self.scene, latest, lambda m: deserialize_message(m[1], m[0]))
        self._scene_channel.log(scene_update(build_scene(self.scene), time.time()),
                                log_time=time.time_ns())
        self.scene_updates += 1


# --- command -------------------------------------------------------------------------------

def add_server_args(p: argparse.ArgumentParser) -> None:
    p.add_argument('--host', default=DEFAULT_HOST,
                   help=f'bind address (default {DEFAULT_HOST}: this machine only)')
    p.add_argument('--rate', type=float, default=DEFAULT_RATE_HZ,
                   help=f'scene updates per second (default {DEFAULT_RATE_HZ:g})')


def register(sub: Any) -> None:
    p = sub.add_parser('viz', help='live Foxglove view of a running graph (WebSocket)',
                       description='Attach to a running graph and serve it to Foxglove: '
                       'every topic as CDR with its ros2msg schema plus a 3-D scene on '
                       f'{SCENE_TOPIC}. Foxglove: Open connection -> ws://HOST:PORT. '
                       'With --snapshot BAG, draw the scene of a recorded bag into a PNG.')
    p.add_argument('--port', type=int, default=DEFAULT_PORT,
                   help=f'WebSocket port (default {DEFAULT_PORT}; 0 = any free port)')
    add_server_args(p)
    p.add_argument('--scenario', default='paper', help='scenario of the pad size (default paper)')
    p.add_argument('--duration', type=float, default=None, help='stop after this many seconds')
    p.add_argument('--snapshot', metavar='BAG', help='draw the scene of a recorded bag instead')
    p.add_argument('--at', type=float, default=None,
                   help='snapshot time, seconds after the bag start (default: its midpoint)')
    p.add_argument('--out', default='scene.png', help='snapshot PNG (default scene.png)')
    p.set_defaults(func=cmd_viz)


def cmd_viz(args: argparse.Namespace) -> int:
    pad = pad_size_of(args.scenario)
    if args.snapshot:
        scene, t = scene_from_bag(args.snapshot, args.at, pad)
        render_png(scene, args.out, f'{args.snapshot} at {t:.1f} s, mode {scene.mode or "?"}')
        print(f'scene at {t:.1f} s written to {args.out}')
        return 0
    stop = threading.Event()
    restore = rosio.install_stop_signals(stop.set)
    try:
        view = LiveView(host=args.host, port=args.port, rate_hz=args.rate, pad_size_m=pad)
        view.start()
    except (ValueError, RuntimeError, OSError) as exc:
        restore()
        print(f'viz: {exc}', file=sys.stderr)
        return 2
    print(f'Foxglove: open connection ws://{args.host}:{view.port} (Ctrl-C stops)', flush=True)
    try:
        stop.wait(args.duration)
    finally:
        view.stop()
        restore()
    return 0
