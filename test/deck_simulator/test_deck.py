"""Deck heave models: triangle (Table 3), sine, sea_state spectrum (Hs, Tp), drift."""

import math
import random

from deck_simulator.deck import (
    Deck,
    SeaStateHeave,
    SineHeave,
    TriangleHeave,
    jonswap,
    pierson_moskowitz,
)
import numpy as np
import pytest


def fd_check(heave, times, h=1e-4, tol_v=1e-6, tol_a=1e-4):
    for t in times:
        zp, vp, _ = heave.state(t + h)
        zm, vm, _ = heave.state(t - h)
        _, v, a = heave.state(t)
        assert (zp - zm) / (2 * h) == pytest.approx(v, abs=tol_v + 1e-3 * abs(v))
        assert (vp - vm) / (2 * h) == pytest.approx(a, abs=tol_a + 1e-3 * abs(a))


def test_triangle_speed_and_stroke():
    hv = TriangleHeave(0.30, 0.09, phase=random.Random(3).random())
    assert hv.period_s == pytest.approx(2 * 0.30 / 0.09)
    ts = np.arange(0.0, 20.0, 0.001)
    z = np.array([hv.state(t)[0] for t in ts])
    v = np.array([hv.state(t)[1] for t in ts])
    assert z.max() - z.min() == pytest.approx(0.30, abs=1e-3)
    assert z.max() == pytest.approx(0.15, abs=1e-3)
    assert np.all(np.abs(np.abs(v) - 0.09) < 1e-12)
    # away from the reversals the derivative is the constant speed
    s = [t for t in ts[::500] if 0.05 < (t / hv.period_s + hv.phase) % 0.5 * hv.period_s < 3.2]
    fd_check(hv, s)


def test_triangle_phase_zero_starts_at_bottom_moving_up():
    z, v, a = TriangleHeave(0.30, 0.09, 0.0).state(0.0)
    assert (z, v, a) == (pytest.approx(-0.15), 0.09, 0.0)


def test_sine_amplitude_and_derivatives():
    hv = SineHeave(0.25, 6.0, 0.4)
    z = [hv.state(t)[0] for t in np.arange(0, 12, 0.01)]
    assert max(z) == pytest.approx(0.25, abs=1e-4) and min(z) == pytest.approx(-0.25, abs=1e-4)
    fd_check(hv, np.linspace(0.1, 11.0, 25))


@pytest.mark.parametrize('spectrum', ['jonswap', 'pierson_moskowitz'])
def test_sea_state_hs_and_peak_period_from_long_realisation(spectrum):
    hs, tp = 1.0, 7.0
    hv = SeaStateHeave(hs, tp, spectrum, random.Random(11), duration_s=10.0)
    t = np.arange(0.0, 7200.0, 0.25)
    z, _, _ = hv.exact_states(t)
    assert 4.0 * np.std(z) == pytest.approx(hs, rel=0.05)
    # peak of the Welch-averaged periodogram (segments of 512 s)
    seg = int(512 / 0.25)
    nseg = len(z) // seg
    p = np.zeros(seg // 2 + 1)
    win = np.hanning(seg)
    for k in range(nseg):
        p += np.abs(np.fft.rfft(z[k * seg:(k + 1) * seg] * win)) ** 2
    f = np.fft.rfftfreq(seg, 0.25)
    kernel = np.ones(15) / 15          # smooth over ~0.03 Hz
    ps = np.convolve(p, kernel, mode='same')
    f_peak = f[np.argmax(ps)]
    assert 1.0 / f_peak == pytest.approx(tp, rel=0.12)


def test_sea_state_spectra_integrate_to_m0():
    w = np.linspace(0.05, 20.0, 200000)
    for fn in (pierson_moskowitz, jonswap):
        m0 = np.trapezoid(fn(w, 1.5, 8.0), w)
        assert 4.0 * math.sqrt(m0) == pytest.approx(1.5, rel=0.03)
    # PM peaks at ω_p = 2π / Tp
    s = pierson_moskowitz(w, 1.5, 8.0)
    assert w[np.argmax(s)] == pytest.approx(2 * math.pi / 8.0, rel=1e-3)


def test_sea_state_table_matches_exact_sum_and_derivatives():
    hv = SeaStateHeave(0.5, 6.0, 'jonswap', random.Random(5), duration_s=60.0)
    ts = np.linspace(0.0, 59.0, 301)
    z, v, a = hv.exact_states(ts)
    got = np.array([hv.state(float(t)) for t in ts])
    assert np.max(np.abs(got[:, 0] - z)) < 2e-4
    assert np.max(np.abs(got[:, 1] - v)) < 2e-3
    assert np.max(np.abs(got[:, 2] - a)) < 2e-2
    # outside the table: the exact sum
    z2, v2, a2 = hv.exact_states(np.array([100.0]))
    assert hv.state(100.0) == pytest.approx((z2[0], v2[0], a2[0]), abs=1e-9)
    # analytic derivatives of the exact sum agree with finite differences
    h = 1e-4
    for t in (3.3, 17.1, 42.0):
        zp, vp, _ = hv.exact_states(np.array([t + h]))
        zm, vm, _ = hv.exact_states(np.array([t - h]))
        _, v0, a0 = hv.exact_states(np.array([t]))
        assert (zp[0] - zm[0]) / (2 * h) == pytest.approx(v0[0], abs=1e-6)
        assert (vp[0] - vm[0]) / (2 * h) == pytest.approx(a0[0], abs=1e-5)


def test_sea_state_seeded_and_seed_dependent():
    a = SeaStateHeave(1.0, 7.0, 'jonswap', random.Random(1), duration_s=20.0)
    b = SeaStateHeave(1.0, 7.0, 'jonswap', random.Random(1), duration_s=20.0)
    c = SeaStateHeave(1.0, 7.0, 'jonswap', random.Random(2), duration_s=20.0)
    assert a.state(12.34) == b.state(12.34)
    assert a.state(12.34) != c.state(12.34)


def test_deck_mean_height_and_drift():
    d = Deck((-3.2, -2.0), (1.05, 0.85), 0.6, SineHeave(0.2, 5.0, 0.0), (0.5, -0.25))
    cx, cy, z, _, _ = d.state(2.0)
    assert (cx, cy) == pytest.approx((-2.2, -2.5))
    assert z == pytest.approx(0.6 + 0.2 * math.sin(2 * math.pi * 2.0 / 5.0))
    assert (d.half_x, d.half_y) == (0.525, 0.425)
