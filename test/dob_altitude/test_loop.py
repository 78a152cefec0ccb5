"""dob_altitude.loop: the altitude node's gating, withholding, resets and dt, without ROS.

The decisions of the package README (Node: 1 disabled, 2 stale, 3 dt from the estimate stamps,
6 frame switches, 8 invalid vertical) on the loop core; the controller is the real DOB where
the command is checked against the model (6), a recorder where the question is what the loop
hands it.
"""

import math

from deckland_common.contract import ApronState, VerticalReference, VerticalState
from dob_altitude.adapter import hover_thrust_n, make_controller
from dob_altitude.loop import AltitudeLoop
from dob_altitude.types import AltitudeOutput
import pytest


def apron(t_s, h=1.5, valid=True):
    v = VerticalState(valid, h, 0.0, h, 0.0, 0.0, 0.0, 0.0, 0, 0.0)
    st = ApronState.untracked(t_s)
    return ApronState(t_s, False, False, math.inf, st.rel_position_m, st.rel_velocity_mps,
                      st.rel_position_var_m2, st.rel_position_body_m, st.rel_velocity_body_mps,
                      st.apron_position_m, st.apron_velocity_mps, v)


class RecordingController:
    def __init__(self):
        self.steps, self.resets = [], 0

    def reset(self):
        self.resets += 1

    def step(self, inp, dt_s, applied_thrust_n=None):
        self.steps.append((inp, dt_s))
        return AltitudeOutput(20.0, 20.0, False, 0.0, 0.0, inp.z_m - inp.z_d_m, 1.0)


def ready(loop, t, frame='relative', z_d=1.5):
    assert loop.on_reference(t, t, frame, z_d, 0.0, 0.0)
    assert loop.on_attitude(t, t, 0.0, 0.0)


def test_at_zero_error_the_command_is_the_hover_thrust_of_model_6():
    ctrl = make_controller('dob')
    loop = AltitudeLoop(ctrl)
    ready(loop, 1.0, z_d=1.5)
    out = loop.on_apron(1.0, apron(1.0, h=1.5))
    # level, e_z = ė_z = 0, d̂ = 0 at start-up: u_z = m g / γ̄(z_p), z_p = h + 0.05
    assert out.thrust_n == pytest.approx(hover_thrust_n(ctrl, 1.55), rel=1e-12)
    assert out.e_z_m == 0.0


def test_dt_is_the_difference_of_the_apron_stamps():
    rec = RecordingController()
    loop = AltitudeLoop(rec, period_s=0.01)
    for t in (1.0, 1.004, 1.013):
        ready(loop, t)
        assert loop.on_apron(t, apron(t)) is not None
    dts = [dt for _, dt in rec.steps]
    assert dts[0] == 0.01                        # first step after the (re)start: the period
    assert dts[1] == pytest.approx(0.004) and dts[2] == pytest.approx(0.009)
    ready(loop, 1.02)
    loop.on_apron(1.02, apron(1.02), dt_s=0.01)  # a fixed-schedule caller gives dt
    assert rec.steps[-1][1] == 0.01


@pytest.mark.parametrize('cause', ['disabled', 'stale', 'invalid_vertical'])
def test_withheld_commands_reset_the_controller(cause):
    rec = RecordingController()
    loop = AltitudeLoop(rec, input_timeout_s=0.2)
    ready(loop, 1.0)
    assert loop.on_apron(1.0, apron(1.0)) is not None
    resets = rec.resets
    if cause == 'disabled':
        loop.on_enabled(False)
        out = loop.on_apron(1.01, apron(1.01))
    elif cause == 'stale':
        out = loop.on_apron(1.25, apron(1.25))     # reference and attitude 0.25 s old
    else:
        ready(loop, 1.01)
        out = loop.on_apron(1.01, apron(1.01, valid=False))
    assert out is None and loop.withheld[cause] == 1 and loop.withheld_reason == cause
    assert rec.resets > resets and loop.need_reset
    # back: a fresh start (reset, nominal dt)
    loop.on_enabled(True)
    ready(loop, 1.3)
    assert loop.on_apron(1.3, apron(1.3)) is not None and rec.steps[-1][1] == loop.period_s


def test_the_runner_flies_through_an_invalid_vertical_estimate():
    loop = AltitudeLoop(RecordingController(), require_valid_vertical=False)
    ready(loop, 1.0)
    assert loop.on_apron(1.0, apron(1.0, valid=False)) is not None


def test_a_frame_switch_restarts_the_controller_in_the_new_frame():
    rec = RecordingController()
    loop = AltitudeLoop(rec)
    ready(loop, 1.0, 'relative', z_d=1.5)
    loop.on_apron(1.0, apron(1.0, h=1.2))
    resets = rec.resets
    ready(loop, 1.01, 'WORLD_RATE', z_d=3.0)
    loop.on_apron(1.01, apron(1.01, h=1.2))
    inp, dt = rec.steps[-1]
    assert loop.counts['frame_switches'] == 1 and rec.resets > resets and dt == loop.period_s
    assert loop.frame_used == 'world_rate' and inp.z_d_m == 3.0
    assert not loop.on_reference(1.02, 1.02, 'surface', 1.0, 0.0, 0.0)   # not a frame name
    assert loop.rejected['bad_frame'] == 1


def test_a_replay_may_name_the_reference_used():
    rec = RecordingController()
    loop = AltitudeLoop(rec)
    ready(loop, 1.0, z_d=1.5)
    loop.on_apron(1.0, apron(1.0), reference=VerticalReference(1.4, 0.0, 0.0, 'relative', 0.99))
    assert rec.steps[-1][0].z_d_m == 1.4
    assert loop.reference.z_d_m == 1.5            # the latest received is kept


def test_bad_inputs_are_refused_and_counted():
    loop = AltitudeLoop(RecordingController())
    assert not loop.on_imu(1.0, 1.0, (1.0, 0.0, 0.0, 0.0), has_orientation=False)
    assert not loop.on_imu(1.0, 1.0, (0.8, 0.0, 0.0, 0.0))
    assert not loop.on_imu(1.0, 1.0, (math.inf, 0.0, 0.0, 0.0))
    assert not loop.on_reference(1.0, 1.0, 'relative', math.nan, 0.0, 0.0)
    assert loop.rejected['bad_quaternion'] == 2 and loop.rejected['non_finite'] == 2
    ready(loop, 1.0)
    assert loop.on_apron(1.0, apron(1.0)) is not None
    assert loop.on_apron(1.0, apron(1.0)) is None                   # repeated t_s
    assert loop.on_apron(1.0, apron(0.99)) is None                  # older
    assert loop.rejected['out_of_order'] == 2
