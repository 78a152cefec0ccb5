"""The landing planner node's ROS parameters (pure: specs and their conversion, no rclpy).

One :class:`~deckland_common.params.ParamSpec` per ``PlannerParams`` field (same name; the
landing area as ``landing_area_x_m`` / ``_y_m``), the horizontal loop's gains (``xy_*``) and the
node's own rate, timeout and map frame; defaults come from the dataclasses, so they never
drift apart. :func:`params_from` builds the core parameter objects from validated values.
"""

from __future__ import annotations

from dataclasses import fields
import math

from deckland_common.params import ParameterError, ParamSpec, non_negative, one_of, positive

from landing_planner.horizontal import HorizontalParams
from landing_planner.planner import DESCENT_PROFILES, PlannerParams

#: Meaning of every PlannerParams field exposed as a ROS parameter (same name).
PLANNER_DESCRIPTIONS: dict[str, str] = {
    'max_xy_dist_m': 'accept a target only this close (m) to where the deck is predicted (the '
                     'landing area before any fix)',
    'acceptance_radius_m': 'horizontally close (m) to the target: may descend (paper 4.2)',
    'acceptance_hold_s': 'stay within the acceptance radius this long (s) before descending',
    'acceptance_hysteresis': 'leave acceptance_radius x this → pause the descent and re-align',
    'align_speed_mps': 'slew limit (m/s) of the setpoint toward the target',
    'approach_height_m': 'height (m) above the surface below for the approach (paper 4.2)',
    'approach_speed_mps': 'horizontal speed (m/s) of the GPS approach leg (Step 2)',
    'approach_accel_mps2': 'acceleration limit (m/s^2) of the approach/search path',
    'approach_jerk_mps3': 'jerk limit (m/s^3) of the approach/search path',
    'arrival_radius_m': 'vehicle this close (m) to the landing area = arrived',
    'arrival_wait_s': 'at the area this long (s) without a target → search (Step 3)',
    'vertical_speed_mps': 'climb/descent speed (m/s) to approach, search and hold heights',
    'vertical_accel_mps2': 'acceleration limit (m/s^2) of the vertical reference',
    'vertical_jerk_mps3': 'jerk limit (m/s^3) of the vertical reference',
    'descent_speed_mps': 'descent speed (m/s) relative to the deck (Step 6)',
    'final_approach_height_m': 'height (m) where the final approach starts (Step 9)',
    'final_speed_mps': 'final descent speed (m/s) relative to the deck (Step 10)',
    'final_press_m': 'final reference this far (m) below the contact height',
    'final_leash_m': 'final descent: the height reference at most this far (m) below the '
                     'measured height (bounds the catch-up speed of the altitude law)',
    'leash_filter_s': 'time constant (s) of the low-pass on the measured height that the '
                      'final-descent leash holds the reference to',
    'search_height_m': 'search height (m) above the surface below (Step 12)',
    'search_speed_mps': 'horizontal speed (m/s) of the search pattern',
    'search_radius_m': 'half side (m) of the square search pattern',
    'search_hold_s': 'hover (s) at the pattern centre before flying the square',
    'search_timeout_s': 'duration (s) of one search attempt',
    'max_searches': 'search attempts before the fallback landing (Steps 11, 14)',
    'target_lost_timeout_s': 'target unseen this long (s) = lost (Step 8)',
    'fallback_speed_mps': 'fallback descent speed (m/s) above the final-approach height',
    'gear_height_m': 'body origin above the bottom of the landing gear (m)',
    'landed_height_tol_m': 'landed: height within this (m) of gear_height_m',
    'landed_speed_tol_mps': 'landed: closing speed magnitude below this (m/s)',
    'landed_hold_s': 'landed: the conditions held this long (s) (Step 15)',
    'max_target_sigma_m': 'no descent while the target position σ (m) exceeds this (an '
                          'unresolved rival IR blob inflates it)',
    'landed_press_m': 'landed: the height reference already this far (m) below the measured '
                      'height (< final_press_m)',
    'invalid_timeout_s': 'invalid vehicle/vertical state this long (s) → safe mode',
    'descent_profile': "'deck_relative' (paper) or 'constant_rate' (world-rate baseline)",
    'constant_rate_mps': "world descent rate (m/s) of the 'constant_rate' profile",
    'timer_debounce_s': 'arrival/acceptance timers reset only after an excursion this long (s)',
    'deck_velocity_filter_s': 'deck track: time constant (s) of the velocity it predicts with',
    'deck_confirm_s': 'deck track: a beacon track predicts with its velocity after this long '
                      '(s) without a gap; before, at rest (telemetry: at once)',
    'track_timeout_s': 'deck track: a prediction older than this (s) is no track',
    'deck_yaw_offset_rad': 'heading (rad) to hold relative to the deck heading (telemetry)',
    'yaw_rate_max_radps': 'yaw alignment: rate limit (rad/s) of the heading command',
    'yaw_tolerance_rad': 'yaw alignment: descend only within this (rad) of the deck heading',
    'timed_touchdown': 'FINAL holds a gear clearance and commits into a predicted window',
    'commit_clearance_m': 'FINAL hold: gear this far (m) above the pad before the commit',
    'commit_timeout_s': 'FINAL hold without a ready deck prediction at most this long (s), then '
                        'the final descent as before',
    'commit_search_s': 'FINAL hold with a ready deck prediction: look for a commit window this '
                       'long (s), then the best commit offered within 3 s, then as before',
    'commit_check_s': 'look for a commit window every this often (s) while holding',
    'commit_follow_lag_s': 'commit window: lag (s) of the vehicle following the deck',
    'commit_leash_m': 'final_leash_m (m) of a descent committed into a window',
    'commit_plan_speed_mps': 'commit window: closing speed (m/s) the final descent achieves',
    'moving_final_speed_mps': 'final_speed_mps on a moving deck (faster than a drifting '
                              'barge): a firmer touchdown, less time for the deck to sway',
    'moving_commit_plan_speed_mps': 'commit_plan_speed_mps on a moving deck',
    'moving_landed_press_m': 'landed_press_m on a moving deck: LANDED (thrust off) sooner '
                             'after contact, before the deck slides out from under the gear',
    'moving_landed_hold_s': 'landed_hold_s on a moving deck',
    'moving_landed_height_tol_m': 'landed_height_tol_m on a moving deck (tighter: a deck '
                                  'receding under the vehicle also refuses the travel)',
    'wide_search_height_m': 'search height (m) above the surface below while the deck has '
                            'never been seen (it may have moved off the landing area)',
    'wide_search_climb_mps': 'climb speed (m/s) to wide_search_height_m',
    'wide_search_accel_mps2': 'acceleration limit (m/s^2) of the climb to '
                              'wide_search_height_m',
    'wide_search_yaw_rate_radps': 'yaw rate (rad/s) of the wide search: the wide axis of '
                                  'the camera sweeps round',
    'max_deck_speed_mps': 'in a wide search (deck never seen) the area gate grows this fast '
                          '(m/s) from the landing start (0: a fixed gate)',
    'max_go_arounds': 'go-arounds (deck broke the prediction, or blind over a moving deck with '
                      'only a prediction) per landing, at most',
    'predictor_warmup_updates': 'deck predictor: model updates before its paths are scored',
    'predictor_min_calibration': 'deck predictor: scored paths before it is ready',
}

_INT_PARAMS = ('max_searches', 'max_go_arounds', 'predictor_warmup_updates',
               'predictor_min_calibration')

#: ROS parameter name → HorizontalParams field, with its meaning.
HORIZONTAL_FIELDS: dict[str, tuple[str, str]] = {
    'xy_kp': ('kp', 'horizontal PID k_p (m/s^2 per m)'),
    'xy_kd': ('kd', 'horizontal PID k_d (m/s^2 per m/s of velocity error)'),
    'xy_ki': ('ki', 'horizontal PID k_i (m/s^2 per m s)'),
    'xy_precise_kp': ('precise_kp', 'k_p over the deck (DESCEND/FINAL)'),
    'xy_precise_kd': ('precise_kd', 'k_d over the deck (DESCEND/FINAL)'),
    'xy_precise_ki': ('precise_ki', 'k_i over the deck (DESCEND/FINAL)'),
    'xy_max_accel_mps2': ('max_accel_mps2', 'horizontal acceleration command limit (m/s^2)'),
    'max_tilt_rad': ('max_tilt_rad', 'tilt limit of the attitude command (rad)'),
    'xy_max_integral_accel_mps2': ('max_integral_accel_mps2',
                                   'clamp of the integral term per axis (m/s^2)'),
    'xy_integral_zone_m': ('integral_zone_m',
                           'integrate only while the position error is below this (m)'),
    'gravity_mps2': ('gravity_mps2', 'gravity used to turn acceleration into tilt (m/s^2)'),
}

_H_RULES = {
    'kp': (lambda v: v > 0, 'must be > 0'), 'kd': (lambda v: v >= 0, 'must be >= 0'),
    'ki': (lambda v: v >= 0, 'must be >= 0'),
    'precise_kp': (lambda v: v > 0, 'must be > 0'),
    'precise_kd': (lambda v: v >= 0, 'must be >= 0'),
    'precise_ki': (lambda v: v >= 0, 'must be >= 0'),
    'max_accel_mps2': (lambda v: v > 0, 'must be > 0'),
    'max_tilt_rad': (lambda v: 0 < v < math.radians(60.0), 'must be in (0, 1.0472) (60 deg)'),
    'max_integral_accel_mps2': (lambda v: v >= 0, 'must be >= 0'),
    'integral_zone_m': (lambda v: v > 0, 'must be > 0'),
    'gravity_mps2': (lambda v: v > 0, 'must be > 0'),
}


def _planner_specs() -> list[ParamSpec]:
    defaults = PlannerParams()
    specs = [
        ParamSpec('landing_area_x_m', float(defaults.landing_area_m[0]),
                  'landing area (expected apron position), ENU x / east (m)'),
        ParamSpec('landing_area_y_m', float(defaults.landing_area_m[1]),
                  'landing area (expected apron position), ENU y / north (m)'),
    ]
    for f in fields(PlannerParams):
        if f.name == 'landing_area_m':
            continue
        default = getattr(defaults, f.name)
        text = PLANNER_DESCRIPTIONS.get(f.name, f'PlannerParams.{f.name} (landing_planner '
                                        'README)')
        if f.name == 'descent_profile':
            specs.append(one_of(f.name, default, DESCENT_PROFILES, text))
        elif f.name in _INT_PARAMS:
            specs.append(ParamSpec(f.name, int(default), text, lambda v: v >= 0,
                                   'must be >= 0'))
        elif f.name == 'timed_touchdown':
            specs.append(ParamSpec(f.name, bool(default), text))
        elif f.name == 'deck_yaw_offset_rad':
            specs.append(ParamSpec(f.name, float(default), text))
        elif f.name == 'max_deck_speed_mps':
            specs.append(non_negative(f.name, float(default), text))
        elif f.name == 'acceptance_hysteresis':
            specs.append(ParamSpec(f.name, float(default), text, lambda v: v >= 1.0,
                                   'must be >= 1'))
        else:
            specs.append(positive(f.name, float(default), text))
    return specs


def _horizontal_specs() -> list[ParamSpec]:
    defaults = HorizontalParams()
    out = []
    for name, (field_name, text) in HORIZONTAL_FIELDS.items():
        check, rule = _H_RULES[field_name]
        out.append(ParamSpec(name, float(getattr(defaults, field_name)), text, check, rule))
    return out


PARAMS: list[ParamSpec] = [
    *_planner_specs(),
    *_horizontal_specs(),
    ParamSpec('rate_hz', 100.0,
              'nominal loop rate (Hz): the loop steps per apron/state; at this rate the '
              'watchdog steps while apron/state is stale, 1/rate_hz is the dt after a pause',
              lambda v: 1.0 <= v <= 1000.0, 'must be in [1, 1000]'),
    positive('input_timeout_s', 0.3,
             'apron/state or vehicle state older than this (s) = stale'),
    ParamSpec('map_frame', 'map', 'world frame id (ENU): required on vehicle/odom and '
              'vehicle/velocity, used on every output', lambda v: bool(v.strip()),
              'must not be empty'),
]


def params_from(values: dict) -> tuple[PlannerParams, HorizontalParams]:
    """Build the core parameter objects from validated ROS parameter values.

    The cores' own cross-field checks (e.g. the height ordering) raise ``ValueError``; it is
    turned into a :class:`ParameterError` naming the node.
    """
    kw = {f.name: values[f.name] for f in fields(PlannerParams)
          if f.name != 'landing_area_m' and f.name in values}
    kw['landing_area_m'] = (values['landing_area_x_m'], values['landing_area_y_m'])
    hkw = {field_name: values[name] for name, (field_name, _) in HORIZONTAL_FIELDS.items()}
    try:
        return PlannerParams(**kw), HorizontalParams(**hkw)
    except ValueError as exc:
        raise ParameterError(f'landing_planner: {exc}') from exc
