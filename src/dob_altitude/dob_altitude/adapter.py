"""Wiring of the altitude controllers to the estimator and planner (pure, no rclpy).

One implementation shared by the ROS node (:mod:`dob_altitude.node`) and the in-process runner
(``deckland.runner``): which controller a configuration builds, and how an estimated
:class:`~apron_estimator.types.VerticalState` plus a planner reference become the controller's
:class:`~dob_altitude.types.AltitudeInput`.

Vertical frames of the reference (paper §3.1 and the constant-rate baseline):

* ``'surface'`` (the paper): z is the body origin's height above the surface below,
  z = z_v − z_s, and ż its rate (closing speed), so (6)-(9) are written in the deck's frame and
  the DOB (18) lumps the deck heave into d. Optionally the estimated surface acceleration a_s is
  fed forward (beyond the paper; dob.py derivation, README decision 8).
* ``'world'`` (the deck-blind constant-rate baseline): z is the vehicle's world altitude z_v and
  ż its vertical speed; the deck's motion is not seen by the loop at all, so no a_s.

In both frames the nominal ground-effect gain γ̄ of (4) uses the rotor plane's height above the
*surface* (z_p = h + rotor offset): ground effect depends on what is under the rotors, not on
the reference frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, replace
import math
from typing import TypeVar

from apron_estimator.types import VerticalState

from dob_altitude.dob import DobAltitudeController, DobParams
from dob_altitude.ground_effect import ground_effect_gain
from dob_altitude.pid import PidAltitudeController, PidParams
from dob_altitude.types import AltitudeInput

#: Controller kinds :func:`make_controller` builds.
CONTROLLER_KINDS = ('dob', 'pid')
#: Gain profiles both parameter classes know.
GAIN_PROFILES = ('default', 'paper')
#: Vertical frames :func:`altitude_input` understands.
VERTICAL_FRAMES = ('surface', 'world')
#: Default rotor plane above the body origin (docs/interfaces.md, vehicle geometry).
ROTOR_HEIGHT_OFFSET_M = 0.05

# Names other components use for the same frames (landing_planner's PlannerOutput.vertical_mode
# says 'relative' / 'world_rate'; an empty joint name means the default, 'surface').
_FRAME_ALIASES = {
    '': 'surface', 'surface': 'surface', 'relative': 'surface',
    'world': 'world', 'world_rate': 'world',
}

AltitudeController = DobAltitudeController | PidAltitudeController


def make_controller(kind: str, profile: str = 'default',
                    overrides: Mapping[str, float] | None = None) -> AltitudeController:
    """Build the altitude controller of a configuration.

    Args:
        kind: ``'dob'`` (paper §3.1, (14)-(19)) or ``'pid'`` (the baseline, gains matched to
            the linearised DOB).
        profile: ``'default'`` or ``'paper'`` (Table 4 gains); see ``DobParams.profile``.
        overrides: parameter fields to replace in the profile (``{'k': 2.0}``,
            ``{'mass_kg': 2.9, 'kp': 30.0}``). Every key must be a field of the kind's params
            class; values are validated by that class.

    Raises:
        ValueError: unknown kind, profile or field, or a value the params class rejects
            (the message names the field). Configuration errors, raised at start-up only.
    """
    if kind == 'dob':
        return DobAltitudeController(_profile_params(DobParams, profile, overrides))
    if kind == 'pid':
        return PidAltitudeController(_profile_params(PidParams, profile, overrides))
    raise ValueError(f'controller kind: must be one of {list(CONTROLLER_KINDS)}, '
                     f'got {kind!r}')


_P = TypeVar('_P', DobParams, PidParams)


def _profile_params(cls: type[_P], profile: str, overrides: Mapping[str, float] | None) -> _P:
    """``cls.profile(profile)`` with ``overrides`` replaced (unknown fields rejected)."""
    params = cls.profile(profile)
    if overrides:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f'{cls.__name__}: unknown field(s) {unknown}; '
                             f'known: {sorted(known)}')
        params = replace(params, **{k: float(v) for k, v in overrides.items()})
    return params


def parse_vertical_frame(name: str) -> str | None:
    """Normalise a vertical-frame name to ``'surface'`` / ``'world'``; None if unknown.

    Accepts the planner's ``vertical_mode`` spellings too (``'relative'``, ``'world_rate'``)
    and ``''`` (unset → ``'surface'``, the paper's frame). Case and surrounding blanks ignored.
    """
    return _FRAME_ALIASES.get(name.strip().lower())


def altitude_input(vertical: VerticalState, z_d_m: float, z_d_dot_mps: float,
                   z_d_ddot_mps2: float, vertical_frame: str, roll_rad: float,
                   pitch_rad: float, rotor_height_offset_m: float = ROTOR_HEIGHT_OFFSET_M,
                   surface_accel_ff: bool = False) -> AltitudeInput:
    """The controller input of one sample (model (6), error (7)-(8), γ̄ of (4)).

    ``'surface'``: z = h = ``vertical.height_m`` (z_v − z_s), ż = ``closing_speed_mps``;
    a_s = ``surface_accel_mps2`` if ``surface_accel_ff`` else 0 (the paper).
    ``'world'``: z = ``vehicle_altitude_m``, ż = ``vehicle_vz_mps``, a_s = 0 always.
    Both: ``rotor_height_m`` = h + ``rotor_height_offset_m`` (z_p of (4)).

    A pure mapping: it does not judge ``vertical.valid`` or finiteness (the caller gates, the
    controller rejects and counts non-finite inputs).

    Raises:
        ValueError: ``vertical_frame`` is not ``'surface'`` / ``'world'`` (a programming
            error; normalise received names with :func:`parse_vertical_frame`).
    """
    h = vertical.height_m
    if vertical_frame == 'surface':
        return AltitudeInput(h, vertical.closing_speed_mps, z_d_m, z_d_dot_mps, z_d_ddot_mps2,
                             roll_rad, pitch_rad, h + rotor_height_offset_m,
                             vertical.surface_accel_mps2 if surface_accel_ff else 0.0)
    if vertical_frame == 'world':
        return AltitudeInput(vertical.vehicle_altitude_m, vertical.vehicle_vz_mps, z_d_m,
                             z_d_dot_mps, z_d_ddot_mps2, roll_rad, pitch_rad,
                             h + rotor_height_offset_m, 0.0)
    raise ValueError(f'vertical_frame: must be one of {list(VERTICAL_FRAMES)}, '
                     f'got {vertical_frame!r}')


def hover_thrust_n(controller: AltitudeController, rotor_height_m: float = math.inf) -> float:
    """m g / γ̄(z_p): the level-hover thrust of the controller's vehicle model, (6) with d = 0."""
    p = controller.params
    gbar = ground_effect_gain(p.rho_bar, p.prop_radius_m, rotor_height_m,
                              p.ge_min_rotor_height_m, p.ge_max_gain)
    return p.mass_kg * p.gravity_mps2 / gbar
