"""``deckland up --foxglove PORT`` end to end: a WebSocket client speaking ``foxglove.sdk.v1``
gets the server info, the advertised channels (the graph's topics as CDR with their ros2msg
schemas, and the scene), and decodable messages while the graph flies."""

import itertools
import json
import math
import pathlib
import signal
import socket
import struct
import subprocess
import sys
import time

from deckland.ros import rosio
import pytest
from rostest import isolated_env

pytestmark = pytest.mark.ros

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))
WANTED = ('/deckland/scene', '/apron/state', '/planner/status', '/vehicle/odom',
          '/altitude/state')


def free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def connect(url, protocol, timeout_s):
    import websocket
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return websocket.create_connection(url, subprotocols=[protocol], timeout=5)
        except (ConnectionRefusedError, OSError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def recv(ws):
    """The next frame; (None, b'') when none came within the socket timeout, ('end', b'')
    when the server went away (the mission ended: a loaded machine may end it early)."""
    import websocket
    try:
        return ws.recv_data()
    except websocket.WebSocketTimeoutException:
        return None, b''
    except (OSError, websocket.WebSocketConnectionClosedException):
        return 'end', b''


def test_live_view_serves_the_flying_graph(tmp_path):
    import websocket
    port = free_port()
    log = open(tmp_path / 'up.log', 'w')   # noqa: SIM115
    up = subprocess.Popen([DECKLAND, 'up', '--scenario', 'paper', '--foxglove', str(port),
                           '--timeout', '120'], stdout=log, stderr=subprocess.STDOUT,
                          env=isolated_env())
    ws = None
    try:
        url = f'ws://127.0.0.1:{port}'
        ws = connect(url, 'foxglove.sdk.v1', 60.0)
        # the old subprotocol name is refused by this SDK (FACTS.md)
        with pytest.raises(websocket.WebSocketBadStatusException):
            websocket.create_connection(url, subprotocols=['foxglove.websocket.v1'],
                                        timeout=5)
        info, channels = None, {}
        deadline = time.monotonic() + 120.0      # the nodes' start-up on a loaded machine
        while time.monotonic() < deadline and not set(WANTED) <= set(channels):
            op, data = recv(ws)
            if op != websocket.ABNF.OPCODE_TEXT:
                continue
            msg = json.loads(data)
            if msg['op'] == 'serverInfo':
                info = msg
            elif msg['op'] == 'advertise':
                channels.update({c['topic']: c for c in msg['channels']})
        assert info is not None and info['name'] == 'deckland', info
        assert set(WANTED) <= set(channels), sorted(channels)
        for topic in WANTED[1:]:
            c = channels[topic]
            assert c['encoding'] == 'cdr' and c['schemaEncoding'] == 'ros2msg', c
            text, _ = rosio.message_definition(c['schemaName'])
            assert c['schema'] == text, topic      # the definition a bag carries
        assert channels['/apron/state']['schemaName'] == 'deckland_interfaces/msg/ApronState'
        scene = channels['/deckland/scene']
        assert scene['schemaName'] == 'foxglove.SceneUpdate' and scene['encoding'] == 'protobuf'

        subs = {i + 1: channels[t] for i, t in enumerate(WANTED)}
        ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
            {'id': sid, 'channelId': c['id']} for sid, c in subs.items()]}))
        got = {t: [] for t in WANTED}
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and (
                len(got['/deckland/scene']) < 40 or len(got['/apron/state']) < 40
                or not got['/planner/status']):
            op, data = recv(ws)
            if op == 'end':
                break
            if op != websocket.ABNF.OPCODE_BINARY or data[0] != 0x01:
                continue
            sid, log_ns = struct.unpack_from('<IQ', data, 1)
            got[subs[sid]['topic']].append((log_ns, bytes(data[13:])))
        assert len(got['/deckland/scene']) >= 10, {t: len(v) for t, v in got.items()}
        store = rosio.typestore()
        states = [(t, store.deserialize_cdr(p, 'deckland_interfaces/msg/ApronState'))
                  for t, p in got['/apron/state']]
        assert len(states) >= 10
        for log_ns, st in states:   # stamped when published, forwarded as it arrived
            assert abs(st.header.stamp.sec + st.header.stamp.nanosec * 1e-9
                       - log_ns * 1e-9) < 5.0
            assert st.vertical.valid and 0.0 < st.vertical.height_m < 5.0
            assert all(math.isfinite(x) for x in st.apron_position_m)
        status = store.deserialize_cdr(got['/planner/status'][-1][1],
                                       'deckland_interfaces/msg/PlannerStatus')
        assert status.mode in range(10) and status.reason
        odom = store.deserialize_cdr(got['/vehicle/odom'][-1][1], 'nav_msgs/msg/Odometry')
        assert 0.0 < odom.pose.pose.position.z < 5.0
        # the scene goes out at its own rate (25 Hz), not per input message
        stamps = sorted(t for t, _ in got['/deckland/scene'])
        gaps = sorted(b - a for a, b in itertools.pairwise(stamps))
        assert 1e9 / 60 < gaps[len(gaps) // 2] < 1e9 / 10, gaps[len(gaps) // 2]
        # only what is known is drawn: a scene sent before the first input is empty (a
        # subscriber that connects early sees those); from the first drawn one on, each has
        # the deck, the vehicle and the rest (an empty SceneUpdate is under 100 bytes)
        sizes = [len(p) for _, p in sorted(got['/deckland/scene'])]
        first = next(i for i, n in enumerate(sizes) if n > 100)
        assert all(n > 100 for n in sizes[first:]), sizes
    finally:
        if ws is not None:
            ws.close()
        up.send_signal(signal.SIGINT)
        try:
            up.wait(timeout=30)
        except subprocess.TimeoutExpired:
            up.kill()
            up.wait()
        log.close()
    text = (tmp_path / 'up.log').read_text()
    assert f'Foxglove: open connection ws://127.0.0.1:{port}' in text, text[-3000:]
