"""The planner node's loop core (pure): apron and vehicle state in; reference, attitude out.

Everything between the node's subscriptions and its commands, on plain numbers: inputs gated
(finite, map frame, unit orientation, stamps in order and not stale or future against
``now``), one tick per accepted apron state — ``planner.step``, then the horizontal loop on
the measured position, velocity and yaw — on the apron state's stamp (measurement time, the
watchdog's on the node clock), the watchdog's safe
fallback while ``apron/state`` is stale, and the commands withheld when the vehicle state is
stale, the planner disables thrust or an output is not finite. The node, the in-process
runner and the golden replay call it (cores: ``planner.LandingPlanner``, ``horizontal``).
"""

from __future__ import annotations

import math

from deckland_common.checks import InputGuard, finite
from deckland_common.contract import ApronState, PlannerOutput, VehicleState
from deckland_common.frames import quaternion_to_euler

from deckland_common import validate as chk
from landing_planner.horizontal import HorizontalController
from landing_planner.planner import LandingPlanner

REJECTED = ('non_finite', 'bad_size', 'bad_layout', 'bad_frame', 'bad_quaternion',
            'out_of_order', 'stale_stamp', 'future_stamp')
WITHHELD = ('no_vehicle', 'vehicle_stale', 'thrust_disabled', 'non_finite_output',
            'clock_not_advancing')

_NAN3 = (math.nan, math.nan, math.nan)

Vec3 = tuple[float, float, float]


class PlannerTick:
    """One step of the loop: the planner's output and what the node publishes of it.

    ``apron`` is the state it stepped on (the fallback's on a watchdog tick), ``command``
    the horizontal loop's (roll, pitch), None when the vehicle state was stale (the loop was
    not stepped). ``withheld`` is '' when ``planner/reference`` and ``control/attitude`` go
    out, ``'thrust_disabled'`` when only the reference does, any other reason when neither
    does. ``stamp_s``: the stamp of both (never decreasing). A plain class: built every tick.
    """

    __slots__ = ('apron', 'command', 'output', 'stamp_s', 'withheld')

    def __init__(self, output: PlannerOutput, apron: ApronState,
                 command: tuple[float, float] | None, stamp_s: float, withheld: str) -> None:
        self.output = output
        self.apron = apron
        self.command = command
        self.stamp_s = stamp_s
        self.withheld = withheld

    @property
    def publish_reference(self) -> bool:
        return self.withheld == '' or self.withheld == 'thrust_disabled'

    @property
    def publish_attitude(self) -> bool:
        return self.withheld == ''


class PlannerLoop(InputGuard):
    """The planner node between its inputs and its commands.

    Args:
        planner, horizontal: the cores it steps.
        period_s: nominal period: the dt of the first step and of the first after a pause
            longer than ``input_timeout_s``; the node's watchdog runs at this period.
        input_timeout_s: apron or vehicle state older than this = stale.
        map_frame: the frame id required on the vehicle position and velocity.
    """

    def __init__(self, planner: LandingPlanner, horizontal: HorizontalController,
                 period_s: float = 0.01, input_timeout_s: float = 0.3,
                 map_frame: str = 'map') -> None:
        chk.positive('PlannerLoop.period_s', period_s)
        chk.positive('PlannerLoop.input_timeout_s', input_timeout_s)
        chk.require(bool(map_frame.strip()), 'PlannerLoop.map_frame', 'must not be empty',
                    map_frame)
        super().__init__(REJECTED, WITHHELD)
        self.planner = planner
        self.horizontal = horizontal
        self.period_s = float(period_s)
        self.timeout_s = float(input_timeout_s)
        self.map_frame = map_frame
        self.apron: ApronState | None = None
        # vehicle pose and velocity, each with its stamp (-inf: none yet); plain attributes,
        # set every tick (see pose / velocity)
        self._t_pose = self._t_vel = -math.inf
        self._pos: Vec3 = _NAN3
        self._vel: Vec3 = _NAN3
        self._roll = self._pitch = self._yaw = math.nan
        self.landed = False
        self.t_step: float | None = None      # now of the last planner step
        self.last_stamp = -math.inf           # last stamp of a published command
        self.last_output: PlannerOutput | None = None
        self.last_command: tuple[float, float] | None = None
        #: planner steps, steps on the stale-apron fallback, commands published
        self.counts: dict[str, int] = {'steps': 0, 'apron_fallback': 0, 'attitude': 0,
                                       'reference': 0}

    # --- inputs ------------------------------------------------------------------------------

    def on_apron(self, now_s: float, state: ApronState,
                 dt_s: float | None = None) -> PlannerTick | None:
        """Accept ``state`` and tick on it (event-driven); None when rejected or not stepped.

        ``dt_s``: see :meth:`step`.
        """
        v = state.vertical
        # everything the planner reads must be finite (time_since_seen_s and camera_stamp_s
        # may legitimately be ±inf and are not used)
        rel, apos, avel = state.rel_position_m, state.apron_position_m, state.apron_velocity_mps
        if not (finite(state.t_s) and finite(rel[0]) and finite(rel[1])
                and finite(apos[0]) and finite(apos[1]) and finite(avel[0])
                and finite(avel[1]) and finite(v.height_m)
                and finite(v.closing_speed_mps) and finite(v.surface_height_m)
                and finite(v.last_rebase_m)):
            self.reject('non_finite', 'apron/state')
            return None
        last = self.apron.t_s if self.apron is not None else -math.inf
        if not self.check_stamp(state.t_s, last, now_s, self.timeout_s, 'apron/state'):
            return None
        self.apron = state
        return self.step(now_s, state, dt_s, tick_s=state.t_s)

    def on_odom(self, now_s: float, stamp_s: float, frame_id: str, position_m: Vec3,
                q: tuple[float, float, float, float]) -> bool:
        """``vehicle/odom``: position and orientation (w, x, y, z) of ``base_link`` in map."""
        if frame_id != self.map_frame:
            self.reject('bad_frame', f'vehicle/odom (frame {frame_id!r}, expected '
                        f'{self.map_frame!r})')
            return False
        if not (finite(position_m[0]) and finite(position_m[1]) and finite(position_m[2])):
            self.reject('non_finite', 'vehicle/odom')
            return False
        qn = self.unit_quaternion(q, 'vehicle/odom orientation')
        if qn is None:
            return False
        roll, pitch, yaw = quaternion_to_euler(qn[0], qn[1], qn[2], qn[3])
        return self.on_pose(now_s, stamp_s, position_m, roll, pitch, yaw)

    def on_pose(self, now_s: float, stamp_s: float, position_m: Vec3, roll_rad: float,
                pitch_rad: float, yaw_rad: float) -> bool:
        """Position and Z-Y-X attitude already as angles (the in-process runner)."""
        if not (finite(position_m[0]) and finite(position_m[1])
                and finite(position_m[2]) and finite(roll_rad) and finite(pitch_rad)
                and finite(yaw_rad)):
            self.reject('non_finite', 'vehicle pose')
            return False
        if not self.check_stamp(stamp_s, self._t_pose, now_s, self.timeout_s, 'vehicle/odom'):
            return False
        self._t_pose, self._pos = stamp_s, position_m
        self._roll, self._pitch, self._yaw = roll_rad, pitch_rad, yaw_rad
        return True

    def on_velocity(self, now_s: float, stamp_s: float, velocity_mps: Vec3,
                    frame_id: str | None = None) -> bool:
        """``vehicle/velocity`` (ENU); ``frame_id`` None = already in the map frame."""
        if frame_id is not None and frame_id != self.map_frame:
            self.reject('bad_frame', f'vehicle/velocity (frame {frame_id!r}, expected '
                        f'{self.map_frame!r})')
            return False
        if not (finite(velocity_mps[0]) and finite(velocity_mps[1])
                and finite(velocity_mps[2])):
            self.reject('non_finite', 'vehicle/velocity')
            return False
        if not self.check_stamp(stamp_s, self._t_vel, now_s, self.timeout_s,
                                'vehicle/velocity'):
            return False
        self._t_vel, self._vel = stamp_s, velocity_mps
        return True

    @property
    def pose(self) -> tuple[float, Vec3, float, float, float] | None:
        """The last accepted (stamp, position, roll, pitch, yaw), None before the first."""
        if self._t_pose == -math.inf:
            return None
        return self._t_pose, self._pos, self._roll, self._pitch, self._yaw

    @property
    def velocity(self) -> tuple[float, Vec3] | None:
        """The last accepted (stamp, velocity), None before the first."""
        return None if self._t_vel == -math.inf else (self._t_vel, self._vel)

    def on_landed(self, landed: bool) -> None:
        """``vehicle/landed``: the autopilot's land detector."""
        self.landed = landed

    # --- mission commands (the node's services) ----------------------------------------------

    def start_landing(self, now_s: float) -> tuple[bool, str]:
        return self.planner.start_landing(now_s)

    def abort(self, now_s: float) -> tuple[bool, str]:
        return self.planner.abort(now_s)

    def takeoff(self, now_s: float) -> tuple[bool, str]:
        return self.planner.takeoff(now_s)

    # --- ticks -------------------------------------------------------------------------------

    def watchdog(self, now_s: float) -> PlannerTick | None:
        """Tick on the core's safe fallback ``ApronState.untracked(now)`` while
        ``apron/state`` is stale or was never received (None while it is fresh)."""
        apron = self.apron
        if apron is not None and now_s - apron.t_s <= self.timeout_s:
            return None                     # the chain is alive: apron/state drives the steps
        if self._t_pose > -math.inf and self._t_vel > -math.inf:
            self.counts['apron_fallback'] += 1
        return self.step(now_s, ApronState.untracked(now_s))

    def vehicle(self, now_s: float) -> VehicleState | None:
        """The vehicle state if both parts are fresh, else None."""
        # never received: the stamp is -inf, now - stamp = inf
        if now_s - self._t_pose > self.timeout_s or now_s - self._t_vel > self.timeout_s:
            return None
        return VehicleState(t_s=self._t_pose, position_m=self._pos, velocity_mps=self._vel,
                            roll_rad=self._roll, pitch_rad=self._pitch, yaw_rad=self._yaw,
                            landed=self.landed)

    def step(self, now_s: float, apron: ApronState, dt_s: float | None = None,
             tick_s: float | None = None) -> PlannerTick | None:
        """One planner + horizontal-loop tick on ``apron``; None if not stepped.

        ``tick_s`` is the time the tick describes: the apron state's stamp on an
        ``apron/state`` tick (the deck track, the predictor, the timers and the references
        then run on measurement time, the same in the node, the runner and a replay, whatever
        the delivery delay), ``now_s`` on a watchdog tick. ``now_s`` (the node clock) judges
        the vehicle state's freshness. ``dt_s`` replaces the time since the last step (a
        caller stepping on a fixed schedule, the in-process runner).
        """
        if self._t_pose == -math.inf or self._t_vel == -math.inf:
            self.withhold('no_vehicle')   # nothing known yet: the planner is not stepped
            return None
        t_tick = now_s if tick_s is None else tick_s
        t_step = self.t_step
        if t_step is not None and t_tick <= t_step:
            self.withhold('clock_not_advancing')
            return None
        if dt_s is not None:
            dt = dt_s
        else:
            dt = t_tick - t_step if t_step is not None else self.period_s
            if dt > self.timeout_s:
                dt = self.period_s            # after a pause: restart at the nominal period
        self.t_step = t_tick

        vehicle = self.vehicle(now_s)
        fed = vehicle if vehicle is not None else VehicleState(
            t_s=now_s, position_m=_NAN3, velocity_mps=_NAN3, roll_rad=math.nan,
            pitch_rad=math.nan, yaw_rad=math.nan, landed=self.landed)
        # a stale vehicle state is fed as a non-finite one: the planner's safe mode runs
        out = self.planner.step(t_tick, dt, fed, apron)
        self.counts['steps'] += 1
        self.last_output = out
        if vehicle is None:
            self.withhold('vehicle_stale')
            return PlannerTick(out, apron, None, self.last_stamp, 'vehicle_stale')
        pos, vel = vehicle.position_m, vehicle.velocity_mps
        roll, pitch = self.horizontal.step(out.setpoint_m, out.velocity_ff_mps,
                                           (pos[0], pos[1]), (vel[0], vel[1]),
                                           vehicle.yaw_rad, dt, precise=out.precise_xy,
                                           accel_ff_mps2=out.accel_ff_mps2)
        sp, ff = out.setpoint_m, out.velocity_ff_mps
        if not (finite(roll) and finite(pitch) and finite(out.yaw_rad)
                and finite(sp[0]) and finite(sp[1]) and finite(ff[0])
                and finite(ff[1]) and finite(out.z_d_m) and finite(out.z_d_dot_mps)
                and finite(out.z_d_ddot_mps2)):
            self.withhold('non_finite_output')   # defensive: the cores never do this
            return PlannerTick(out, apron, (roll, pitch), self.last_stamp, 'non_finite_output')
        stamp_s = max(apron.t_s, self.last_stamp)
        self.last_stamp = stamp_s
        self.counts['reference'] += 1
        if not out.thrust_enabled:
            self.withhold('thrust_disabled')
            return PlannerTick(out, apron, (roll, pitch), stamp_s, 'thrust_disabled')
        self.withheld_reason = ''
        self.last_command = (roll, pitch)
        self.counts['attitude'] += 1
        return PlannerTick(out, apron, (roll, pitch), stamp_s, '')

    def diagnostic_values(self, now_s: float) -> dict[str, str]:
        """Input ages, counters and the cores' rejections, as diagnostics key/values."""
        apron = self.apron

        def age(stamp_s: float) -> str:
            return f'{now_s - stamp_s:.3f}'   # a never-received input: -inf, age inf

        values = {'apron_age_s': age(apron.t_s if apron is not None else -math.inf),
                  'odom_age_s': age(self._t_pose), 'velocity_age_s': age(self._t_vel),
                  'landed': str(self.landed)}
        values.update({k: str(v) for k, v in self.counts.items()})
        values.update({f'rejected_{k}': str(v) for k, v in self.rejected.items()})
        values.update({f'withheld_{k}': str(v) for k, v in self.withheld.items()})
        values.update({f'planner_rejected_{k}': str(v)
                       for k, v in self.planner.rejected.items()})
        values.update({f'horizontal_rejected_{k}': str(v)
                       for k, v in self.horizontal.rejected.items()})
        return values
