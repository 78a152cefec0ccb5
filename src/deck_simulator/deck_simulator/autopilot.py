"""The simulator-side autopilot: what flies the vehicle between the companion and the physics.

:class:`Autopilot` is what the world steps every physics sub-step. :class:`EmulatedAutopilot`
is the PX4-like stand-in flown on the world's truth: modes, offboard acceptance, the offboard-
loss failsafe (hold, then land or return: ``COM_OF_LOSS_T``, ``COM_FAIL_ACT_T``,
``COM_OBL_RC_ACT``), the land detector (``COM_DISARM_LAND``) and the hold / land / return
flight laws. Its companion side is driven by a MAVLink personality
(:class:`~deck_simulator.px4_emulator.Px4Emulator`) or by the in-process command link
(:class:`~deck_simulator.link.CommandLink`). Firmware backends (PX4 SITL, ArduPilot JSON)
implement :class:`Autopilot` only: the firmware speaks MAVLink to the companion itself.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

from deckland_common.frames import world_to_body_xy
from deckland_common.validate import is_finite_number, one_of, positive, require

if TYPE_CHECKING:
    from deck_simulator.world import World

# generic modes; a personality maps them to its own (PX4 custom modes, ArduCopter modes)
POSITION = 'position'   # PX4 POSCTL: the start hover (after a manual take-off)
ALTITUDE = 'altitude'   # PX4 ALTCTL, flown as a position hold here
OFFBOARD = 'offboard'   # PX4 OFFBOARD / ArduCopter GUIDED_NOGPS: the companion's setpoints
HOLD = 'hold'           # PX4 AUTO.LOITER
LAND = 'land'           # PX4 AUTO.LAND
RETURN = 'return'       # PX4 AUTO.RTL
MODES = (POSITION, ALTITUDE, OFFBOARD, HOLD, LAND, RETURN)
#: offboard-loss actions (COM_OBL_RC_ACT): 'position' is PX4's default 0, without RC a descent
#: while the mode reads POSCTL
LOSS_ACTIONS = ('land', 'hold', 'return', 'position')

# command results, as MAV_RESULT
ACCEPTED = 0
TEMPORARILY_REJECTED = 1
DENIED = 2
UNSUPPORTED = 3

# flight laws (PX4 position-controller stand-in on truth)
LAW_PERIOD_S = 0.01      # 100 Hz
MAX_TILT_RAD = 0.3
BRAKED_MPS = 0.3         # horizontal speed below which the hold point is fixed
HOME_RADIUS_M = 0.3      # return: at home (and braked) → land there


class AttitudeSetpoint(NamedTuple):
    """A companion setpoint: attitude (FLU in ENU, Z-Y-X) and collective thrust u_z (N)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_n: float


class Autopilot(Protocol):
    """What the world needs from an autopilot backend (one per world)."""

    #: stepped by the world (:meth:`tick` every physics sub-step) while True
    active: bool
    #: the motors run (the world cuts them while False)
    armed: bool
    #: offboard-loss failsafes engaged so far
    failsafes: int

    def tick(self, t_s: float, world: World) -> None:
        """Every physics sub-step at ``t_s``, before the physics: run the autopilot and set
        the vehicle's input (``world.vehicle`` attitude/thrust command, or motor commands)."""

    @property
    def failsafe(self) -> str | None:
        """The failsafe phase flown now (``'hold'``, ``'return'``, ``'land'``) or None."""


@dataclass(frozen=True, slots=True)
class AutopilotParams:
    """Behaviour of :class:`EmulatedAutopilot`; comments name the PX4 parameter it stands for."""

    offboard_loss_timeout_s: float = 1.0   # COM_OF_LOSS_T
    offboard_loss_action: str = 'land'     # COM_OBL_RC_ACT: land | hold | return | position
    action_delay_s: float = 0.0            # COM_FAIL_ACT_T: hold this long before the action
    land_speed_mps: float = 0.7            # MPC_LAND_SPEED
    min_alt_m: float = 0.0                 # failsafe hold/return: climb to this world altitude
    climb_speed_mps: float = 0.5           # ... at this rate (below MPC_Z_VEL_MAX_UP, gentle)
    return_speed_mps: float = 1.0          # RTL horizontal speed toward home
    reengage_offboard: bool = False        # a setpoint ends a failsafe (the in-process stand-in
    #                                        of the companion asking for OFFBOARD again)
    disarm_landed_s: float = 2.0           # COM_DISARM_LAND (<= 0: off)
    disarm_preflight_s: float = 10.0       # COM_DISARM_PRFLT (<= 0: off)

    def __post_init__(self) -> None:
        for name in ('offboard_loss_timeout_s', 'land_speed_mps', 'climb_speed_mps',
                     'return_speed_mps'):
            positive(f'AutopilotParams.{name}', getattr(self, name))
        for name in ('action_delay_s', 'min_alt_m'):
            v = getattr(self, name)
            require(is_finite_number(v) and v >= 0, f'AutopilotParams.{name}',
                    'must be a finite number >= 0', v)
        for name in ('disarm_landed_s', 'disarm_preflight_s'):
            require(is_finite_number(getattr(self, name)), f'AutopilotParams.{name}',
                    'must be a finite number', getattr(self, name))
        one_of('AutopilotParams.offboard_loss_action', self.offboard_loss_action, LOSS_ACTIONS)
        require(isinstance(self.reengage_offboard, bool), 'AutopilotParams.reengage_offboard',
                'must be true or false', self.reengage_offboard)


def with_link_fault(base: AutopilotParams, spec: Any) -> AutopilotParams:
    """``base`` with the autopilot settings a scenario's link fault carries
    (:class:`deck_simulator.faults._LinkFault`: COM_OF_LOSS_T, the land/climb/return speeds,
    the failsafe altitude, and ``action: return`` → RTL)."""
    return replace(base, offboard_loss_timeout_s=spec.loss_timeout_s,
                   offboard_loss_action=('return' if spec.action == 'return'
                                         else base.offboard_loss_action),
                   land_speed_mps=spec.land_speed_mps, min_alt_m=spec.min_alt_m,
                   climb_speed_mps=spec.climb_speed_mps,
                   return_speed_mps=spec.return_speed_mps)


def in_process_params(spec: Any = None) -> AutopilotParams:
    """The in-process autopilot of a world: PX4's defaults, or with a link fault (``spec``)
    the fault's settings, its ``hold_s`` before the action and its ``reengage_offboard``;
    the land detector on (``COM_DISARM_LAND``: it disarms 2 s after touchdown), no preflight
    disarm (the run starts in the air)."""
    base = AutopilotParams(disarm_preflight_s=0.0)
    if spec is None:
        return base
    return replace(with_link_fault(base, spec), action_delay_s=spec.hold_s,
                   reengage_offboard=spec.reengage_offboard)


class EmulatedAutopilot:
    """A PX4-like autopilot on the world's truth (see the module docstring).

    Companion side: :meth:`engage_offboard` (in-process: the companion streams from now on),
    :meth:`on_setpoint`, :meth:`request_mode`, :meth:`request_arm`. Simulator side:
    :meth:`tick` (the world, every sub-step) or :meth:`update` (mode logic only, for an
    emulator without a world). With a ``world`` a setpoint in OFFBOARD is applied at once
    (``world.set_command``); the other modes are flown by :meth:`tick` at 100 Hz:

    * hold (POSCTL, ALTCTL, AUTO.LOITER, the failsafe's hold): brake to rest, then hold that
      point, the heading and the altitude of the switch (a failsafe climbs to ``min_alt_m`` at
      ``climb_speed_mps``): PD on position → tilt, (3) inverted for the thrust
      u_z = m (g + a_z) / (γ cφ cθ) with the true γ of (4);
    * land: the same over the held point, descending at ``land_speed_mps``, zero thrust once
      resting on a surface;
    * return (RTL): after braking the hold point slews to home (where OFFBOARD was engaged) at
      ``return_speed_mps``; at home and braked it lands there (the mode stays RETURN);
    * disarmed: level, zero thrust.
    """

    def __init__(self, params: AutopilotParams, world: World | None = None) -> None:
        self.params = params
        self.world = world
        self.active = False
        self.armed = False
        self.mode = POSITION
        self.in_failsafe = False
        self.failsafes = 0
        self.landed = False
        #: (x, y) ENU where OFFBOARD was last engaged: the RTL target (None before)
        self.home_m: tuple[float, float] | None = None
        self.setpoint: AttitudeSetpoint | None = None
        self.last_setpoint_s = -math.inf
        self.rejected: dict[str, int] = {'nan': 0}
        self._user_mode = POSITION    # the mode last asked for: restored after a failsafe
        self._law = 'idle'            # 'offboard' | 'idle' | 'hold' | 'land' | 'return'
        self._ref = (0.0, 0.0, 0.0, 0.0)   # held x, y, z, yaw
        self._braked = False
        self._phase_t0_s = 0.0
        self._next_s = 0.0
        self._action_pending = False
        self._landed_since_s = -1.0   # < 0: not resting
        self._airborne_since_arm = False

    # --- state ---------------------------------------------------------------------------

    @property
    def failsafe(self) -> str | None:
        """The failsafe phase flown now: ``'hold'``, ``'return'``, ``'land'``, or None."""
        return self._law if self.in_failsafe and self.armed else None

    @property
    def kind(self) -> str:
        """What flies the vehicle: ``'idle'`` (disarmed), ``'offboard'``, ``'hold'``, ``'land'``,
        ``'return'`` (``'failsafe_'`` before the last three in a failsafe)."""
        if not self.armed:
            return 'idle'
        if self.mode == OFFBOARD:
            return 'offboard'
        if self.in_failsafe:
            return 'failsafe_' + ('hold' if self._law == HOLD and self.mode == HOLD
                                  else RETURN if self.mode == RETURN else LAND)
        return LAND if self.mode == LAND else HOLD

    @property
    def hold_point_m(self) -> tuple[float, float, float]:
        """The point the hold / land / return law flies to now (world ENU)."""
        return self._ref[0], self._ref[1], self._ref[2]

    # --- companion side ------------------------------------------------------------------

    def start_in_air(self, t_s: float) -> None:
        """Armed and flying in POSITION mode, holding where the vehicle is (the mission starts
        after a manual take-off); stepped by the world from now on."""
        self.active = True
        self.armed = True
        self._airborne_since_arm = True
        self._set_mode(POSITION, t_s)

    def engage_offboard(self, t_s: float) -> None:
        """The companion has the vehicle from ``t_s`` on (in-process: its first command; the
        handshake a real companion makes is implied): armed, OFFBOARD, home here."""
        self.active = True
        self.armed = True
        self._airborne_since_arm = True
        self.last_setpoint_s = t_s
        self._user_mode = OFFBOARD
        self._set_mode(OFFBOARD, t_s)

    def on_setpoint(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float,
                    thrust_n: float) -> None:
        """A companion setpoint arrived at ``t_s`` (finite values: the caller checks)."""
        self.last_setpoint_s = t_s
        self.setpoint = AttitudeSetpoint(roll_rad, pitch_rad, yaw_rad, thrust_n)
        if self.in_failsafe:
            if not self.params.reengage_offboard:
                return   # PX4 stays in its failsafe until someone switches it back
            self.mode = OFFBOARD   # home stays where OFFBOARD was first engaged
            self.in_failsafe = False
            self._action_pending = False
            self._law = 'offboard' if self.armed else 'idle'
        elif self.mode != OFFBOARD:
            return
        w = self.world
        if w is not None and self.armed:
            w.set_command(roll_rad, pitch_rad, yaw_rad, thrust_n)

    def request_mode(self, t_s: float, mode: str) -> int:
        """A mode change asked by the companion; a MAV_RESULT code. OFFBOARD needs a
        setpoint younger than COM_OF_LOSS_T when armed and is always accepted while disarmed
        (PX4 v1.16)."""
        if mode not in MODES:
            return UNSUPPORTED
        if mode == OFFBOARD and self.armed and not self.setpoint_fresh(t_s):
            return TEMPORARILY_REJECTED
        self._user_mode = mode
        self._set_mode(mode, t_s)
        return ACCEPTED

    def request_arm(self, t_s: float, arm: bool, force: bool = False) -> int:
        """Arm (in OFFBOARD only with a fresh setpoint), or disarm (on the ground, when
        forced, or when not armed; in the air TEMPORARILY_REJECTED, as PX4 v1.16); a
        MAV_RESULT code."""
        if arm:
            if self.mode == OFFBOARD and not self.armed and not self.setpoint_fresh(t_s):
                return TEMPORARILY_REJECTED
            if not self.armed:
                self.armed = True
                self._airborne_since_arm = not self.landed
                self._landed_since_s = -1.0
                self._set_mode(self.mode, t_s)
            return ACCEPTED
        if self.landed or force or not self.armed:
            self._disarm()
            return ACCEPTED
        return TEMPORARILY_REJECTED   # "Disarming denied: not landed"

    def setpoint_fresh(self, t_s: float) -> bool:
        """The last setpoint is younger than COM_OF_LOSS_T."""
        return t_s - self.last_setpoint_s <= self.params.offboard_loss_timeout_s

    # --- simulator side ------------------------------------------------------------------

    def tick(self, t_s: float, world: World) -> None:
        """Every physics sub-step: mode logic, then the flight law due at 100 Hz."""
        self.update(t_s, world.resting_on is not None)
        law = self._law
        if law == 'offboard':
            return    # the last setpoint stays in force
        v = world.vehicle
        if law == 'return' and self._braked:
            hx, hy = self.home_m if self.home_m is not None else (v.x, v.y)
            if (math.hypot(v.x - hx, v.y - hy) <= HOME_RADIUS_M
                    and v.vx * v.vx + v.vy * v.vy <= BRAKED_MPS ** 2
                    and abs(v.z - self._ref[2]) < 0.3):
                self._law = 'land'
        if t_s >= self._next_s - 1e-12:
            self._next_s = t_s + LAW_PERIOD_S
            self._fly(world)

    def update(self, t_s: float, landed: bool) -> None:
        """Mode logic at ``t_s``: offboard loss → failsafe, its action after the delay, the
        land detector (``landed``: resting on a surface)."""
        p = self.params
        if (self.armed and self.mode == OFFBOARD
                and t_s - self.last_setpoint_s > p.offboard_loss_timeout_s):
            self.failsafes += 1
            self.mode = HOLD
            self.in_failsafe = True
            self._action_pending = True
            self._enter('hold', t_s, p.min_alt_m)
        if self._action_pending and t_s - self._phase_t0_s >= p.action_delay_s:
            self._action_pending = False
            act = p.offboard_loss_action
            if act != 'hold':
                self.mode = (RETURN if act == 'return' else POSITION if act == 'position'
                             else LAND)
                if self.armed:
                    self._law = RETURN if act == 'return' else LAND
        self.landed = landed
        if not self.armed:
            return
        if not landed:
            self._airborne_since_arm = True
            self._landed_since_s = -1.0
            return
        if self._landed_since_s < 0.0:
            self._landed_since_s = t_s
        limit = p.disarm_landed_s if self._airborne_since_arm else p.disarm_preflight_s
        if limit > 0.0 and t_s - self._landed_since_s >= limit:
            self._disarm()

    # --- internals -----------------------------------------------------------------------

    def _set_mode(self, mode: str, t_s: float) -> None:
        was = self.mode
        self.mode = mode
        self.in_failsafe = False
        self._action_pending = False
        w = self.world
        if mode == OFFBOARD:
            if (was != OFFBOARD or self.home_m is None) and w is not None:
                self.home_m = (w.vehicle.x, w.vehicle.y)
            self._law = 'offboard'
            sp = self.setpoint
            if w is not None and sp is not None and self.armed:
                w.set_command(sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_n)
        else:
            self._enter(LAND if mode == LAND else RETURN if mode == RETURN else HOLD, t_s, 0.0)
        if not self.armed:
            self._law = 'idle'

    def _enter(self, law: str, t_s: float, min_alt_m: float) -> None:
        """Start flying ``law`` from where the vehicle is (climbing to ``min_alt_m``)."""
        self._law = law if self.armed else 'idle'
        self._braked = False
        self._phase_t0_s = t_s
        self._next_s = t_s
        w = self.world
        if w is not None:
            v = w.vehicle
            self._ref = (v.x, v.y, max(v.z, min_alt_m), v.yaw)

    def _disarm(self) -> None:
        self.armed = False
        if self.in_failsafe:
            # PX4 restores the mode asked for once the failsafe clears (at disarm): after a
            # failsafe landing it reads OFFBOARD while disarmed (v1.16, measured)
            self.mode = self._user_mode
        self.in_failsafe = False   # self.failsafes keeps the history
        self._action_pending = False
        self._landed_since_s = -1.0
        self._law = 'idle'

    def _fly(self, world: World) -> None:
        """The flight law of the current phase (see the class docstring)."""
        v = world.vehicle
        law = self._law
        if law == 'idle':
            v.cmd_roll = 0.0
            v.cmd_pitch = 0.0
            v.cmd_yaw = v.yaw
            v.cmd_thrust = 0.0
            return
        p = world.params
        sp = self.params
        g = p.gravity_mps2
        x0, y0, z0, yaw0 = self._ref
        if not self._braked:
            # PX4 Hold: brake first, then hold where the vehicle came to rest
            if v.vx * v.vx + v.vy * v.vy > BRAKED_MPS ** 2:
                x0, y0 = v.x, v.y
            else:
                self._braked = True
            self._ref = (x0, y0, z0, yaw0)
        elif law == 'return' and self.home_m is not None:
            ex, ey = self.home_m[0] - x0, self.home_m[1] - y0
            n = math.hypot(ex, ey)
            step = sp.return_speed_mps * LAW_PERIOD_S
            if n > step:
                ex, ey = ex * step / n, ey * step / n
            x0, y0 = x0 + ex, y0 + ey
            self._ref = (x0, y0, z0, yaw0)
        ax = 1.0 * (x0 - v.x) - 1.8 * v.vx
        ay = 1.0 * (y0 - v.y) - 1.8 * v.vy
        a_max = g * math.tan(MAX_TILT_RAD)
        n = math.hypot(ax, ay)
        if n > a_max:
            ax, ay = ax * a_max / n, ay * a_max / n
        fwd, left = world_to_body_xy(ax, ay, v.yaw)
        pitch = math.atan2(fwd, g)
        roll = -math.atan2(left, g)
        if law != 'land':
            # PD on altitude; the error is capped so that a climb runs at climb_speed_mps
            ez_max = sp.climb_speed_mps / 0.8
            az = 2.0 * max(-ez_max, min(ez_max, z0 - v.z)) - 2.5 * v.vz
        else:
            az = 2.0 * (-sp.land_speed_mps - v.vz)
        az = max(-0.5 * g, min(0.5 * g, az))
        surface = world.surface_below_vehicle()
        gamma = p.gamma(v.z + p.rotor_height_m - surface)
        thrust = p.mass_kg * (g + az) / (gamma * math.cos(roll) * math.cos(pitch))
        if law == 'land' and world.resting_on is not None:
            thrust = 0.0
        if not math.isfinite(roll + pitch + thrust):
            self.rejected['nan'] += 1    # a non-finite state: keep the previous command
            return
        v.cmd_roll, v.cmd_pitch, v.cmd_yaw = roll, pitch, yaw0
        v.cmd_thrust = thrust


__all__ = ['ACCEPTED', 'ALTITUDE', 'DENIED', 'HOLD', 'LAND', 'MODES', 'OFFBOARD', 'POSITION',
           'RETURN', 'TEMPORARILY_REJECTED', 'UNSUPPORTED', 'AttitudeSetpoint', 'Autopilot',
           'AutopilotParams', 'EmulatedAutopilot', 'in_process_params', 'with_link_fault']
