"""landing_planner.loop: the planner node's tick, gating and withholding, without ROS.

The planner core is replaced by a recorder where the question is what the loop hands it (dt,
the vehicle state); the real cores are used where the question is what goes out.
"""

import math

from deckland_common.contract import ApronState, Mode, PlannerOutput
from deckland_common.frames import euler_to_quaternion
from landing_planner.horizontal import HorizontalController
from landing_planner.loop import PlannerLoop
from landing_planner.planner import LandingPlanner, PlannerParams
import pytest


class RecordingPlanner:
    """Stands in for LandingPlanner: records each step's (t, dt, vehicle, apron)."""

    def __init__(self, thrust=True):
        self.calls = []
        self.thrust = thrust
        self.mode = Mode.APPROACH

    def step(self, t_s, dt_s, vehicle, apron):
        self.calls.append((t_s, dt_s, vehicle, apron))
        return PlannerOutput(t_s, self.mode, (1.0, 0.0), (0.0, 0.0), 0.0, 1.0, 0.0, 0.0,
                             self.thrust, 0, '')


def loop_with(planner, **kw):
    return PlannerLoop(planner, HorizontalController(), period_s=0.01, input_timeout_s=0.3,
                       **kw)


def feed_vehicle(loop, t, now=None):
    now = t if now is None else now
    assert loop.on_odom(now, t, 'map', (0.0, 0.0, 1.5), (1.0, 0.0, 0.0, 0.0))
    assert loop.on_velocity(now, t, (0.0, 0.0, 0.0), 'map')


def test_nothing_is_stepped_before_the_vehicle_state():
    rec = RecordingPlanner()
    loop = loop_with(rec)
    assert loop.on_apron(1.0, ApronState.untracked(1.0)) is None
    assert loop.withheld['no_vehicle'] == 1 and not rec.calls


def test_dt_is_the_node_clock_interval_and_restarts_after_a_pause():
    rec = RecordingPlanner()
    loop = loop_with(rec)
    for now in (1.0, 1.01, 1.025, 2.0):
        feed_vehicle(loop, now)
        assert loop.on_apron(now, ApronState.untracked(now)) is not None
    dts = [c[1] for c in rec.calls]
    assert dts[0] == 0.01                            # first step: the nominal period
    assert dts[1] == pytest.approx(0.01) and dts[2] == pytest.approx(0.015)
    assert dts[3] == 0.01                            # after a pause > input_timeout_s
    assert loop.on_apron(2.0, ApronState.untracked(2.0)) is None   # the clock did not advance
    assert loop.withheld['clock_not_advancing'] == 1 and len(rec.calls) == 4
    # a fixed-schedule caller gives dt itself
    feed_vehicle(loop, 2.01)
    loop.on_apron(2.01, ApronState.untracked(2.01), dt_s=0.01)
    assert rec.calls[-1][1] == 0.01


def test_a_stale_vehicle_state_runs_the_safe_mode_and_withholds_the_commands():
    rec = RecordingPlanner()
    loop = loop_with(rec)
    feed_vehicle(loop, 1.0)
    tick = loop.on_apron(1.4, ApronState.untracked(1.4))   # vehicle 0.4 s old
    vehicle = rec.calls[-1][2]
    assert math.isnan(vehicle.position_m[0]) and math.isnan(vehicle.yaw_rad)
    assert tick.command is None and tick.withheld == 'vehicle_stale'
    assert not tick.publish_reference and not tick.publish_attitude


def test_disabled_thrust_publishes_the_reference_but_no_attitude():
    loop = loop_with(RecordingPlanner(thrust=False))
    feed_vehicle(loop, 1.0)
    tick = loop.on_apron(1.0, ApronState.untracked(1.0))
    assert tick.publish_reference and not tick.publish_attitude
    assert tick.command is not None and loop.counts['attitude'] == 0


def test_watchdog_steps_on_the_fallback_only_while_apron_state_is_stale():
    rec = RecordingPlanner()
    loop = loop_with(rec)
    feed_vehicle(loop, 1.0)
    loop.on_apron(1.0, ApronState.untracked(1.0))
    assert loop.watchdog(1.2) is None                 # fresh (0.2 s < 0.3 s)
    feed_vehicle(loop, 1.35)
    tick = loop.watchdog(1.4)
    assert tick is not None and loop.counts['apron_fallback'] == 1
    fallback = rec.calls[-1][3]
    assert fallback.t_s == 1.4 and not fallback.tracked and not fallback.vertical.valid


def test_command_stamps_never_decrease():
    loop = loop_with(RecordingPlanner())
    feed_vehicle(loop, 1.0)
    a = loop.on_apron(1.0, ApronState.untracked(1.0))
    feed_vehicle(loop, 1.5)
    b = loop.watchdog(1.5)          # the fallback's t_s = now
    feed_vehicle(loop, 1.51)
    c = loop.on_apron(1.51, ApronState.untracked(1.505))
    assert a.stamp_s == 1.0 and b.stamp_s == 1.5 and c.stamp_s == 1.505


def test_bad_vehicle_inputs_are_refused_and_counted():
    loop = loop_with(RecordingPlanner())
    assert not loop.on_odom(1.0, 1.0, 'odom', (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    assert not loop.on_odom(1.0, 1.0, 'map', (0.0, 0.0, 1.0), (0.9, 0.0, 0.0, 0.0))
    assert not loop.on_odom(1.0, 1.0, 'map', (math.nan, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    assert not loop.on_velocity(1.0, 1.0, (0.0, 0.0, 0.0), 'base_link')
    assert not loop.on_velocity(1.0, 0.5, (0.0, 0.0, 0.0))       # 0.5 s old
    assert loop.rejected['bad_frame'] == 2 and loop.rejected['bad_quaternion'] == 1
    assert loop.rejected['non_finite'] == 1 and loop.rejected['stale_stamp'] == 1
    assert loop.pose is None and loop.velocity is None
    st = ApronState.untracked(1.0)
    assert loop.on_apron(1.0, ApronState(math.nan, *[getattr(st, f) for f in (
        'tracked', 'visible', 'time_since_seen_s', 'rel_position_m', 'rel_velocity_mps',
        'rel_position_var_m2', 'rel_position_body_m', 'rel_velocity_body_mps',
        'apron_position_m', 'apron_velocity_mps', 'vertical')])) is None
    assert loop.rejected['non_finite'] == 2


def test_odom_attitude_is_the_quaternion_yaw_and_the_tick_flies_toward_the_setpoint():
    """Real cores: the vehicle hovering east of the landing area is commanded west."""
    planner = LandingPlanner(PlannerParams(landing_area_m=(0.0, 0.0)))
    loop = PlannerLoop(planner, HorizontalController())
    yaw = math.pi / 2.0                                  # nose north
    q = euler_to_quaternion(0.0, 0.0, yaw)
    for i in range(50):
        t = 0.01 * i
        loop.on_odom(t, t, 'map', (5.0, 0.0, 2.0), q)
        loop.on_velocity(t, t, (0.0, 0.0, 0.0), 'map')
        if i == 0:
            assert loop.start_landing(t)[0]
        tick = loop.on_apron(t, ApronState.untracked(t))
    assert loop.pose[4] == pytest.approx(yaw, abs=1e-12)
    assert tick.output.mode is Mode.APPROACH
    roll, _pitch = tick.command
    # nose north, the target west = to the left: FLU roll < 0 (left side down)
    assert roll < 0.0
