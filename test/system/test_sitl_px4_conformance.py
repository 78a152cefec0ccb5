"""One set of expectations, two autopilots: the emulated PX4 (deck_simulator.px4_emulator) and
the real PX4 v1.16 SITL (SIH quadrotor, airframe 10040). Each expectation is a finding of the
first test against PX4 (issue 14); the emulator must answer as PX4 does so that its tests mean
something about PX4. The PX4 variant is marked ``sitl`` and skipped when PX4 is not found."""

import math
import socket
import time

from deck_simulator.px4_emulator import EmulatorParams, MemoryLink, Px4Emulator
from deckland.sitl.px4 import SIH_QUADX, Px4NotFoundError, Px4Sitl, find_px4
from mavlink_bridge.conversions import (
    distance_sensor_to_rep117,
    param_value_from_wire,
    param_value_to_wire,
    px4_mode_name,
)
from pymavlink.dialects.v20 import common as mavlink
import pytest

try:
    PX4_ROOT = find_px4()
    NO_PX4 = 'PX4 SITL not found (set DECKLAND_PX4_SITL or provide ../shared/px4-sitl)'
except Px4NotFoundError as exc:      # DECKLAND_PX4_SITL set to a wrong folder
    PX4_ROOT, NO_PX4 = None, str(exc)
BACKENDS = ['emulator', pytest.param('px4', marks=[
    pytest.mark.sitl, pytest.mark.skipif(PX4_ROOT is None, reason=NO_PX4)])]
ACCEPTED, TEMP_REJECTED, FAILED = 0, 1, 4
LOITER = (4, 3)


class _Writer:
    def __init__(self, send):
        self.write = send


class Link:
    """The companion's side, the same API over either autopilot.

    ``advance(seconds)`` lets time pass (the emulator: simulated at 100 Hz; PX4: the wall
    clock) while messages are collected; setpoints stream at 50 Hz while ``streaming``."""

    def __init__(self):
        self.rx = mavlink.MAVLink(None)
        self.rx.robust_parsing = True
        self.msgs = []                      # (t, message), everything received
        self.streaming = False
        self.thrust = 0.5
        self.t = 0.0

    def command(self, cmd, *params):
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.target, 1, cmd, 0, *p)

    def setpoint(self):
        self.mav.set_attitude_target_send(0, self.target, 1, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0,
                                          0.0, self.thrust)

    def since(self, t0, kind):
        return [m for t, m in self.msgs if t >= t0 and m.get_type() == kind]

    def acks(self, t0, command):
        return [m.result for m in self.since(t0, 'COMMAND_ACK') if m.command == command]

    def heartbeat(self):
        hbs = [m for _, m in self.msgs if m.get_type() == 'HEARTBEAT' and
               m.get_srcComponent() == 1]
        return hbs[-1] if hbs else None

    def mode(self):
        hb = self.heartbeat()
        return ((hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF), bool(
            hb.base_mode & 128)

    def wait(self, pred, timeout_s):
        end = self.t + timeout_s
        while self.t < end:
            self.advance(0.1)
            if pred():
                return True
        return False

    def param(self, name, timeout_s=2.0):
        t0 = self.t
        self.mav.param_request_read_send(self.target, 1, name.encode(), -1)
        assert self.wait(lambda: any(m.param_id == name for m in self.since(t0, 'PARAM_VALUE')),
                         timeout_s), name
        m = [m for m in self.since(t0, 'PARAM_VALUE') if m.param_id == name][-1]
        return m.param_type, param_value_from_wire(m.param_value, m.param_type, True)

    def _parse(self, data):
        for m in self.rx.parse_buffer(data) or []:
            if m.get_type() != 'BAD_DATA':
                self.msgs.append((self.t, m))


class EmulatorLink(Link):
    """The emulator with PX4's defaults (COM_OBL_RC_ACT = 0, Position); the test plays the
    vehicle: on the ground, or 2.5 m up once :meth:`airborne`; a landing takes 1 s of
    AUTO.LAND."""

    def __init__(self):
        super().__init__()
        self.mem = MemoryLink()
        self.emu = Px4Emulator(EmulatorParams(offboard_loss_action='position'),
                               transport=self.mem.a)
        self.mav = mavlink.MAVLink(self.mem.b, srcSystem=1, srcComponent=191)
        self.target = 1
        self.in_air = False
        self._land_since = None

    def airborne(self):
        self.command(400, 1)
        self.advance(0.05)
        self.in_air = True
        self.advance(1.2)                   # (the heartbeat is 1 Hz)

    def advance(self, seconds):
        end = self.t + seconds
        while self.t < end - 1e-9:
            if self.streaming and round(self.t * 100) % 2 == 0:
                self.setpoint()
            emu = self.emu
            descending = emu.kind in ('land', 'failsafe_land')
            if self.in_air and descending:
                self._land_since = self.t if self._land_since is None else self._land_since
                if self.t - self._land_since >= 1.0:
                    self.in_air = False
            emu.update(self.t)
            rng = 2.5 if self.in_air else 0.0
            emu.publish_state(self.t, (0.0, 0.0, rng), (0.0, 0.0, 0.0), 0.0, 0.0, 0.0,
                              (0.0, 0.0, 0.0), (0.0, 0.0, 9.81), rng, not self.in_air)
            for data, _ in self.mem.b.receive():
                self._parse(data)
            self.t = round(self.t + 0.01, 9)

    def close(self):
        self.emu.close()


class Px4Link(Link):
    """PX4 SITL over its onboard UDP link (we listen on 14540 + i as a companion does)."""

    def __init__(self, px4: Px4Sitl):
        super().__init__()
        p = px4.ports
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', p['onboard_remote']))
        self.sock.settimeout(0.01)
        remote = ('127.0.0.1', p['onboard_local'])
        self.mav = mavlink.MAVLink(_Writer(lambda b: self.sock.sendto(b, remote)),
                                   srcSystem=px4.system_id, srcComponent=191)
        self.target = px4.system_id
        self.t0 = time.monotonic()
        self._next_sp = 0.0

    def airborne(self):
        """Arm (retried while EKF2 settles) and take off with PX4's own take-off."""
        for _ in range(60):
            self.command(400, 1)
            self.advance(0.5)
            if self.mode()[1]:
                break
        assert self.mode()[1], 'PX4 did not arm'
        t0 = self.t
        self.command(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        assert self.wait(lambda: self.mode()[0] == (4, 2), 5.0), 'no AUTO.TAKEOFF'
        assert self.wait(lambda: self.mode()[0] == LOITER, 30.0), 'take-off did not finish'
        assert self.t - t0 < 30.0

    def advance(self, seconds):
        end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            self.t = now - self.t0
            if self.streaming and now >= self._next_sp:
                self._next_sp = now + 0.02
                self.setpoint()
            if now >= end:
                break
            try:
                data = self.sock.recv(65535)
            except (TimeoutError, BlockingIOError):
                continue
            self._parse(data)

    def close(self):
        self.sock.close()


@pytest.fixture(scope='module')
def px4_sih():
    with Px4Sitl(SIH_QUADX, nice=10) as px4:
        px4.wait_for_log('Ready for takeoff', 60.0)
        yield px4


@pytest.fixture(params=BACKENDS)
def link(request):
    if request.param == 'px4':
        lk = Px4Link(request.getfixturevalue('px4_sih'))
        assert lk.wait(lambda: lk.heartbeat() is not None, 10.0), 'no heartbeat from PX4'
    else:
        lk = EmulatorLink()
        lk.advance(1.1)
    try:
        yield lk
    finally:
        lk.close()


def test_on_the_ground(link):
    hb = link.heartbeat()
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.type == mavlink.MAV_TYPE_QUADROTOR
    # 1, 6: the parameters the bridge reads, with PX4's defaults and its bytewise INT32
    assert link.param('COM_OBL_RC_ACT') == (mavlink.MAV_PARAM_TYPE_INT32, 0.0)   # Position
    typ, lt = link.param('COM_OF_LOSS_T')
    assert typ == mavlink.MAV_PARAM_TYPE_REAL32 and lt == pytest.approx(1.0)
    assert link.param('MPC_THR_HOVER')[1] == pytest.approx(0.5)
    # 3: SET_MESSAGE_INTERVAL(HEARTBEAT) is refused, a telemetry interval accepted
    t0 = link.t
    link.command(511, 0, 1e6)
    link.advance(0.3)
    link.command(511, 30, 1e4)
    link.advance(0.3)
    assert link.acks(t0, 511) == [FAILED, ACCEPTED]
    # 9: the downward distance sensor on the ground reads <= min_distance: REP-117 "too close"
    t0 = link.t
    link.advance(0.5)
    ds = link.since(t0, 'DISTANCE_SENSOR')[-1]
    assert distance_sensor_to_rep117(ds.current_distance, ds.min_distance,
                                     ds.max_distance) == -math.inf
    # 4: OFFBOARD while disarmed, no setpoint at all: accepted (two ACKs); heartbeat OFFBOARD
    t0 = link.t
    link.command(176, 1, 6)
    assert link.wait(lambda: link.mode() == ((6, 0), False), 2.5)
    assert link.acks(t0, 176) == [ACCEPTED, ACCEPTED]
    assert px4_mode_name(link.heartbeat().custom_mode) == 'OFFBOARD'
    t0 = link.t
    link.command(176, 1, 4, 3)                                     # back to AUTO.LOITER
    assert link.wait(lambda: link.mode()[0] == LOITER, 2.5)
    assert link.acks(t0, 176) == [ACCEPTED, ACCEPTED]


def test_in_the_air(link):
    link.airborne()
    assert link.mode()[1]
    # 4: OFFBOARD with no setpoint in the air: receiver ACCEPTED, commander TEMPORARILY_REJECTED
    t0 = link.t
    link.command(176, 1, 6)
    link.advance(0.5)
    assert link.acks(t0, 176) == [ACCEPTED, TEMP_REJECTED]
    # ... one fresh setpoint is enough
    t0 = link.t
    link.thrust = 0.5
    link.setpoint()
    link.command(176, 1, 6)
    link.streaming = True
    assert link.wait(lambda: link.mode() == ((6, 0), True), 2.5)
    assert link.acks(t0, 176) == [ACCEPTED, ACCEPTED]
    # 2: a disarm in the air is TEMPORARILY_REJECTED (one ACK), the vehicle stays armed
    t0 = link.t
    link.command(400, 0)
    link.advance(0.5)
    assert link.acks(t0, 400) == [TEMP_REJECTED] and link.mode() == ((6, 0), True)
    # 1: COM_OBL_RC_ACT = 4 (Land), set over MAVLink (bytewise), then the setpoints stop
    t0 = link.t
    link.mav.param_set_send(link.target, 1, b'COM_OBL_RC_ACT', param_value_to_wire(4, 6, True), 6)
    assert link.wait(lambda: link.since(t0, 'PARAM_VALUE'), 2.0)
    assert param_value_from_wire(link.since(t0, 'PARAM_VALUE')[-1].param_value, 6, True) == 4
    link.streaming = False
    t_stop = link.t
    assert link.wait(lambda: link.mode()[0] == (4, 6), 3.0), link.mode()
    # (the heartbeat is 1 Hz: the switch is seen within 1 s after COM_OF_LOSS_T)
    assert 0.9 <= link.t - t_stop <= 1.0 + 1.2
    # 5: landed and disarmed, PX4 reads OFFBOARD again (the user's mode), disarmed
    assert link.wait(lambda: not link.mode()[1], 25.0), 'no landing/disarm'
    assert link.wait(lambda: link.mode() == ((6, 0), False), 3.0), link.mode()


def test_default_offboard_loss_action_descends_in_posctl(link):
    # 1: PX4's default COM_OBL_RC_ACT = 0 (Position): with no RC the heartbeat reads POSCTL
    # while PX4 descends by itself: the action the bridge refuses to fly OFFBOARD with
    t0 = link.t
    link.mav.param_set_send(link.target, 1, b'COM_OBL_RC_ACT', param_value_to_wire(0, 6, True), 6)
    assert link.wait(lambda: link.since(t0, 'PARAM_VALUE'), 2.0)
    link.command(176, 1, 4, 3)
    link.advance(1.2)
    link.airborne()
    link.setpoint()
    link.command(176, 1, 6)
    link.streaming = True
    assert link.wait(lambda: link.mode() == ((6, 0), True), 2.5)
    link.streaming = False
    assert link.wait(lambda: link.mode()[0] != (6, 0), 3.0)
    assert link.mode() == ((3, 0), True)                       # POSCTL, armed
    assert link.wait(lambda: not link.mode()[1], 30.0), 'no descent to a disarm'
