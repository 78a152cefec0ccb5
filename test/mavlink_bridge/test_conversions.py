"""mavlink_bridge.conversions and .core: frames, thrust calibration, wire encoding, decisions."""

import io
import itertools
import math
import random

from deckland_common.frames import euler_to_quaternion, rot_body_to_world
from hypothesis import given, settings
from hypothesis import strategies as st
from mavlink_bridge.conversions import (
    ThrustCalibration,
    attitude_target_type_mask,
    attitude_to_enu,
    decode_attitude_target,
    distance_sensor_to_range_m,
    do_set_mode_params,
    euler_enu_to_quat_ned,
    imu_frd_to_flu,
    landing_target_ardupilot,
    landing_target_px4,
    local_position_ned_to_enu,
    mode_name,
    param_value_to_wire,
    px4_custom_mode,
    px4_mode_name,
    quat_enu_flu_to_ned_frd,
    quat_mul,
    quat_ned_frd_to_enu_flu,
    quat_ned_to_euler_enu,
    range_m_to_distance_cm,
    set_attitude_target_fields,
)
from mavlink_bridge.core import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    BridgeCore,
    BridgeParams,
    StreamLimiter,
)
from pymavlink.dialects.v20 import common as mavlink
import pytest

angles = st.floats(-1.4, 1.4)
yaws = st.floats(-math.pi + 1e-3, math.pi - 1e-3)


def rotate(q, v):
    """Rotate vector v by unit quaternion q (w, x, y, z)."""
    r = quat_mul(quat_mul(q, (0.0, *v)), (q[0], -q[1], -q[2], -q[3]))
    return r[1:]


def same_rotation(a, b, tol=1e-9):
    return abs(abs(sum(x * y for x, y in zip(a, b, strict=True))) - 1.0) < tol


# --- frames ---------------------------------------------------------------------------------

def test_yaw_east_is_ned_half_pi_and_north_is_zero():
    q = euler_enu_to_quat_ned(0.0, 0.0, 0.0)            # nose east in ENU
    assert same_rotation(q, euler_to_quaternion(0.0, 0.0, math.pi / 2))
    assert quat_ned_to_euler_enu(q)[2] == pytest.approx(0.0, abs=1e-12)
    q = euler_enu_to_quat_ned(0.0, 0.0, math.pi / 2)    # nose north
    assert same_rotation(q, (1.0, 0.0, 0.0, 0.0))


def test_nose_down_pitch_is_positive_flu_negative_frd():
    # FLU pitch +0.3 puts the nose below the horizon: body x has a negative world-up part.
    nose_enu = [row[0] for row in rot_body_to_world(0.0, 0.3, 0.0)]
    assert nose_enu[2] < 0.0
    q = euler_enu_to_quat_ned(0.0, 0.3, 0.0)
    nose_ned = rotate(q, (1.0, 0.0, 0.0))               # FRD x = forward
    assert nose_ned[2] > 0.0                            # NED down is positive: nose down
    _roll, pitch, _yaw = quaternion_to_euler_ned(q)
    assert pitch == pytest.approx(-0.3)                 # FRD convention: nose down < 0


def quaternion_to_euler_ned(q):
    from deckland_common.frames import quaternion_to_euler
    return quaternion_to_euler(*q)


@settings(max_examples=200, deadline=None)
@given(angles, angles, yaws)
def test_quaternion_conversion_maps_the_same_physical_axes(roll, pitch, yaw):
    q_enu = euler_to_quaternion(roll, pitch, yaw)
    q_ned = quat_enu_flu_to_ned_frd(q_enu)
    # body z (up, FLU) in ENU must be the negative of body z (down, FRD) in NED, axes swapped.
    up_enu = rotate(q_enu, (0.0, 0.0, 1.0))
    down_ned = rotate(q_ned, (0.0, 0.0, 1.0))
    assert down_ned == pytest.approx((-up_enu[1], -up_enu[0], up_enu[2]), abs=1e-9)
    fwd_enu = rotate(q_enu, (1.0, 0.0, 0.0))
    fwd_ned = rotate(q_ned, (1.0, 0.0, 0.0))
    assert fwd_ned == pytest.approx((fwd_enu[1], fwd_enu[0], -fwd_enu[2]), abs=1e-9)
    # Euler route and quaternion route agree, and the round trip is the identity.
    assert same_rotation(q_ned, euler_enu_to_quat_ned(roll, pitch, yaw))
    assert same_rotation(quat_ned_frd_to_enu_flu(q_ned), q_enu)
    assert quat_ned_to_euler_enu(q_ned) == pytest.approx((roll, pitch, yaw), abs=1e-7)


def test_telemetry_vectors():
    pos, vel = local_position_ned_to_enu(1.0, 2.0, -3.0, 0.1, 0.2, 0.3)
    assert pos == (2.0, 1.0, 3.0) and vel == (0.2, 0.1, -0.3)
    (r, p, y), rates = attitude_to_enu(0.1, -0.2, 0.0, 0.01, 0.02, 0.03)
    assert (r, p, y) == pytest.approx((0.1, 0.2, math.pi / 2))
    assert rates == pytest.approx((0.01, -0.02, -0.03))
    acc, gyro = imu_frd_to_flu(0.0, 0.0, -9.81, 0.1, 0.2, 0.3)   # at rest, FRD reads −g
    assert acc == pytest.approx((0.0, 0.0, 9.81))                # REP-145: +g up in FLU
    assert gyro == pytest.approx((0.1, -0.2, -0.3))


def test_distance_sensor():
    assert distance_sensor_to_range_m(250, 5, 4000, 25) == pytest.approx(2.5)
    assert distance_sensor_to_range_m(250, 5, 4000, 0) is None      # forward-facing sensor
    assert distance_sensor_to_range_m(4001, 5, 4000, 25) is None    # ArduPilot: max + 1
    assert distance_sensor_to_range_m(0, 5, 4000, 25) is None
    assert distance_sensor_to_range_m(3, 5, 4000, 25) is None
    assert range_m_to_distance_cm(None, 4000) == 4001
    assert range_m_to_distance_cm(1.234, 4000) == 123


def test_modes():
    assert px4_custom_mode(6) == 6 << 16
    assert px4_mode_name(px4_custom_mode(6)) == 'OFFBOARD'
    assert px4_mode_name(px4_custom_mode(4, 6)) == 'AUTO.LAND'
    assert px4_mode_name(px4_custom_mode(3)) == 'POSCTL'
    assert mode_name('ardupilot', 20) == 'GUIDED_NOGPS'
    assert mode_name('ardupilot', 4) == 'GUIDED' and mode_name('ardupilot', 9) == 'LAND'
    assert do_set_mode_params('px4', 'OFFBOARD') == (1.0, 6.0, 0.0)
    assert do_set_mode_params('px4', 'AUTO.LAND') == (1.0, 4.0, 6.0)
    assert do_set_mode_params('ardupilot', 'GUIDED_NOGPS') == (1.0, 20.0, 0.0)
    with pytest.raises(ValueError):
        do_set_mode_params('px4', 'NOPE')


def test_landing_target_builders():
    f = landing_target_px4(5, (10.0, 20.0, 1.5))
    assert (f['x'], f['y'], f['z'], f['frame'], f['position_valid']) == (20.0, 10.0, -1.5, 1, 1)
    # target 1 m ahead and 2 m below: FRD (1, 0, 2); image top toward the nose → angle_y < 0
    f = landing_target_ardupilot(5, (1.0, 0.0, -2.0))
    assert f['frame'] == 12
    assert f['angle_x'] == pytest.approx(0.0)
    assert f['angle_y'] == pytest.approx(-math.atan(0.5))
    assert f['distance'] == pytest.approx(math.sqrt(5.0))


# --- thrust calibration -----------------------------------------------------------------------

@pytest.mark.parametrize('expo', [0.0, 0.3, 0.65, 1.0])
def test_hover_maps_to_hover_norm_and_inverse(expo):
    cal = ThrustCalibration(mass_kg=2.71, hover_thrust_norm=0.42, expo=expo)
    assert cal.to_norm(2.71 * 9.81) == pytest.approx(0.42)
    assert cal.to_newtons(0.42) == pytest.approx(2.71 * 9.81)
    assert cal.to_newtons(1.0) == pytest.approx(cal.max_thrust_n)
    rng = random.Random(3)
    for _ in range(200):
        n = rng.uniform(0.0, 1.0)
        assert cal.to_norm(cal.to_newtons(n)) == pytest.approx(n, abs=1e-9)


def test_thrust_monotonic_clamped_and_nan_safe():
    cal = ThrustCalibration(expo=0.65)
    xs = [cal.to_norm(f) for f in (0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0)]
    assert all(b > a for a, b in itertools.pairwise(xs))
    assert cal.to_norm(-5.0) == 0.0
    assert cal.to_norm(1e6) == 1.0
    assert cal.to_norm(math.nan) == 0.0
    # quadratic part: half the command gives less than half the thrust when e > 0
    assert cal.to_newtons(0.5) < 0.5 * cal.max_thrust_n
    lin = ThrustCalibration(expo=0.0, hover_thrust_norm=0.5)
    assert lin.max_thrust_n == pytest.approx(2 * 2.71 * 9.81)


def test_thrust_from_max_thrust_and_validation():
    cal = ThrustCalibration.from_max_thrust(60.0, 0.5)
    assert cal.max_thrust_n == pytest.approx(60.0)
    assert cal.to_newtons(cal.hover_thrust_norm) == pytest.approx(2.71 * 9.81)
    with pytest.raises(ValueError, match='expo'):
        ThrustCalibration(expo=1.5)
    with pytest.raises(ValueError, match='hover_thrust_norm'):
        ThrustCalibration(hover_thrust_norm=1.0)
    with pytest.raises(ValueError, match='mass_kg'):
        ThrustCalibration(mass_kg=math.nan)
    with pytest.raises(ValueError, match='max_thrust_n'):
        ThrustCalibration.from_max_thrust(10.0, 0.5)


def test_type_mask_bits():
    assert attitude_target_type_mask() == 7
    assert attitude_target_type_mask(ignore_body_rates=False) == 0
    assert attitude_target_type_mask(ignore_thrust=True) == 7 | 64
    assert attitude_target_type_mask(False, False, True) == 128


# --- encode / decode through an in-memory buffer ----------------------------------------------

def test_set_attitude_target_wire_round_trip():
    buf = io.BytesIO()
    tx = mavlink.MAVLink(buf, srcSystem=1, srcComponent=191)
    cal = ThrustCalibration(hover_thrust_norm=0.45, expo=0.3)
    fields = set_attitude_target_fields(0.1, 0.2, 1.0, 30.0, cal, target_system=7,
                                        target_component=1, time_boot_ms=1234)
    tx.set_attitude_target_send(**fields)
    data = buf.getvalue()
    assert data[0] == 0xFD  # MAVLink 2 frame
    rx = mavlink.MAVLink(None)
    msgs = rx.parse_buffer(data)
    assert len(msgs) == 1
    m = msgs[0]
    assert m.get_type() == 'SET_ATTITUDE_TARGET'
    assert (m.target_system, m.target_component, m.type_mask, m.time_boot_ms) == (7, 1, 7, 1234)
    assert m.get_srcComponent() == 191
    assert m.thrust == pytest.approx(cal.to_norm(30.0), abs=1e-6)
    tgt = decode_attitude_target(tuple(m.q), m.thrust, m.type_mask, cal)
    assert (tgt.roll_rad, tgt.pitch_rad, tgt.yaw_rad) == pytest.approx((0.1, 0.2, 1.0), abs=1e-6)
    assert tgt.thrust_n == pytest.approx(30.0, abs=1e-4)
    assert decode_attitude_target((math.nan, 0, 0, 0), 0.5, 7, cal) is None
    assert decode_attitude_target((0, 0, 0, 0), 0.5, 7, cal) is None


# --- core ------------------------------------------------------------------------------------

def link_core(params=None, t=0.0, px4_params=True):
    """A core linked to a PX4 (heartbeat) that has read a safe PX4 set-up: COM_OBL_RC_ACT = 4
    (Land, INT32 sent bytewise as PX4 does), COM_OF_LOSS_T = 1 s, MPC_THR_HOVER = 0.5."""
    core = BridgeCore(params or BridgeParams())
    assert core.on_heartbeat(t, 1, 1, 2, 12, 0, px4_custom_mode(3))
    if px4_params and core.params.autopilot == 'px4':
        core.on_param_value('COM_OBL_RC_ACT', param_value_to_wire(4, 6, True), 6)
        core.on_param_value('COM_OF_LOSS_T', 1.0, 9)
        core.on_param_value('MPC_THR_HOVER', 0.5, 9)
    return core


def q_of(r, p, y):
    return euler_to_quaternion(r, p, y)


def test_core_needs_link_and_fresh_attitude():
    core = BridgeCore()
    assert core.on_thrust_command(0.0, 0.0, 20.0) is None          # no heartbeat yet
    assert core.counters['no_link'] == 1
    core.on_heartbeat(0.0, 1, 1, 2, 12, 0, 0)
    assert core.on_thrust_command(0.01, 0.01, 20.0) is None        # no attitude yet
    core.on_attitude_command(0.02, 0.02, q_of(0.1, 0.2, 0.3))
    sp = core.on_thrust_command(0.03, 0.03, 20.0)
    assert sp is not None and sp.type_mask == 7
    assert sp.thrust_norm == pytest.approx(core.params.thrust.to_norm(20.0))
    assert quat_ned_to_euler_enu(sp.q_ned_frd) == pytest.approx((0.1, 0.2, 0.3))
    # attitude 0.21 s old (> input_timeout_s 0.2): stop, never reuse the old attitude
    assert core.on_thrust_command(0.02 + 0.21, 0.24, 20.0) is None
    assert core.counters['stale_attitude'] == 2   # (the first: no attitude at all)
    # link lost after 3 s without heartbeat
    core.on_attitude_command(3.5, 3.5, q_of(0, 0, 0))
    assert core.on_thrust_command(3.51, 3.51, 20.0) is None


def test_core_rejects_bad_input_and_keeps_state():
    core = link_core()
    core.on_attitude_command(0.0, 1.0, q_of(0.1, 0.0, 0.0))
    assert not core.on_attitude_command(0.01, 0.5, q_of(0.3, 0.0, 0.0))   # out of order
    assert not core.on_attitude_command(0.01, 1.1, (math.nan, 0.0, 0.0, 0.0))
    assert not core.on_attitude_command(0.01, 1.1, (0.0, 0.0, 0.0, 0.0))
    assert core.on_thrust_command(0.02, 1.0, math.inf) is None
    sp = core.on_thrust_command(0.02, 1.0, 20.0)
    assert quat_ned_to_euler_enu(sp.q_ned_frd)[0] == pytest.approx(0.1)
    assert core.on_thrust_command(0.05, 0.9, 20.0) is None                # out of order
    assert core.rejected['out_of_order'] == 2
    assert core.rejected['nan'] == 2 and core.rejected['bad_quaternion'] == 1
    assert core.step(math.nan) == []


def _stream(core, events):
    """Feed (receive time, source stamp) thrust commands; return the receive times sent."""
    sent = []
    for t, stamp in events:
        core.on_attitude_command(t, stamp, q_of(0, 0, 0))
        if core.on_thrust_command(t, stamp, 20.0) is not None:
            sent.append(t)
    return sent


def test_limiter_caps_a_flood_at_max_stream_rate():
    # 1 kHz of commands for 1 s, each only 1 ms newer than the previous: the bucket holds the
    # long-term rate to max_stream_rate_hz (+ the initial burst), and once it is empty the
    # sends are exactly 1/rate apart
    core = link_core(BridgeParams(max_stream_rate_hz=250.0, stream_burst=3))
    sent = _stream(core, [(i * 1e-3, i * 1e-3) for i in range(1000)])
    assert 250 <= len(sent) <= 250 + 3
    steady = [b - a for a, b in itertools.pairwise(sent[10:])]
    assert min(steady) >= 0.004 - 1e-9 and max(steady) <= 0.004 + 1e-3 + 1e-9
    assert core.counters['rate_limited'] == 1000 - len(sent)


def test_imu_and_camera_commands_of_one_instant_both_go_out():
    # The control clock: a command per 100 Hz IMU state; every second tick a camera frame of
    # the same instant produces a second state (and command) 1 ms later, with a stamp only
    # 1 ms newer. Both must go out at once (the camera one carries the new image).
    events = []
    for k in range(250):
        t = 0.1 + k * 0.01
        events.append((t, t))
        if k % 2 == 0:
            events.append((t + 0.001, t + 0.001))
    core = link_core(BridgeParams(max_stream_rate_hz=250.0, stream_burst=3))
    assert len(_stream(core, events)) == len(events)             # 150 Hz < 250 Hz: nothing
    assert core.counters['rate_limited'] == 0
    # a plain minimum interval (burst 1) drops exactly those camera commands (why the
    # default is a bucket); the old 0.9 / 100 Hz interval dropped them too
    plain = link_core(BridgeParams(max_stream_rate_hz=250.0, stream_burst=1))
    assert len(_stream(plain, events)) == 250
    assert plain.counters['rate_limited'] == 125


def test_fresh_data_is_never_rate_limited():
    # A cap far below the input rate (10 Hz, burst 1): commands whose source stamp is one
    # camera period (20 ms) newer than the last one sent still go out, the rest are thinned.
    p = BridgeParams(max_stream_rate_hz=10.0, stream_burst=1, fresh_period_s=0.02)
    core = link_core(p)
    events = [(0.1 + i * 0.005, 0.1 + i * 0.005) for i in range(400)]    # 200 Hz for 2 s
    sent = _stream(core, events)
    gaps = [b - a for a, b in itertools.pairwise(sent)]
    assert max(gaps) <= p.fresh_period_s + 1e-9                         # never starved
    assert min(gaps) >= p.fresh_period_s - 1e-9                         # but thinned
    assert len(sent) == 100                                             # 50 Hz, not 10 Hz
    # stale inputs still cut the stream, whatever the limiter says
    core.on_attitude_command(2.2, 2.2, q_of(0, 0, 0))
    assert core.on_thrust_command(2.2 + p.input_timeout_s + 0.01, 2.5, 20.0) is None
    assert core.counters['stale_attitude'] == 1


def test_limiter_refill_ignores_receive_time_going_backwards():
    lim = StreamLimiter(250.0, 1, 0.02)
    assert lim.allow(1.0, 1.0)
    assert not lim.allow(0.5, 1.001)       # no refill from a backwards receive time
    assert not lim.allow(1.001, 1.002)
    assert lim.allow(1.004, 1.003)         # 4 ms later: one token again


@pytest.mark.parametrize('field, value', [('stream_burst', 0), ('stream_burst', True),
                                          ('stream_burst', 2.5), ('max_stream_rate_hz', 0.0),
                                          ('fresh_period_s', math.nan),
                                          ('fresh_period_s', 0.6)])
def test_stream_parameters_are_validated(field, value):
    with pytest.raises(ValueError, match=field):
        BridgeParams(**{field: value})


def test_core_offboard_waits_for_warm_stream_then_retries_until_heartbeat():
    core = link_core()
    ok, _ = core.request_offboard(0.0)
    assert ok
    modes_sent = []
    t = 0.0
    while t < 2.0:
        core.on_heartbeat(t, 1, 1, 2, 12, 0, px4_custom_mode(3))
        core.on_attitude_command(t, t, q_of(0, 0, 0))
        core.on_thrust_command(t, t, 20.0)
        modes_sent += [(t, o) for o in core.step(t) if o.command == MAV_CMD_DO_SET_MODE]
        t += 0.01
    assert modes_sent, 'OFFBOARD never requested'
    first = modes_sent[0][0]
    # only while streaming, after offboard_warmup_s (PX4 v1.16 itself needs one setpoint
    # younger than COM_OF_LOSS_T, not "> 1 s of setpoints")
    assert core.params.offboard_warmup_s - 1e-9 <= first < 0.5
    assert modes_sent[0][1].params[:3] == (1.0, 6.0, 0.0)
    assert len(modes_sent) >= 2                              # retried (no ACK, no mode change)
    core.on_heartbeat(t, 1, 1, 2, 12, 128, px4_custom_mode(6))      # armed, OFFBOARD
    core.step(t)
    assert core.last_result == 'OFFBOARD active' and not core.pending()['offboard']


def test_core_offboard_never_sent_when_inputs_go_stale():
    core = link_core()
    core.request_offboard(0.0)
    t, sent = 0.0, 0
    while t < 0.15:                              # a stream shorter than the warm-up, then
        core.on_attitude_command(t, t, q_of(0, 0, 0))
        core.on_thrust_command(t, t, 20.0)
        sent += sum(o.command == MAV_CMD_DO_SET_MODE for o in core.step(t))
        t += 0.01
    while t < 2.5:
        core.on_heartbeat(t, 1, 1, 2, 12, 0, px4_custom_mode(3))
        sent += sum(o.command == MAV_CMD_DO_SET_MODE for o in core.step(t))
        t += 0.01
    assert sent == 0 and not core.streaming(t)


def test_core_ack_denied_cancels_and_enabled_false_disarms():
    core = link_core()
    core.request_arm(0.0, True)
    out = core.step(0.0)
    arm = [o for o in out if o.command == MAV_CMD_COMPONENT_ARM_DISARM]
    assert arm and arm[0].params[0] == 1.0
    assert sum(o.command == MAV_CMD_SET_MESSAGE_INTERVAL for o in out) == 6
    core.on_command_ack(0.1, MAV_CMD_COMPONENT_ARM_DISARM, 4)   # FAILED
    assert core.pending()['arm'] is None and 'refused' in core.last_result
    core.on_heartbeat(0.2, 1, 1, 2, 12, 128, px4_custom_mode(6))  # armed in OFFBOARD
    assert core.armed
    core.on_attitude_command(0.3, 0.3, q_of(0, 0, 0))
    core.on_enabled(0.3, False)
    assert core.on_thrust_command(0.31, 0.31, 20.0) is None       # stream stops
    out = core.step(1.0)
    disarm = [o for o in out if o.command == MAV_CMD_COMPONENT_ARM_DISARM]
    assert disarm and disarm[0].params[0] == 0.0
    assert not core.request_offboard(1.0)[0]


def test_core_ignores_gcs_and_other_systems():
    core = BridgeCore()
    assert not core.on_heartbeat(0.0, 255, 190, 6, 8, 0, 0)           # a GCS
    assert core.on_heartbeat(0.0, 1, 1, 2, 12, 0, 0)
    assert not core.on_heartbeat(0.1, 2, 1, 2, 12, 128, 0)            # another vehicle
    assert not core.armed and core.rejected['other_system'] == 1


def test_core_ardupilot_checks_guid_options():
    core = link_core(BridgeParams(autopilot='ardupilot'))
    reqs = [o.param_id for o in core.step(0.0) if o.kind == 'param_request']
    # ArduCopter 4.5 calls the tilt boost ATC_ANGLE_BOOST (ANGLE_BOOST is never answered)
    assert reqs[:4] == ['GUID_OPTIONS', 'ATC_ANGLE_BOOST', 'GUID_TIMEOUT', 'MOT_THST_HOVER']
    core.on_param_value('GUID_OPTIONS', 0.0, 6)
    core.on_param_value('ATC_ANGLE_BOOST', 0.0, 2)
    core.on_param_value('GUID_TIMEOUT', 1.0, 9)
    core.on_param_value('MOT_THST_HOVER', 0.35, 9)
    ok, msg = core.request_offboard(0.1)
    assert not ok and 'GUID_OPTIONS' in msg
    core.on_param_value('GUID_OPTIONS', 8.0, 6)
    ok, msg = core.request_offboard(0.1)
    assert ok and 'GUIDED_NOGPS' in msg


def test_params_validation():
    with pytest.raises(ValueError, match='offboard_warmup_s'):
        BridgeParams(offboard_warmup_s=-0.1)
    with pytest.raises(ValueError, match='offboard_loss_actions'):
        BridgeParams(offboard_loss_actions=('land', 'loiter'))
    with pytest.raises(ValueError, match='hover_thrust_source'):
        BridgeParams(hover_thrust_source='guess')
    with pytest.raises(ValueError, match='autopilot'):
        BridgeParams(autopilot='inav')
    with pytest.raises(ValueError, match='input_timeout_s'):
        BridgeParams(input_timeout_s=math.nan)


