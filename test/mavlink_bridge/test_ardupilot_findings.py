"""The nine findings of the first test against ArduCopter 4.5.6 SITL (issue 17), one test each,
on the bridge's core, conversions and transport with the values ArduCopter really sends
(measured on ``../shared/ardupilot-sitl``: types and values of PARAM_VALUE, COMMAND_ACK
results, STATUSTEXT wording; the SITL tests repeat them against ArduCopter itself)."""

import itertools
import math
import os
import socket
import threading
import time

from mavlink_bridge.conversions import (
    ARDUCOPTER_MODES,
    ardupilot_mode_from_name,
    ardupilot_mode_name,
    distance_sensor_to_rep117,
)
from mavlink_bridge.core import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MSG_ID,
    BridgeCore,
    BridgeParams,
)
import pytest

STABILIZE, GUIDED, LOITER, LAND, GUIDED_NOGPS = 0, 4, 5, 9, 20
DISARMED, ARMED = 81, 209            # ArduCopter's base_mode (custom, stabilize, manual input)
ACCEPTED, DENIED, FAILED = 0, 2, 4
INT8, INT16, INT32, REAL32 = 2, 4, 6, 9
#: ArduCopter 4.5.6 SITL at boot (copter.parm), as PARAM_VALUE carries them: (value, type)
SITL_PARAMS = {'GUID_OPTIONS': (0.0, INT32), 'ATC_ANGLE_BOOST': (1.0, INT8),
               'GUID_TIMEOUT': (3.0, REAL32), 'MOT_THST_HOVER': (0.39, REAL32),
               'MOT_THST_EXPO': (0.65, REAL32), 'FS_GCS_ENABLE': (0.0, INT8),
               'SYSID_MYGCS': (255.0, INT16)}
#: the mission's set-up (deckland.sitl.ardupilot.MISSION_PARAMS)
MISSION = {'GUID_OPTIONS': (8.0, INT32), 'ATC_ANGLE_BOOST': (0.0, INT8),
           'GUID_TIMEOUT': (1.0, REAL32)}


class ArduPilot:
    """Feeds a core what ArduCopter 4.5.6 sends; 100 Hz setpoints while ``stream``."""

    def __init__(self, params=None, answered=None, mode=STABILIZE, base=DISARMED):
        """``answered``: parameters over the SITL boot values (None: the mission's set-up)."""
        self.core = BridgeCore(params or BridgeParams(autopilot='ardupilot'))
        self.t = 0.0
        self.hb = (mode, base)
        self.heartbeat(mode, base)
        table = dict(SITL_PARAMS)
        table.update(answered if answered is not None else MISSION)
        for name, (value, typ) in table.items():
            self.core.on_param_value(name, value, typ)

    def heartbeat(self, mode, base=None):
        self.hb = (mode, self.hb[1] if base is None else base)
        self.core.on_heartbeat(self.t, 1, 1, 2, 3, self.hb[1], mode)

    def run(self, seconds, stream=True, on_out=None):
        out = []
        end = self.t + seconds
        while self.t < end - 1e-9:
            if round(self.t * 100) % 100 == 0:
                self.heartbeat(*self.hb)
            if stream:
                self.core.on_attitude_command(self.t, self.t, (1.0, 0.0, 0.0, 0.0))
                self.core.on_thrust_command(self.t, self.t, 26.6)
            got = self.core.step(self.t)
            if on_out:
                on_out(got)
            out += got
            self.t = round(self.t + 0.01, 9)
        return out


def commands(out, cmd):
    return [o for o in out if o.kind == 'command' and o.command == cmd]


def intervals(out, msg_id):
    return [o for o in commands(out, MAV_CMD_SET_MESSAGE_INTERVAL) if o.params[0] == msg_id
            and o.params[1] > 0]


def answer_intervals(core, t, out, refuse=(MSG_ID['HIGHRES_IMU'],)):
    """ArduCopter answers every SET_MESSAGE_INTERVAL at once, in order: DENIED for an id it
    has no message for (HIGHRES_IMU)."""
    for o in commands(out, MAV_CMD_SET_MESSAGE_INTERVAL):
        core.on_command_ack(t, MAV_CMD_SET_MESSAGE_INTERVAL,
                            DENIED if int(o.params[0]) in refuse else ACCEPTED)


# --- 1. no HIGHRES_IMU: SCALED_IMU, driven by the ACK ---------------------------------------

def test_highres_imu_denied_falls_back_to_scaled_imu_without_a_request_storm():
    ap = ArduPilot()
    out = ap.run(60.0, stream=False, on_out=lambda got: answer_intervals(ap.core, ap.t, got))
    core = ap.core
    assert core.imu_msg == 'SCALED_IMU' and core.counters['imu_fallback'] == 1
    # HIGHRES_IMU asked once on this connection (each request is a STATUSTEXT "No
    # ap_message for mavlink id (105)" broadcast to every link); SCALED_IMU right after the
    # refusal and at every refresh (10 s) after that
    assert len(intervals(out, MSG_ID['HIGHRES_IMU'])) == 1
    scaled = intervals(out, MSG_ID['SCALED_IMU'])
    assert len(scaled) == 6 and scaled[0].params[1] == 1e4          # 100 Hz
    assert MSG_ID['SCALED_IMU'] in core.used_msg_ids()
    assert MSG_ID['HIGHRES_IMU'] not in core.used_msg_ids()
    assert 'SCALED_IMU' in core.last_result or core.last_result == ''
    # a reconnection (another or a rebooted autopilot) tries HIGHRES_IMU again, once
    ap.t += 5.0
    ap.heartbeat(STABILIZE, DISARMED)
    assert core.imu_msg == 'HIGHRES_IMU'


def test_use_highres_imu_false_streams_scaled_imu_from_the_start():
    ap = ArduPilot(BridgeParams(autopilot='ardupilot', use_highres_imu=False))
    out = ap.run(0.05, stream=False)
    assert intervals(out, MSG_ID['SCALED_IMU']) and not intervals(out, MSG_ID['HIGHRES_IMU'])
    from mavlink_bridge.node import PARAMS
    spec = {p.name: p for p in PARAMS}['use_highres_imu']
    assert spec.default is True


# --- 2. ATC_ANGLE_BOOST, not ANGLE_BOOST ----------------------------------------------------

def test_angle_boost_is_read_as_atc_angle_boost_and_a_default_of_1_refuses():
    ap = ArduPilot(answered={})                   # ArduCopter's boot values: boost on
    ap.core.on_param_value('GUID_OPTIONS', 8.0, INT32)
    ap.core.on_param_value('GUID_TIMEOUT', 1.0, REAL32)
    ok, why = ap.core.request_offboard(ap.t)
    assert not ok and 'ATC_ANGLE_BOOST = 1' in why
    # a fresh core: ATC_ANGLE_BOOST is requested, ANGLE_BOOST (never answered) is not; a
    # parameter that is never answered is asked at most param_max_requests times, and the
    # refusal says so
    core = BridgeCore(BridgeParams(autopilot='ardupilot'))
    core.on_heartbeat(0.0, 1, 1, 2, 3, DISARMED, STABILIZE)
    names = []
    for i in range(3000):
        t = i * 0.01
        if i % 100 == 0:
            core.on_heartbeat(t, 1, 1, 2, 3, DISARMED, STABILIZE)
        names += [o.param_id for o in core.step(t) if o.kind == 'param_request']
        if i == 0:
            core.on_param_value('GUID_OPTIONS', 8.0, INT32)
    assert 'ANGLE_BOOST' not in names and names.count('ATC_ANGLE_BOOST') == 5
    ok, why = core.request_offboard(30.0)
    assert not ok and 'ATC_ANGLE_BOOST not read yet (not answered after 5 requests)' in why


# --- 3. fail closed: bridge/offboard before GUID_OPTIONS is known -----------------------------

def test_offboard_before_guid_options_is_known_never_sends_do_set_mode():
    ap = ArduPilot(answered={}, mode=GUIDED, base=ARMED)
    core = ap.core
    core.autopilot_params.clear()
    ok, why = core.request_offboard(ap.t)
    assert not ok and 'GUID_OPTIONS not read yet' in why
    # known and safe: accepted; then the autopilot reports GUID_OPTIONS = 0 (a re-read, or a
    # late answer) before the warm-up is over: the DO_SET_MODE is never sent
    for name, (v, typ) in {**SITL_PARAMS, **MISSION}.items():
        core.on_param_value(name, v, typ)
    assert core.request_offboard(ap.t)[0]
    out = ap.run(0.1)
    core.on_param_value('GUID_OPTIONS', 0.0, INT32)
    out += ap.run(1.0)
    assert not commands(out, MAV_CMD_DO_SET_MODE)
    assert 'GUID_OPTIONS = 0' in core.last_result and 'cancelled' in core.last_result


# --- 4. the loss model: ArduPilot never lands by itself; the bridge commands LAND ---------------

def in_guided_nogps(params=None):
    ap = ArduPilot(params, mode=GUIDED, base=ARMED)
    assert ap.core.request_offboard(ap.t)[0]
    out = ap.run(0.5)
    (sent,) = commands(out, MAV_CMD_DO_SET_MODE)
    assert sent.params[:2] == (1.0, float(GUIDED_NOGPS))
    ap.core.on_command_ack(ap.t, MAV_CMD_DO_SET_MODE, ACCEPTED)
    ap.heartbeat(GUIDED_NOGPS)
    ap.run(1.0)
    assert ap.core.in_offboard()
    return ap


def test_setpoints_stopping_in_guided_nogps_make_the_bridge_command_land():
    ap = in_guided_nogps()
    t_stop = ap.core.setpoint_stats._last_s           # the last setpoint sent
    sent = []
    out = ap.run(2.0, stream=False, on_out=lambda got: sent.extend(
        (ap.t, o) for o in commands(got, MAV_CMD_DO_SET_MODE)))
    assert sent and sent[0][1].params[1] == float(LAND)
    after = ap.core.params.stop_after_s
    assert after < sent[0][0] - t_stop <= after + 0.011
    assert len(sent) == 4           # re-sent every 0.5 s until the heartbeat shows LAND
    assert 'control inputs stale' in ap.core.last_result
    ap.core.on_command_ack(ap.t, MAV_CMD_DO_SET_MODE, ACCEPTED)
    ap.heartbeat(LAND)
    assert not commands(ap.run(2.0, stream=False), MAV_CMD_DO_SET_MODE)
    assert ap.core.counters['stop_actions'] == 1 and 'LAND active' in ap.core.last_result
    assert not commands(out, MAV_CMD_COMPONENT_ARM_DISARM)


def test_stop_action_none_leaves_arducopter_in_guided_nogps_and_loiter_falls_back_to_land():
    ap = in_guided_nogps(BridgeParams(autopilot='ardupilot', ardupilot_stop_action='none'))
    assert not commands(ap.run(5.0, stream=False), MAV_CMD_DO_SET_MODE)
    ap = in_guided_nogps(BridgeParams(autopilot='ardupilot', ardupilot_stop_action='loiter'))
    out = ap.run(0.4, stream=False)
    assert commands(out, MAV_CMD_DO_SET_MODE)[0].params[1] == float(LOITER)
    ap.core.on_command_ack(ap.t, MAV_CMD_DO_SET_MODE, FAILED)     # no position estimate
    out = ap.run(0.1, stream=False)
    assert commands(out, MAV_CMD_DO_SET_MODE)[0].params[1] == float(LAND)


def test_an_operator_changing_the_mode_ends_the_stop_request():
    ap = in_guided_nogps()
    ap.run(0.4, stream=False)
    ap.heartbeat(LOITER)                      # the operator took over
    assert not commands(ap.run(2.0, stream=False), MAV_CMD_DO_SET_MODE)
    assert 'the mode is now LOITER' in ap.core.last_result


# --- 5. hover calibration from MOT_THST_HOVER -------------------------------------------------

def test_hover_thrust_comes_from_arducopter_not_the_configured_half():
    ap = ArduPilot(mode=GUIDED, base=ARMED)
    core = ap.core
    assert core.request_offboard(ap.t)[0]
    cal = core.thrust
    assert core.hover_source == 'MOT_THST_HOVER' and cal.hover_thrust_norm == pytest.approx(0.39)
    assert cal.to_norm(cal.mass_kg * cal.gravity_mps2) == pytest.approx(0.39)
    # ArduCopter's own hover (GUIDED after its take-off): ATTITUDE_TARGET 0.345 (measured)
    ap = ArduPilot(mode=GUIDED, base=ARMED)
    core = ap.core
    core.on_extended_sys_state(2)
    for i in range(60):
        core.on_attitude_target(ap.t + i * 0.1, 0.345 + 0.002 * math.sin(i), 1.0, 0.01)
    assert core.hover.valid
    assert core.request_offboard(ap.t)[0]
    assert core.thrust.hover_thrust_norm == pytest.approx(0.345, abs=0.002)
    assert 'measured' in core.hover_source
    # unknown: refused (fail closed), and re-read after each disarm (ArduCopter saves the
    # learned MOT_THST_HOVER then)
    fresh = ArduPilot()
    fresh.core.autopilot_params.pop('MOT_THST_HOVER')
    ok, why = fresh.core.request_offboard(0.0)
    assert not ok and 'MOT_THST_HOVER' in why
    ap.heartbeat(GUIDED, DISARMED)
    assert 'MOT_THST_HOVER' not in core.autopilot_params
    reqs = [o.param_id for o in ap.run(0.1, stream=False) if o.kind == 'param_request']
    assert 'MOT_THST_HOVER' in reqs


# --- 6. disarm after landing: FAILED while the land detector catches up -----------------------

def test_landed_disarm_commands_land_and_is_retried_while_arducopter_refuses():
    ap = in_guided_nogps()
    core = ap.core
    core.on_enabled(ap.t, False)             # the planner says landed
    sent = []

    def answer(got):
        for o in got:
            if o.kind == 'command':
                sent.append((ap.t, o.command, o.params[:2]))
                if o.command == MAV_CMD_COMPONENT_ARM_DISARM and ap.t < 12.0 + t0:
                    core.on_command_ack(ap.t, o.command, FAILED)   # the land detector
    t0 = ap.t
    ap.run(12.0, stream=False, on_out=answer)
    modes = [p for _, c, p in sent if c == MAV_CMD_DO_SET_MODE]
    disarms = [t for t, c, _ in sent if c == MAV_CMD_COMPONENT_ARM_DISARM]
    assert modes and modes[0] == (1.0, float(LAND))
    assert len(disarms) >= 10 and core._arm is not None        # still retried after 12 s
    assert all(b - a >= 0.99 for a, b in itertools.pairwise(disarms))
    assert core.counters['disarm_refused'] >= 10
    ap.heartbeat(LAND, DISARMED)              # LAND's land detector: ArduCopter disarms
    ap.run(0.1, stream=False)
    assert core._arm is None and core.last_result == 'disarmed'


def test_landed_flicker_during_arducopters_own_take_off_is_not_landed_by_the_bridge():
    """An operator's GUIDED take-off (deckland up --autopilot ardupilot-sitl): the planner's
    control/enabled follows the landed state, which flickers at lift-off (measured: True,
    False, True within 0.2 s). Not in GUIDED_NOGPS the vehicle is not ours: no LAND (the
    first mission on deckland's physics was landed at 1.08 m/s by it), no disarm."""
    ap = ArduPilot(mode=GUIDED, base=ARMED)
    core = ap.core
    ap.run(1.0, stream=False)
    for enabled in (True, False, True, False):
        core.on_enabled(ap.t, enabled)
    sent = []
    ap.run(3.0, stream=False, on_out=lambda got: sent.extend(
        o.command for o in got if o.kind == 'command'))
    assert MAV_CMD_DO_SET_MODE not in sent and MAV_CMD_COMPONENT_ARM_DISARM not in sent
    assert core._stop is None and core._arm is None


def test_no_setpoints_reach_arducopter_in_its_own_guided():
    """ArduCopter's GUIDED flies a SET_ATTITUDE_TARGET as an angle command (it overrides its
    own take-off: on deckland's physics the stack's thrust in GUIDED hopped the vehicle and
    touched down at 1.14 m/s). The bridge streams only in GUIDED_NOGPS or while it asks for
    it; PX4 ignores setpoints outside OFFBOARD, so it streams there as before."""
    ap = ArduPilot(mode=GUIDED, base=ARMED)
    core = ap.core
    core.on_enabled(ap.t, True)
    ap.run(1.0)
    assert core.counters['setpoints_sent'] == 0 and core.counters['not_guided_nogps'] >= 90
    assert core.request_offboard(ap.t)[0]                   # bridge/offboard: the entry
    ap.run(0.5)
    sent = core.counters['setpoints_sent']
    assert sent >= 45
    ap.heartbeat(GUIDED_NOGPS)
    ap.run(0.5)
    assert core.counters['setpoints_sent'] >= sent + 45


# --- 8. STATUSTEXT, mode table, range below RNGFND1_MIN_CM -----------------------------------

def test_statustext_is_kept_joined_and_repeats_are_not_logged_again():
    core = BridgeCore(BridgeParams(autopilot='ardupilot'))
    assert core.on_statustext(1.0, 4, 'No such mode 13') == 'No such mode 13'
    assert core.on_statustext(2.0, 4, 'No such mode 13') is None        # a repeat
    assert core.on_statustext(7.5, 4, 'No such mode 13') == 'No such mode 13'
    # MAVLink 2 chunks of 50 characters with one id (measured on AUTO_RTL's refusal)
    first = 'Mode change to AUTO RTL failed: No landing sequenc'
    assert core.on_statustext(8.0, 4, first, text_id=3, chunk_seq=0) is None
    assert core.on_statustext(8.0, 4, 'e found', text_id=3, chunk_seq=1) == (
        'Mode change to AUTO RTL failed: No landing sequence found')
    assert core.statustexts[-1][1:] == (4, 'Mode change to AUTO RTL failed: No landing '
                                           'sequence found')
    assert core.counters['statustext_rx'] == 4 and core.counters['statustext_repeats'] == 1


def test_arducopter_45_mode_table_has_turtle_and_no_sport():
    assert ardupilot_mode_name(28) == 'TURTLE' and ardupilot_mode_from_name('TURTLE') == 28
    assert ardupilot_mode_name(13) == 'UNKNOWN(13)' and 'SPORT' not in ARDUCOPTER_MODES.values()
    # the numbers ArduCopter 4.5.6 SITL accepts or refuses with a reason other than "No such
    # mode" (measured: 8, 10, 12, 13, 26, 29, 30 are "No such mode" in a copter build)
    assert set(ARDUCOPTER_MODES) - {26} == {0, 1, 2, 3, 4, 5, 6, 7, 9, 11, 14, 15, 16, 17, 18,
                                             19, 20, 21, 22, 23, 24, 25, 27, 28}


def test_range_below_rngfnd1_min_is_too_close_and_above_max_is_no_return():
    # ArduCopter's DISTANCE_SENSOR (RNGFND1_MIN_CM 20, MAX_CM 700): 0 on the ground, the raw
    # reading beyond the maximum (947 cm at 9.5 m, measured). (Already right since issue 14.)
    assert distance_sensor_to_rep117(0, 20, 700) == -math.inf
    assert distance_sensor_to_rep117(12, 20, 700) == -math.inf
    assert distance_sensor_to_rep117(947, 20, 700) == math.inf
    assert distance_sensor_to_rep117(285, 20, 700) == pytest.approx(2.85)


# --- 7. TCP link loss (the node's transport) -------------------------------------------------

class TcpAutopilot:
    """A TCP server on ``port`` that sends an ArduCopter heartbeat at 10 Hz to its client."""

    def __init__(self, port=0):
        from pymavlink.dialects.v20 import common as mavlink
        self.srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(('127.0.0.1', port))
        self.srv.listen(1)
        self.port = self.srv.getsockname()[1]
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.stop = False
        self.th = threading.Thread(target=self.run, daemon=True)
        self.th.start()

    def run(self):
        self.srv.settimeout(0.1)
        conn = None
        while not self.stop:
            if conn is None:
                try:
                    conn, _ = self.srv.accept()
                except TimeoutError:
                    continue
            msg = self.mav.heartbeat_encode(2, 3, DISARMED, STABILIZE, 3)
            try:
                conn.sendall(msg.pack(self.mav))
            except OSError:
                conn = None
            time.sleep(0.1)
        if conn is not None:
            conn.close()
        self.srv.close()

    def close(self):
        self.stop = True
        self.th.join(timeout=2.0)


def _cpu_s():
    t = os.times()
    return t.user + t.system


@pytest.mark.ros
def test_tcp_link_loss_no_busy_loop_no_log_storm_and_reconnect(ros_context, capfd):
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.parameter import Parameter

    context, executor = ros_context
    ap = TcpAutopilot()
    port = ap.port
    bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
        Parameter('connection', value=f'tcp:127.0.0.1:{port}'),
        Parameter('autopilot', value='ardupilot')])
    executor.add_node(bridge)

    def up():
        return bridge.core.link_up(time.monotonic())

    end = time.monotonic() + 5.0
    while not up() and time.monotonic() < end:
        time.sleep(0.05)
    assert up()
    ap.close()                                  # the peer goes away (ArduPilot killed)
    time.sleep(0.5)
    capfd.readouterr()
    c0, t0 = _cpu_s(), time.monotonic()
    time.sleep(3.0)
    cpu = (_cpu_s() - c0) / (time.monotonic() - t0)
    out = capfd.readouterr()
    lines = (out.out + out.err).count('\n')
    # before: the reader spun at 100 % of a core printing "EOF on TCP socket"
    print(f'bridge process CPU while the peer is gone: {cpu:.1%} of a core')
    assert cpu < 0.35, cpu
    assert 'EOF on TCP socket' not in out.out + out.err and lines < 20, lines
    # the peer comes back on the same port: the bridge reconnects and sees its heartbeat
    ap2 = TcpAutopilot(port)
    try:
        end = time.monotonic() + 8.0
        while time.monotonic() < end and bridge.conn.stats['connects'] < 2:
            time.sleep(0.05)
        assert bridge.conn.stats['connects'] == 2 and bridge.conn.stats['disconnects'] == 1
        end = time.monotonic() + 5.0
        while not up() and time.monotonic() < end:
            time.sleep(0.05)
        assert up()
    finally:
        ap2.close()


def test_map_anchor_puts_arducopters_gps_origin_where_it_lies_in_map():
    """ArduCopter's local origin is its first GPS fix (SET_GPS_GLOBAL_ORIGIN refused while
    EKF3 uses GPS, measured: "EKF3 refusing set origin"): with the map's geodetic anchor the
    bridge shifts LOCAL_POSITION_NED by the origin's place in map. 1e-5 deg of latitude is
    1.1132 m north; of longitude at 35.36 deg S, 1.1132 cos(35.36 deg) = 0.9077 m east."""
    from mavlink_bridge.conversions import origin_offset_enu, parse_llh
    anchor = parse_llh('-35.363261,149.165230,0')
    e, n, u = origin_offset_enu((-353632610 + 100, 1491652300 + 100, 150), anchor)
    assert n == pytest.approx(1.1132, abs=1e-4)
    assert e == pytest.approx(1.1132 * math.cos(math.radians(35.363251)), abs=1e-4)
    assert u == pytest.approx(0.15)
    # measured on deckland's physics: the vehicle resting at (-2.8, -0.3) m, origin set 20 s
    # after EKF3 started (its position drifted ~0.4 m in the mean time)
    e, n, u = origin_offset_enu((-353632615, 1491651949, 150), anchor)
    assert (e, n) == pytest.approx((-3.187, -0.056), abs=1e-3)
    assert parse_llh('') is None
    for bad in ('1,2', 'a,b,c', '95,0,0', '0,0,nan'):
        with pytest.raises(ValueError):
            parse_llh(bad)
