"""deckland_common.contract and .checks: the shared value types and the input guard."""

import math

from deckland_common.checks import InputGuard, stamp_verdict
from deckland_common.contract import (
    APRON_STATE_V1_LEN,
    VERTICAL_FRAMES,
    ApronState,
    VehicleDescription,
    VerticalState,
    parse_vertical_frame,
)
from mavlink_bridge.conversions import ThrustCalibration
import pytest


def a_state(**changes):
    v = VerticalState(True, 1.2, -0.1, 1.4, -0.1, 0.2, 0.05, 0.3, 2, 0.45)
    fields = {'t_s': 3.0, 'tracked': True, 'visible': True, 'time_since_seen_s': 0.02,
              'rel_position_m': (0.1, -0.2), 'rel_velocity_mps': (0.01, 0.02),
              'rel_position_var_m2': (1e-4, 2e-4), 'rel_position_body_m': (0.2, 0.1),
              'rel_velocity_body_mps': (0.02, -0.01), 'apron_position_m': (5.1, 0.8),
              'apron_velocity_mps': (1.0, 0.0), 'vertical': v, 'camera_stamp_s': 2.98}
    fields.update(changes)
    return ApronState(**fields)


def test_apron_state_array_round_trip_and_nan_check():
    st = a_state()
    data = st.to_array()
    assert len(data) == APRON_STATE_V1_LEN
    assert ApronState.from_array(data) == st
    assert not st.has_nan() and not ApronState.untracked(1.0).has_nan()  # ±inf is not NaN
    for i in range(APRON_STATE_V1_LEN):
        bad = list(data)
        bad[i] = math.nan
        if i in (2, 3, 19, 27):     # flags and the epoch cannot carry a NaN as types
            continue
        st_bad = ApronState(*_fields_from(bad))
        assert st_bad.has_nan(), i


def _fields_from(a):
    v = VerticalState(a[19] > 0.5, a[20], a[21], a[22], a[23], a[24], a[25], a[26],
                      int(a[27]), a[28])
    return (a[0], a[2] > 0.5, a[3] > 0.5, a[4], (a[5], a[6]), (a[7], a[8]), (a[9], a[10]),
            (a[11], a[12]), (a[13], a[14]), (a[15], a[16]), (a[17], a[18]), v, a[1])


def test_one_name_per_vertical_frame():
    assert VERTICAL_FRAMES == ('relative', 'world_rate')
    assert [parse_vertical_frame(n) for n in ('relative', ' World_Rate ', '')] == [
        'relative', 'world_rate', 'relative']
    for alias in ('surface', 'world', 'map'):
        assert parse_vertical_frame(alias) is None


def test_vehicle_description_is_the_calibration_of_the_bridge():
    paper = VehicleDescription()
    assert (paper.mass_kg, paper.gravity_mps2, paper.hover_thrust_norm) == (2.71, 9.81, 0.5)
    sim = VehicleDescription.from_thrust_to_weight(2.71, 2.5)
    assert sim.hover_thrust_norm == pytest.approx(0.4)
    cal = ThrustCalibration.from_vehicle(sim)
    assert cal.to_norm(sim.weight_n) == pytest.approx(0.4)            # hover at 1/(T/W)
    assert cal.max_thrust_n == pytest.approx(2.5 * 2.71 * 9.81)         # full thrust = T/W m g
    assert ThrustCalibration() == ThrustCalibration.from_vehicle(paper)  # one set of defaults
    with pytest.raises(ValueError, match=r'VehicleDescription\.mass_kg'):
        VehicleDescription(mass_kg=0.0)
    with pytest.raises(ValueError, match='thrust_to_weight'):
        VehicleDescription.from_thrust_to_weight(2.71, 0.9)   # cannot hover
    with pytest.raises(ValueError, match='hover_thrust_norm'):
        VehicleDescription(hover_thrust_norm=1.0)


def test_stamp_verdict_reasons():
    assert stamp_verdict(1.0, 0.9, 1.05, 0.2) == ''
    assert stamp_verdict(1.0, -math.inf, 1.05, 0.2) == ''     # nothing accepted yet
    assert stamp_verdict(math.nan, -math.inf, 1.0, 0.2) == 'non_finite'
    assert stamp_verdict(0.8, 0.9, 1.0, 0.2) == 'out_of_order'
    assert stamp_verdict(0.7, -math.inf, 1.0, 0.2) == 'stale_stamp'
    assert stamp_verdict(1.3, -math.inf, 1.0, 0.2) == 'future_stamp'


def test_input_guard_counts_and_reports_changes_of_the_withholding_reason():
    guard = InputGuard(('non_finite',), ('stale', 'disabled'))
    seen = []
    guard.on_reject = lambda reason, what: seen.append(('reject', reason, what))
    guard.on_withhold = lambda reason: seen.append(('withhold', reason))
    guard.reject('non_finite', 'x')
    for reason in ('stale', 'stale', 'disabled'):
        guard.withhold(reason)
    assert guard.rejected == {'non_finite': 1}
    assert guard.withheld == {'stale': 2, 'disabled': 1}
    assert seen == [('reject', 'non_finite', 'x'), ('withhold', 'stale'),
                    ('withhold', 'disabled')]
    assert not guard.check_stamp(0.0, 1.0, 1.0, 0.2, 'y') and guard.rejected['out_of_order'] == 1
