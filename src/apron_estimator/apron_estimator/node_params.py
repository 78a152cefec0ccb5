"""The apron estimator node's ROS parameters (pure: specs and their conversion, no rclpy).

Every ``EstimatorParams`` field flattened as ``section.field`` (``camera.``, ``horizontal.``,
``vertical.``) or ``field``, and every ``DeckFusionParams`` field as ``deck.field``, with its
meaning; defaults come from the dataclasses, so they never drift apart. Then the node's own
parameters (clock, rate, timeouts, frames). :func:`estimator_params_from` and
:func:`deck_params_from` build the cores' parameters from validated values.
"""

from __future__ import annotations

from dataclasses import MISSING, fields
import re

from deckland_common.params import ParameterError, ParamSpec, in_range, one_of, positive

from apron_estimator.camera import CameraParams
from apron_estimator.deck import DeckFusionParams
from apron_estimator.estimator import EstimatorParams
from apron_estimator.horizontal import HorizontalParams
from apron_estimator.loop import UNKNOWN_VAR
from apron_estimator.vertical import VerticalParams

#: Parameter prefix of each nested dataclass of EstimatorParams.
SECTIONS = (('camera', CameraParams), ('horizontal', HorizontalParams),
            ('vertical', VerticalParams))

#: Meaning of every estimator parameter (ROS name → description); defaults come from the
#: dataclasses so they never drift apart.
ESTIMATOR_DESCRIPTIONS = {
    'camera.fov_x_deg': 'full horizontal field of view of the Pixy; α_x = fov/2 in (27) '
                        '(Table 2: 60)',
    'camera.fov_y_deg': 'full vertical field of view; α_y = fov/2 in (28) (Table 2: 47)',
    'camera.width_px': 'image width; x_max = width/2 in (29)',
    'camera.height_px': 'image height; y_max = height/2 in (30)',
    'camera.cx_px': 'principal point x (image x right)',
    'camera.cy_px': 'principal point y (image y down)',
    'camera.mount_x_m': 'camera position from the body origin, FLU x (forward)',
    'camera.mount_y_m': 'camera position from the body origin, FLU y (left)',
    'camera.mount_z_m': 'camera position from the body origin, FLU z (up)',
    'camera.mount_roll_rad': 'extra camera rotation vs the default down-looking mount, roll',
    'camera.mount_pitch_rad': 'extra camera rotation vs the default mount, pitch',
    'camera.mount_yaw_rad': 'extra camera rotation vs the default mount, yaw',
    'camera.min_ray_down_cos': 'rays flatter than acos(this) from straight down give no fix',
    'camera.k1': 'lens distortion, radial k1 (Brown–Conrady on normalised coordinates; '
                 'default the Pixy lens, AP_IRLock characterisation)',
    'camera.k2': 'lens distortion, radial k2',
    'camera.p1': 'lens distortion, tangential p1',
    'camera.p2': 'lens distortion, tangential p2 (k1 = k2 = p1 = p2 = 0: the pinhole)',
    'camera.paper_exact': 'use (29)-(30) with the raw lidar range, no tilt compensation, '
                          'yaw-only (35)',
    'horizontal.accel_psd_m2ps3': 'q of the relative-position KF: Q = diag(0, q dt) per axis '
                                  '(31)',
    'horizontal.sigma0_m': 'camera measurement sigma at zero height (R of (33))',
    'horizontal.sigma_per_m': 'camera measurement sigma growth per metre of height',
    'horizontal.nis_gate': '2-D chi-square gate on the normalised innovation',
    'horizontal.acquire_hits': 'consistent detections before the apron is tracked',
    'horizontal.lost_timeout_s': 'no accepted detection for this long = track lost',
    'horizontal.init_vel_sigma_mps': 'relative velocity sigma at (re-)initialisation',
    'horizontal.use_accel_input': 'drive the KF with u = -vehicle acceleration (beyond the '
                                  'paper)',
    'horizontal.accel_history_s': 'acceleration history kept (>= lost_timeout_s)',
    'horizontal.rival_gate_m': 'false blobs: a detection this close (m) to a rival is that rival',
    'horizontal.rival_confirm_hits': 'false blobs: detections before a rival makes the target '
                                     'ambiguous',
    'horizontal.rival_timeout_s': 'false blobs: an unresolved rival unseen this long (s) is '
                                  'dropped',
    'horizontal.rejected_rival_timeout_s': 'false blobs: a rejected rival is remembered this '
                                           'long (s)',
    'horizontal.ambiguity_min_sep_m': 'false blobs: rivals closer (m) than this to the track do '
                                      'not matter',
    'horizontal.verify_radius_m': 'false blobs: lidar spot this close (m) to a hypothesis → '
                                  'surface sample',
    'horizontal.verify_dwell_s': 'false blobs: hover this long (s) before sampling',
    'horizontal.deck_rise_m': "false blobs: the beacon's surface is higher by at least this (m)",
    'horizontal.max_rivals': 'false blobs: rival hypotheses kept at most',
    'vertical.sigma_lidar_m': 'lidar sigma',
    'vertical.sigma_altitude_m': 'local position z sigma (GPS/EKF)',
    'vertical.sigma_vz_mps': 'local velocity z sigma',
    'vertical.use_vz': 'fuse the local vertical velocity',
    'vertical.vehicle_accel_psd_m2ps3': 'process noise of the vehicle acceleration input',
    'vertical.surface_accel_sigma_mps2': 'stationary sigma of the deck acceleration (Singer)',
    'vertical.surface_tau_s': 'Singer time constant of the deck acceleration',
    'vertical.surface_model': "'accel' (z_s, v_s, a_s) or 'velocity' (z_s, v_s)",
    'vertical.jump_threshold_m': 'minimum lidar innovation of a surface jump (re-base)',
    'vertical.jump_sigma': 'or this many innovation sigmas, if larger',
    'vertical.jump_confirm': 'consecutive consistent samples to re-base the surface',
    'vertical.jump_consistency_m': 'max spread of the innovations of a jump run',
    'vertical.jump_window_s': 'max age of a pending jump run',
    'vertical.rebase_vs_sigma_mps': 'surface velocity sigma after a re-base',
    'vertical.altitude_gate': 'NIS gate of the altitude / vz updates',
    'vertical.lidar_timeout_s': 'vertical state invalid after this long without a used lidar '
                                'sample',
    'vertical.range_min_m': 'shortest accepted lidar range',
    'vertical.range_max_m': 'longest accepted lidar range',
    'vertical.max_tilt_rad': 'no lidar fusion beyond this roll/pitch',
    'vertical.late_tolerance_s': 'samples this much older than the filter are applied now; '
                                 'older ones are out of order',
    'vertical.adapt_noise': 'lidar variance scaled by the noise learnt from the innovations '
                            '(covariance matching, >= the configured sigma)',
    'vertical.adapt_weight': 'weight of one accepted range in the learnt lidar noise',
    'vertical.adapt_max_scale': 'learnt lidar variance at most this times sigma_lidar_m^2',
    'horizontal.adapt_noise': 'camera variance scaled by the noise learnt from the innovations '
                              '(covariance matching, >= the configured sigma)',
    'horizontal.adapt_weight': 'weight of one accepted detection in the learnt camera noise',
    'horizontal.adapt_max_scale': 'learnt camera variance at most this times sigma^2',
    'horizontal.deck_jerk_psd_m2ps5': "q of the deck-acceleration filter (white jerk): the "
                                      "deck's acceleration fed forward by the planner",
    'horizontal.deck_accel_init_sigma_mps2': 'deck acceleration sigma at (re-)acquisition',
    'horizontal.deck_accel_max_sigma_mps2': 'deck acceleration published once its sigma is '
                                            'below this',
    'horizontal.deck_accel_max_height_m': 'deck acceleration published only from at most '
                                          'this high (m)',
    'beacon_signature': 'Pixy signature of the beacon (0 = any)',
    'attitude_history_s': 'attitude history kept for exposure-stamp look-ups',
    'max_attitude_gap_s': 'camera frame rejected without an attitude sample this close',
    'height_fallback_timeout_s': 'raw lidar height usable this long when the filter is invalid',
    'visible_timeout_s': "'visible' also needs a camera frame this recent",
    'max_position_extrapolation_s': 'cap of the vehicle position extrapolation for '
                                    'apron_position',
}


#: Meaning of every ``DeckFusionParams`` field, as the node's ``deck.<field>`` parameter.
DECK_DESCRIPTIONS = {
    'deck.telemetry_timeout_s': 'a deck/odom sample older than this (s) is not the deck any '
                                'more',
    'deck.attitude_timeout_s': 'deck attitude valid while this fresh (s)',
    'deck.attitude_extrapolation_s': 'deck roll / pitch / heading carried forward at most this '
                                     'long (s)',
    'deck.max_extrapolation_s': 'telemetry position carried forward at most this long (s)',
    'deck.offset_tau_s': 'averaging time (s) of the learnt GNSS offset (beacon - telemetry)',
    'deck.offset_gate_m': 'a residual this far (m) from the learnt offset is refused',
    'deck.offset_max_rel_m': 'the offset is learnt only with the vehicle this close (m) above '
                             'the beacon',
    'deck.beacon_history_s': 'beacon estimates kept (s) to meet delayed telemetry at its stamp',
    'deck.prediction_timeout_s': 'constant-velocity prediction of a lost deck at most this '
                                 'long (s)',
    'deck.accel_tau_s': "low-pass time constant (s) of the telemetry's deck acceleration",
    'deck.max_accel_mps2': 'clamp (m/s^2) of the published deck acceleration',
    'deck.beacon_accel': "while tracked, publish the beacon filter's deck acceleration rather "
                         "than the telemetry's",
}


def _deck_specs() -> list[ParamSpec]:
    """One ParamSpec per DeckFusionParams field, as ``deck.field``."""
    return [ParamSpec(f'deck.{f.name}', f.default,
                      DECK_DESCRIPTIONS[f'deck.{f.name}'] + ' (core default; the core validates)')
            for f in fields(DeckFusionParams)]


def _estimator_specs() -> list[ParamSpec]:
    """One ParamSpec per EstimatorParams field, flattened as ``section.field`` / ``field``."""
    specs = []
    rows = [(f'{prefix}.{f.name}', f.default) for prefix, cls in SECTIONS
            for f in fields(cls)]
    rows += [(f.name, f.default) for f in fields(EstimatorParams) if f.default is not MISSING]
    for name, default in rows:
        desc = ESTIMATOR_DESCRIPTIONS.get(name, 'estimator field (see the package README)')
        desc += ' (core default; the core validates)'
        if name == 'vertical.surface_model':
            specs.append(one_of(name, default, ('accel', 'velocity'), desc))
        else:
            specs.append(ParamSpec(name, default, desc))
    return specs


def _nonempty(name: str, default: str, description: str) -> ParamSpec:
    return ParamSpec(name, default, description, lambda v: bool(v.strip()), 'must not be empty')


NODE_PARAMS = [
    ParamSpec('rate_hz', 100.0,
              'control rate: the loop rate (clock=loop), or the IMU thinning rate (clock=imu: '
              'an IMU message publishes unless the previous IMU-triggered publication is less '
              'than 0.5/rate_hz old)',
              lambda v: 1.0 <= v <= 1000.0, 'must be in [1, 1000]'),
    one_of('clock', 'loop', ('loop', 'imu'),
           "what publishes apron/state: 'loop' = a rate_hz loop phase-locked to the camera "
           "frames; 'imu' = each vehicle/imu message and each camera frame (event-driven)"),
    in_range('loop_lead_s', 0.001, 0.0, 0.004,
             'clock=loop: wanted time from a processed camera frame to the next tick'),
    in_range('loop_max_slew_s', 0.0002, 0.0, 0.001,
             'clock=loop: largest phase correction per camera frame (period change)'),
    in_range('loop_max_wait_s', 0.003, 0.0, 0.009,
             'clock=loop: a frame further than this before its tick is published at once; '
             'must be >= loop_lead_s'),
    positive('input_timeout_s', 0.5,
             'inputs older (or newer) than this vs the node clock are rejected; no output '
             'while vehicle/imu or the local position is this stale'),
    positive('gravity_mps2', 9.81, 'g removed from the rotated IMU specific force'),
    in_range('position_pair_tolerance_s', 0.005, 0.0, 0.1,
             'max stamp difference of a vehicle/odom + vehicle/velocity pair'),
    ParamSpec('odom_when_untracked', False,
              'also publish apron/odom while not tracked (position = vehicle + 0, variance '
              f'{UNKNOWN_VAR:g}); off because LANDING_TARGET consumers ignore covariance'),
    _nonempty('map_frame', 'map', 'header.frame_id of apron/odom (world, ENU)'),
    _nonempty('apron_frame', 'apron', 'child_frame_id of apron/odom'),
    _nonempty('relative_frame', 'base_link',
              'frame_id of apron/relative(_velocity): heading-aligned FLU axes (Figure 8)'),
]

PARAMS = _estimator_specs() + _deck_specs() + NODE_PARAMS

_CLASS_PREFIX = {'CameraParams': 'camera.', 'HorizontalParams': 'horizontal.',
                 'VerticalParams': 'vertical.', 'EstimatorParams': '',
                 'DeckFusionParams': 'deck.'}


def estimator_params_from(values: dict) -> EstimatorParams:
    """Build EstimatorParams from validated flat values; ParameterError names the parameter."""
    try:
        nested = {prefix: cls(**{f.name: values[f'{prefix}.{f.name}'] for f in fields(cls)})
                  for prefix, cls in SECTIONS}
        top = {f.name: values[f.name] for f in fields(EstimatorParams)
               if f.default is not MISSING}
        return EstimatorParams(**nested, **top)
    except ValueError as exc:
        raise ParameterError(f'parameter {_name_of(exc)!r}: {exc}') from exc


def _name_of(exc: ValueError) -> str:
    """The ROS parameter a core's ``Class.field`` error names ('?' if none)."""
    m = re.match(r'(\w+)\.(\w+)', str(exc))
    return (_CLASS_PREFIX.get(m.group(1), '') + m.group(2)) if m else '?'


def deck_params_from(values: dict) -> DeckFusionParams:
    """Build DeckFusionParams from validated flat values; ParameterError names the parameter."""
    try:
        return DeckFusionParams(**{f.name: values[f'deck.{f.name}']
                                   for f in fields(DeckFusionParams)})
    except ValueError as exc:
        raise ParameterError(f'parameter {_name_of(exc)!r}: {exc}') from exc
