"""deck_simulator node, ROS-free part: SimulationLoop + the emulated autopilot over a memory link.

The emulated autopilot is driven the way mavlink_bridge drives PX4 (MAVLink bytes on a
MemoryLink); the Pixy bytes are parsed with pixy_driver's parser. Assertions are physics
(hover, Δv = (T − m g)/m · Δt, land speed, image centre under a down-looking camera) and the
campaign's outcome semantics.
"""

import dataclasses
import json
import math
import random

from deck_simulator.autopilot import AutopilotParams, EmulatedAutopilot
from deck_simulator.loop import TickSchedule, body_rates
from deck_simulator.outcome import RunOutcome, outcome_json
from deck_simulator.scenario import load_scenario
from deck_simulator.transport import parse_mavlink_url
from deckland.batch.runner import RunResult
from deckland_common.frames import rot_body_to_world
from pixy_driver.protocol import PixyParser
from pymavlink.dialects.v20 import common as mavlink
import pytest
from simloop_rig import G, M, Rig, calm


def test_parse_mavlink_url_pairs_with_pymavlink_syntax():
    assert parse_mavlink_url('udpout:127.0.0.1:14540') == ('out', '127.0.0.1', 14540)
    assert parse_mavlink_url('udpin:0.0.0.0:14550') == ('in', '0.0.0.0', 14550)
    assert parse_mavlink_url('udp:localhost:0') == ('in', '127.0.0.1', 0)
    for bad in ('tcp:127.0.0.1:5760', 'udpout:127.0.0.1:0', 'udpin:127.0.0.1:70000',
                'udpout:example.com:14540', '/dev/ttyACM0', ''):
        with pytest.raises(ValueError):
            parse_mavlink_url(bad)


def test_body_rates_match_rotation_derivative():
    """ω× = Rᵀ Ṙ for R = Rz(ψ)Ry(θ)Rx(φ) (frames.py) — checked by finite differences."""
    rng = random.Random(4)
    for _ in range(20):
        e = [rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-3.0, 3.0)]
        de = [rng.uniform(-1.0, 1.0) for _ in range(3)]
        h = 1e-6
        r0 = rot_body_to_world(*e)
        r1 = rot_body_to_world(*(a + h * b for a, b in zip(e, de, strict=True)))
        rd = [[(r1[i][j] - r0[i][j]) / h for j in range(3)] for i in range(3)]
        w = [[sum(r0[k][i] * rd[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        p, q, r = body_rates(e[0], e[1], *de)
        assert (w[2][1], w[0][2], w[1][0]) == pytest.approx((p, q, r), abs=1e-4)


def test_holds_start_hover_without_offboard_in_gusts():
    """Before OFFBOARD the autopilot emulation holds the (randomised) start of `paper`
    (0.5 m/s wind, 0.3 m/s gusts): truth within 0.3 m for 20 s, level, nothing rejected."""
    rig = Rig(load_scenario('paper'), seed=7)
    p0 = rig.truth().position_m
    worst = 0.0
    for _ in range(100):
        rig.run(0.2)
        worst = max(worst, math.dist(rig.truth().position_m, p0))
    tr = rig.truth()
    assert worst < 0.3
    assert abs(tr.roll_rad) < 0.1 and abs(tr.pitch_rad) < 0.1
    assert rig.sim.last_kind == 'hold' and rig.emu.armed and rig.emu.mode == 'POSCTL'
    assert rig.sim.counters['autopilot_steps'] == pytest.approx(2000, abs=2)
    assert rig.sim.world.contact is None and rig.outcomes == []
    assert sum(rig.emu.rejected.values()) == 0 and sum(rig.sim.world.rejected.values()) == 0


def test_telemetry_streams_like_px4():
    rig = Rig()
    rig.run(2.0)
    msgs = rig.received()
    by = {}
    for m in msgs:
        by.setdefault(m.get_type(), []).append(m)
    hb = by['HEARTBEAT'][-1]
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert (hb.custom_mode >> 16) & 0xFF == 3                       # POSCTL
    assert 95 <= len(by['ATTITUDE']) <= 105                         # 50 Hz default for 2 s
    tr = rig.truth()
    lp = by['LOCAL_POSITION_NED'][-1]                               # NED = (y, x, -z) ENU
    pos, _ = rig.sim.world.read_local_position()                   # the EKF's, delivered
    assert (lp.x, lp.y, lp.z) == pytest.approx((pos[1], pos[0], -pos[2]), abs=0.05)
    ds = by['DISTANCE_SENSOR'][-1]
    assert ds.orientation == 25 and abs(ds.current_distance - 100 * tr.position_m[2]) <= 10
    # FRD specific force in hover: the IMU model's (vibration σ 0.35 m/s² per sample), averaged
    imus = by['HIGHRES_IMU']
    n = len(imus)
    assert n > 50
    assert sum(m.zacc for m in imus) / n == pytest.approx(-G, abs=0.15)
    assert abs(sum(m.xacc for m in imus) / n) < 0.15 and abs(sum(m.yacc for m in imus) / n) < 0.15
    ess = by['EXTENDED_SYS_STATE'][-1]
    assert ess.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR


def test_pixy_datagrams_show_the_beacon_below_at_the_image_centre():
    """Hovering over the pad centre, the beacon projects to the principal point (160, 100)
    with blob size fx·0.08 m / depth, fx = 160 / tan 30°; one datagram per 20 ms frame."""
    rig = Rig(calm(start_position_m=[-3.2, -2.0, 2.0]))
    rig.run(2.0)
    assert len(rig.frames) == pytest.approx(100, abs=1)
    parser = PixyParser()
    frames = []
    for datagram in rig.frames:
        got = parser.feed_datagram(datagram)
        assert len(got) == 1
        frames.append(got[0])
    seen = [f.blocks[0] for f in frames if f.blocks]
    assert len(seen) >= 90                                          # 2 % dropout
    depth = rig.truth().position_m[2] - 0.60
    w_expected = (160 / math.tan(math.radians(30))) * 0.08 / depth
    for b in seen[-20:]:
        assert abs(b.x_px - 160) <= 4 and abs(b.y_px - 100) <= 4
        assert abs(b.width_px - w_expected) <= 1.5
    assert parser.checksum_errors == 0


def test_offboard_setpoints_fly_the_vehicle_then_failsafe_lands_straight_down():
    rig = Rig()
    hover = (0.0, 0.0, 0.0, M * G)
    rig.run(1.3, setpoint=hover)                                    # warm-up > 1 s at 50 Hz
    rig.set_mode(6)
    rig.run(0.2, setpoint=hover)
    assert rig.emu.mode == 'OFFBOARD' and rig.sim.last_kind == 'offboard'
    # (3) with γ ≈ 1: thrust 1.2 m g level → z̈ = +0.2 g, then 0.8 m g → −0.2 g
    v0 = rig.truth().velocity_mps[2]
    rig.run(0.5, setpoint=(0.0, 0.0, 0.0, 1.2 * M * G))
    dv = rig.truth().velocity_mps[2] - v0
    assert 0.2 * G * 0.5 * 0.8 < dv < 0.2 * G * 0.5 * 1.05          # motor lag 40 ms
    rig.run(0.5, setpoint=(0.0, 0.0, 0.0, 0.8 * M * G))
    assert abs(rig.truth().velocity_mps[2] - v0) < 0.15
    rig.run(0.2, setpoint=hover)
    # setpoints stop: after COM_OF_LOSS_T = 1 s the emulator lands (failsafe)
    xy0 = rig.truth().position_m[:2]
    rig.run(1.1)
    assert rig.emu.failsafe_active and rig.sim.last_kind == 'failsafe_land'
    rig.run(1.5)
    assert rig.truth().velocity_mps[2] == pytest.approx(-0.7, abs=0.12)   # MPC_LAND_SPEED
    for _ in range(60):
        rig.run(0.1)
        if rig.outcomes:
            break
    assert len(rig.outcomes) == 1
    out = rig.outcomes[0]
    c = rig.sim.world.contact
    assert c.kind == 'ground' and math.dist(c.position_m[:2], xy0) < 0.3
    assert out['contact_kind'] == 'ground' and out['fallback'] and not out['success']
    assert not out['crash'] and out['touchdown_speed_mps'] == pytest.approx(0.7, abs=0.15)
    assert out['time_to_land_s'] is None                            # no landing trigger seen
    # land detector → auto-disarm after 2 s → motors idle; the outcome is not repeated
    rig.run(3.0)
    assert not rig.emu.armed and rig.sim.last_kind == 'idle' and len(rig.outcomes) == 1


def test_scenario_return_failsafe_flies_home_climbs_and_lands_there():
    """A scenario whose command-path fault says `action: return` configures the emulated PX4
    (COM_OF_LOSS_T = its loss_timeout_s, COM_OBL_RC_ACT = Return): when the setpoints stop it
    switches to AUTO.RTL, climbs to min_alt_m, flies back to where OFFBOARD was engaged at no
    more than return_speed_mps, and lands there (a deliberate fallback, no crash) — the graph's
    counterpart of the in-process World's 'return' failsafe."""
    fault = {'type': 'node_kill', 'node': 'dob_altitude', 'start_s': 100.0, 'action': 'return',
             'loss_timeout_s': 0.3, 'min_alt_m': 2.5, 'return_speed_mps': 1.0}
    rig = Rig(calm(faults=[fault]))
    assert rig.sim.autopilot.params.offboard_loss_action == 'return'
    assert rig.sim.autopilot.params.offboard_loss_timeout_s == 0.3
    hover = (0.0, 0.0, 0.0, M * G)
    rig.run(1.3, setpoint=hover)
    rig.set_mode(6)
    rig.run(0.2, setpoint=hover)
    assert rig.emu.mode == 'OFFBOARD'
    home = rig.emu.home_m     # the position PX4 reported (GPS: noise) at the switch
    assert math.dist(home, rig.truth().position_m[:2]) < 0.3
    # fly away: nose down 8° east (yaw 0 = east) for 2 s, then level
    tilt = math.radians(8.0)
    rig.run(2.0, setpoint=(0.0, tilt, 0.0, M * G / math.cos(tilt)))
    rig.run(0.5, setpoint=hover)
    away = rig.truth().position_m
    assert math.dist(away[:2], home) > 1.5
    rig.run(0.4)                                     # > 0.3 s without setpoints
    assert rig.emu.mode == 'AUTO.RTL' and rig.emu.failsafe_active
    assert rig.sim.last_kind == 'failsafe_return'
    z_max, speeds = 0.0, []
    for _ in range(300):
        rig.run(0.1)
        tr = rig.truth()
        z_max = max(z_max, tr.position_m[2])
        speeds.append(math.hypot(*tr.velocity_mps[:2]))
        if rig.outcomes:
            break
    assert z_max > 2.4                               # climbed to the return altitude first
    # once braked (the first 2 s: it was flying away at ~2 m/s), the way back is flown at
    # the return speed (+ the PD's overshoot)
    assert max(speeds[20:]) < 1.0 * 1.3
    (out,) = rig.outcomes
    c = rig.sim.world.contact
    assert c.kind == 'ground' and math.dist(c.position_m[:2], home) < 0.5
    assert out['fallback'] and not out['crash'] and not out['success']
    # the record names the mode PX4's heartbeat showed to the end (RTL lands as AUTO.RTL),
    # not the final descent's flight law: `deckland up` reports it when the bridge is gone
    assert out['failsafe_mode'] == 'return'


def test_outcome_on_the_pad_counts_trigger_and_searches():
    """AUTO.LAND over the pad centre: 'pad' contact, success, and time_to_land_s measured from
    the first planner mode outside IDLE/HOLD/TAKEOFF; SEARCH entries counted."""
    rig = Rig(calm(start_position_m=[-3.2, -2.0, 2.0]))
    rig.sim.on_planner_mode('IDLE')
    rig.run(0.5)
    rig.sim.on_planner_mode('TAKEOFF')
    rig.sim.on_planner_mode('HOLD')
    rig.run(0.5)
    rig.sim.on_planner_mode('APPROACH')
    t_trigger = rig.sim.world.t_s
    for mode in ('SEARCH', 'SEARCH', 'ALIGN', 'SEARCH', 'DESCEND', 'bogus'):
        rig.sim.on_planner_mode(mode)
    rig.sim.on_planner_mode('')
    rig.sim.on_planner_mode(None)
    assert rig.sim.rejected['bad_mode'] == 2
    rig.set_mode(4, 6)                                               # AUTO.LAND
    for _ in range(60):
        rig.run(0.1)
        if rig.outcomes:
            break
    out = json.loads(outcome_json(rig.outcomes[0]))
    c = rig.sim.world.contact
    assert out['contact_kind'] == 'pad' and out['landed_on_deck'] and out['success']
    assert out['time_to_land_s'] == pytest.approx(c.t_s - t_trigger, abs=1e-9)
    assert out['time_to_land_s'] > 1.0                             # 1.4 m at 0.7 m/s
    assert out['searches'] == 2 and out['final_mode'] == 'BOGUS'
    assert out['max_thrust_n'] >= M * G * 0.99
    assert out['horizontal_error_m'] < 0.1 and out['seed'] == 1
    assert out['scenario'] == 'calm_test'
    # one outcome record: the runner's RunResult fields minus what only the runner knows
    assert set(out) == {f.name for f in dataclasses.fields(RunOutcome)}
    assert set(out) == set(RunResult(seed=1, scenario='s').summary()) - {
        'controller', 'link_degraded_s', 'link_latency_s'}
    assert out['outcome'] == 'deck' and out['failsafes'] == 0 and out['failsafe_mode'] == ''


def test_timeout_outcome_counts_from_the_trigger():
    rig = Rig(calm(timeout_s=1.0))
    rig.run(0.6)
    rig.sim.on_planner_mode('APPROACH')                             # deadline 0.6 + 1.0 s
    rig.run(0.9)
    assert rig.outcomes == []
    rig.run(0.2)
    assert len(rig.outcomes) == 1
    out = rig.outcomes[0]
    assert out['reason'] == 'timeout' and not out['success'] and out['contact_kind'] == 'none'
    assert out['detail'] == 'no touchdown within 1 s of the landing trigger'
    assert out['outcome'] == 'hold'                  # hovering at the timeout, not a failure
    assert out['sim_time_s'] == pytest.approx(1.6, abs=0.01)
    assert out['horizontal_error_m'] is None and out['time_to_land_s'] is None
    rig.run(1.0)
    assert len(rig.outcomes) == 1
    # strict JSON (no NaN tokens)
    json.loads(outcome_json(out), parse_constant=lambda s: pytest.fail(f'non-JSON {s}'))


def test_garbage_and_nan_from_the_wire_are_rejected_and_hover_continues():
    rig = Rig()
    rig.run(0.5)
    p0 = rig.truth().position_m
    rng = random.Random(11)
    nan_q = [math.nan, 0.0, 0.0, 0.0]
    for _ in range(50):
        rig.link.b.send(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 80))))
        rig.link.b.send(b'\xfd' + bytes(20))                          # truncated MAVLink 2
        rig.mav.set_attitude_target_send(0, 1, 1, 0, nan_q, 0.0, 0.0, 0.0, 0.5)
        rig.mav.set_attitude_target_send(0, 1, 1, 0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                         math.nan)
        rig.run(0.04)
    assert rig.emu.rejected['nan'] >= 50 and rig.emu.rejected['bad_data'] >= 50
    assert rig.emu.counters['setpoints_rx'] == 0 and rig.sim.last_kind == 'hold'
    assert sum(rig.sim.world.rejected.values()) == 0
    assert math.dist(rig.truth().position_m, p0) < 0.1
    rig.sim.advance(math.nan)
    rig.sim.advance(-1.0)
    assert rig.sim.rejected['bad_dt'] == 2


def test_the_autopilot_holds_where_a_mode_is_entered_and_idles_when_disarmed():
    rig = Rig()
    ap = rig.sim.autopilot
    assert rig.sim.world.autopilot is ap and rig.emu.autopilot is ap   # one autopilot
    assert ap.kind == 'hold' and ap.hold_point_m == rig.truth().position_m
    hover = (0.0, 0.0, 0.0, M * G)
    rig.run(1.3, setpoint=hover)
    rig.set_mode(6)
    rig.run(0.5, setpoint=(0.0, 0.1, 0.0, M * G / math.cos(0.1)))      # drift east
    rig.set_mode(3)                                                  # POSCTL again
    rig.run(0.02, setpoint=hover)
    tr = rig.truth()
    assert ap.kind == 'hold' and math.dist(ap.hold_point_m, tr.position_m) < 0.02
    rig.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196,
                              0, 0, 0, 0, 0)                         # forced disarm
    rig.run(0.04)
    assert ap.kind == 'idle' and rig.sim.world.vehicle.cmd_thrust == 0.0
    with pytest.raises(ValueError, match='land_speed_mps'):
        AutopilotParams(land_speed_mps=-1.0)
    with pytest.raises(ValueError, match='offboard_loss_action'):
        EmulatedAutopilot(AutopilotParams(offboard_loss_action='panic'))


# --- TickSchedule: absolute deadlines ------------------------------------------------------

def run_schedule(sched, clock, work, n):
    """Drive ``n`` ticks the way the node's thread does: sleep to the deadline (the fake clock
    jumps there), tick, then "work" for work(k) seconds. Returns the deadlines."""
    deadlines = []
    for k in range(n):
        wait = sched.wait_s(clock[0])
        if wait > 0.0:
            clock[0] += wait
        deadlines.append(sched.tick(clock[0]))
        clock[0] += work(k)
    return deadlines


def test_schedule_never_drifts_whatever_the_work_takes():
    rng = random.Random(3)
    clock = [100.0]
    sched = TickSchedule(0.01, 0.1, clock[0])
    deadlines = run_schedule(sched, clock, lambda k: rng.uniform(0.0, 0.009), 10_000)
    # tick k is due at start + k P exactly (the old loop slept P *after* the work: it drifted
    # by the work time every tick, i.e. by ~45 s here)
    assert all(d == pytest.approx(100.0 + k * 0.01, abs=1e-9) for k, d in enumerate(deadlines))
    assert sched.next_s == pytest.approx(100.0 + 10_000 * 0.01, abs=1e-9)
    assert sched.late == sched.overruns == sched.ticks_dropped == 0
    assert sched.ticks == 10_000


def test_schedule_catches_up_a_late_tick_without_sleeping():
    clock = [0.0]
    sched = TickSchedule(0.01, 0.1, clock[0])
    # tick 5 takes 35 ms (a preemption): ticks 6-8 are already due, run back to back, and the
    # world still advances by exactly one period per deadline (no sim time lost)
    deadlines = run_schedule(sched, clock, lambda k: 0.035 if k == 5 else 0.001, 20)
    assert deadlines == pytest.approx([k * 0.01 for k in range(20)], abs=1e-12)
    assert sched.late == 3            # ticks 6, 7 and 8 ran > 2 ms after their deadlines
    assert sched.overruns == 0
    assert sched.wait_s(clock[0]) > 0.0      # back on schedule


def test_schedule_gives_up_a_stall_longer_than_max_lag():
    clock = [0.0]
    sched = TickSchedule(0.01, 0.1, clock[0])
    deadlines = run_schedule(sched, clock, lambda k: 0.5 if k == 2 else 0.0, 6)
    # tick 3 runs 0.49 s late: the 49 other deadlines passed meanwhile are dropped and the
    # schedule re-anchors at the tick
    assert deadlines[:3] == pytest.approx([0.0, 0.01, 0.02])
    assert deadlines[3] == pytest.approx(0.52) and deadlines[4] == pytest.approx(0.53)
    assert sched.overruns == 1 and sched.ticks_dropped == 49


@pytest.mark.parametrize('period, lag, needle', [(0.0, 0.1, 'period_s'),
                                                 (math.nan, 0.1, 'period_s'),
                                                 (0.01, 0.005, 'max_lag_s')])
def test_schedule_rejects_bad_configuration(period, lag, needle):
    with pytest.raises(ValueError, match=needle):
        TickSchedule(period, lag, 0.0)
