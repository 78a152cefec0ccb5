"""Inputs and outputs of the landing planner (docs/interfaces.md, ``landing_planner``).

Pure module: plain frozen dataclasses with slots, ENU world / FLU body conventions of
:mod:`deckland_common.frames`. ``ApronState`` and ``VerticalState`` are defined by
``apron_estimator.types``; the planner only reads their fields.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum

#: ``PlannerOutput.vertical_mode`` values.
VERTICAL_RELATIVE = 'relative'
VERTICAL_WORLD_RATE = 'world_rate'


class Mode(enum.Enum):
    """Named states of the landing state machine (paper section 3.3, README diagram)."""

    IDLE = 0
    TAKEOFF = 1
    APPROACH = 2
    ALIGN = 3
    DESCEND = 4
    FINAL = 5
    SEARCH = 6
    FALLBACK = 7
    HOLD = 8
    LANDED = 9


@dataclass(frozen=True, slots=True)
class VehicleState:
    """What the autopilot reports (local position ENU, attitude FLU in ENU, Z-Y-X Euler)."""

    t_s: float
    position_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    armed: bool = True
    landed: bool = False  # the autopilot's own land detector, if any


@dataclass(frozen=True, slots=True)
class PlannerOutput:
    """One planner step.

    ``vertical_mode`` (an addition to docs/interfaces.md) says how to read the vertical
    reference:

    * ``'relative'`` (default, the paper): ``z_d_m`` is the height of the body origin above the
      surface below (deck or ground) and the altitude controller tracks it with the measured
      height ``h`` and closing speed (7)-(9); the DOB absorbs the deck heave.
    * ``'world_rate'`` (``descent_profile='constant_rate'`` baseline, DESCEND/FINAL only):
      ``z_d_m`` is a *world* altitude (ENU z of the body origin, same datum as
      ``VerticalState.vehicle_altitude_m``) descending at a constant rate ``z_d_dot_mps``;
      the runner tracks it with a world-altitude controller, blind to the deck.
    """

    t_s: float
    mode: Mode
    setpoint_m: tuple[float, float]       # horizontal position setpoint, world ENU
    velocity_ff_mps: tuple[float, float]  # feed-forward (deck velocity when tracking)
    yaw_rad: float
    z_d_m: float                          # reference height (see vertical_mode)
    z_d_dot_mps: float
    z_d_ddot_mps2: float
    thrust_enabled: bool                  # False after LANDED (disarm / idle)
    searches: int
    reason: str                           # why the last transition happened
    vertical_mode: str = VERTICAL_RELATIVE

    @property
    def precise_xy(self) -> bool:
        """Fly the horizontal controller's stiffer gain set (over the deck, descending)."""
        return self.mode in (Mode.DESCEND, Mode.FINAL)
