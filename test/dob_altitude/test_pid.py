"""PID baseline: same interface and plant as the DOB controller, integral action, anti-windup,
and the exact small-signal equivalence with the DOB law (16)-(19) for matched gains."""

import dataclasses
import math

from dob_altitude.dob import DobAltitudeController, DobParams
from dob_altitude.pid import PidAltitudeController, PidParams
from dob_altitude.types import AltitudeInput, AltitudeOutput
import pytest

P = PidParams()
M, G = P.mass_kg, P.gravity_mps2


def simulate(ctrl, t_end, *, delta=lambda t: 0.0, ref=lambda t: (1.0, 0.0, 0.0), z0=1.0,
             thrust_limit=None, dt_sim=1e-3, n_sub=10, feed_applied=False):
    """Plant (3) far from the ground (γ = γ̄ ≈ 1) at dt_sim, controller every n_sub steps.
    ``thrust_limit`` is an actuator limit unknown to the controller."""
    z, v = z0, 0.0
    u = M * G
    applied = None
    log = []
    for i in range(round(t_end / dt_sim)):
        t = i * dt_sim
        if i % n_sub == 0:
            zd, zd_dot, zd_ddot = ref(t)
            out = ctrl.step(AltitudeInput(z, v, zd, zd_dot, zd_ddot, 0.0, 0.0, 50.0),
                            dt_sim * n_sub, applied if feed_applied else None)
            u = out.thrust_n if thrust_limit is None else min(out.thrust_n, thrust_limit)
            applied = u
            log.append((t, z, out))
        acc = -G + out.gamma_bar / M * u + delta(t)
        z += v * dt_sim + 0.5 * acc * dt_sim * dt_sim
        v += acc * dt_sim
    return log


class NaivePid:
    """The same PID without anti-windup (textbook integral), for comparison."""

    def __init__(self, p):
        self.p, self.i = p, 0.0

    def step(self, inp, dt_s, applied=None):
        p = self.p
        e, e_dot = inp.z_m - inp.z_d_m, inp.z_dot_mps - inp.z_d_dot_mps
        self.i += e * dt_s
        u_unsat = M * (-p.kp * e - p.kd * e_dot - p.ki * self.i + G + inp.z_d_ddot_mps2)
        u = min(p.thrust_max_n, max(p.thrust_min_n, u_unsat))
        return AltitudeOutput(u, u_unsat, u != u_unsat, 0.0, p.ki * self.i, e, 1.0)


def test_matched_gains_and_validation():
    dob = DobParams()
    pid = PidParams.from_dob(dob)
    k, lam, gam = dob.k, dob.lam, dob.gamma_obs
    assert pid.kd == pytest.approx(k + lam + gam)
    assert pid.kp == pytest.approx(k * lam + k * gam + lam * gam)
    assert pid.ki == pytest.approx(k * lam * gam)
    assert PidParams.profile('paper') == pid == PidParams()
    tuned = PidParams.profile('default')    # the equal-effort sweep's winner (pid.py)
    assert (tuned.kp, tuned.ki, tuned.kd) == (16.2069, 8.5435, 20.672)
    assert tuned.mass_kg == pid.mass_kg and tuned.thrust_max_n == pid.thrust_max_n
    with pytest.raises(ValueError, match='unknown profile'):
        PidParams.profile('x')
    for field, value in [('kp', -1.0), ('ki', math.nan), ('thrust_max_n', 10.0),
                         ('integral_limit_mps2', 0.0), ('max_tilt_rad', 2.0)]:
        with pytest.raises(ValueError, match=f'PidParams.{field}'):
            PidParams(**{field: value})


def test_hover_equilibrium_and_interface():
    ctrl = PidAltitudeController(P)
    for _ in range(10):
        out = ctrl.step(AltitudeInput(2.0, 0.0, 2.0, 0.0, 0.0, 0.2, 0.1, 2.05), 0.01)
    assert isinstance(out, AltitudeOutput)
    assert out.thrust_n == pytest.approx(M * G / (out.gamma_bar * math.cos(0.2) * math.cos(0.1)))
    assert out.d_hat_mps2 == 0.0 and out.sigma == 0.0 and not out.saturated


@pytest.mark.parametrize('d', [-2.0, 1.5])
def test_step_and_ramp_without_steady_state_error(d):
    step = simulate(PidAltitudeController(P), 15.0, delta=lambda t: d,
                    ref=lambda t: (1.0 if t < 2.0 else 1.5, 0.0, 0.0))
    assert abs(step[-1][1] - 1.5) < 1e-3
    assert step[-1][2].d_hat_mps2 == pytest.approx(d, rel=1e-2)  # K_i ∫e cancels d
    ramp = simulate(PidAltitudeController(P), 15.0, delta=lambda t: d,
                    ref=lambda t: (1.0 + 0.3 * t, 0.3, 0.0))
    assert abs(ramp[-1][1] - (1.0 + 0.3 * ramp[-1][0])) < 1e-3


def test_conditional_integration_prevents_windup():
    """3 m step with only 1.3 m g thrust: the textbook integral winds up and overshoots."""
    params = dataclasses.replace(P, thrust_max_n=1.3 * M * G)

    def ref(t):
        return (1.0 if t < 1.0 else 4.0, 0.0, 0.0)

    aw = simulate(PidAltitudeController(params), 15.0, ref=ref)
    naive = simulate(NaivePid(params), 15.0, ref=ref)
    assert sum(out.saturated for *_, out in aw) > 50
    over_aw = max(z for _, z, _ in aw) - 4.0
    over_naive = max(z for _, z, _ in naive) - 4.0
    assert over_naive > 0.5
    assert over_aw < 0.5 * over_naive
    # while saturated high with e < 0 the integral (at 0 before the step) is frozen
    assert all(out.d_hat_mps2 == 0.0 for *_, out in aw if out.thrust_n == params.thrust_max_n)
    assert abs(aw[-1][1] - 4.0) < 0.01


def test_applied_thrust_reports_an_actuator_limit():
    """If the actuator applied less thrust than commanded (a limit the controller does not
    know), a negative error is not integrated; with the command applied it is."""
    below = AltitudeInput(1.0, 0.0, 1.1, 0.0, 0.0, 0.0, 0.0, 1.05)  # e = −0.1
    ctrl = PidAltitudeController(P)
    first = ctrl.step(below, 0.01)
    held = ctrl.step(below, 0.01, applied_thrust_n=first.thrust_n - 5.0)
    assert ctrl.integral == 0.0 and ctrl.clamped['integral'] == 1
    second = ctrl.step(below, 0.01, applied_thrust_n=held.thrust_n)
    assert ctrl.integral == pytest.approx(-0.1 * 0.01)
    # the same for an actuator stuck above the command with a positive error
    above = AltitudeInput(1.2, 0.0, 1.1, 0.0, 0.0, 0.0, 0.0, 1.25)
    ctrl.reset()
    ctrl.step(above, 0.01)
    ctrl.step(above, 0.01, applied_thrust_n=second.thrust_n + 20.0)
    assert ctrl.integral == 0.0


def test_small_signal_equivalence_with_the_dob_law():
    """Linearised, (16)-(19) is the PID with K_d = K+Λ+Γ, K_p = KΛ+KΓ+ΛΓ, K_i = KΛΓ: for a small
    disturbance step and a small reference motion both give the same trajectory."""
    dob = DobParams()

    def ref(t):  # starts at rest (ż_d(0) = 0) so both start in the same equilibrium
        return (1.0 - 0.01 * math.cos(0.7 * t), 0.007 * math.sin(0.7 * t),
                0.0049 * math.cos(0.7 * t))

    def delta(t):
        return 0.3 if t >= 0.5 else 0.0

    a = simulate(DobAltitudeController(dob), 10.0, delta=delta, ref=ref, z0=0.99)
    b = simulate(PidAltitudeController(PidParams.from_dob(dob)), 10.0, delta=delta, ref=ref,
                 z0=0.99)
    e_max = max(abs(z - ref(t)[0]) for t, z, _ in a)
    assert e_max > 5e-3
    diff = max(abs(za - zb) for (_, za, _), (_, zb, _) in zip(a, b, strict=True))
    assert diff < 0.02 * e_max
    # at the end both estimate the same constant disturbance
    assert a[-1][2].d_hat_mps2 == pytest.approx(0.3, abs=0.01)
    assert b[-1][2].d_hat_mps2 == pytest.approx(0.3, abs=0.01)


def test_bad_input_is_rejected():
    ctrl = PidAltitudeController(P)
    first = ctrl.step(AltitudeInput(math.nan, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0), 0.01)
    assert first.thrust_n == pytest.approx(M * G)
    good = ctrl.step(AltitudeInput(1.0, 0.0, 1.2, 0.0, 0.0, 0.0, 0.0, 1.05), 0.01)
    good2 = ctrl.step(AltitudeInput(1.0, 0.0, 1.2, 0.0, 0.0, 0.0, 0.0, 1.05), 0.01)
    integral = ctrl.integral
    assert ctrl.step(AltitudeInput(1.0, math.inf, 1.2, 0.0, 0.0, 0.0, 0.0, 1.05), 0.01) is good2
    assert ctrl.step(AltitudeInput(1.0, 0.0, 1.2, 0.0, 0.0, 0.0, 0.0, 1.05), -1.0) is good2
    assert ctrl.integral == integral
    assert ctrl.rejected == {'nan': 2, 'bad_dt': 1}
    assert good.thrust_n != good2.thrust_n  # the integral acted between the good samples
