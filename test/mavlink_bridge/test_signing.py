"""MAVLink 2 signing for real: the bridge node signs with its key file, the emulated
autopilot verifies (and signs) behind deck_simulator's ``signing_key_file``.

Oracle for a signature: the MAVLink 2 spec, independently of pymavlink's check —
signature = SHA-256(secret_key + header + payload + CRC + link_id + timestamp)[:6], the
packet's incompat_flags has bit 0x01, the last 13 bytes are link_id(1) timestamp(6) sig(6).
"""

import hashlib
import os
import socket
import time

from deck_simulator.px4_emulator import EmulatorParams, MemoryLink, Px4Emulator
from mavlink_bridge.conversions import set_attitude_target_fields
from pymavlink.dialects.v20 import common as mavlink
import pytest

KEY = bytes(range(1, 33))
OTHER = bytes(range(101, 133))
TS0 = int((time.time() - 1420070400) * 1e5)     # signing time base: 10 µs since 2015


def spec_signature_ok(packet: bytes, key: bytes) -> bool:
    """Signature check straight from the MAVLink 2 packet layout."""
    if packet[0] != 0xFD or not packet[2] & 0x01:
        return False
    body, sig = packet[:-6], packet[-6:]
    return hashlib.sha256(key + body).digest()[:6] == sig


def parse(datagrams, key=None):
    """Messages of the datagrams as a receiver with ``key`` (None: no verification) sees them."""
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    if key is not None:
        rx.signing.secret_key = key
        rx.signing.timestamp = 0
    out = []
    for d in datagrams:
        out += rx.parse_buffer(d) or []
    return out, rx


def write_key(path, key, hexform=False):
    path.write_bytes(key.hex().encode() + b'\n' if hexform else key)
    return str(path)


# --- the emulator (pure, MemoryLink) -------------------------------------------------------

def signed_companion(link_end, key, link_id=3):
    mav = mavlink.MAVLink(link_end, srcSystem=1, srcComponent=191)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = link_id
        mav.signing.timestamp = TS0
    return mav


@pytest.mark.parametrize('sender_key, accepted', [(KEY, True), (OTHER, False), (None, False)])
def test_keyed_emulator_takes_only_setpoints_signed_with_its_key(sender_key, accepted):
    link = MemoryLink()
    emu = Px4Emulator(EmulatorParams(), transport=link.a)
    emu.setup_signing(KEY, TS0)
    mav = signed_companion(link.b, sender_key)
    for k in range(20):
        mav.set_attitude_target_send(**set_attitude_target_fields(0.0, 0.0, 0.0, 26.0,
                                                                  emu.params.thrust))
        emu.update(0.01 * k)
    if accepted:
        assert emu.counters['setpoints_rx'] == 20 and emu.rejected['bad_signature'] == 0
    else:
        assert emu.counters['setpoints_rx'] == 0 and emu.rejected['bad_signature'] == 20
        assert emu.setpoint is None


def test_a_forged_future_timestamp_does_not_lock_out_the_genuine_stream():
    """pymavlink records a new stream's timestamp before comparing the hash; the emulator
    (verify_signature_first) refuses the forged packet without touching the stream state."""
    link = MemoryLink()
    emu = Px4Emulator(EmulatorParams(), transport=link.a)
    emu.setup_signing(KEY, TS0)
    forged = signed_companion(link.b, OTHER, link_id=3)
    forged.signing.timestamp = TS0 + 86400 * 100_000          # a day ahead
    forged.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4)
    emu.update(0.0)
    genuine = signed_companion(link.b, KEY, link_id=3)         # same stream key (3, 1, 191)
    genuine.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4)
    emu.update(0.01)
    assert emu.rejected['bad_signature'] == 1 and emu.counters['heartbeats_rx'] == 1
    # replay protection itself still works: the same genuine packet again is refused
    pkt = genuine.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4).pack(
        genuine)
    link.b.send(pkt)
    link.b.send(pkt)
    emu.update(0.02)
    assert emu.counters['heartbeats_rx'] == 2 and emu.rejected['bad_signature'] == 2


def test_keyed_emulator_signs_its_telemetry():
    link = MemoryLink()
    emu = Px4Emulator(EmulatorParams(), transport=link.a)
    emu.setup_signing(KEY, TS0, link_id=7)
    for k in range(50):
        emu.publish_state(0.02 * k, (0, 0, 2), (0, 0, 0), 0, 0, 0, (0, 0, 0), (0, 0, 9.81),
                          2.0, False)
    data = [d for d, _ in link.b.receive()]
    assert len(data) > 50
    assert all(spec_signature_ok(d, KEY) and not spec_signature_ok(d, OTHER) for d in data)
    assert all(d[-13] == 7 for d in data)                      # link id
    stamps = [int.from_bytes(d[-12:-6], 'little') for d in data]
    assert stamps == sorted(set(stamps)) and stamps[0] >= TS0  # strictly increasing
    good, rx = parse(data, KEY)
    assert good and all(m.get_type() != 'BAD_DATA' and m.get_signed() for m in good)
    assert rx.signing.goodsig_count == len(data)
    bad, rx = parse(data, OTHER)
    assert all(m.get_type() == 'BAD_DATA' and m.reason == 'Invalid signature' for m in bad)
    assert rx.signing.badsig_count == len(data)
    with pytest.raises(ValueError, match='32 bytes'):
        emu.setup_signing(b'short', TS0)


# --- the bridge node -----------------------------------------------------------------------

def _free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def bridge(context, namespace='', **params):
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.parameter import Parameter
    return MavlinkBridgeNode(context=context, namespace=namespace, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])


def recv_all(sock, seconds):
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            data, addr = sock.recvfrom(65535)
        except TimeoutError:
            continue
        out.append((data, addr))
    return out


@pytest.mark.ros
@pytest.mark.parametrize('hexform', [False, True])
def test_keyed_bridge_signs_what_it_sends_and_drops_unsigned_input(ros_context, tmp_path,
                                                                    hexform):
    from deckland_common.ros_node import LATCHED_QOS
    from rclpy.node import Node
    from std_msgs.msg import String

    context, executor = ros_context
    port = _free_udp_port()
    ap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)     # the autopilot's socket
    ap.bind(('127.0.0.1', port))
    ap.settimeout(0.1)
    # a namespace per run: a latched vehicle/mode of the previous parametrisation's bridge
    # (same domain, same process) must not be taken for this one's
    ns = f'sig_{int(hexform)}_{port}'
    node = bridge(context, namespace=ns, connection=f'udpout:127.0.0.1:{port}',
                  signing_key_file=write_key(tmp_path / 'key', KEY, hexform))
    helper = Node('signing_helper', context=context)
    modes = []
    helper.create_subscription(String, f'/{ns}/vehicle/mode', modes.append, LATCHED_QOS)
    executor.add_node(node)
    executor.add_node(helper)
    try:
        got = recv_all(ap, 2.3)                               # 1 Hz heartbeats
        assert len(got) >= 2
        data = [d for d, _ in got]
        assert all(spec_signature_ok(d, KEY) for d in data)
        assert not any(spec_signature_ok(d, OTHER) for d in data)
        msgs, _ = parse(data, KEY)
        assert {m.get_type() for m in msgs} == {'HEARTBEAT'}
        assert all(m.get_signed() for m in msgs)
        bad, _ = parse(data, OTHER)
        assert all(m.get_type() == 'BAD_DATA' for m in bad)   # an autopilot with another key
        # input: an unsigned PX4 heartbeat is dropped, a signed one is taken
        bridge_addr = got[0][1]
        hb = {'type': mavlink.MAV_TYPE_QUADROTOR, 'autopilot': mavlink.MAV_AUTOPILOT_PX4,
              'base_mode': mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
              'custom_mode': 6 << 16, 'system_status': mavlink.MAV_STATE_ACTIVE}

        class Out:
            def write(self, b):
                ap.sendto(b, bridge_addr)

        for key in (None, OTHER):
            px4 = mavlink.MAVLink(Out(), srcSystem=1, srcComponent=1)
            if key is not None:
                # forged with a timestamp a day ahead: pymavlink alone would record it as
                # the stream's replay mark and refuse the genuine stream below
                px4.signing.secret_key, px4.signing.sign_outgoing = key, True
                px4.signing.timestamp = TS0 + 86400 * 100_000
            for _ in range(5):
                px4.heartbeat_send(**hb)
                time.sleep(0.05)
        time.sleep(0.5)
        assert modes == [] and node.core.rejected.get('bad_signature', 0) == 10
        px4 = mavlink.MAVLink(Out(), srcSystem=1, srcComponent=1)
        px4.signing.secret_key, px4.signing.sign_outgoing = KEY, True
        px4.signing.timestamp = int((time.time() - 1420070400) * 1e5)
        px4.heartbeat_send(**hb)
        end = time.monotonic() + 3.0
        while not modes and time.monotonic() < end:
            time.sleep(0.02)
        assert modes and modes[-1].data == 'OFFBOARD'
    finally:
        ap.close()


@pytest.mark.ros
@pytest.mark.parametrize('content, needle', [
    (b'x' * 31, 'need 32 raw bytes or 64 hex'),
    (b'z' * 64, 'need 32 raw bytes or 64 hex'),
    (None, 'cannot read'),
])
def test_bad_signing_key_file_is_a_clear_parameter_error(ros_context, tmp_path, content,
                                                        needle):
    from deckland_common.params import ParameterError
    context, _ = ros_context
    path = tmp_path / 'key'
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(ParameterError, match=f"'signing_key_file'.*{needle}"):
        bridge(context, connection=f'udpout:127.0.0.1:{_free_udp_port()}',
               signing_key_file=str(path))


@pytest.mark.ros
@pytest.mark.parametrize('sim_key, linked', [(KEY, True), (OTHER, False)])
def test_bridge_and_simulator_with_keys_talk_only_when_the_keys_match(ros_context, tmp_path,
                                                                      sim_key, linked):
    """The two nodes as in ``deckland up`` (bridge udpin, simulator udpout): with the same
    key telemetry flows (vehicle/odom); with different keys neither side takes the other's
    messages (bad_signature counted on both)."""
    from deck_simulator.node import DeckSimulatorNode
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    context, executor = ros_context
    port = _free_udp_port()
    pixy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    pixy.bind(('127.0.0.1', 0))
    ns = f'pair_{port}'
    br = bridge(context, namespace=ns, connection=f'udpin:127.0.0.1:{port}',
                signing_key_file=write_key(tmp_path / 'bridge.key', KEY))
    sim = DeckSimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario', value='paper'), Parameter('seed', value=1),
        Parameter('mavlink_url', value=f'udpout:127.0.0.1:{port}'),
        Parameter('pixy_udp_port', value=pixy.getsockname()[1]),
        Parameter('signing_key_file',
                  value=write_key(tmp_path / 'sim.key', sim_key, hexform=True))])
    helper = Node('signing_pair_helper', context=context)
    odom = []
    helper.create_subscription(Odometry, f'/{ns}/vehicle/odom', odom.append, 10)
    for n in (br, sim, helper):
        executor.add_node(n)
    try:
        time.sleep(3.0)
        if linked:
            assert len(odom) > 30
            assert br.core.rejected.get('bad_signature', 0) == 0
            assert sim.emulator.rejected['bad_signature'] == 0
            assert sim.emulator.counters['heartbeats_rx'] >= 1   # the bridge's, signed
        else:
            assert odom == []
            assert br.core.rejected.get('bad_signature', 0) > 30
            assert sim.emulator.counters['heartbeats_rx'] == 0
            # the bridge's heartbeats: sent to the simulator only once it heard from it
            # (udpin learns the peer), so none may arrive at all; nothing is accepted
    finally:
        pixy.close()


def test_key_file_forms(tmp_path):
    from deckland_common.params import ParameterError
    from mavlink_bridge.signing import load_signing_key
    assert load_signing_key(write_key(tmp_path / 'a', KEY)) == KEY
    assert load_signing_key(write_key(tmp_path / 'b', KEY, hexform=True)) == KEY
    # a raw key whose first/last bytes are whitespace (0x20, 0x0a) is kept byte for byte
    ws = b' ' + bytes(range(33, 63)) + b'\n'
    assert load_signing_key(write_key(tmp_path / 'd', ws)) == ws
    # 40 hex characters: neither form (note: 32 hex characters *are* 32 raw bytes)
    (tmp_path / 'c').write_bytes(os.urandom(20).hex().encode())
    with pytest.raises(ParameterError, match='signing_key_file'):
        load_signing_key(str(tmp_path / 'c'))
