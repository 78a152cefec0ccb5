"""Touchdown speed after a deck reversal: planner + real altitude law + vertical point mass.

Campaign-free closed loop (planner README, "Touchdown speed"): the vertical plant is (6) with
the controller's own nominal ground effect (so the model is exact), the deck heaves at a
constant 0.09 m/s (the paper's actuators) and reverses downward at a chosen moment of the
final descent, and the "estimator" sees the deck through a second-order tracker (natural
frequency ω, damping 0.7): right after the reversal its deck speed lags the truth, as the
vertical filter's does. The vehicle lags the reference while the deck falls away; without
the leash the reference keeps running down at the final speed and the law turns that height
error into catch-up speed at contact (Λ·e_z on the DOB's sliding surface (14)).
"""

from deckland_common.contract import Mode
from dob_altitude.adapter import ROTOR_HEIGHT_OFFSET_M, altitude_input, make_controller
from dob_altitude.ground_effect import ground_effect_gain
from landing_planner.planner import LandingPlanner, PlannerParams
from planner_support import make_apron, make_vehicle, make_vertical
import pytest

DT = 0.01
SUBSTEPS = 4
DECK_SPEED_MPS = 0.09


def fly(kind, t_reversal_s, omega_radps=6.0, params=None):
    """Land on a deck rising at 0.09 m/s that reverses ``t_reversal_s`` into FINAL.

    Returns (|vehicle vz − deck vz| at contact, mode at contact, LANDED before contact).
    """
    planner = LandingPlanner(params or PlannerParams())
    pp = planner.params
    ctl = make_controller(kind)
    cp = ctl.params
    m, g = cp.mass_kg, cp.gravity_mps2
    zs, vs = 0.0, DECK_SPEED_MPS               # true deck
    zv, vv = 0.6, DECK_SPEED_MPS               # vehicle 0.6 m above it, moving with it
    zse, vse = zs, vs                          # the estimator's deck
    zeta = 0.7
    planner.start_landing(0.0)
    t, t_final, landed_early = 0.0, None, False
    for _ in range(6000):
        vert = make_vertical(zv - zse, vv - vse, zse)
        apron = make_apron(t, (0.0, 0.0), (0.0, 0.0), vert)
        out = planner.step(t, DT, make_vehicle(t, (0.0, 0.0), zv), apron)
        if out.mode is Mode.FINAL and t_final is None:
            t_final = t
        landed_early = landed_early or out.mode is Mode.LANDED
        inp = altitude_input(vert, out.z_d_m, out.z_d_dot_mps, out.z_d_ddot_mps2, 'relative',
                             0.0, 0.0)
        thrust = ctl.step(inp, DT).thrust_n if out.thrust_enabled else 0.0
        h = DT / SUBSTEPS
        for _ in range(SUBSTEPS):
            if t_final is not None and t - t_final >= t_reversal_s:
                vs = -DECK_SPEED_MPS
            gam = ground_effect_gain(cp.rho_bar, cp.prop_radius_m,
                                     zv - zs + ROTOR_HEIGHT_OFFSET_M,
                                     cp.ge_min_rotor_height_m, cp.ge_max_gain)
            vv += (gam * thrust / m - g) * h
            zv += vv * h
            zs += vs * h
            e = zs - zse
            zse += (vse + 2.0 * zeta * omega_radps * e) * h
            vse += omega_radps * omega_radps * e * h
            if zv - zs <= pp.gear_height_m:
                return abs(vv - vs), out.mode, landed_early
        t += DT
    pytest.fail(f'no contact within {t:.0f} s (mode {planner.mode.name})')


# reversals from early in FINAL to after the nominal contact (0.3 m at 0.08 m/s ≈ 3.8 s)
REVERSALS_S = [0.5 + 0.25 * i for i in range(16)]


def test_deck_falling_away_in_the_final_descent_is_not_caught_up_at_contact():
    """DOB: the catch-up is bounded by the leash, Λ·final_leash_m, on top of the final
    speed, wherever in FINAL the deck turns down (without the leash: 0.157 m/s)."""
    pp = PlannerParams()
    lam = make_controller('dob').params.lam
    bound = pp.final_speed_mps + lam * pp.final_leash_m
    speeds = [fly('dob', t_rev)[0] for t_rev in REVERSALS_S]
    assert max(speeds) <= bound
    # and the undisturbed landings touch down at the final speed itself
    assert min(speeds) == pytest.approx(pp.final_speed_mps, abs=0.005)


def test_pid_baseline_gets_the_same_final_descent():
    pp = PlannerParams()
    lam = make_controller('dob').params.lam
    speeds = [fly('pid', t_rev)[0] for t_rev in REVERSALS_S]
    assert max(speeds) <= pp.final_speed_mps + lam * pp.final_leash_m


@pytest.mark.parametrize('kind', ['dob', 'pid'])
def test_a_slow_estimator_never_declares_landed_above_the_deck(kind):
    """A laggier deck estimate (ω = 3 rad/s) reads the receding deck too close; the leash
    must not turn that into LANDED (motors cut) before contact."""
    for t_rev in REVERSALS_S:
        speed, mode, landed_early = fly(kind, t_rev, omega_radps=3.0)
        assert not landed_early and mode is Mode.FINAL
        assert speed <= 0.15
