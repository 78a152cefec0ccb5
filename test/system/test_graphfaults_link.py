"""Scenario MAVLink faults in the node graph: deck_simulator.link.ImpairedLink on the wire.

Pure part: SimulationLoop + Px4Emulator over a MemoryLink, the test playing the bridge
(sim time, deterministic). Node part: DeckSimulatorNode in a private rclpy context, a pymavlink
endpoint as the bridge over real UDP (wall clock, a few seconds).
"""

import json
import math
import socket
import time

from deck_simulator.link import ImpairedLink
from deck_simulator.loop import SimulationLoop
from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
from deck_simulator.scenario import scenario_from_dict
from deck_simulator.transport import MemoryLink
from deck_simulator.vehicle import VehicleParams
from mavlink_bridge.conversions import set_attitude_target_fields
from pymavlink.dialects.v20 import common as mavlink
import pytest

G = VehicleParams().gravity_mps2
M = VehicleParams().mass_kg
HOVER = (0.0, 0.0, 0.0, M * G)

CALM = {
    'name': 'graphfaults_test',
    'timeout_s': 60.0,
    'start_position_m': [3.0, 3.0, 2.0],
    'apron': {'position_m': [-3.2, -2.0], 'heave': {'model': 'none'}},
    'wind': {'mean_mps': [0.0, 0.0], 'gust_std_mps': 0.0},
    'randomize': {'heave_phase': False, 'gps_bias': False},
}


def scenario(*faults):
    data = json.loads(json.dumps(CALM))
    data['faults'] = list(faults)
    return scenario_from_dict(data, 'test')


class Rig:
    """The loop with the emulator on a MemoryLink; ``mav`` is the bridge's side."""

    def __init__(self, sc, seed=1, downlink='cut'):
        self.link = MemoryLink()
        self.emu = Px4Emulator(EmulatorParams(), transport=self.link.a)
        self.sim = SimulationLoop(sc, seed, self.emu, lambda _b: None, link_downlink=downlink)
        self.mav = mavlink.MAVLink(self.link.b, srcSystem=1, srcComponent=191)
        self.rx = mavlink.MAVLink(None)
        self.sent = 0

    def received(self):
        out = []
        for data, _ in self.link.b.receive():
            out += self.rx.parse_buffer(data) or []
        return out

    def run(self, seconds, setpoint=HOVER, chunk_s=0.02):
        """Advance in 20 ms chunks, one setpoint datagram per chunk (50 Hz)."""
        for _ in range(round(seconds / chunk_s)):
            if setpoint is not None:
                self.mav.set_attitude_target_send(**set_attitude_target_fields(
                    *setpoint, self.emu.params.thrust))
                self.sent += 1
            self.sim.advance(chunk_s)

    def offboard(self):
        self.run(1.3)
        self.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
        self.run(0.2)                 # (the mode command is delayed by a latency fault too)
        assert self.emu.mode == 'OFFBOARD'


def test_link_loss_window_cuts_both_ways_and_the_emulator_takes_its_failsafe():
    rig = Rig(scenario({'type': 'mavlink_link_loss', 'start_s': 3.0, 'end_s': 6.0,
                        'loss_timeout_s': 0.5, 'land_speed_mps': 0.5}))
    assert isinstance(rig.sim.link, ImpairedLink) and rig.emu.transport is rig.sim.link
    # the autopilot's failsafe settings are the fault's keys
    assert rig.sim.autopilot.params.offboard_loss_timeout_s == 0.5
    assert rig.sim.autopilot.params.land_speed_mps == 0.5
    rig.offboard()
    rig.run(3.0 - rig.sim.world.t_s)                   # up to the window
    t_cut = rig.sim.world.t_s
    assert t_cut == pytest.approx(3.0, abs=0.011)
    rig.run(0.02)                                      # the last datagram before the cut
    rig.received()
    n_sp = rig.emu.counters['setpoints_rx']
    rig.run(0.46)
    assert rig.emu.mode == 'OFFBOARD' and not rig.emu.failsafe_active
    rig.run(0.06)                                      # COM_OF_LOSS_T = 0.5 s after the cut
    assert rig.emu.failsafe_active and rig.emu.mode == 'AUTO.LAND'
    assert rig.sim.last_kind == 'failsafe_land'
    rig.run(5.9 - rig.sim.world.t_s)
    assert rig.emu.counters['setpoints_rx'] == n_sp    # nothing got through
    assert rig.received() == []                        # telemetry cut too (downlink 'cut')
    c = rig.sim.link.counters
    assert c['rx_cut'] == pytest.approx(2.9 / 0.02, abs=2) and c['tx_cut'] > 100
    # the link comes back: telemetry again, setpoints again, but PX4 does not re-enter
    # OFFBOARD by itself (the bridge would have to ask)
    rig.run(1.0)
    msgs = rig.received()
    hb = [m for m in msgs if m.get_type() == 'HEARTBEAT']
    assert hb and (hb[-1].custom_mode >> 16) & 0xFF == 4 and hb[-1].custom_mode >> 24 == 6
    assert rig.emu.counters['setpoints_rx'] >= n_sp + 45
    assert rig.emu.mode == 'AUTO.LAND'
    # descending at the fault's land speed on the emulated autopilot
    assert rig.sim.world.truth().velocity_mps[2] == pytest.approx(-0.5, abs=0.1)
    # one autopilot: the world flies the emulator's, the in-process command link is unused
    assert rig.sim.world.autopilot is rig.emu.autopilot and rig.sim.world.link is None
    assert rig.sim.world.failsafe == 'land' and rig.sim.autopilot.failsafes == 1


@pytest.mark.parametrize('p', [0.3, 0.6])
def test_packet_loss_drops_setpoints_at_the_configured_rate(p):
    rig = Rig(scenario({'type': 'mavlink_loss', 'probability': p}), seed=3)
    rig.run(1.3)                      # before OFFBOARD: the stream is impaired all the same
    rig.run(10.0)
    n = rig.sent
    got = rig.emu.counters['setpoints_rx']
    sigma = math.sqrt(p * (1.0 - p) / n)
    assert (1.0 - p) - 4 * sigma < got / n < (1.0 - p) + 4 * sigma, (got, n)
    c = rig.sim.link.counters
    assert c['rx'] == n and c['rx_lost'] == n - got
    # telemetry is not thinned by default ('cut' only): 50 Hz ATTITUDE for 11.3 s
    att = [m for m in rig.received() if m.get_type() == 'ATTITUDE']
    assert len(att) == pytest.approx(11.3 * 50, abs=3)


def test_packet_loss_on_the_downlink_too_with_all():
    rig = Rig(scenario({'type': 'mavlink_loss', 'probability': 0.5}), seed=4, downlink='all')
    rig.run(10.0)
    att = [m for m in rig.received() if m.get_type() == 'ATTITUDE']
    n = 10.0 * 50
    assert 0.5 * n - 4 * math.sqrt(n / 4) < len(att) < 0.5 * n + 4 * math.sqrt(n / 4)


def test_latency_delays_each_setpoint_and_keeps_the_order():
    lat = 0.15
    rig = Rig(scenario({'type': 'mavlink_latency', 'latency_s': lat}))
    rig.offboard()
    rig.run(1.0)
    # one distinct setpoint, then silence: it lands lat later (≤ 10 ms polling)
    t_sent = rig.sim.world.t_s
    rig.run(0.02, setpoint=(0.0, 0.0, 0.0, 1.1 * M * G))
    rig.run(0.1, setpoint=None)
    assert rig.emu.setpoint.thrust_n == pytest.approx(M * G, rel=1e-3)     # not yet
    rig.run(0.06, setpoint=None)
    assert rig.emu.setpoint.thrust_n == pytest.approx(1.1 * M * G, rel=1e-3)
    assert lat - 1e-6 <= rig.emu.last_setpoint_s - t_sent <= lat + 0.011
    # a ramp arrives in order (FIFO: never reordered)
    seen = []
    for k in range(30):
        rig.run(0.01, setpoint=(0.0, 0.0, 0.0, (1.0 + 0.003 * min(k, 19)) * M * G),
                chunk_s=0.01)
        seen.append(rig.emu.setpoint.thrust_n / (M * G))
    ramp = [round(v, 6) for v in seen if v < 1.099]      # the 1.1 step arrives first
    assert ramp == sorted(ramp) and len(set(ramp)) >= 12, seen
    assert rig.sim.link.counters['rx_delayed'] == rig.sim.link.counters['rx'] == rig.sent + 1
    assert rig.sim.link.counters['rx_lost'] == rig.sim.link.counters['rx_cut'] == 0


def test_height_triggered_link_loss_opens_when_the_world_says_so():
    """``trigger_height_m`` windows are resolved by the world (shared FaultSet objects)."""
    rig = Rig(scenario({'type': 'mavlink_link_loss', 'trigger_height_m': 1.0,
                        'duration_s': 2.0, 'loss_timeout_s': 0.3}))
    rig.offboard()
    rig.run(2.0)
    assert rig.sim.link.counters['rx_cut'] == 0 and not rig.emu.failsafe_active
    # descend at ~0.5 m/s: 0.95 m g (3) → −0.05 g, then hold the sink rate
    for _ in range(200):
        rig.run(0.1, setpoint=(0.0, 0.0, 0.0, (0.97 if rig.sim.world.truth().velocity_mps[2]
                                                > -0.5 else 1.0) * M * G))
        if rig.emu.failsafe_active:
            break
    tr = rig.sim.world.truth()
    assert rig.emu.failsafe_active and rig.sim.link.counters['rx_cut'] > 0
    # the cut began below 1 m and the failsafe followed 0.3 s later, ~0.15 m lower
    assert tr.height_above_surface_m < 1.0


def test_no_wire_faults_means_no_wrapper_and_node_kill_is_left_to_deckland_up():
    for sc in (scenario(), scenario({'type': 'lidar_dropout', 'start_s': 1.0})):
        rig = Rig(sc)
        assert rig.sim.link is None and rig.emu.transport is rig.link.a
        assert rig.sim.autopilot.params.offboard_loss_timeout_s == 1.0
        assert rig.sim.autopilot.params.offboard_loss_action == 'land'
    # node_kill: `deckland up` kills the process, nothing on the wire; its failsafe keys still
    # configure the emulated PX4 (the same autopilot settings as for the MAVLink faults)
    rig = Rig(scenario({'type': 'node_kill', 'node': 'dob_altitude', 'start_s': 1.0,
                        'loss_timeout_s': 0.3, 'action': 'return'}))
    assert rig.sim.link is None and rig.emu.transport is rig.link.a
    assert rig.sim.autopilot.params.offboard_loss_timeout_s == 0.3
    assert rig.sim.autopilot.params.offboard_loss_action == 'return'
    with pytest.raises(ValueError, match='downlink'):
        Rig(scenario({'type': 'mavlink_loss'}), downlink='sometimes')


def test_bad_datagrams_through_the_impaired_link_are_still_counted_not_fatal():
    rig = Rig(scenario({'type': 'mavlink_latency', 'latency_s': 0.05}))
    for i in range(10):
        rig.link.b.send(bytes([0xFD, 9, 0, 0, i, 1, 1, 0, 0]))
        rig.mav.set_attitude_target_send(0, 1, 1, 0, [math.nan, 0, 0, 0], 0, 0, 0, 0.5)
    rig.run(0.2, setpoint=None)
    assert rig.emu.rejected['nan'] == 10 and rig.emu.rejected['bad_data'] >= 1
    assert rig.sim.last_kind == 'hold'


# --- the node over real UDP -------------------------------------------------------------

def _free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.mark.ros
def test_node_link_loss_window_triggers_the_emulator_failsafe_over_udp(ros_context, tmp_path):
    """The node with a 1.5 s link-loss window from world time 3.5 s (COM_OF_LOSS_T 0.4 s): a
    pymavlink endpoint (the bridge) streams setpoints at 50 Hz and asks for OFFBOARD; the
    heartbeats go silent in the window and come back in AUTO.LAND."""
    from deck_simulator.node import DeckSimulatorNode
    from pymavlink import mavutil
    from rclpy.parameter import Parameter

    context, executor = ros_context
    port = _free_udp_port()
    pixy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    pixy.bind(('127.0.0.1', 0))
    sc = tmp_path / 'linkloss.yaml'
    sc.write_text(
        'name: linkloss\ntimeout_s: 30.0\nstart_position_m: [1.0, 2.0, 2.0]\n'
        'wind: {mean_mps: [0.0, 0.0], gust_std_mps: 0.0}\n'
        'faults:\n  - {type: mavlink_link_loss, start_s: 3.5, duration_s: 1.5, '
        'loss_timeout_s: 0.4}\n', encoding='utf-8')
    node = DeckSimulatorNode(context=context, parameter_overrides=[
        Parameter('scenario', value=str(sc)), Parameter('seed', value=2),
        Parameter('mavlink_url', value=f'udpout:127.0.0.1:{port}'),
        Parameter('pixy_udp_port', value=pixy.getsockname()[1])])
    executor.add_node(node)
    conn = mavutil.mavlink_connection(f'udpin:127.0.0.1:{port}', dialect='common',
                                      source_system=1, source_component=191)
    try:
        assert conn.recv_match(type='HEARTBEAT', blocking=True, timeout=3.0) is not None
        cal = node.emulator.params.thrust
        conn.mav.command_long_send(1, 1, 511, 0, 0, 50_000, 0, 0, 0, 0, 0)   # HEARTBEAT 20 Hz
        hbs = []          # (world time at receipt, main mode, sub mode)
        asked = 0.0
        end = time.monotonic() + 8.0
        next_sp = time.monotonic()
        while time.monotonic() < end and node.sim.world.t_s < 7.0:
            now = time.monotonic()
            if now >= next_sp:
                next_sp += 0.02
                conn.mav.set_attitude_target_send(**set_attitude_target_fields(*HOVER, cal))
            if now > asked and node.sim.world.t_s < 3.3 and node.emulator.mode != 'OFFBOARD':
                asked = now + 0.3      # retried until the warm-up (> 1 s of setpoints) is done
                conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0,
                                           0, 0, 0, 0)
            m = conn.recv_match(type='HEARTBEAT', blocking=True, timeout=0.005)
            if m is not None:
                hbs.append((node.sim.world.t_s, (m.custom_mode >> 16) & 0xFF,
                            m.custom_mode >> 24))
        modes = [(round(t, 2), main, sub) for t, main, sub in hbs]
        # OFFBOARD before the cut; no heartbeat inside the window; AUTO.LAND after it
        assert any(main == 6 and t < 3.5 for t, main, _ in hbs), modes
        assert not any(3.55 < t < 4.95 for t, _, _ in hbs), modes
        assert any(3.0 < t < 3.5 for t, _, _ in hbs) and any(5.0 < t < 5.5 for t, _, _ in hbs)
        assert any(main == 4 and sub == 6 and t > 5.0 for t, main, sub in hbs), modes
        assert node.emulator.failsafe_active and node.sim.autopilot.failsafes == 1
        c = node.sim.link.counters
        assert c['rx_cut'] > 50 and c['tx_cut'] > 50
        assert node.thread_errors == 0
    finally:
        conn.close()
        pixy.close()
