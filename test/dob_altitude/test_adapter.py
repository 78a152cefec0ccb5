"""dob_altitude.adapter: controller construction and the VerticalState → AltitudeInput wiring.

The closed-loop checks integrate the vertical model (3)/(6) of a level vehicle over a heaving
deck at 1 kHz with the controller at 100 Hz (zero-order hold); the plant is written here,
independently of the package.
"""

import math

from deckland_common.contract import VerticalState, parse_vertical_frame
from dob_altitude.adapter import altitude_input, hover_thrust_n, make_controller
from dob_altitude.dob import DobAltitudeController, DobParams
from dob_altitude.pid import PidAltitudeController, PidParams
import pytest

G = 9.81
M = 2.71
R = 0.127


def vstate(h=2.0, closing=-0.3, alt=5.0, vz=-0.1, surf=3.0, surf_vz=0.2, surf_acc=0.7):
    return VerticalState(True, h, closing, alt, vz, surf, surf_vz, surf_acc, 0, 0.0)


def gamma(z_p, rho=1.0):
    """(4), written here independently: 1 / (1 − ρ (r / 4 z_p)²)."""
    return 1.0 / (1.0 - rho * (R / (4.0 * z_p)) ** 2)


# --- make_controller -------------------------------------------------------------------------

def test_make_controller_kinds_and_profiles():
    dob = make_controller('dob', 'paper')
    assert isinstance(dob, DobAltitudeController)
    assert (dob.params.k, dob.params.lam, dob.params.gamma_obs) == (0.85, 10.47, 1.6)  # Table 4
    pid = make_controller('pid', 'default')
    assert isinstance(pid, PidAltitudeController)
    assert pid.params == PidParams.profile('default')
    assert make_controller('dob').params == DobParams.profile('default')


def test_make_controller_overrides_are_applied_and_validated():
    ctrl = make_controller('dob', 'paper', {'k': 2.0, 'mass_kg': 3, 'thrust_max_n': 70.0})
    assert ctrl.params.k == 2.0 and ctrl.params.lam == 10.47
    assert ctrl.params.mass_kg == 3.0 and isinstance(ctrl.params.mass_kg, float)
    assert make_controller('pid', 'paper', {'ki': 0.0}).params.ki == 0.0  # PD is expressible
    with pytest.raises(ValueError, match='kp'):
        make_controller('dob', 'default', {'kp': 1.0})  # a PID field on the DOB
    with pytest.raises(ValueError, match=r'DobParams\.gamma_obs'):
        make_controller('dob', 'default', {'gamma_obs': 0.0})
    with pytest.raises(ValueError, match='thrust_max_n'):
        make_controller('pid', 'default', {'thrust_max_n': 20.0})  # below m g
    with pytest.raises(ValueError, match='controller kind'):
        make_controller('lqr')
    with pytest.raises(ValueError, match='profile'):
        make_controller('pid', 'fast')


def test_hover_thrust_is_weight_over_ground_effect_gain():
    ctrl = make_controller('dob')
    assert hover_thrust_n(ctrl) == pytest.approx(M * G)
    assert hover_thrust_n(ctrl, 0.25) == pytest.approx(M * G / gamma(0.25), rel=1e-12)


# --- altitude_input --------------------------------------------------------------------------

def test_surface_frame_uses_height_and_closing_speed():
    v = vstate()
    inp = altitude_input(v, 1.5, -0.4, 0.1, 'relative', 0.05, -0.02)
    assert (inp.z_m, inp.z_dot_mps) == (v.height_m, v.closing_speed_mps)
    assert (inp.z_d_m, inp.z_d_dot_mps, inp.z_d_ddot_mps2) == (1.5, -0.4, 0.1)
    assert (inp.roll_rad, inp.pitch_rad) == (0.05, -0.02)
    assert inp.rotor_height_m == pytest.approx(2.05)
    assert inp.surface_accel_mps2 == 0.0  # the paper: no feed-forward unless enabled
    ff = altitude_input(v, 1.5, -0.4, 0.1, 'relative', 0.0, 0.0, 0.1, surface_accel_ff=True)
    assert ff.surface_accel_mps2 == v.surface_accel_mps2
    assert ff.rotor_height_m == pytest.approx(2.1)


def test_world_frame_uses_altitude_but_ground_effect_still_sees_the_surface():
    v = vstate()
    for enabled in (False, True):
        inp = altitude_input(v, 4.0, -0.5, 0.0, 'world_rate', 0.0, 0.0, surface_accel_ff=enabled)
        assert (inp.z_m, inp.z_dot_mps) == (v.vehicle_altitude_m, v.vehicle_vz_mps)
        assert inp.rotor_height_m == pytest.approx(v.height_m + 0.05)  # not altitude + 0.05
        assert inp.surface_accel_mps2 == 0.0  # deck-blind: never a deck feed-forward


def test_unknown_frame_raises_and_names_are_normalised():
    with pytest.raises(ValueError, match='vertical_frame'):
        altitude_input(vstate(), 1.0, 0.0, 0.0, 'deck', 0.0, 0.0)
    assert parse_vertical_frame('') == 'relative'          # an unset joint name: the paper's
    assert parse_vertical_frame(' Relative ') == 'relative'
    assert parse_vertical_frame('WORLD_RATE') == 'world_rate'
    assert parse_vertical_frame('surface') is None          # one name per frame: no aliases
    assert parse_vertical_frame('map') is None


def test_first_command_at_zero_error_is_hover_thrust_with_ground_effect_of_the_surface():
    """(16) with e = ė = 0 and d̂ = 0 (start-up): u = m g / (γ̄ cφcθ), γ̄ = (4) at h + offset."""
    h, roll, pitch = 0.2, 0.1, -0.05
    v = VerticalState(True, h, 0.0, 1.2, 0.0, 1.0, 0.0, 0.0, 0, 0.0)
    c = math.cos(roll) * math.cos(pitch)
    for kind in ('dob', 'pid'):
        out = make_controller(kind).step(
            altitude_input(v, 1.2, 0.0, 0.0, 'world_rate', roll, pitch), 0.01)
        assert out.gamma_bar == pytest.approx(gamma(h + 0.05), rel=1e-12)
        assert out.thrust_n == pytest.approx(M * G / (gamma(h + 0.05) * c), rel=1e-9)


# --- closed loop over a heaving deck ---------------------------------------------------------

def fly(frame, ff, z_d, amp=0.5, period_s=6.0, t_end=30.0, kind='dob'):
    """Level vehicle over a sinusoidally heaving deck; returns the samples after 18 s."""
    w = 2.0 * math.pi / period_s
    ctrl = make_controller(kind, 'paper')
    dt, div = 0.001, 10
    z_v = z_d  # deck at 0 at t = 0: same start in both frames
    v_v = amp * w if frame == 'relative' else 0.0
    u = M * G
    log = []
    for k in range(int(t_end / dt)):
        t = k * dt
        z_s, v_s, a_s = amp * math.sin(w * t), amp * w * math.cos(w * t), -amp * w * w * math.sin(
            w * t)
        h = z_v - z_s
        if k % div == 0:
            vert = VerticalState(True, h, v_v - v_s, z_v, v_v, z_s, v_s, a_s, 0, 0.0)
            out = ctrl.step(altitude_input(vert, z_d, 0.0, 0.0, frame, 0.0, 0.0,
                                           surface_accel_ff=ff), div * dt)
            u = out.thrust_n
            if t >= 18.0:
                log.append((t, h, z_v, out))
        acc = -G + gamma(h + 0.05) * u / M  # (3) with ρ = ρ̄ = 1, level
        z_v += v_v * dt + 0.5 * acc * dt * dt
        v_v += acc * dt
    return log


def test_surface_frame_rejects_heave_as_disturbance_and_feed_forward_removes_it():
    amp, period = 0.5, 6.0
    w = 2.0 * math.pi / period
    paper = fly('relative', False, 2.0, amp, period)
    err_paper = max(abs(h - 2.0) for _, h, _, _ in paper)
    # linearised DOB loop: e/d = s / ((s+K)(s+Γ)(s+Λ)), d = −a_s of amplitude A ω²
    s = complex(0.0, w)
    predicted = amp * w * w * abs(s / ((s + 0.85) * (s + 1.6) * (s + 10.47)))
    assert err_paper == pytest.approx(predicted, rel=0.15)
    with_ff = fly('relative', True, 2.0, amp, period)
    err_ff = max(abs(h - 2.0) for _, h, _, _ in with_ff)
    assert err_ff < 0.1 * err_paper
    # with the feed-forward the observer no longer has to explain the heave: d̂ ≈ 0
    assert max(abs(o.d_hat_mps2) for *_, o in with_ff) < 0.05 * amp * w * w


def test_world_frame_is_blind_to_the_deck():
    amp = 0.5
    for ff in (False, True):
        log = fly('world_rate', ff, 2.5, amp)
        assert max(abs(z_v - 2.5) for _, _, z_v, _ in log) < 1e-3  # holds its world altitude
        heights = [h for _, h, _, _ in log]
        assert max(heights) - min(heights) == pytest.approx(2.0 * amp, rel=0.02)


