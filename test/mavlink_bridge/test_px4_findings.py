"""The nine findings of the first test against PX4 v1.16 SITL (issue 14), one test each, on the
bridge's pure core and conversions with the values PX4 really sends (measured on
``../shared/px4-sitl``, SIH airframe 10040; the SITL tests repeat them against PX4 itself)."""

import math

from mavlink_bridge.conversions import (
    distance_sensor_to_rep117,
    param_value_from_wire,
    param_value_to_wire,
    px4_custom_mode,
    px4_mode_from_name,
    px4_mode_name,
)
from mavlink_bridge.core import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    BridgeCore,
    BridgeParams,
)
from mavlink_bridge.monitors import HoverThrustEstimator, SetpointStats
import pytest

INT32, REAL32 = 6, 9
LOITER, OFFBOARD, POSCTL = px4_custom_mode(4, 3), px4_custom_mode(6), px4_custom_mode(3)
ARMED = 128


class Px4:
    """Feeds a core what PX4 v1.16 sends, at 100 Hz of setpoints; ``t`` in seconds."""

    def __init__(self, params=None, loss_action=4, loss_timeout=1.0, hover=0.5):
        self.core = BridgeCore(params or BridgeParams())
        self.t = 0.0
        self.heartbeat(LOITER, ARMED)
        for name, value, typ in (('COM_OBL_RC_ACT', loss_action, INT32),
                                 ('COM_OF_LOSS_T', loss_timeout, REAL32),
                                 ('MPC_THR_HOVER', hover, REAL32)):
            if value is not None:
                wire = param_value_to_wire(value, typ, True)
                self.core.on_param_value(name, wire, typ)

    def heartbeat(self, custom_mode, base_mode=0):
        self.hb = (custom_mode, base_mode)
        self.core.on_heartbeat(self.t, 1, 1, 2, 12, base_mode, custom_mode)

    def run(self, seconds, stream=True, on_step=None):
        """Advance, streaming setpoints; returns every Outgoing the core produced."""
        out = []
        end = self.t + seconds
        while self.t < end - 1e-9:
            if round(self.t * 100) % 100 == 0:                    # PX4's 1 Hz heartbeat
                self.heartbeat(*self.hb)
            if stream:
                self.core.on_attitude_command(self.t, self.t, (1.0, 0.0, 0.0, 0.0))
                self.core.on_thrust_command(self.t, self.t, 26.6)
            got = self.core.step(self.t)
            out += got
            if on_step:
                on_step(got)
            self.t = round(self.t + 0.01, 9)
        return out


def commands(out, cmd):
    return [o for o in out if o.kind == 'command' and o.command == cmd]


# --- 1. offboard-loss action ----------------------------------------------------------------

def test_offboard_refused_until_the_offboard_loss_action_is_read_and_safe():
    # fail closed: nothing read yet
    px4 = Px4(loss_action=None, loss_timeout=None)
    reqs = [o.param_id for o in px4.core.step(0.0) if o.kind == 'param_request']
    assert reqs == ['COM_OBL_RC_ACT', 'COM_OF_LOSS_T']
    ok, why = px4.core.request_offboard(0.0)
    assert not ok and 'COM_OBL_RC_ACT' in why and 'unknown' in why
    # PX4's default 0 (Position): an emergency descent without RC, heartbeat POSCTL
    px4.core.on_param_value('COM_OBL_RC_ACT', param_value_to_wire(0, INT32, True), INT32)
    ok, why = px4.core.request_offboard(0.0)
    assert not ok and 'position' in why and 'COM_OBL_RC_ACT = 4' in why
    px4.core.on_param_value('COM_OBL_RC_ACT', param_value_to_wire(4, INT32, True), INT32)
    ok, why = px4.core.request_offboard(0.0)
    assert not ok and 'COM_OF_LOSS_T' in why
    px4.core.on_param_value('COM_OF_LOSS_T', 10.0, REAL32)       # a 10 s stale setpoint
    assert not px4.core.request_offboard(0.0)[0]
    px4.core.on_param_value('COM_OF_LOSS_T', 1.0, REAL32)
    assert px4.core.request_offboard(0.0)[0]
    assert px4.core.params.offboard_loss_actions == ('land', 'hold')
    # Hold (5) is accepted too, Return (3) only when configured
    assert Px4(loss_action=5).core.request_offboard(0.0)[0]
    assert not Px4(loss_action=3).core.request_offboard(0.0)[0]
    rtl = Px4(BridgeParams(offboard_loss_actions=('land', 'return')), loss_action=3)
    assert rtl.core.request_offboard(0.0)[0]


def test_px4_integer_parameters_arrive_bytewise():
    # measured: MPC_USE_HTE = 1 (INT32) arrives as 1.4e-45, NAV_RCL_ACT = 2 as 2.8e-45
    assert param_value_from_wire(1.401298464324817e-45, INT32, True) == 1.0
    assert param_value_from_wire(2.802596928649634e-45, INT32, True) == 2.0
    assert param_value_from_wire(0.5, REAL32, True) == 0.5
    assert param_value_from_wire(8.0, INT32, False) == 8.0            # ArduPilot casts
    for v in (0, 4, 5, 7, -1, 123456):
        assert param_value_from_wire(param_value_to_wire(v, INT32, True), INT32, True) == v
    core = BridgeCore()
    core.on_param_value('COM_OBL_RC_ACT', 5.605193857299268e-45, INT32)
    assert core.autopilot_params['COM_OBL_RC_ACT'] == 4.0


# --- 2. disarm in the air ------------------------------------------------------------------

def test_disarm_refused_in_the_air_waits_for_the_land_detector():
    px4 = Px4()
    px4.core.on_extended_sys_state(2)                    # in the air
    px4.core.on_enabled(px4.t, False)                    # the planner says landed: disarm
    sent = []

    def ack(out):
        for _ in commands(out, MAV_CMD_COMPONENT_ARM_DISARM):
            sent.append(px4.t)
            px4.core.on_command_ack(px4.t, MAV_CMD_COMPONENT_ARM_DISARM, 1)  # TEMP_REJECTED

    px4.run(3.0, stream=False, on_step=ack)
    # today's bridge re-sent every 0.5 s: ten refusals, each a critical message on the GCS
    assert len(sent) == 1 and px4.core.counters['disarm_deferred'] == 1
    assert 'deferred' in px4.core.last_result
    px4.core.on_extended_sys_state(1)                    # PX4's land detector: landed
    out = px4.run(0.1, stream=False)
    assert len(commands(out, MAV_CMD_COMPONENT_ARM_DISARM)) == 1
    px4.heartbeat(LOITER, 0)
    px4.run(0.05, stream=False)
    assert px4.core.last_result == 'disarmed'


# --- 3. SET_MESSAGE_INTERVAL(HEARTBEAT) ---------------------------------------------------

def test_heartbeat_interval_is_never_requested():
    px4 = Px4()
    out = px4.run(25.0, stream=False)                     # three refresh periods
    ids = [int(o.params[0]) for o in commands(out, MAV_CMD_SET_MESSAGE_INTERVAL)
           if o.params[1] > 0]
    assert 0 not in ids                                   # PX4: FAILED, every time
    assert {30, 32, 83, 105, 132, 245} <= set(ids)


# --- 4. two ACKs per DO_SET_MODE, one fresh setpoint ------------------------------------------

def test_px4_mode_acks_first_receiver_then_commander():
    px4 = Px4()
    assert px4.core.request_offboard(0.0)[0]
    sends = []

    def answer(out):
        for _ in commands(out, MAV_CMD_DO_SET_MODE):
            sends.append(px4.t)
            px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, 0)   # MAVLink receiver
            px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, 0)   # commander: accepted

    px4.run(1.5, on_step=answer)                          # PX4's heartbeat is 1 Hz: none yet
    assert len(sends) == 1                                # the verdict ends the re-sends
    assert px4.core.params.offboard_warmup_s - 1e-9 <= sends[0] < 0.5
    px4.heartbeat(OFFBOARD, ARMED)
    px4.run(0.02)
    assert px4.core.last_result == 'OFFBOARD active'


def test_px4_receiver_accepted_then_commander_refusal():
    px4 = Px4()
    px4.core.request_offboard(0.0)
    verdicts = iter([1, 1, 0])            # TEMPORARILY_REJECTED twice, then accepted
    sends = []

    def answer(out):
        for _ in commands(out, MAV_CMD_DO_SET_MODE):
            sends.append(px4.t)
            px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, 0)
            px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, next(verdicts))

    px4.run(2.0, on_step=answer)
    assert len(sends) == 3 and px4.core.pending()['offboard']
    # a final refusal after the receiver's ACCEPTED cancels
    px4 = Px4()
    px4.core.request_offboard(0.0)
    px4.run(0.3)
    px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, 0)
    assert px4.core.pending()['offboard']
    px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, 2)            # DENIED
    assert not px4.core.pending()['offboard'] and 'refused' in px4.core.last_result


def test_offboard_warmup_follows_px4s_one_fresh_setpoint_rule():
    BridgeParams(offboard_warmup_s=0.0)            # was refused: "must be > 1 s"
    px4 = Px4(BridgeParams(offboard_warmup_s=0.0))
    px4.core.request_offboard(0.0)
    out = px4.run(0.02)
    assert commands(out, MAV_CMD_DO_SET_MODE)      # with the first setpoint


# --- 5. OFFBOARD while disarmed after a failsafe landing ------------------------------------

def test_disarmed_offboard_after_a_failsafe_landing_is_not_offboard_control():
    px4 = Px4()
    px4.heartbeat(OFFBOARD, 0)            # PX4 after its failsafe landing: OFFBOARD, disarmed
    assert not px4.core.in_offboard()
    ok, msg = px4.core.request_offboard(px4.t)
    assert ok and 'already' not in msg and px4.core.pending()['offboard']
    out = px4.run(0.5, on_step=lambda o: [
        px4.core.on_command_ack(px4.t, MAV_CMD_DO_SET_MODE, 0)
        for _ in range(2 * len(commands(o, MAV_CMD_DO_SET_MODE)))])
    assert commands(out, MAV_CMD_DO_SET_MODE)
    assert px4.core.last_result == 'OFFBOARD selected (disarmed)'
    px4.heartbeat(OFFBOARD, ARMED)
    assert px4.core.in_offboard()
    assert px4.core.request_offboard(px4.t) == (True, 'already in OFFBOARD')


# --- 6. hover thrust from PX4 --------------------------------------------------------------

def test_hover_thrust_is_what_px4_commands_in_its_own_hover():
    px4 = Px4(hover=0.5)                                   # MPC_THR_HOVER: 2 % high on SIH
    px4.core.on_extended_sys_state(2)
    k = [0]

    def sample(_out):                                      # AUTO.LOITER, ATTITUDE_TARGET 10 Hz
        k[0] += 1
        if k[0] % 10 == 0:
            wobble = 0.002 * math.sin(k[0])
            px4.core.on_attitude_target(px4.t, 0.4947 / math.cos(0.02) + wobble,
                                        math.cos(0.02), 0.01)

    px4.run(4.0, stream=False, on_step=sample)
    assert px4.core.hover.estimate == pytest.approx(0.4947, abs=0.002)
    ok, msg = px4.core.request_offboard(px4.t)
    assert ok and 'measured' in msg
    cal = px4.core.thrust
    assert cal.hover_thrust_norm == pytest.approx(0.4947, abs=0.002)
    assert cal.to_norm(cal.mass_kg * cal.gravity_mps2) == pytest.approx(0.4947, abs=0.002)
    px4.core.on_attitude_command(px4.t, px4.t, (1.0, 0.0, 0.0, 0.0))
    sp = px4.core.on_thrust_command(px4.t, px4.t, cal.mass_kg * cal.gravity_mps2)
    assert sp.thrust_norm == pytest.approx(0.4947, abs=0.002)
    # without a measurement: MPC_THR_HOVER; without either: refused (fail closed)
    only_param = Px4(hover=0.5)
    assert 'MPC_THR_HOVER' in only_param.core.request_offboard(0.0)[1]
    assert only_param.core.thrust.hover_thrust_norm == 0.5
    nothing = Px4(hover=None)
    ok, why = nothing.core.request_offboard(0.0)
    assert not ok and 'hover thrust' in why
    configured = Px4(BridgeParams(hover_thrust_source='parameter'), hover=None)
    assert configured.core.request_offboard(0.0)[0]


def test_hover_samples_only_from_px4s_own_steady_hover():
    est = HoverThrustEstimator(window_s=2.0)
    for k in range(25):                                    # climbing at 0.5 m/s: no
        est.on_sample(0.1 * k, 0.6, 1.0, 0.5)
    assert not est.valid
    for k in range(25):                                    # a 0.1 spread: no
        est.on_sample(3.0 + 0.1 * k, 0.45 + 0.1 * (k % 2), 1.0, 0.0)
    assert not est.valid
    for k in range(25):
        est.on_sample(6.0 + 0.1 * k, 0.49, 1.0, 0.0)
    assert est.estimate == pytest.approx(0.49)
    px4 = Px4()
    px4.core.on_extended_sys_state(2)
    px4.heartbeat(OFFBOARD, ARMED)          # in OFFBOARD ATTITUDE_TARGET echoes our setpoints
    for k in range(30):
        px4.core.on_attitude_target(0.1 * k, 0.7, 1.0, 0.0)
    assert not px4.core.hover.valid


# --- 7. telemetry trim, setpoint rate and gaps --------------------------------------------

def test_unused_px4_streams_are_trimmed():
    px4 = Px4()
    for mid in (30, 32, 105, 132, 245, 83, 0, 77, 111, 253, 410, 24, 33, 31, 74, 1):
        px4.core.on_message(mid)
    out = px4.run(1.0, stream=False)
    trims = sorted(int(o.params[0]) for o in commands(out, MAV_CMD_SET_MESSAGE_INTERVAL)
                   if o.params[1] == -1.0)
    assert trims == [1, 24, 31, 33, 74]     # SYS_STATUS, GPS_RAW_INT, ATT_QUAT, GPOS, VFR_HUD
    for _ in range(5):                      # still arriving: asked at most 3 times
        px4.core.on_message(24)
        out = px4.run(1.0, stream=False)
    assert px4.core._trimmed[24] == 3
    # a reconnection (PX4 rebooted) trims again
    px4.t += 4.0
    px4.heartbeat(LOITER, ARMED)
    px4.core.on_message(24)
    out = px4.run(1.0, stream=False)
    assert [int(o.params[0]) for o in commands(out, MAV_CMD_SET_MESSAGE_INTERVAL)
            if o.params[1] == -1.0] == [24]
    assert not BridgeCore(BridgeParams(trim_telemetry=False)).used_msg_ids() - {
        0, 22, 30, 32, 77, 83, 105, 111, 132, 245, 253, 410, 411, 413}


def test_setpoint_rate_and_largest_gap_are_reported():
    stats = SetpointStats()
    t = 0.0
    for k in range(13):                       # an overloaded publisher: 13 Hz with a gap
        stats.on_sent(t)
        t += 0.862 if k == 6 else 0.0115
    rate, gap = stats.window(1.0)
    assert gap == pytest.approx(0.862) and rate == pytest.approx(13.0, rel=0.05)
    rate, gap = stats.window(2.0)             # silence since: the gap grows, rate 0
    assert rate == 0.0 and gap >= 1.0
    px4 = Px4()
    px4.heartbeat(OFFBOARD, ARMED)
    px4.run(1.0)
    rate, gap, warn = px4.core.stream_diagnostics(px4.t)
    assert rate == pytest.approx(100.0, rel=0.02) and gap == pytest.approx(0.01) and not warn
    px4.run(0.6, stream=False)
    px4.run(0.4)
    rate, gap, warn = px4.core.stream_diagnostics(px4.t)
    assert gap == pytest.approx(0.61, abs=0.011) and 'COM_OF_LOSS_T' in warn


# --- 8. mode names -------------------------------------------------------------------------

def test_px4_mode_names_termination_and_auto_sub_modes():
    assert px4_mode_name(655360) == 'TERMINATION'                 # measured: main mode 10
    assert px4_mode_name(px4_custom_mode(4, 10)) == 'AUTO.VTOL_TAKEOFF'
    assert px4_mode_name(px4_custom_mode(4, 11)) == 'AUTO.EXTERNAL1'
    assert px4_mode_name(px4_custom_mode(4, 18)) == 'AUTO.EXTERNAL8'
    assert px4_mode_name(px4_custom_mode(4, 9)) == 'AUTO.PRECLAND'
    assert px4_mode_name(px4_custom_mode(9)) == 'UNKNOWN(589824)'  # reserved
    assert px4_mode_from_name('AUTO.EXTERNAL3') == (4, 13)
    assert px4_mode_from_name('TERMINATION') == (10, 0)


# --- 9. distance sensor on the ground ------------------------------------------------------

def test_distance_on_the_ground_is_too_close_not_no_return():
    assert distance_sensor_to_rep117(0, 0, 10000) == -math.inf     # SIH on the ground
    assert distance_sensor_to_rep117(65531, 0, 10000) == -math.inf  # SIH: -5 cm, wrapped
    assert distance_sensor_to_rep117(3, 5, 4000) == -math.inf       # below min_distance
    assert distance_sensor_to_rep117(4001, 5, 4000) == math.inf     # ArduPilot: max + 1
    assert distance_sensor_to_rep117(0xFFFF, 5, 4000) == math.inf   # unknown
    assert distance_sensor_to_rep117(250, 5, 4000) == pytest.approx(2.5)
    assert distance_sensor_to_rep117(250, 0, 0) == pytest.approx(2.5)   # max unknown


def test_bad_parameter_and_attitude_target_input_changes_nothing():
    px4 = Px4()
    before = dict(px4.core.autopilot_params)
    for value, typ in ((math.nan, REAL32), (math.inf, REAL32), (0.5, 200), (-1e38, 0)):
        px4.core.on_param_value('COM_OF_LOSS_T', value, typ)
    px4.core.on_param_value(None, 1.0, REAL32)
    # (a value of an unknown type is taken as a float; a nonsense timeout then refuses)
    assert px4.core.autopilot_params['COM_OF_LOSS_T'] in (before['COM_OF_LOSS_T'], -1e38)
    assert not px4.core.request_offboard(px4.t)[0]
    px4.core.on_extended_sys_state(2)
    for bad in ((math.nan, 1.0, 0.0), (0.5, math.nan, 0.0), (0.5, 1.0, math.inf),
                (1.5, 1.0, 0.0), (-0.2, 1.0, 0.0)):
        px4.core.on_attitude_target(0.0, *bad)
    assert not px4.core.hover.valid and px4.core.hover._samples == []
