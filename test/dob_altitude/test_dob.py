"""DOB altitude controller against the paper's equations (6), (14)-(22) and physics.

The plant is the paper's vertical model (3)/(6) integrated here independently at 1 kHz:
    z̈ = −g + (γ/m) cφ cθ u_z + δ(t)   (world frame; a moving surface is subtracted explicitly)
with γ from (4) (the same ρ as the controller's ρ̄ unless a test says otherwise).
"""

import dataclasses
import math

from dob_altitude.dob import DobAltitudeController, DobParams
from dob_altitude.ground_effect import ground_effect_gain
from dob_altitude.types import AltitudeInput, AltitudeOutput
import pytest

P = DobParams()
M, G = P.mass_kg, P.gravity_mps2
ROTOR = 0.05  # rotor plane above the body origin (docs/interfaces.md)


def simulate(ctrl, params, t_end, *, delta=lambda t: 0.0, ref=lambda t: (1.0, 0.0, 0.0),
             surface=lambda t: (0.0, 0.0, 0.0), feed_surface_accel=False, z0=1.0, v0=0.0,
             att=(0.0, 0.0), rho_true=None, dt_sim=1e-3, n_sub=10, applied=None):
    """Closed loop: plant (3) at dt_sim, controller every n_sub plant steps (zero-order hold).

    ``surface(t)`` → (z_s, ż_s, z̈_s): the controller sees z = z_v − z_s (relative height).
    ``applied='unsat'`` feeds the previous *unsaturated* command back as the applied thrust
    (the wind-up variant). Returns a list of (t, z_rel, z_rel_dot, out, delta(t), z_s_ddot).
    """
    rho = params.rho_bar if rho_true is None else rho_true
    r, hmin, gmax = params.prop_radius_m, params.ge_min_rotor_height_m, params.ge_max_gain
    c_true = math.cos(att[0]) * math.cos(att[1])
    zs0 = surface(0.0)
    zv, vv = z0 + zs0[0], v0 + zs0[1]
    u = params.mass_kg * params.gravity_mps2
    prev_unsat = None
    log = []
    for i in range(round(t_end / dt_sim)):
        t = i * dt_sim
        zs, vs, a_s = surface(t)
        if i % n_sub == 0:
            zd, zd_dot, zd_ddot = ref(t)
            inp = AltitudeInput(zv - zs, vv - vs, zd, zd_dot, zd_ddot, att[0], att[1],
                                zv - zs + ROTOR, a_s if feed_surface_accel else 0.0)
            out = ctrl.step(inp, dt_sim * n_sub, prev_unsat if applied == 'unsat' else None)
            prev_unsat = out.thrust_unsat_n
            u = out.thrust_n
            log.append((t, zv - zs, vv - vs, out, delta(t), a_s))
        gamma = ground_effect_gain(rho, r, zv - zs + ROTOR, hmin, gmax)
        acc = -params.gravity_mps2 + gamma / params.mass_kg * c_true * u + delta(t)  # (3)
        zv += vv * dt_sim + 0.5 * acc * dt_sim * dt_sim
        vv += acc * dt_sim
    return log


def inp_at(z=1.0, z_dot=0.0, z_d=1.0, roll=0.0, pitch=0.0, rotor=None, **kw):
    rotor = z + ROTOR if rotor is None else rotor
    return AltitudeInput(z, z_dot, z_d, kw.get('zd_dot', 0.0), kw.get('zd_ddot', 0.0), roll,
                         pitch, rotor, kw.get('a_s', 0.0))


def log_slope(points):
    n = len(points)
    mt = sum(t for t, _ in points) / n
    my = sum(y for _, y in points) / n
    return (sum((t - mt) * (y - my) for t, y in points)
            / sum((t - mt) ** 2 for t, _ in points))


# --- parameters ---------------------------------------------------------------------------

def test_profiles_and_validation():
    paper = DobParams.profile('paper')
    assert (paper.k, paper.lam, paper.gamma_obs) == (0.85, 10.47, 1.6)  # Table 4
    assert DobParams.profile('default') == DobParams()
    assert dataclasses.replace(paper, k=2.0).k == 2.0
    with pytest.raises(ValueError, match='unknown profile'):
        DobParams.profile('fast')
    for field, value in [('k', 0.0), ('lam', -1.0), ('gamma_obs', math.nan),
                         ('mass_kg', math.inf), ('thrust_max_n', 20.0),
                         ('thrust_min_n', -1.0), ('thrust_min_n', 20.0),
                         ('max_tilt_rad', 1.5), ('ge_max_gain', 0.9), ('rho_bar', -0.1),
                         ('d_hat_limit_mps2', 0.0)]:
        with pytest.raises(ValueError, match=f'DobParams.{field}'):
            DobParams(**{field: value})


# --- equilibrium, (4), tilt guard ---------------------------------------------------------

@pytest.mark.parametrize(('roll', 'pitch', 'z'), [(0.0, 0.0, 2.0), (0.2, -0.1, 0.3),
                                                  (0.0, 0.3, 0.05), (-0.25, 0.0, 0.0)])
def test_hover_equilibrium(roll, pitch, z):
    """d = 0 and e = ė = 0 → u = m g / (γ̄ cφ cθ), and it stays there (d̂ stays 0)."""
    ctrl = DobAltitudeController(P)
    rotor = z + ROTOR
    gbar = ground_effect_gain(1.0, P.prop_radius_m, rotor, 0.05, 1.5)
    expected = M * G / (gbar * math.cos(roll) * math.cos(pitch))
    for _ in range(50):
        out = ctrl.step(inp_at(z=z, z_d=z, roll=roll, pitch=pitch), 0.01)
        assert out.thrust_n == pytest.approx(expected, rel=1e-12)
        assert out.d_hat_mps2 == pytest.approx(0.0, abs=1e-9)
    assert out.gamma_bar == gbar and not out.saturated and out.sigma == 0.0


def test_ground_effect_enters_with_nominal_rho():
    near = DobAltitudeController(P).step(inp_at(z=0.05, z_d=0.05), 0.01)
    far = DobAltitudeController(P).step(inp_at(z=5.0, z_d=5.0), 0.01)
    # rotor plane 0.1 m above the surface: (4) with ρ̄ = 1
    gamma = 1.0 / (1.0 - P.prop_radius_m ** 2 / (4 * 0.1) ** 2)
    assert near.gamma_bar == pytest.approx(gamma)
    assert near.thrust_n == pytest.approx(far.thrust_n * far.gamma_bar / gamma)


def test_tilt_guard_limits_the_division():
    ctrl = DobAltitudeController(P)
    out = ctrl.step(inp_at(z=3.0, z_d=3.0, roll=math.radians(60)), 0.01)
    gbar = out.gamma_bar
    assert out.thrust_n == pytest.approx(M * G / (gbar * math.cos(P.max_tilt_rad)))
    assert ctrl.clamped['tilt'] == 1
    upside_down = DobAltitudeController(P).step(inp_at(z=3.0, z_d=3.0, roll=3.0), 0.01)
    assert upside_down.thrust_n == pytest.approx(out.thrust_n)


# --- observer (18)-(19) and error dynamics (20), (22) ---------------------------------------

@pytest.mark.parametrize(('gamma_obs', 'n_sub'), [(1.6, 10), (3.0, 10), (1.6, 20)])
def test_estimation_error_decays_at_rate_gamma(gamma_obs, n_sub):
    """(22) with ḋ = 0: d̃(t) = d̃(0) e^(−Γt); measured log-slope of |d̃| ≈ −Γ."""
    params = dataclasses.replace(P, gamma_obs=gamma_obs)
    d = 3.0
    log = simulate(DobAltitudeController(params), params, 3.5, delta=lambda t: d,
                   n_sub=n_sub)
    assert log[0][3].d_hat_mps2 == 0.0  # start-up: d̂(0) = 0, so d̃(0) = d
    pts = [(t, math.log(abs(dd - out.d_hat_mps2))) for t, _, _, out, dd, _ in log if t > 0.0]
    assert log_slope(pts) == pytest.approx(-gamma_obs, rel=0.01)
    # and the vehicle returns to the reference with the disturbance estimated
    assert abs(log[-1][1] - 1.0) < 0.05


def test_sigma_obeys_equation_20_along_the_trajectory():
    """σ̇ = −K σ + d̃ (20), checked by central differences along a disturbed, tilted, moving
    trajectory in ground effect (γ = γ̄ varying with height)."""
    dt = 1e-3

    def ref(t):
        return (0.4 + 0.2 * math.sin(1.1 * t), 0.22 * math.cos(1.1 * t),
                -0.242 * math.sin(1.1 * t))

    log = simulate(DobAltitudeController(P), P, 6.0, delta=lambda t: 2.0 * math.sin(2.0 * t),
                   ref=ref, z0=0.6, att=(0.15, -0.1), dt_sim=dt, n_sub=1)
    errors, scale = [], 0.0
    for k in range(1, len(log) - 1):
        sig_dot = (log[k + 1][3].sigma - log[k - 1][3].sigma) / (2 * dt)
        out, d = log[k][3], log[k][4]
        assert not out.saturated
        predicted = -P.k * out.sigma + (d - out.d_hat_mps2)
        errors.append(abs(sig_dot - predicted))
        scale = max(scale, abs(sig_dot))
    assert scale > 1.0  # the check is not vacuous
    assert max(errors) < 0.01 * scale


def test_uniform_ultimate_bound_under_time_varying_disturbance():
    """Theorem 1 proves uniform ultimate boundedness. The cascade (22) → (20) → (14) gives an
    explicit ultimate bound: |d̃| ≤ sup|ḋ|/Γ, |σ| ≤ |d̃|/K, |e/√(e²+1)| ≤ |σ|/Λ. Linearised,
    e/d = s / ((s+K)(s+Γ)(s+Λ)), which predicts the steady amplitude."""
    amp, w = 2.0, 1.3
    w_ref = 2.0 * math.pi / 6.67  # heave-like reference: 0.3 m stroke, ~0.14 m/s

    def ref(t):
        return (1.0 + 0.15 * math.sin(w_ref * t), 0.15 * w_ref * math.cos(w_ref * t),
                -0.15 * w_ref ** 2 * math.sin(w_ref * t))

    log = simulate(DobAltitudeController(P), P, 40.0,
                   delta=lambda t: 1.0 + amp * math.sin(w * t), ref=ref)
    tail = [abs(z - ref(t)[0]) for t, z, *_ in log if t > 20.0]
    s = amp * w / P.gamma_obs / P.k / P.lam
    bound = s / math.sqrt(1.0 - s * s)
    assert max(tail) < bound
    k, g, lam = P.k, P.gamma_obs, P.lam
    predicted = amp * w / math.prod(math.hypot(w, p) for p in (k, g, lam))
    assert max(tail) == pytest.approx(predicted, rel=0.05)
    assert max(tail) < 0.1


def test_observer_absorbs_ground_effect_mismatch():
    """(5)-(6): with true ρ ≠ ρ̄ the lumped d = (cφcθ/m) Δγ u is estimated; no steady error."""
    z_d = 0.08  # rotor plane 0.13 m above the surface
    log = simulate(DobAltitudeController(P), P, 12.0, ref=lambda t: (z_d, 0.0, 0.0), z0=z_d,
                   rho_true=0.6)
    gamma = ground_effect_gain(0.6, P.prop_radius_m, z_d + ROTOR)
    gbar = ground_effect_gain(1.0, P.prop_radius_m, z_d + ROTOR)
    d_expected = G * (gamma - gbar) / gamma  # at equilibrium γ u / m = g
    assert d_expected < -0.2
    out = log[-1][3]
    assert out.d_hat_mps2 == pytest.approx(d_expected, rel=0.01)
    assert abs(log[-1][1] - z_d) < 1e-3


def test_surface_acceleration_feed_forward():
    """Relative height z = z_v − z_s: z̈ = −g + (γ̄/m)cφcθ u + δ − a_s. Feeding a_s moves it out of
    the lumped disturbance: d̂ then estimates δ alone and the heave no longer excites e."""
    w = 2.0 * math.pi / 5.0

    def surface(t):
        return (math.sin(w * t), w * math.cos(w * t), -w * w * math.sin(w * t))

    kw = {'delta': lambda t: 1.0, 'ref': lambda t: (2.0, 0.0, 0.0), 'z0': 2.0,
          'surface': surface}
    fed = simulate(DobAltitudeController(P), P, 20.0, feed_surface_accel=True, **kw)
    paper = simulate(DobAltitudeController(P), P, 20.0, feed_surface_accel=False, **kw)
    e_fed = max(abs(z - 2.0) for t, z, *_ in fed if t > 10.0)
    e_paper = max(abs(z - 2.0) for t, z, *_ in paper if t > 10.0)
    assert e_paper > 0.03  # −a_s is a disturbance of 1.6 m/s² amplitude for the paper's law
    assert e_fed < 0.05 * e_paper
    assert all(abs(out.d_hat_mps2 - 1.0) < 0.01 for t, _, _, out, *_ in fed if t > 10.0)
    # without feed-forward, d̂ tracks δ − a_s (lagging: it is a first-order filter)
    swing = [out.d_hat_mps2 for t, _, _, out, *_ in paper if t > 10.0]
    assert max(swing) - min(swing) > 2.0


def test_zero_surface_acceleration_is_the_paper_law():
    a = DobAltitudeController(P)
    b = DobAltitudeController(P)
    for k in range(20):
        x = AltitudeInput(1.0 + 0.01 * k, -0.1, 1.2, 0.05, 0.3, 0.05, 0.02, 1.1)
        y = AltitudeInput(1.0 + 0.01 * k, -0.1, 1.2, 0.05, 0.3, 0.05, 0.02, 1.1, 0.0)
        assert a.step(x, 0.01) == b.step(y, 0.01)
    # and a_s enters exactly like z̈_d
    c = DobAltitudeController(P)
    d = DobAltitudeController(P)
    for k in range(20):
        x = AltitudeInput(1.0 + 0.01 * k, -0.1, 1.2, 0.05, 0.3 + 0.7, 0.05, 0.02, 1.1)
        y = AltitudeInput(1.0 + 0.01 * k, -0.1, 1.2, 0.05, 0.3, 0.05, 0.02, 1.1, 0.7)
        assert c.step(x, 0.01).thrust_n == pytest.approx(d.step(y, 0.01).thrust_n, rel=1e-12)


# --- saturation and wind-up ---------------------------------------------------------------

def test_no_windup_with_applied_thrust():
    """A 3 m reference step with only 1.3 m g of thrust: the command saturates for ~1.5 s.
    Integrating the applied thrust keeps d̂ honest (the true d is 0); feeding the unsaturated
    command to the observer (the wind-up variant) drives d̂ to its bound and overshoots."""
    params = dataclasses.replace(P, thrust_max_n=1.3 * M * G)

    def ref(t):
        return (1.0 if t < 1.0 else 4.0, 0.0, 0.0)

    good = simulate(DobAltitudeController(params), params, 12.0, ref=ref)
    wound = simulate(DobAltitudeController(params), params, 12.0, ref=ref, applied='unsat')
    assert sum(out.saturated for *_, out, _, _ in good) > 50
    d_good = [abs(out.d_hat_mps2) for t, _, _, out, *_ in good if 1.6 < t < 2.5]
    d_wound = [abs(out.d_hat_mps2) for t, _, _, out, *_ in wound if 1.6 < t < 2.5]
    assert max(d_good) < 10.0  # only the decaying Γσ step of (18)
    assert max(d_wound) == pytest.approx(params.d_hat_limit_mps2)  # wound up to the bound
    over_good = max(z for _, z, *_ in good) - 4.0
    over_wound = max(z for _, z, *_ in wound) - 4.0
    assert over_good < 0.02
    assert over_wound > 10 * max(over_good, 0.01)
    assert abs(good[-1][1] - 4.0) < 0.01


def test_saturation_reports_and_clamps():
    ctrl = DobAltitudeController(P)
    low = ctrl.step(inp_at(z=1.0, z_d=1.0, z_dot=8.0), 0.01)  # climbing fast: cut thrust
    assert low.saturated and low.thrust_n == P.thrust_min_n > low.thrust_unsat_n
    ctrl.reset()
    high = ctrl.step(inp_at(z=1.0, z_d=1.0, z_dot=-8.0), 0.01)
    assert high.saturated and high.thrust_n == P.thrust_max_n < high.thrust_unsat_n


# --- bad input ----------------------------------------------------------------------------

def test_nan_and_bad_dt_are_rejected_without_touching_the_state():
    ctrl = DobAltitudeController(P)
    first = ctrl.step(inp_at(z=0.0, z_d=0.0, rotor=math.nan), 0.01)  # before any good sample
    assert ctrl.rejected['nan'] == 1
    assert first.thrust_n == pytest.approx(M * G)  # free-air hover: no ground-effect credit
    good = ctrl.step(inp_at(z=1.0, z_d=1.2, z_dot=0.1), 0.01)
    mu = ctrl.mu
    for bad in (inp_at(z=math.nan), inp_at(z_dot=math.inf), inp_at(roll=math.nan),
                AltitudeInput(1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, math.nan)):
        assert ctrl.step(bad, 0.01) is good
    assert ctrl.step(inp_at(), 0.01, applied_thrust_n=math.nan) is good
    for dt in (0.0, -0.01, math.nan, math.inf):
        assert ctrl.step(inp_at(), dt) is good
    assert ctrl.rejected == {'nan': 6, 'bad_dt': 4}
    assert ctrl.mu == mu
    out = ctrl.step(inp_at(z=1.0, z_d=1.2, z_dot=0.1), 0.01)
    assert all(math.isfinite(v) for v in (out.thrust_n, out.sigma, out.d_hat_mps2))


def test_rejected_samples_time_is_not_lost():
    """A rejected sample's dt is added to the next good one: good, NaN(dt), good(dt) is the
    same observer update as good, good(2 dt) with the thrust held meanwhile."""
    a = DobAltitudeController(P)
    b = DobAltitudeController(P)
    x0, x1 = inp_at(z=1.0, z_d=1.3, z_dot=0.2), inp_at(z=1.05, z_d=1.3, z_dot=0.3)
    a.step(x0, 0.01)
    a.step(inp_at(z=math.nan), 0.01)
    out_a = a.step(x1, 0.01)
    b.step(x0, 0.01)
    out_b = b.step(x1, 0.02)
    assert out_a == out_b
    assert isinstance(out_a, AltitudeOutput)


def test_reset_restarts_the_observer():
    ctrl = DobAltitudeController(P)
    for _ in range(100):
        ctrl.step(inp_at(z=1.0, z_d=1.0, z_dot=0.0), 0.01, applied_thrust_n=20.0)
    assert abs(ctrl.step(inp_at(), 0.01).d_hat_mps2) > 1.0
    ctrl.reset()
    assert ctrl.mu == 0.0
    assert ctrl.step(inp_at(z=0.5, z_d=1.0), 0.01).d_hat_mps2 == 0.0
