"""Wiring of the altitude controllers to the estimator and planner (pure, no rclpy).

:func:`make_controller` builds the controller of a configuration; :func:`altitude_input` turns
an estimated :class:`~deckland_common.contract.VerticalState` plus a planner reference into the
controller's :class:`~dob_altitude.types.AltitudeInput` in the reference's vertical frame
(``deckland_common.contract.VERTICAL_FRAMES``): ``'relative'`` (the paper: z = z_v − z_s, the
DOB (18) lumps the heave into d) or ``'world_rate'`` (the deck-blind baseline: z = z_v). In
both, γ̄ of (4) uses the rotor plane's height above the *surface* (z_p = h + rotor offset).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, replace
import math
from typing import Any, TypeVar

from deckland_common.contract import (
    VERTICAL_FRAMES,
    VERTICAL_RELATIVE,
    VERTICAL_WORLD_RATE,
    VerticalState,
)

from dob_altitude.dob import DobAltitudeController, DobParams
from dob_altitude.ground_effect import ground_effect_gain
from dob_altitude.pid import PidAltitudeController, PidParams
from dob_altitude.types import AltitudeInput

#: Controller kinds :func:`make_controller` builds.
CONTROLLER_KINDS = ('dob', 'pid')
#: Gain profiles both parameter classes know.
GAIN_PROFILES = ('default', 'paper')
#: Default rotor plane above the body origin (docs/interfaces.md, vehicle geometry).
ROTOR_HEIGHT_OFFSET_M = 0.05

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


#: The gain fields of each kind; a node parameter below zero means "the profile's value".
GAIN_FIELDS = {'dob': ('k', 'lam', 'gamma_obs'), 'pid': ('kp', 'ki', 'kd')}


def controller_overrides(values: Mapping[str, Any]) -> dict[str, float]:
    """The controller fields set by the node's parameters ``values``: the gains of its
    ``controller`` kind that are given and >= 0, and the vehicle's mass and thrust limits."""
    out: dict[str, float] = {}
    for name in GAIN_FIELDS[str(values['controller'])]:
        v = values.get(name)
        if isinstance(v, (int, float)) and v >= 0.0:
            out[name] = float(v)
    for name in ('mass_kg', 'thrust_min_n', 'thrust_max_n'):
        out[name] = float(values[name])
    return out


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


def altitude_input(vertical: VerticalState, z_d_m: float, z_d_dot_mps: float,
                   z_d_ddot_mps2: float, vertical_frame: str, roll_rad: float,
                   pitch_rad: float, rotor_height_offset_m: float = ROTOR_HEIGHT_OFFSET_M,
                   surface_accel_ff: bool = False) -> AltitudeInput:
    """The controller input of one sample (model (6), error (7)-(8), γ̄ of (4)).

    ``'relative'``: z = h = ``vertical.height_m`` (z_v − z_s), ż = ``closing_speed_mps``;
    a_s = ``surface_accel_mps2`` if ``surface_accel_ff`` else 0 (the paper).
    ``'world_rate'``: z = ``vehicle_altitude_m``, ż = ``vehicle_vz_mps``, a_s = 0 always.
    Both: ``rotor_height_m`` = h + ``rotor_height_offset_m`` (z_p of (4)).

    A pure mapping: it does not judge ``vertical.valid`` or finiteness (the caller gates, the
    controller rejects and counts non-finite inputs).

    Raises:
        ValueError: ``vertical_frame`` is not one of ``VERTICAL_FRAMES`` (a programming
            error; normalise received names with ``contract.parse_vertical_frame``).
    """
    h = vertical.height_m
    if vertical_frame == VERTICAL_RELATIVE:
        return AltitudeInput(h, vertical.closing_speed_mps, z_d_m, z_d_dot_mps, z_d_ddot_mps2,
                             roll_rad, pitch_rad, h + rotor_height_offset_m,
                             vertical.surface_accel_mps2 if surface_accel_ff else 0.0)
    if vertical_frame == VERTICAL_WORLD_RATE:
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
