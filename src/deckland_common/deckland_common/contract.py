"""The value types the packages exchange (pure, no rclpy): docs/interfaces.md.

Camera blocks (pixy_driver → estimator), the apron state and its flat ``apron_state_v1`` array
(estimator → planner, altitude loop), the vehicle state (autopilot → planner), the planner's
modes, output and vertical reference (planner → altitude loop, horizontal loop), the vertical
frame names, and the vehicle description (mass, hover thrust) shared by the altitude
controller and the MAVLink bridge. Frames and units: :mod:`deckland_common.frames`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import enum
import math

from deckland_common import validate as chk

# ======================================================================== camera blocks


@dataclass(frozen=True, slots=True)
class PixyBlock:
    """One Pixy colour block (CMUcam5 block protocol), pixel coordinates of the frame."""

    signature: int
    x_px: float   # 0..319, image x right
    y_px: float   # 0..199, image y down
    width_px: float
    height_px: float


# ========================================================================== apron state

APRON_STATE_LAYOUT = 'apron_state_v1'

#: Field name at each index of the flat ``apron_state_v1`` array (``apron/state``,
#: std_msgs/Float64MultiArray). Booleans are 0.0 / 1.0, ``surface_epoch`` is an integer
#: stored as a float, ``time_since_seen_s`` / ``camera_stamp_s`` may be ±inf (never NaN).
APRON_STATE_V1_FIELDS: tuple[str, ...] = (
    't_s',                       # 0
    'camera_stamp_s',            # 1  stamp of the latest camera frame processed, -inf if none
    'tracked',                   # 2
    'visible',                   # 3
    'time_since_seen_s',         # 4  inf if never seen
    'rel_position_x_m',          # 5  beacon minus vehicle, ENU
    'rel_position_y_m',          # 6
    'rel_velocity_x_mps',        # 7
    'rel_velocity_y_mps',        # 8
    'rel_position_var_x_m2',     # 9
    'rel_position_var_y_m2',     # 10
    'rel_position_body_x_m',     # 11 heading frame (FLU): forward
    'rel_position_body_y_m',     # 12 heading frame (FLU): left
    'rel_velocity_body_x_mps',   # 13
    'rel_velocity_body_y_mps',   # 14
    'apron_position_x_m',        # 15 world ENU
    'apron_position_y_m',        # 16
    'apron_velocity_x_mps',      # 17
    'apron_velocity_y_mps',      # 18
    'vertical_valid',            # 19
    'height_m',                  # 20 body origin above the surface below
    'closing_speed_mps',         # 21 dh/dt
    'vehicle_altitude_m',        # 22
    'vehicle_vz_mps',            # 23
    'surface_height_m',          # 24
    'surface_vz_mps',            # 25
    'surface_accel_mps2',        # 26
    'surface_epoch',             # 27
    'last_rebase_m',             # 28
)
APRON_STATE_V1_LEN = len(APRON_STATE_V1_FIELDS)


@dataclass(frozen=True, slots=True)
class VerticalState:
    """Vertical state relative to the surface below (apron_estimator.vertical)."""

    valid: bool                   # lidar seen within timeout and filter initialised
    height_m: float               # body origin above the surface below (h = z_v − z_s)
    closing_speed_mps: float      # dh/dt
    vehicle_altitude_m: float     # z_v, world
    vehicle_vz_mps: float
    surface_height_m: float       # z_s, world (ground ≈ 0, deck = its top)
    surface_vz_mps: float
    surface_accel_mps2: float
    surface_epoch: int            # +1 every time the filter re-bases on a surface jump
    last_rebase_m: float          # size of the last jump (new z_s − old z_s)

    @classmethod
    def invalid(cls) -> VerticalState:
        """An all-zero, not-valid state (before the first lidar sample)."""
        return cls(False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0.0)


def _nan(x: float) -> bool:
    return x != x   # a plain float test (math.isnan is a Python call in the compiled cores)


#: Where the deck's position and velocity in :class:`ApronState` come from, best first.
DECK_SOURCE_BEACON = 'beacon'
DECK_SOURCE_TELEMETRY = 'telemetry'
DECK_SOURCE_PREDICTION = 'prediction'
DECK_SOURCE_NONE = 'none'
DECK_SOURCES = (DECK_SOURCE_BEACON, DECK_SOURCE_TELEMETRY, DECK_SOURCE_PREDICTION,
                DECK_SOURCE_NONE)


@dataclass(frozen=True, slots=True)
class ApronState:
    """Everything the planner and controllers need about the apron at time ``t_s``.

    ``camera_stamp_s``: the exposure stamp of the latest camera frame the estimator
    processed, ``-inf`` before the first one.
    """

    t_s: float
    tracked: bool                 # horizontal estimate valid (accepted detection within timeout)
    visible: bool                 # the latest camera frame had an accepted detection
    time_since_seen_s: float      # inf if never seen
    rel_position_m: tuple[float, float]   # beacon minus vehicle, ENU axes
    rel_velocity_mps: tuple[float, float]
    rel_position_var_m2: tuple[float, float]
    rel_position_body_m: tuple[float, float]   # the same in the heading (FLU) frame, Figure 8
    rel_velocity_body_mps: tuple[float, float]
    apron_position_m: tuple[float, float]      # world ENU = vehicle local position + rel
    apron_velocity_mps: tuple[float, float]    # = vehicle velocity + rel velocity
    vertical: VerticalState
    camera_stamp_s: float = -math.inf
    # The deck (landing area) as a moving target. ``source`` says where ``apron_position_m`` /
    # ``apron_velocity_mps`` come from (:data:`DECK_SOURCES`): the tracked beacon, the ship's
    # telemetry, or a prediction from the last estimate; ``'none'`` before any.
    source: str = 'none'
    apron_accel_mps2: tuple[float, float] = (0.0, 0.0)   # world ENU, deck horizontal accel
    deck_attitude_valid: bool = False                    # deck_rpy_rad / yaw rate known
    deck_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)   # deck roll, pitch, yaw (ENU)
    deck_yaw_rate_radps: float = 0.0

    @classmethod
    def untracked(cls, t_s: float) -> ApronState:
        """Nothing known yet: not tracked, never seen, zeros, invalid vertical state."""
        z = (0.0, 0.0)
        return cls(t_s, False, False, math.inf, z, z, z, z, z, z, z, VerticalState.invalid())

    def to_array(self) -> list[float]:
        """Flat ``apron_state_v1`` list of floats (index table: APRON_STATE_V1_FIELDS)."""
        v = self.vertical
        return [
            float(self.t_s), float(self.camera_stamp_s),
            1.0 if self.tracked else 0.0, 1.0 if self.visible else 0.0,
            float(self.time_since_seen_s),
            float(self.rel_position_m[0]), float(self.rel_position_m[1]),
            float(self.rel_velocity_mps[0]), float(self.rel_velocity_mps[1]),
            float(self.rel_position_var_m2[0]), float(self.rel_position_var_m2[1]),
            float(self.rel_position_body_m[0]), float(self.rel_position_body_m[1]),
            float(self.rel_velocity_body_mps[0]), float(self.rel_velocity_body_mps[1]),
            float(self.apron_position_m[0]), float(self.apron_position_m[1]),
            float(self.apron_velocity_mps[0]), float(self.apron_velocity_mps[1]),
            1.0 if v.valid else 0.0,
            float(v.height_m), float(v.closing_speed_mps),
            float(v.vehicle_altitude_m), float(v.vehicle_vz_mps),
            float(v.surface_height_m), float(v.surface_vz_mps), float(v.surface_accel_mps2),
            float(v.surface_epoch), float(v.last_rebase_m),
        ]

    def has_nan(self) -> bool:
        """Any field NaN (what :meth:`to_array` would carry; the estimator never does this)."""
        v = self.vertical
        return (_nan(self.t_s) or _nan(self.camera_stamp_s) or _nan(self.time_since_seen_s)
                or _nan(self.rel_position_m[0]) or _nan(self.rel_position_m[1])
                or _nan(self.rel_velocity_mps[0]) or _nan(self.rel_velocity_mps[1])
                or _nan(self.rel_position_var_m2[0]) or _nan(self.rel_position_var_m2[1])
                or _nan(self.rel_position_body_m[0]) or _nan(self.rel_position_body_m[1])
                or _nan(self.rel_velocity_body_mps[0]) or _nan(self.rel_velocity_body_mps[1])
                or _nan(self.apron_position_m[0]) or _nan(self.apron_position_m[1])
                or _nan(self.apron_velocity_mps[0]) or _nan(self.apron_velocity_mps[1])
                or _nan(v.height_m) or _nan(v.closing_speed_mps) or _nan(v.vehicle_altitude_m)
                or _nan(v.vehicle_vz_mps) or _nan(v.surface_height_m) or _nan(v.surface_vz_mps)
                or _nan(v.surface_accel_mps2) or _nan(v.last_rebase_m))

    @classmethod
    def from_array(cls, data: Sequence[float]) -> ApronState:
        """Inverse of :meth:`to_array`; raises ValueError on a wrong length or a NaN."""
        a = [float(x) for x in data]
        if len(a) != APRON_STATE_V1_LEN:
            raise ValueError(f'{APRON_STATE_LAYOUT}: expected {APRON_STATE_V1_LEN} values, '
                             f'got {len(a)}')
        if any(math.isnan(x) for x in a):
            raise ValueError(f'{APRON_STATE_LAYOUT}: NaN in data')
        vertical = VerticalState(a[19] > 0.5, a[20], a[21], a[22], a[23], a[24], a[25], a[26],
                                 round(a[27]), a[28])
        return cls(
            t_s=a[0], tracked=a[2] > 0.5, visible=a[3] > 0.5, time_since_seen_s=a[4],
            rel_position_m=(a[5], a[6]), rel_velocity_mps=(a[7], a[8]),
            rel_position_var_m2=(a[9], a[10]), rel_position_body_m=(a[11], a[12]),
            rel_velocity_body_mps=(a[13], a[14]), apron_position_m=(a[15], a[16]),
            apron_velocity_mps=(a[17], a[18]), vertical=vertical, camera_stamp_s=a[1])


def decode_apron_array(label: str | None, data: Sequence[float]
                       ) -> tuple[ApronState | None, str, str]:
    """Decode an ``apron/state`` array for a consumer: ``(state, reason, detail)``.

    ``state`` is None when the message must be rejected; ``reason`` is then the counter name
    (``'bad_layout'``, ``'bad_size'`` or ``'non_finite'``) and ``detail`` what to log. A
    missing layout label is accepted (the size decides); a different label is not.
    """
    if label is not None and label != APRON_STATE_LAYOUT:
        return None, 'bad_layout', f'apron/state (layout {label!r})'
    try:
        return ApronState.from_array(data), '', ''
    except ValueError as exc:
        return None, 'non_finite' if 'NaN' in str(exc) else 'bad_size', f'apron/state: {exc}'
    except OverflowError:  # an infinite surface_epoch cannot be rounded to an int
        return None, 'non_finite', 'apron/state (surface_epoch)'


# ======================================================================== vehicle state


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


# ============================================================ planner modes and output

#: The vertical frame of a height reference (``PlannerOutput.vertical_mode``, the joint name
#: of ``planner/reference``, the altitude loop's input): ``'relative'`` = height of the body
#: origin above the surface below (the paper), ``'world_rate'`` = world altitude of the body
#: origin (ENU z, the deck-blind constant-rate baseline).
VERTICAL_RELATIVE = 'relative'
VERTICAL_WORLD_RATE = 'world_rate'
VERTICAL_FRAMES = (VERTICAL_RELATIVE, VERTICAL_WORLD_RATE)


def parse_vertical_frame(name: str) -> str | None:
    """A received frame name → one of :data:`VERTICAL_FRAMES`, or None if unknown.

    Case and surrounding blanks are ignored; an empty name (an unset joint name) is the
    paper's ``'relative'``.
    """
    key = name.strip().lower()
    if not key:
        return VERTICAL_RELATIVE
    return key if key in VERTICAL_FRAMES else None


class Mode(enum.Enum):
    """Named states of the landing state machine (paper section 3.3, planner README)."""

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
class PlannerOutput:
    """One planner step.

    ``vertical_mode`` says how to read the vertical reference (:data:`VERTICAL_FRAMES`):
    ``'relative'`` (the paper) — ``z_d_m`` is the height of the body origin above the surface
    below, tracked with the measured height and closing speed (7)-(9), so the DOB absorbs the
    heave; ``'world_rate'`` (``descent_profile='constant_rate'``, DESCEND/FINAL only) —
    ``z_d_m`` is a world altitude (same datum as ``VerticalState.vehicle_altitude_m``)
    descending at the constant rate ``z_d_dot_mps``, blind to the deck.
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
    accel_ff_mps2: tuple[float, float] = (0.0, 0.0)   # deck acceleration feed-forward, ENU

    @property
    def precise_xy(self) -> bool:
        """Fly the horizontal controller's stiffer gain set (over the deck, descending)."""
        return self.mode in (Mode.DESCEND, Mode.FINAL)


@dataclass(frozen=True, slots=True)
class VerticalReference:
    """The vertical part of ``planner/reference`` as the altitude loop receives it."""

    z_d_m: float
    z_d_dot_mps: float
    z_d_ddot_mps2: float
    frame: str        # one of VERTICAL_FRAMES
    stamp_s: float    # the t_s of the apron state the planner computed it from


# ================================================================== vehicle description

#: Take-off mass of the paper's quadcopter (Table 2), kg.
PAPER_MASS_KG = 2.71
#: Gravity of the paper (Table 2), m/s².
GRAVITY_MPS2 = 9.81


@dataclass(frozen=True, slots=True)
class VehicleDescription:
    """Mass and thrust curve of the flying vehicle: the one source the altitude controller
    (its model (6)) and the MAVLink bridge (newtons ↔ normalised thrust) are given.

    In simulation it comes from the scenario (:meth:`from_thrust_to_weight`), on hardware from
    parameters. Thrust curve (PX4 ``THR_MDL_FAC`` / ArduPilot ``MOT_THST_EXPO``):
    F(n) = F_max (e n² + (1 − e) n), with hover F = m g at n = ``hover_thrust_norm``.
    """

    mass_kg: float = PAPER_MASS_KG
    gravity_mps2: float = GRAVITY_MPS2
    hover_thrust_norm: float = 0.5     # PX4 MPC_THR_HOVER; 1 / thrust-to-weight when e = 0
    thrust_expo: float = 0.0           # e above, in [0, 1]

    def __post_init__(self) -> None:
        o = 'VehicleDescription'
        chk.positive(f'{o}.mass_kg', self.mass_kg)
        chk.positive(f'{o}.gravity_mps2', self.gravity_mps2)
        chk.require(chk.is_finite_number(self.hover_thrust_norm)
                    and 0.0 < self.hover_thrust_norm < 1.0,
                    f'{o}.hover_thrust_norm', 'must be in (0, 1)', self.hover_thrust_norm)
        chk.in_range(f'{o}.thrust_expo', self.thrust_expo, 0.0, 1.0)

    @classmethod
    def from_thrust_to_weight(cls, mass_kg: float, thrust_to_weight: float,
                              gravity_mps2: float = GRAVITY_MPS2) -> VehicleDescription:
        """A vehicle with a linear thrust curve (e = 0) whose full thrust is ``thrust_to_weight``
        times its weight: hover at 1 / thrust_to_weight (the simulator's vehicle)."""
        chk.require(chk.is_finite_number(thrust_to_weight) and thrust_to_weight > 1.0,
                    'VehicleDescription.thrust_to_weight', 'must be > 1', thrust_to_weight)
        return cls(mass_kg=mass_kg, gravity_mps2=gravity_mps2,
                   hover_thrust_norm=1.0 / thrust_to_weight, thrust_expo=0.0)

    @property
    def weight_n(self) -> float:
        """m g (N): the hover thrust out of ground effect."""
        return self.mass_kg * self.gravity_mps2
