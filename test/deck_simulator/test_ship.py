"""Ship deck model: parameters, response functions, motion statistics against the spectrum,
the encounter-frequency shift, lever-arm kinematics, the interpolated table, determinism."""

import dataclasses
import math
import pathlib
import random
import re

from deck_simulator.deck import Deck, SineHeave
from deck_simulator.deck_motion import DeckMotion, HeaveDeckMotion, PadState
from deck_simulator.ship import (
    DOF,
    ShipMotion,
    encounter_frequency,
    motion_variances,
    response_functions,
    second_order,
)
from deck_simulator.ship_params import SHIP_BUILTINS, ShipParams
from deckland_common.frames import rot_body_to_world
import numpy as np
import pytest
import yaml

G = 9.81
DOC = pathlib.Path(__file__).resolve().parents[2] / 'docs' / 'world' / 'ship.md'
HEAVE, ROLL, PITCH = 2, 3, 4


def ship(p: ShipParams, seed: int = 1, duration_s: float = 120.0) -> ShipMotion:
    return ShipMotion(p, random.Random(f'{seed}:ship'), duration_s)


def long_crested(**kw) -> ShipParams:
    return ShipParams(spreading_s=None, **kw)


# --- parameters ----------------------------------------------------------------------------------

@pytest.mark.parametrize(('key', 'value', 'message'), [
    ('length_m', 0.0, 'length_m must be in'),
    ('speed_mps', -1.0, 'speed_mps must be in'),
    ('turn_rate_radps', 2.0, 'turn_rate_radps must be in'),
    ('pad_offset_m', (1.0, 2.0), 'pad_offset_m must be 3 finite numbers'),
    ('pad_offset_m', (0.0, 0.0, -5.0), 'pad_offset_m must put the pad top above'),
    ('significant_height_m', float('nan'), 'significant_height_m must be in'),
    ('spectrum', 'bretschneider', 'spectrum must be one of'),
    ('spreading_s', -1.0, 'spreading_s must be in'),
    ('components', 1, 'components must be an integer >= 2'),
    ('roll_damping', 0.0, 'roll_damping must be in (0, 2]'),
    ('table_dt_s', 1.0, 'table_dt_s must be in'),
])
def test_bad_parameter_is_refused_naming_the_field(key, value, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        ShipParams(**{key: value})
    with pytest.raises(ValueError, match=re.escape('ship.' + message)):
        ShipParams.from_mapping({key: value})


def test_mapping_accepts_yaml_lists_and_ints_and_refuses_unknown_keys():
    p = ShipParams.from_mapping(yaml.safe_load(
        'speed_mps: 3\npad_offset_m: [-4, 0, 2]\npad_position_m: [1, 2]\nspreading_s: null\n'))
    assert p.speed_mps == 3.0 and isinstance(p.speed_mps, float)
    assert p.pad_offset_m == (-4.0, 0.0, 2.0) and p.pad_position_m == (1.0, 2.0)
    assert p.spreading_s is None
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['speed'\]"):
        ShipParams.from_mapping({'speed': 2.0})
    with pytest.raises(ValueError, match='must be a mapping'):
        ShipParams.from_mapping([1, 2])


def test_doc_yaml_of_each_builtin_is_the_preset():
    """docs/world/ship.md shows each built-in's `ship:` block; it must load to the preset."""
    text = DOC.read_text(encoding='utf-8')
    blocks = re.findall(r'```yaml\n# (ship_\w+)\n(.*?)```', text, re.S)
    assert sorted(name for name, _ in blocks) == sorted(SHIP_BUILTINS)
    for name, body in blocks:
        assert ShipParams.from_mapping(yaml.safe_load(body)['ship']) == SHIP_BUILTINS[name]
    # every key of the schema table is a field, and every field is in the table
    keys = set(re.findall(r'^\| `(\w+)` \|', text, re.M))
    assert keys == {f.name for f in dataclasses.fields(ShipParams)}


def test_builtins_match_their_names():
    ss3, ss4, turn = (SHIP_BUILTINS[n] for n in ('ship_ss3', 'ship_ss4', 'ship_turning'))
    assert 0.5 <= ss3.significant_height_m < 1.25 <= ss4.significant_height_m < 2.5   # WMO
    for p in (ss3, ss4):
        assert 2.0 <= p.speed_mps <= 3.0 and p.turn_rate_radps == 0.0
    assert ss3.wave_heading_rad == pytest.approx(math.pi)                 # head seas
    assert 0.0 < ss4.wave_heading_rad < 0.5 * math.pi                    # stern quartering
    assert turn.turn_rate_radps != 0.0


# --- response functions --------------------------------------------------------------------------

def test_encounter_frequency_head_and_following_seas():
    w = np.array([0.5, 1.0, 2.0])
    u = 5.0
    np.testing.assert_allclose(encounter_frequency(w, math.pi, u), w + w * w * u / G)
    np.testing.assert_allclose(encounter_frequency(w, 0.0, u), w - w * w * u / G)
    assert encounter_frequency(2.0, 0.0, u) < 0.0                        # overtaken by waves
    np.testing.assert_allclose(encounter_frequency(w, 0.5 * math.pi, u), w, atol=1e-15)


def test_second_order_system_gain_phase_and_symmetry():
    tn, z = 5.4, 0.08
    wn = 2 * math.pi / tn
    assert abs(second_order(0.0, tn, z)) == pytest.approx(1.0)
    assert abs(second_order(wn, tn, z)) == pytest.approx(1.0 / (2 * z))       # resonance
    assert np.angle(second_order(wn, tn, z)) == pytest.approx(-0.5 * math.pi)
    assert abs(second_order(10 * wn, tn, z)) == pytest.approx(1 / 99, rel=0.01)
    w = np.linspace(0.1, 5.0, 50)
    np.testing.assert_allclose(second_order(-w, tn, z), np.conj(second_order(w, tn, z)))


def test_negative_encounter_frequency_is_the_causal_response():
    """x'' + 2ζω_n x' + ω_n² x = ω_n² Re(e^{iω_e t}) with ω_e < 0, integrated (RK4): the steady
    state is Re(H(ω_e) e^{iω_e t}), H(ω_e) = conj H(|ω_e|) (a wave overtaking the ship)."""
    tn, z, we = 2.8, 0.25, -1.7
    wn = 2 * math.pi / tn
    h = second_order(we, tn, z)

    def f(t, s):
        return np.array([s[1], wn * wn * (math.cos(we * t) - s[0]) - 2 * z * wn * s[1]])

    dt, s, t = 1e-3, np.zeros(2), 0.0
    for _ in range(int(40.0 / dt)):                   # ≫ the decay time 1/(ζ ω_n) = 1.8 s
        k1 = f(t, s)
        k2 = f(t + dt / 2, s + dt / 2 * k1)
        k3 = f(t + dt / 2, s + dt / 2 * k2)
        k4 = f(t + dt, s + dt * k3)
        s = s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += dt
    assert s[0] == pytest.approx((h * np.exp(1j * we * t)).real, abs=1e-6)
    assert s[1] == pytest.approx((1j * we * h * np.exp(1j * we * t)).real, abs=1e-6)


def test_response_functions_long_and_short_wave_limits():
    p = ShipParams(speed_mps=0.0)
    w = 0.02                                          # λ = 150 km: the hull follows the surface
    k = w * w / G
    for beta in (0.3, 1.0, 2.5):
        h = response_functions(p, w, beta)            # (lag 2ζ ω/ω_n ≤ 0.01 rad at this ω)
        assert h[HEAVE] == pytest.approx(1.0, abs=1e-2)
        assert h[PITCH] == pytest.approx(1j * k * math.cos(beta), rel=1e-2)   # θ = −∂η/∂x
        assert h[ROLL] == pytest.approx(-1j * k * math.sin(beta), rel=1e-2)   # φ = ∂η/∂y
        assert h[0] == pytest.approx(-1j * math.cos(beta), rel=1e-3)    # orbit radius = a
        assert h[1] == pytest.approx(-1j * math.sin(beta), rel=1e-3)
    # head seas: no roll, sway, yaw; beam seas: no pitch, surge (long-crested symmetry)
    head = response_functions(p, np.linspace(0.3, 3, 20), math.pi)
    beam = response_functions(p, np.linspace(0.3, 3, 20), 0.5 * math.pi)
    assert np.max(np.abs(head[[1, 3, 5]])) < 1e-15
    assert np.max(np.abs(beam[[0, 4]])) < 1e-15
    # waves much shorter than the hull average out (λ = 2 m on a 20 m x 6 m hull)
    short = response_functions(p, math.sqrt(2 * math.pi * G / 2.0), 0.7)
    assert np.max(np.abs(short[[0, 1, 2]])) < 1e-2


def test_roll_resonance_in_beam_seas_at_zero_speed():
    p = ShipParams(speed_mps=0.0)
    wn = 2 * math.pi / p.roll_period_s
    k = wn * wn / G
    h = response_functions(p, wn, 0.5 * math.pi)[ROLL]
    excitation = k * math.exp(-k * p.draft_m)         # slope x Smith factor (beam factor ≈ 1)
    assert abs(h) == pytest.approx(excitation / (2 * p.roll_damping), rel=0.03)


# --- statistics against the spectrum -------------------------------------------------------------

@pytest.mark.parametrize('name', ['ship_ss3', 'ship_ss4'])
def test_realisation_variance_is_the_spectral_integral(name):
    """Σ|c_ij|²/2 of a realisation (its exact variance) against ∫∫|H_j|² S D dδ dω: unbiased
    over seeds (mean within 3 standard errors) and each seed within its stated scatter."""
    p = SHIP_BUILTINS[name]
    ref = motion_variances(p)
    r = np.array([ship(p, seed, 0.0).component_variances() / ref for seed in range(40)])
    mean, se = r.mean(axis=0), r.std(axis=0, ddof=1) / math.sqrt(len(r))
    assert np.all(np.abs(mean - 1.0) < 3 * se + 1e-3), dict(zip(DOF, mean, strict=True))
    # per-seed scatter (100 components; 1σ over 200 seeds: heave ≤ 0.5 %, pitch ≤ 2.2 %,
    # roll 6 % quartering / 12 % head seas): every seed within about 4σ
    assert np.max(np.abs(r[:, HEAVE] - 1)) < 0.02
    assert np.max(np.abs(r[:, PITCH] - 1)) < 0.10
    assert np.max(np.abs(r[:, ROLL] - 1)) < 0.50


def test_time_series_variance_of_motions_and_pad_heave():
    """A 3-hour record: sample variances of heave/roll/pitch equal the realisation's Σ|c|²/2,
    and the pad heave's equals that of the linear lever-arm combination heave − l_x θ + l_y φ
    (FACTS.md: deck-spot vertical motion), with l_y ≠ 0 to include roll."""
    p = dataclasses.replace(SHIP_BUILTINS['ship_ss4'], pad_offset_m=(-8.0, 2.0, 1.9),
                            wave_heading_rad=math.pi)
    m = ship(p, 3)
    t = np.arange(0.0, 10800.0, 0.5)
    q, _, _ = m.motions(t)
    var = m.component_variances()
    for j in (HEAVE, ROLL, PITCH):
        assert np.var(q[j]) == pytest.approx(var[j], rel=0.05)
    lx, ly, _ = p.pad_offset_m
    c = m._c0
    lin = c[HEAVE] - lx * c[PITCH] + ly * c[ROLL]
    var_pad = np.sum(np.abs(lin) ** 2) / 2.0
    z_pad = m.exact_rows(t[::4])[:, 2]
    assert np.var(z_pad) == pytest.approx(var_pad, rel=0.05)
    assert var_pad > 1.2 * var[HEAVE]                 # the lever arm matters on this pad


def test_ss4_roll_and_pitch_are_of_the_order_of_the_seakeeping_limits():
    """FACTS.md: helicopter-operation limits roll 5°, pitch 3° significant single amplitude
    (2σ); a 15-30 m vessel in sea state 4 should be of that order (here: within 0.5-2x)."""
    for beta in (math.pi, 0.75 * math.pi, 0.25 * math.pi):
        p = dataclasses.replace(SHIP_BUILTINS['ship_ss4'], wave_heading_rad=beta)
        sd = np.sqrt(motion_variances(p))
        assert 2.5 <= math.degrees(2 * sd[ROLL]) <= 10.0
        assert 1.5 <= math.degrees(2 * sd[PITCH]) <= 6.0


def _welch_centroid(x: np.ndarray, dt: float, seg_s: float = 512.0) -> float:
    """Mean frequency [rad/s] of the Welch periodogram (Hann, 50 % overlap)."""
    n = int(seg_s / dt)
    win = np.hanning(n)
    p = np.zeros(n // 2 + 1)
    for start in range(0, len(x) - n + 1, n // 2):
        p += np.abs(np.fft.rfft((x[start:start + n] - x[start:start + n].mean()) * win)) ** 2
    w = 2 * math.pi * np.fft.rfftfreq(n, dt)
    return float(np.sum(w * p) / np.sum(p))


def test_encounter_shift_in_the_spectrum_of_the_pad_heave():
    """Long-crested seas, Tp 7.5 s: the pad heave's mean frequency is that of its encounter
    spectrum Σ|c_i|²|ω_e,i| / Σ|c_i|² — higher in head seas, lower in following seas, and
    folded where the waves overtake the ship (ω_e < 0) at 8 m/s in following seas, Tp 6 s."""
    cases = {'zero speed': (0.0, math.pi, 7.5), 'head 5 m/s': (5.0, math.pi, 7.5),
             'following 5 m/s': (5.0, 0.0, 7.5), 'following 8 m/s': (8.0, 0.0, 6.0)}
    got = {}
    for label, (u, beta, tp) in cases.items():
        p = long_crested(speed_mps=u, wave_heading_rad=beta, peak_period_s=tp,
                         pad_offset_m=(-5.0, 0.0, 1.9))
        m = ship(p, 5)
        comp = m.wave_components()
        lin = m._c0[HEAVE] - p.pad_offset_m[0] * m._c0[PITCH]
        weights = np.abs(lin) ** 2
        predicted = float(np.sum(weights * np.abs(comp['omega_e'])) / np.sum(weights))
        t = np.arange(0.0, 7200.0, 0.25)
        z = m.exact_rows(t)[:, 2]
        got[label] = (_welch_centroid(z, 0.25), predicted)
        assert got[label][0] == pytest.approx(predicted, rel=0.03), label
        if label == 'following 8 m/s':
            overtaking = float(np.sum(weights[comp['omega_e'] < 0]) / np.sum(weights))
            assert overtaking > 0.1                   # the case really has ω_e < 0
            assert np.var(z) == pytest.approx(np.sum(weights) / 2, rel=0.05)
    assert got['head 5 m/s'][0] > 1.3 * got['zero speed'][0]
    assert got['following 5 m/s'][0] < 0.8 * got['zero speed'][0]


def test_motions_are_the_component_sum_at_the_moving_ship():
    """Independent re-summation: Re Σ a_i H(ω_i, θ_i − ψ) e^{i(ω_i t − k_i·p(t) + φ_i)} along the
    straight track p(t) = p0 + U t e_ψ (following seas, partly overtaking)."""
    p = ShipParams(speed_mps=8.0, wave_heading_rad=0.3, peak_period_s=5.0, heading_rad=0.7)
    m = ship(p, 9)
    c = m.wave_components()
    t = np.linspace(0.0, 60.0, 301)
    x0, y0 = (v[0] for v in m.track(np.array([0.0]))[:2])
    px = x0 + p.speed_mps * math.cos(p.heading_rad) * t
    py = y0 + p.speed_mps * math.sin(p.heading_rad) * t
    k = c['omega'] ** 2 / G
    chi = (np.outer(t, c['omega']) - np.outer(px, k * np.cos(c['theta']))
           - np.outer(py, k * np.sin(c['theta'])) + c['phase'])
    h = c['amplitude'] * response_functions(p, c['omega'], c['theta'] - p.heading_rad)
    expect = np.einsum('ji,ki->jk', h, np.exp(1j * chi)).real
    q, _, _ = m.motions(t)
    np.testing.assert_allclose(q, expect, atol=1e-12)


# --- kinematics ----------------------------------------------------------------------------------

def _pad_series(m: ShipMotion, t: np.ndarray, hot: bool):
    get = m.pad_state if hot else m.exact_pad_state
    return [get(float(tk)) for tk in t]


@pytest.mark.parametrize('name', ['ship_ss4', 'ship_turning'])
@pytest.mark.parametrize('hot', [True, False])
def test_pad_velocity_and_acceleration_are_the_time_derivatives(name, hot):
    """Finite differences (h = 1 ms) of position, velocity, ω and R against velocity,
    acceleration, α and [ω]x R. Turning, the table interpolates each row's coefficients
    separately: consistent to the hot-vs-exact tolerance (10x looser, R 100x)."""
    m = ship(SHIP_BUILTINS[name], 2)
    h = 1e-3
    scale = 10.0 if hot and SHIP_BUILTINS[name].turn_rate_radps else 1.0
    for t in (3.21, 17.5, 44.44, 89.0):
        sm, s0, sp = _pad_series(m, np.array([t - h, t, t + h]), hot)
        for quantity, derivative, tol in (('position_m', 'velocity_mps', 2e-5),
                                          ('velocity_mps', 'accel_mps2', 2e-4),
                                          ('omega_radps', 'alpha_radps2', 2e-4)):
            fd = (np.array(getattr(sp, quantity)) - np.array(getattr(sm, quantity))) / (2 * h)
            np.testing.assert_allclose(fd, getattr(s0, derivative), atol=tol * scale)
        # dR/dt = [ω]x R
        rd = (np.array(sp.rotation) - np.array(sm.rotation)) / (2 * h)
        wx, wy, wz = s0.omega_radps
        skew = np.array([[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]])
        np.testing.assert_allclose(rd, skew @ np.array(s0.rotation), atol=2e-6 * scale ** 2)


def test_pad_rides_on_the_hull_at_its_lever_arm():
    """Pad = centre of motion + R l; small angles: pad heave ≈ heave − l_x θ + l_y φ + l_z."""
    p = dataclasses.replace(SHIP_BUILTINS['ship_ss4'], pad_offset_m=(-6.0, 1.5, 1.9))
    m = ship(p, 4)
    t = np.linspace(0.0, 100.0, 41)
    q, _, _ = m.motions(t)
    rows = m.exact_rows(t)
    lx, ly, lz = p.pad_offset_m
    for k in range(len(t)):
        roll, pitch, yaw = rows[k, 9:12]
        r = np.array(rot_body_to_world(roll, pitch, yaw))
        centre = rows[k, 0:3] - r @ np.array(p.pad_offset_m)
        assert centre[2] == pytest.approx(p.motion_centre_height_m + q[HEAVE, k], abs=1e-12)
        lin = p.motion_centre_height_m + q[HEAVE, k] - lx * pitch + ly * roll + lz
        second_order_terms = 0.5 * (roll ** 2 + pitch ** 2) * (abs(lx) + abs(ly) + lz)
        assert abs(rows[k, 2] - lin) <= second_order_terms + 1e-12
        assert (roll, pitch) == (q[ROLL, k], q[PITCH, k])


def test_calm_water_track_straight_and_turning():
    calm = {'significant_height_m': 0.0, 'pad_position_m': (10.0, -4.0), 'heading_rad': 0.4}
    m = ship(ShipParams(speed_mps=3.0, **calm))
    s0 = m.pad_state(0.0)
    assert s0.position_m == pytest.approx((10.0, -4.0, 0.6 + 1.9))
    s = m.pad_state(20.0)
    assert s.position_m[:2] == pytest.approx((10.0 + 60.0 * math.cos(0.4),
                                              -4.0 + 60.0 * math.sin(0.4)), abs=1e-9)
    assert s.velocity_mps == pytest.approx((3.0 * math.cos(0.4), 3.0 * math.sin(0.4), 0.0))
    assert s.rpy_rad == pytest.approx((0.0, 0.0, 0.4))
    r = 0.05
    m = ship(ShipParams(speed_mps=3.0, turn_rate_radps=r, **calm), duration_s=200.0)
    centre = None
    for t in (0.0, 13.0, 77.7, 150.0):
        s = m.pad_state(t)
        assert s.rpy_rad[2] == pytest.approx(math.remainder(0.4 + r * t, 2 * math.pi))
        assert s.omega_radps == pytest.approx((0.0, 0.0, r))
        # the pad (5 m aft of the centre of motion) circles the turn centre at a fixed radius
        c = m.track(np.array([t]))
        turn_centre = (c[0][0] - 3.0 / r * math.sin(0.4 + r * t),
                       c[1][0] + 3.0 / r * math.cos(0.4 + r * t))
        centre = centre or turn_centre
        assert turn_centre == pytest.approx(centre, abs=1e-9)
        radius = math.hypot(s.position_m[0] - centre[0], s.position_m[1] - centre[1])
        assert radius == pytest.approx(math.hypot(3.0 / r, 5.0), abs=1e-9)
        speed = math.hypot(*s.velocity_mps[:2])
        assert speed == pytest.approx(r * math.hypot(3.0 / r, 5.0), rel=1e-9)


def test_turning_changes_heading_at_the_set_rate():
    p = SHIP_BUILTINS['ship_turning']
    m = ship(p, 6, duration_s=300.0)
    t = np.arange(0.0, 300.0, 0.5)
    yaw = np.unwrap([m.pad_state(float(tk)).rpy_rad[2] for tk in t])
    dev = yaw - (p.heading_rad + p.turn_rate_radps * t)
    dev -= 2 * math.pi * round(float(dev[0]) / (2 * math.pi))
    slope = np.polyfit(t, yaw, 1)[0]
    assert slope == pytest.approx(p.turn_rate_radps, rel=0.01)
    assert abs(dev.mean()) < 4 * dev.std() / math.sqrt(300.0 / 10.0)   # wave yaw zero-mean
    assert dev.std() < math.radians(2.0)


def test_deck_helpers_plane_frames_and_point_motion():
    m = ship(SHIP_BUILTINS['ship_ss4'], 8)
    t, h = 33.3, 1e-3
    s = m.pad_state(t)
    n = np.array(s.normal())
    assert np.linalg.norm(n) == pytest.approx(1.0)
    assert s.plane()[0] == s.position_m
    foot = (0.4, -0.3, 0.0)                           # a point on the deck, deck frame
    w = s.to_world(foot)
    assert s.height_under(w[0], w[1]) == pytest.approx(w[2], abs=1e-12)
    assert np.dot(np.array(w) - np.array(s.position_m), n) == pytest.approx(0.0, abs=1e-12)
    above = (0.4, -0.3, 0.25)
    assert s.to_deck(s.to_world(above)) == pytest.approx(above, abs=1e-12)
    # a deck-fixed point: velocity and acceleration by finite differences
    sm, sp = m.pad_state(t - h), m.pad_state(t + h)
    wm, wp = np.array(sm.to_world(above)), np.array(sp.to_world(above))
    np.testing.assert_allclose((wp - wm) / (2 * h), s.point_velocity(s.to_world(above)),
                               atol=1e-4)
    vm = np.array(sm.point_velocity(sm.to_world(above)))
    vp = np.array(sp.point_velocity(sp.to_world(above)))
    np.testing.assert_allclose((vp - vm) / (2 * h), s.point_accel(s.to_world(above)),
                               atol=1e-3)
    # a body moving with that point has no velocity relative to the deck
    assert s.relative_velocity(s.to_world(above), s.point_velocity(s.to_world(above))) == (
        pytest.approx((0.0, 0.0, 0.0), abs=1e-12))
    # descending at 0.5 m/s (world) over a still deck point: deck-frame z speed ≈ −0.5 n_z
    v = s.point_velocity(w)
    rel = s.relative_velocity(w, (v[0], v[1], v[2] - 0.5))
    assert rel[2] == pytest.approx(-0.5 * n[2], abs=1e-12)


# --- table, determinism, interface ---------------------------------------------------------------

@pytest.mark.parametrize(('name', 'tol'), [
    ('ship_ss3', (1e-5, 1e-4, 1e-3, 1e-6, 1e-5, 1e-4)),
    ('ship_ss4', (1e-5, 1e-4, 1e-3, 1e-6, 1e-5, 1e-4)),
    ('ship_turning', (5e-4, 1e-3, 5e-3, 2e-4, 5e-4, 5e-3)),
])
def test_interpolated_hot_path_equals_the_exact_sum(name, tol):
    """Tolerances (position m, velocity m/s, acceleration m/s², angles rad, ω rad/s, α rad/s²):
    straight: cubic Hermite on a 0.1 s table; turning: plus the coefficients interpolated
    over 0.02 rad of turn (docs/world/ship.md)."""
    m = ship(SHIP_BUILTINS[name], 11, duration_s=100.0)
    for t in np.random.default_rng(0).uniform(0.0, 100.0, 150):
        hot, exact = m.pad_state(float(t)), m.exact_pad_state(float(t))
        for j, (a, b, e) in enumerate(zip(hot.as_tuple(), exact.as_tuple(), tol, strict=True)):
            d = np.array(a) - np.array(b)
            if j == 3:                                # angles: yaw wraps
                d = np.array([math.remainder(v, 2 * math.pi) for v in d])
            assert np.max(np.abs(d)) < e, (j, d)
    # outside the table: the exact sum
    for t in (-1.0, 100.5, 250.0):
        assert m.pad_state(t).as_tuple() == m.exact_pad_state(t).as_tuple()
    with pytest.raises(ValueError, match='t_s must be a finite number'):
        m.pad_state(float('nan'))


@pytest.mark.parametrize('name', sorted(SHIP_BUILTINS))
def test_deterministic_for_a_seed_whatever_the_query_order(name):
    p = SHIP_BUILTINS[name]
    ts = [float(t) for t in np.random.default_rng(1).uniform(0.0, 60.0, 50)]
    a = ship(p, 21, 60.0)
    b = ship(p, 21, 60.0)
    forward = [a.pad_state(t).as_tuple() for t in sorted(ts)]
    backward = {t: b.pad_state(t).as_tuple() for t in sorted(ts, reverse=True)}
    assert forward == [backward[t] for t in sorted(ts)]
    c = ship(p, 22, 60.0)
    assert c.pad_state(ts[0]).as_tuple() != a.pad_state(ts[0]).as_tuple()


def test_heave_deck_adapter_is_a_level_deck_motion():
    deck = Deck((-3.2, -2.0), (1.05, 0.85), 0.6, SineHeave(0.2, 5.0, 0.3), (0.5, -0.25))
    motion: DeckMotion = HeaveDeckMotion(deck)
    for t in (0.0, 1.7, 8.25):
        s = motion.pad_state(t)
        assert isinstance(s, PadState)
        cx, cy, z, vz, az = deck.state(t)
        assert s.position_m == (cx, cy, z)
        assert s.velocity_mps == (0.5, -0.25, vz) and s.accel_mps2 == (0.0, 0.0, az)
        assert s.normal() == (0.0, 0.0, 1.0) and s.rpy_rad == (0.0, 0.0, 0.0)
        assert s.height_under(cx + 3.0, cy - 1.0) == z
        assert s.point_velocity((cx + 1.0, cy, z)) == (0.5, -0.25, vz)
    ship_motion: DeckMotion = ship(SHIP_BUILTINS['ship_ss3'])
    assert isinstance(ship_motion.pad_state(1.0), PadState)
