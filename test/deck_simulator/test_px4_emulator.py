"""deck_simulator.px4_emulator over an in-memory link: PX4 offboard rules and failsafes (the
emulator without a world runs its autopilot's mode logic itself)."""

import math
import random

from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
from deck_simulator.transport import MemoryLink
from mavlink_bridge.conversions import ThrustCalibration, set_attitude_target_fields
from pymavlink.dialects.v20 import common as mavlink
import pytest


class Companion:
    def __init__(self, params=None):
        self.link = MemoryLink()
        self.emu = Px4Emulator(params or EmulatorParams(), transport=self.link.a)
        self.mav = mavlink.MAVLink(self.link.b, srcSystem=1, srcComponent=191)
        self.rx = mavlink.MAVLink(None)

    def received(self):
        out = []
        for data, _ in self.link.b.receive():
            out += self.rx.parse_buffer(data) or []
        return out

    def setpoint(self, thrust_n=20.0, att=(0.1, 0.05, 1.0)):
        self.mav.set_attitude_target_send(**set_attitude_target_fields(
            *att, thrust_n, self.emu.params.thrust))

    def command(self, cmd, *params):
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(1, 1, cmd, 0, *p)

    def state(self, t, landed=False, vz=0.0):
        self.emu.publish_state(t, (1.0, 2.0, 3.0), (0.0, 0.0, vz), 0.0, 0.0, 0.3,
                               (0.0, 0.0, 0.0), (0.0, 0.0, 9.81), 2.0, landed)


def stream(c, t0, t1, hz=50.0, **kw):
    t = t0
    while t < t1:
        c.setpoint(**kw)
        c.emu.update(t)
        t += 1.0 / hz
    return t


def test_telemetry_is_ned_frd_cm():
    c = Companion()
    c.emu.update(0.0)
    c.emu.publish_state(0.0, (1.0, 2.0, 3.0), (0.5, -0.2, 0.1), 0.1, 0.2, 0.3,
                        (0.01, 0.02, 0.03), (0.0, 0.0, 9.81), 2.345, False)
    msgs = {m.get_type(): m for m in c.received()}
    assert msgs['HEARTBEAT'].autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert (msgs['HEARTBEAT'].custom_mode >> 16) & 0xFF == 3                # POSCTL
    lp = msgs['LOCAL_POSITION_NED']
    assert (lp.x, lp.y, lp.z) == pytest.approx((2.0, 1.0, -3.0))
    assert (lp.vx, lp.vy, lp.vz) == pytest.approx((-0.2, 0.5, -0.1))
    at = msgs['ATTITUDE']
    assert (at.roll, at.pitch, at.yaw) == pytest.approx((0.1, -0.2, math.pi / 2 - 0.3))
    assert (at.rollspeed, at.pitchspeed, at.yawspeed) == pytest.approx((0.01, -0.02, -0.03))
    ds = msgs['DISTANCE_SENSOR']
    assert (ds.current_distance, ds.orientation) == (234, 25) or ds.current_distance == 235
    assert msgs['HIGHRES_IMU'].zacc == pytest.approx(-9.81)                 # FRD specific force
    assert msgs['EXTENDED_SYS_STATE'].landed_state == mavlink.MAV_LANDED_STATE_IN_AIR


def test_set_message_interval_changes_rate():
    c = Companion()
    c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30, 10000)    # ATTITUDE at 100 Hz
    c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 132, -1)      # DISTANCE_SENSOR off
    c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 1000)   # unknown id
    c.emu.update(0.0)
    acks = [(m.command, m.result) for m in c.received() if m.get_type() == 'COMMAND_ACK']
    assert acks == [(511, 0), (511, 0), (511, mavlink.MAV_RESULT_UNSUPPORTED)]
    counts = {}
    for i in range(400):                                          # 1 s at 400 Hz
        c.state(i / 400.0)
        for m in c.received():
            counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
    assert 99 <= counts['ATTITUDE'] <= 101
    assert 'DISTANCE_SENSOR' not in counts
    assert 29 <= counts['LOCAL_POSITION_NED'] <= 31


def test_offboard_needs_one_fresh_setpoint_when_armed():
    c = Companion()
    c.state(0.0, landed=False)
    c.command(400, 1.0)                                           # arm (in the air)
    c.emu.update(0.0)
    c.command(176, 1.0, 6.0)                                      # OFFBOARD, no setpoint yet
    c.emu.update(0.01)
    # PX4 v1.16: the receiver's ACCEPTED, then the commander's TEMPORARILY_REJECTED
    assert c.emu.acks[-2:] == [(176, 0), (176, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)]
    assert c.emu.mode == 'POSCTL'
    c.setpoint()                                                  # one setpoint is enough
    c.command(176, 1.0, 6.0)
    c.emu.update(0.02)
    assert c.emu.acks[-2:] == [(176, 0), (176, 0)]
    assert c.emu.mode == 'OFFBOARD' and c.emu.armed and c.emu.kind == 'offboard'
    sp = c.emu.setpoint
    assert (sp.roll_rad, sp.pitch_rad, sp.yaw_rad) == pytest.approx((0.1, 0.05, 1.0),
                                                                    abs=1e-6)
    assert sp.thrust_n == pytest.approx(20.0, abs=1e-4)


def test_offboard_setpoint_older_than_com_of_loss_t_is_refused():
    c = Companion()
    c.state(0.0, landed=False)
    c.command(400, 1.0)
    c.setpoint()
    c.emu.update(0.0)
    c.command(176, 1.0, 6.0)
    c.emu.update(1.05)                                            # > COM_OF_LOSS_T later
    assert c.emu.acks[-1] == (176, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
    # disarmed, PX4 accepts OFFBOARD with no setpoint at all (then refuses to arm in it)
    d = Companion()
    d.state(0.0, landed=True)
    d.command(176, 1.0, 6.0)
    d.emu.update(0.0)
    assert d.emu.mode == 'OFFBOARD' and not d.emu.armed
    d.command(400, 1.0)
    d.emu.update(0.1)
    assert not d.emu.armed and d.emu.acks[-1] == (400, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)


def test_offboard_loss_failsafe_lands_after_com_of_loss_t():
    c = Companion()
    c.state(0.0, landed=True)
    c.command(400, 1.0)
    t = stream(c, 0.0, 1.3)
    c.command(176, 1.0, 6.0)
    c.emu.update(t)
    c.state(t, landed=False)
    last = t
    t += 0.5
    c.emu.update(t)                                               # 0.5 s silence: hold last
    assert c.emu.mode == 'OFFBOARD' and c.emu.kind == 'offboard'
    t = last + 1.05
    c.emu.update(t)
    assert c.emu.mode == 'AUTO.LAND' and c.emu.failsafe_active
    assert c.emu.kind == 'failsafe_land' and c.emu.autopilot.failsafes == 1
    # setpoints coming back do not re-enter OFFBOARD by themselves
    t = stream(c, t, t + 2.0)
    assert c.emu.mode == 'AUTO.LAND' and c.emu.failsafe_active
    # the companion's request does (and ends the failsafe)
    c.command(176, 1.0, 6.0)
    c.emu.update(t)
    assert c.emu.mode == 'OFFBOARD' and not c.emu.failsafe_active


def test_disarm_rules():
    c = Companion(EmulatorParams(disarm_preflight_s=0.0))
    c.state(0.0, landed=False)
    c.command(400, 1.0)
    c.emu.update(0.0)
    c.command(400, 0.0)                                           # in the air: refused
    c.emu.update(0.1)
    assert c.emu.armed and c.emu.acks[-1] == (400, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
    c.command(400, 0.0, 21196.0)                                  # forced
    c.emu.update(0.2)
    assert not c.emu.armed and c.emu.kind == 'idle'
    # auto-disarm 2 s after touchdown (COM_DISARM_LAND)
    c.command(400, 1.0)
    c.emu.update(0.3)
    c.state(0.3, landed=False)
    c.emu.update(0.4)
    c.state(0.5, landed=True)
    c.emu.update(0.5)
    c.emu.update(2.4)
    assert c.emu.armed
    c.emu.update(2.6)
    assert not c.emu.armed


def test_px4_parameters_answered_with_px4_names_defaults_and_encoding():
    from mavlink_bridge.conversions import param_value_from_wire, param_value_to_wire
    c = Companion(EmulatorParams(offboard_loss_action='position'))   # PX4's default
    for name in ('COM_OBL_RC_ACT', 'COM_OF_LOSS_T', 'MPC_THR_HOVER', 'NO_SUCH_PARAM'):
        c.mav.param_request_read_send(1, 1, name.encode(), -1)
    c.emu.update(0.0)
    got = {m.param_id: m for m in c.received() if m.get_type() == 'PARAM_VALUE'}
    assert set(got) == {'COM_OBL_RC_ACT', 'COM_OF_LOSS_T', 'MPC_THR_HOVER'}   # PX4: silence
    act = got['COM_OBL_RC_ACT']
    assert act.param_type == 6 and param_value_from_wire(act.param_value, 6, True) == 0.0
    assert got['COM_OF_LOSS_T'].param_value == pytest.approx(1.0)
    assert got['MPC_THR_HOVER'].param_value == pytest.approx(0.5)
    # PARAM_SET COM_OBL_RC_ACT = 4 (bytewise) switches the loss action to Land
    c.mav.param_set_send(1, 1, b'COM_OBL_RC_ACT', param_value_to_wire(4, 6, True), 6)
    c.emu.update(0.1)
    (echo,) = [m for m in c.received() if m.get_type() == 'PARAM_VALUE']
    assert param_value_from_wire(echo.param_value, 6, True) == 4.0
    assert c.emu.params.offboard_loss_action == 'land'


def test_heartbeat_interval_refused_as_px4_does():
    c = Companion()
    c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 1e6)
    c.emu.update(0.0)
    assert c.emu.acks[-1] == (511, mavlink.MAV_RESULT_FAILED)


def _fly_offboard(c):
    c.state(0.0, landed=False)
    c.command(400, 1.0)
    c.setpoint()
    c.command(176, 1.0, 6.0)
    c.emu.update(0.0)
    assert c.emu.mode == 'OFFBOARD'


def test_default_px4_loss_action_descends_in_posctl():
    c = Companion(EmulatorParams(offboard_loss_action='position'))
    _fly_offboard(c)
    c.emu.update(1.05)
    # PX4 default COM_OBL_RC_ACT = 0 without RC: the heartbeat reads POSCTL, it descends
    assert c.emu.mode == 'POSCTL' and c.emu.failsafe_active
    assert c.emu.kind == 'failsafe_land'


def test_after_a_failsafe_landing_px4_reads_offboard_while_disarmed():
    c = Companion(EmulatorParams(disarm_landed_s=2.0))
    _fly_offboard(c)
    c.emu.update(1.05)
    assert c.emu.mode == 'AUTO.LAND'
    c.state(1.5, landed=True)
    c.emu.update(1.5)
    c.emu.update(3.6)                                             # COM_DISARM_LAND = 2 s
    assert not c.emu.armed and c.emu.mode == 'OFFBOARD' and not c.emu.failsafe_active
    c.emu.update(10.0)                                            # no failsafe while disarmed
    assert c.emu.mode == 'OFFBOARD' and c.emu.kind == 'idle'


def test_garbage_and_bad_setpoints_are_counted_not_raised():
    c = Companion()
    rng = random.Random(7)
    for _ in range(50):
        c.link.b.send(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))))
    c.link.b.send(b'\xfd\x09\x00\x00')                            # truncated v2 header
    bad = dict(set_attitude_target_fields(0.0, 0.0, 0.0, 20.0, ThrustCalibration()))
    bad['thrust'] = math.nan
    c.mav.set_attitude_target_send(**bad)
    c.emu.update(0.0)
    assert c.emu.rejected['bad_data'] > 0
    assert c.emu.rejected['nan'] == 1 and c.emu.setpoint is None
    c.setpoint()
    c.emu.update(0.1)
    assert c.emu.setpoint is not None
    c.emu.publish_state(0.2, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0), 0, 0, 0, (0, 0, 0),
                        (0, 0, 9.81), None, False)
    assert c.emu.rejected['nan'] == 2


