"""The simulated world: vehicle truth, the deck (heaving apron or ship), wind, sensors, landing.

``World(scenario, seed)`` is the API of docs/interfaces.md. Every random draw comes from a
named stream of ``seed`` (``random.Random(f'{seed}:<name>')``, :func:`normal_stream` for the
Gaussian noise), so e.g. reading the camera more often never changes the GPS noise. The
vehicle is a free rigid body throughout; its gear and prop tips meet the deck (a box that
moves and tilts) and the ground (or the sea) as contact physics, and a touchdown monitor
scores the whole landing (:mod:`deck_simulator.touchdown`). The world flies an autopilot
(:mod:`deck_simulator.autopilot`) every physics tick; the motors run while it is armed.
Decisions: the package README and docs/world/contact.md, docs/world/ship.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
import random
from typing import Any

from deckland_common.frames import Mat3, rot_body_to_world

from deck_simulator.autopilot import (
    ACCEPTED,
    MODES,
    Autopilot,
    EmulatedAutopilot,
    in_process_params,
)
from deck_simulator.contact import Surface, ground_surface
from deck_simulator.deck import Deck, make_heave
from deck_simulator.deck_motion import DeckMotion, HeaveDeckMotion, PadState
from deck_simulator.faults import FaultSet
from deck_simulator.link import CommandLink
from deck_simulator.scenario import Scenario
from deck_simulator.sensor_imu import accel_world_through, body_rates_from_euler
from deck_simulator.sensor_lidar import Surface as LidarSurface
from deck_simulator.sensor_lidar import ground_plane, horizontal_rectangle
from deck_simulator.sensor_suite import SensorSuite
from deck_simulator.sensors import Block, Camera, Normal, lidar_range_along, normal_stream
from deck_simulator.ship import ShipMotion
from deck_simulator.ship_link import ShipLink, ShipMessage
from deck_simulator.touchdown import LandingRecord, Pad, TouchdownMonitor
from deck_simulator.vehicle import Vehicle

#: the sensors of :meth:`World.delivered`
SENSOR_STREAMS = ('imu', 'attitude', 'local_position', 'lidar', 'camera')
GUST_UPDATE_S = 0.01 - 1e-9   # gusts (τ ~ s) are held over 10 ms
#: the apron's box reaches this far below its top (through the ground: it stands on it)
APRON_DEPTH_EXTRA_M = 10.0


@dataclass(frozen=True, slots=True)
class ContactEvent:
    """The first contact of the landing (from the touchdown monitor's record)."""

    kind: str                       # 'pad' | 'deck' | 'edge' | 'ground' | 'water' | 'hull'
    t_s: float
    touchdown_speed_mps: float      # relative, along the surface normal (before contact acts)
    horizontal_error_m: float       # centre of mass to the pad centre, in the pad plane
    tilt_rad: float                 # body z vs the surface normal
    vehicle_vz_mps: float           # at the end of the physics tick of the first contact
    surface_vz_mps: float           # the deck's (0 for the ground), same instant
    position_m: tuple[float, float, float]   # centre of mass, same instant
    lateral_speed_mps: float = 0.0  # relative, along the surface (before contact acts)


@dataclass(frozen=True, slots=True)
class Outcome:
    """What the runner turns into the run's outcome fields: the landing record, mapped."""

    landed_on_deck: bool            # the record's class is 'deck' (every rule kept)
    crash: bool                     # a crash rule broken (docs/world/contact.md)
    fallback: bool                  # first contact on the ground (a landing elsewhere)
    contact_kind: str               # first contact: 'pad' | 'deck' | 'edge' | 'ground' | ...
    t_s: float                      # contact time (or current time if no contact)
    horizontal_error_m: float       # at contact (or now)
    touchdown_speed_mps: float      # first contact, relative normal; 0.0 without contact
    tilt_rad: float                 # first contact, relative (or the tilt now)
    max_thrust_n: float             # largest collective thrust the motors produced
    reason: str
    landing: str = 'none'           # record class: deck | failed | crash | fallback | none
    lateral_speed_mps: float = 0.0  # first contact, relative, along the surface
    impacts: int = 0                # the first contact and every later impact
    max_impact_speed_mps: float = 0.0
    bounces: int = 0
    max_bounce_height_m: float = 0.0
    settled: bool = False


@dataclass(frozen=True, slots=True)
class Truth:
    t_s: float
    position_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]
    accel_mps2: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    euler_rates_radps: tuple[float, float, float]
    beacon_position_m: tuple[float, float, float]   # pad centre on the pad top
    deck_height_m: float                            # pad top above ground (mean sea level)
    deck_vz_mps: float
    deck_az_mps2: float
    deck_velocity_mps: tuple[float, float]          # horizontal velocity of the pad centre
    over_pad: bool                                  # vehicle centre above the pad rectangle
    surface_height_m: float                         # surface below the vehicle centre
    height_above_surface_m: float                   # body origin above that surface
    gamma: float                                    # mean true ground-effect gain of the rotors
    thrust_n: float                                 # collective the motors produce now
    wind_mps: tuple[float, float, float]
    resting_on: str | None                          # surface the vehicle rests on, if any
    deck_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)   # pad attitude (Z-Y-X)
    armed: bool = True                              # the motors run


class World:
    """Closed-loop plant: ``set_command`` → ``step`` → ``read_*`` / ``truth`` / ``contact``."""

    def __init__(self, scenario: Scenario, seed: int, physics_dt_s: float = 1.0 / 400.0) -> None:
        if not (physics_dt_s > 0 and math.isfinite(physics_dt_s)):
            raise ValueError(f'physics_dt_s must be > 0, got {physics_dt_s!r}')
        self.scenario = scenario
        self.seed = seed
        self.physics_dt_s = physics_dt_s
        sc, rz = scenario, scenario.randomize

        def stream(name: str) -> random.Random:
            return random.Random(f'{seed}:{name}')

        def noise(name: str) -> Normal:
            return normal_stream(f'{seed}:{name}:normal')

        setup = stream('setup')
        r = rz.start_offset_m * math.sqrt(setup.random())
        a = setup.uniform(0.0, 2.0 * math.pi)
        sx, sy, sz = sc.start_position_m
        start = (sx + r * math.cos(a), sy + r * math.sin(a), sz)
        yaw0 = sc.start_yaw_rad + setup.uniform(-rz.start_yaw_rad, rz.start_yaw_rad)
        rot = setup.uniform(-rz.wind_direction_rad, rz.wind_direction_rad)
        mx, my = sc.wind.mean_mps
        self.wind_mean = (mx * math.cos(rot) - my * math.sin(rot),
                          mx * math.sin(rot) + my * math.cos(rot))
        mean_h = sc.apron.mean_height_m + setup.uniform(-rz.mean_height_m, rz.mean_height_m)
        vp = sc.vehicle
        self.params = vp
        cp = vp.contact
        ap_spec = sc.apron
        ship_p = ap_spec.ship
        self.pad_half_x, self.pad_half_y = 0.5 * ap_spec.size_m[0], 0.5 * ap_spec.size_m[1]
        # the deck: the paper's heaving apron (level, axis-aligned: a box standing on the
        # ground) or a ship's deck (moving, tilted; the pad on it, the sea around it)
        self.deck: Deck | None = None
        self.ship: ShipMotion | None = None
        if ship_p is None:
            heave = make_heave(ap_spec.heave, stream('heave'), sc.timeout_s + 60.0,
                               random_phase=rz.heave_phase)
            self.deck_mean_m = max(0.0, mean_h)
            deck = Deck(ap_spec.position_m, ap_spec.size_m, self.deck_mean_m, heave,
                        ap_spec.drift_velocity_mps)
            self.deck = deck
            self.deck_motion: DeckMotion = HeaveDeckMotion(deck)
            deck_surface = Surface('deck', deck.half_x, deck.half_y,
                                   self.deck_mean_m + APRON_DEPTH_EXTRA_M, cp.friction_deck)
            ground = ground_surface(cp.friction_ground)
            pad = Pad()
        else:
            ship = ShipMotion(ship_p, stream('ship'), sc.timeout_s + 60.0)
            self.ship = ship
            self.deck_motion = ship
            top = ship_p.motion_centre_height_m + ship_p.pad_offset_m[2]
            self.deck_mean_m = top
            # the deck reaches down through the waterline (the hull)
            deck_surface = Surface('deck', 0.5 * ship_p.deck_size_m[0],
                                   0.5 * ship_p.deck_size_m[1], top + ship_p.draft_m,
                                   cp.friction_deck)
            ground = Surface('water', math.inf, math.inf, math.inf, cp.friction_ground)
            pad = Pad(0, 0.0, 0.0, self.pad_half_x, self.pad_half_y)
        self.deck_surface = deck_surface
        self.ground = ground
        #: what the gear, the prop tips and the rotor wakes meet: [deck, ground or sea]
        self.surfaces: list[Surface] = [deck_surface, ground]
        self.t_s = 0.0
        self._pad_now: PadState | None = None
        # deck state at self.t_s: the heave deck's (cx, cy, z_top, vz, az) tuple (the
        # sensors' and truth()'s), the ship's PadState; one evaluation per contact sub-step
        self._deck_now: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
        self._set_deck(0.0)

        surf0 = self._surface_below(start[0], start[1], start[2])
        hover = vp.mass_kg * vp.gravity_mps2 / vp.gamma(start[2] + vp.rotor_height_m - surf0)
        self.vehicle = Vehicle(vp, start, yaw0, hover, self.surfaces)
        self.monitor = TouchdownMonitor(sc.outcome, self.vehicle.contact, pad,
                                        vp.gear.static_tip_angle_rad())
        self.vehicle.monitor = self.monitor
        self._watching = True     # False while resting where placed (place_on_surface)
        self._armed = True        # the motors' state while no autopilot flies
        #: the autopilot's last failsafe mode (:attr:`failsafe_mode`; '' = none)
        self.last_failsafe = ''
        self._contact: ContactEvent | None = None

        self._wind_rng = stream('wind')
        self._wind_normal = n = noise('wind')
        w = sc.wind
        s = w.gust_std_mps
        self.gust = [s * n() if s > 0 else 0.0,
                     s * n() if s > 0 else 0.0,
                     s * w.vertical_gust_ratio * n() if s > 0 else 0.0]
        self._gust_dt = -1.0
        self._gust_elapsed = 0.0
        self._gust_a = self._gust_q = 0.0
        # constants of the 400 Hz sub-step, hoisted (the scenario is frozen)
        self._gust_on = w.gust_std_mps > 0.0
        self._gust_tau = w.gust_tau_s
        self._gust_std = w.gust_std_mps
        self._gust_vratio = w.vertical_gust_ratio


        self.resting_on: str | None = None
        self.max_thrust_n = self.vehicle.thrust_n
        self.rejected: dict[str, int] = {'nan': 0, 'bad_dt': 0, 'out_of_order': 0}

        # fault injection (deck_simulator.faults): nothing at all without faults
        p0 = self.deck_motion.pad_state(0.0).position_m
        self.faults: FaultSet | None = (FaultSet(sc.faults, seed, (p0[0], p0[1]),
                                                 self.deck_mean_m) if sc.faults else None)
        self._init_sensors(stream('camera'), noise('camera'))
        # the autopilot (deck_simulator.autopilot): in-process the world's own, engaged by
        # the first command_link (with link faults through the command link,
        # deck_simulator.link); the simulator node attaches its emulator's instead
        spec = self.faults.link_spec if self.faults is not None and self.faults.has_link else None
        ap = EmulatedAutopilot(in_process_params(spec), self)
        self.autopilot: Autopilot | None = ap
        self._own_autopilot: EmulatedAutopilot | None = ap
        self.link: CommandLink | None = None
        if spec is not None and self.faults is not None:
            self.link = CommandLink(self.faults, seed, ap, self.rejected)
        # the ship's own telemetry stream (deck_simulator.ship_link), if the scenario has one
        st = sc.ship_telemetry
        self.ship_link: ShipLink | None = (
            ShipLink(st, self.deck_motion.pad_state, f'{seed}:ship_link') if st is not None
            else None)

    # --- commands and stepping -------------------------------------------------------------

    def set_command(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                    thrust_n: float) -> None:
        """Attitude setpoint (FLU in ENU, Z-Y-X) and collective thrust u_z in newtons, to the
        vehicle's attitude loop directly (what the autopilot does in OFFBOARD)."""
        # one isfinite on the sum: NaN/inf anywhere makes it non-finite (finite commands would
        # need magnitudes near 1e308 to overflow it)
        if not math.isfinite(roll_rad + pitch_rad + yaw_rad + thrust_n):
            self.rejected['nan'] += 1
            return
        v = self.vehicle
        # the autopilot holds the heading on its estimate (ATTITUDE's yaw, what the companion
        # sees): the true heading is off by the estimate's error, R = Rz(−e_up) R_sp. Its
        # tilt error (0.2° σ) is not applied: a level setpoint stays truly level (README)
        v.cmd_roll, v.cmd_pitch = roll_rad, pitch_rad
        v.cmd_yaw = yaw_rad - self.sensor_suite.attitude.heading_error_rad
        v.cmd_thrust = thrust_n if thrust_n > 0.0 else 0.0

    def command_link(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float,
                     thrust_n: float) -> bool:
        """Send a command to the world's autopilot (the companion's MAVLink setpoint); True if
        it gets through.

        The first accepted call engages OFFBOARD (home = here); from then on the autopilot
        applies the setpoints while armed, runs its land detector (``COM_DISARM_LAND``) and
        its offboard-loss failsafe. With ``mavlink_loss`` / ``mavlink_latency`` /
        ``mavlink_link_loss`` / ``node_kill`` faults the command goes through
        :class:`~deck_simulator.link.CommandLink`: it may be lost (False; the vehicle keeps
        the previous command) or applied ``latency_s`` later (FIFO); when no command has
        arrived for ``loss_timeout_s`` the failsafe flies (:attr:`failsafe`): hold for
        ``hold_s``, then the fault's ``action`` (land at ``land_speed_mps``, or return home
        and land); ``reengage_offboard`` lets the next command end it. A non-finite value or
        a ``t_s`` older than the previous call's (with link faults) is rejected
        (``rejected['nan']`` / ``['out_of_order']``, False). With an attached autopilot (the
        simulator node's) this is :meth:`set_command`.
        """
        link = self.link
        if link is not None:
            return link.send(t_s, roll_rad, pitch_rad, yaw_rad, thrust_n)
        if not math.isfinite(t_s + roll_rad + pitch_rad + yaw_rad + thrust_n):
            self.rejected['nan'] += 1
            return False
        ap = self._own_autopilot
        if ap is None:
            self.set_command(roll_rad, pitch_rad, yaw_rad, thrust_n)
            return True
        if not ap.active:
            ap.engage_offboard(t_s)
        ap.on_setpoint(t_s, roll_rad, pitch_rad, yaw_rad, thrust_n)
        return True

    def disarm(self, t_s: float | None = None) -> bool:
        """The companion's disarm request (the bridge's, when the planner is LANDED); True if
        accepted. The world's autopilot disarms on the ground only (PX4 refuses in the air;
        its land detector disarms later). Before any autopilot flies (tests commanding the
        vehicle directly) the motors stop at once."""
        ap = self.autopilot
        t = self.t_s if t_s is None else t_s
        if isinstance(ap, EmulatedAutopilot) and ap.active:
            return ap.request_arm(t, False) == ACCEPTED
        if ap is None or not ap.active:
            self._armed = False
            return True
        return False

    @property
    def armed(self) -> bool:
        """The motors run: the flying autopilot's arming state (True before one flies)."""
        ap = self.autopilot
        if ap is None or not ap.active:
            return self._armed
        return ap.armed

    def timesync_rtt_s(self, t_s: float) -> float | None:
        """The simulated MAVLink TIMESYNC: round trip (s) of a request sent at ``t_s``
        through the same link as :meth:`command_link` (0 without link faults), None if lost
        (:meth:`deck_simulator.link.CommandLink.timesync_rtt_s`). A non-finite ``t_s`` is
        rejected (``rejected['nan']``, None)."""
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return None
        link = self.link
        if link is None:
            return 0.0
        return link.timesync_rtt_s(t_s)

    def attach_autopilot(self, autopilot: Autopilot) -> None:
        """Fly ``autopilot`` instead of the in-process one (the simulator node: the link
        faults then act on the wire, so :meth:`command_link` becomes :meth:`set_command`)."""
        self.autopilot = autopilot
        self._own_autopilot = None
        self.link = None

    @property
    def failsafe(self) -> str | None:
        """The autopilot's failsafe phase: None, ``'hold'``, ``'return'`` or ``'land'``."""
        ap = self.autopilot
        return ap.failsafe if ap is not None else None

    @property
    def failsafe_mode(self) -> str | None:
        """The autopilot's mode while it flies a failsafe, as its heartbeat reads it (an
        RTL's final descent is still ``'return'``, AUTO.RTL); None outside a failsafe."""
        ap = self.autopilot
        phase = ap.failsafe if ap is not None else None
        if phase is None:
            return None
        mode = getattr(ap, 'mode', None)
        return mode if mode in MODES else phase

    @property
    def link_stats(self) -> dict[str, int]:
        """In-process link counters ``sent``, ``lost``, ``delayed`` and the autopilot's
        ``failsafes``."""
        out = dict(self.link.stats) if self.link is not None else {
            'sent': 0, 'lost': 0, 'delayed': 0}
        out['failsafes'] = self.autopilot.failsafes if self.autopilot is not None else 0
        return out

    def surface_below_vehicle(self) -> float:
        """Height of the surface below the vehicle centre now: the deck's top (the pad top
        over the apron) under it, if the vehicle is above it, else the ground (0)."""
        v = self.vehicle
        return self._surface_below(v.x, v.y, v.z)

    def _surface_below(self, x: float, y: float, z: float) -> float:
        if self.ship is None:
            cx, cy, ztop, _, _ = self._deck_now
            over = abs(x - cx) <= self.pad_half_x and abs(y - cy) <= self.pad_half_y
            return ztop if over and z > ztop else 0.0
        s = self.deck_surface
        a, b, h = s.local(x, y, z)
        if h > 0.0 and abs(a) <= s.half_u and abs(b) <= s.half_w:
            return z - h / s.nz if s.nz > 1e-6 else z - h   # the plane under (x, y)
        return 0.0

    def pad_state(self, t_s: float | None = None) -> PadState:
        """The pad (deck frame: pad centre on its top, hull axes) at ``t_s``, default now (the
        state every contact sub-step used last; the sensors' deck pose)."""
        if t_s is not None:
            return self.deck_motion.pad_state(t_s)
        ps = self._pad_now
        if ps is None:
            ps = self._pad_now = self.deck_motion.pad_state(self.t_s)
        return ps

    def active_faults(self, t_s: float | None = None) -> tuple[str, ...]:
        """Types of the scenario faults active at ``t_s`` (default now), for logging."""
        if self.faults is None:
            return ()
        return self.faults.active(self.t_s if t_s is None else t_s)

    def place_on_surface(self) -> None:
        """Rest the vehicle level on the surface below it (gear at its static deflection),
        still, motors off; the touchdown monitor watches from its first lift-off on (no
        touchdown at the start). For a firmware's own take-off (PX4 in the loop)."""
        v = self.vehicle
        p = self.params
        surf = self._surface_below(v.x, v.y, v.z + 1e3)
        sag = p.mass_kg * p.gravity_mps2 / p.contact.stiffness_n_per_m
        v.set_attitude(0.0, 0.0, v.yaw)
        v.z = surf + p.gear.height_m - sag
        v.vx = v.vy = v.vz = 0.0
        v.ax = v.ay = v.az = 0.0
        v.f1 = v.f2 = v.f3 = v.f4 = 0.0
        v.reset_attitude_loop()
        self._watching = False
        v.monitor = None
        if surf == 0.0:
            self.resting_on = self.ground.kind
        else:
            self.resting_on = 'pad' if self._over_pad_now() else 'deck'

    def step(self, dt_s: float) -> None:
        """Advance the physics by dt_s, in ticks of at most ``physics_dt_s``."""
        if dt_s == self.physics_dt_s:   # the runner's case (a float equal to a float)
            self._substep(dt_s)
            return
        if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and dt_s > 0.0):
            self.rejected['bad_dt'] += 1
            return
        n = max(1, math.ceil(dt_s / self.physics_dt_s - 1e-9))
        h = dt_s / n
        for _ in range(n):
            self._substep(h)

    def _set_deck(self, t_s: float) -> None:
        """The deck at ``t_s``: the contact surface's pose and velocity (and the state the
        sensors read while ``t_s`` is now)."""
        s = self.deck_surface
        deck = self.deck
        if deck is not None:
            dk = deck.state(t_s)
            self._deck_now = dk
            s.cx, s.cy, s.cz = dk[0], dk[1], dk[2]
            s.vx, s.vy, s.vz = deck.drift_x, deck.drift_y, dk[3]
            self._pad_now = None
            return
        ps = self.deck_motion.pad_state(t_s)
        self._pad_now = ps
        r = ps.rotation
        s.set_pose(ps.position_m, (r[0][2], r[1][2], r[2][2]), (r[0][0], r[1][0], r[2][0]),
                   ps.velocity_mps, ps.omega_radps)

    def _substep(self, h: float) -> None:
        """One physics tick of h: the autopilot, the wind, the vehicle (contact sub-steps,
        each with the deck at its time), then the deck at the new time."""
        t0 = self.t_s
        v = self.vehicle
        ap = self.autopilot
        if ap is not None and ap.active:
            if self.link is not None:
                self.link.deliver_due(t0)
            ap.tick(t0, self)
            if ap.failsafes:
                fs_mode = self.failsafe_mode
                if fs_mode is not None:
                    self.last_failsafe = fs_mode
        # wind: mean + OU gusts, updated every GUST_UPDATE_S with the exact discretisation
        # g ← a g + σ √(1−a²) n, a = exp(−Δt/τ) (zero-order hold in between)
        g = self.gust
        if self._gust_on:
            self._gust_elapsed += h
            if self._gust_elapsed >= GUST_UPDATE_S:
                dtg = self._gust_elapsed
                self._gust_elapsed = 0.0
                if dtg != self._gust_dt:
                    self._gust_dt = dtg
                    self._gust_a = math.exp(-dtg / self._gust_tau)
                    self._gust_q = self._gust_std * math.sqrt(1.0 - self._gust_a ** 2)
                a, q, n = self._gust_a, self._gust_q, self._wind_normal
                g[0] = a * g[0] + q * n()
                g[1] = a * g[1] + q * n()
                g[2] = a * g[2] + q * self._gust_vratio * n()
        fs = self.faults
        wmx, wmy = self.wind_mean
        wx, wy, wz = wmx + g[0], wmy + g[1], g[2]
        if fs is not None:
            if fs.pending:
                fs.update_height(t0, v.z - self._surface_below(v.x, v.y, v.z))
            if fs.wind:
                ws = fs.wind_step(t0)
                if ws is not None:
                    wx, wy, wz = wx + ws[0], wy + ws[1], wz + ws[2]
        v.armed = self.armed
        n_sub = v.begin(h, wx, wy, wz)
        if n_sub == 1:
            v.substep(h, t0)
        else:
            hs = h / n_sub
            for k in range(n_sub):
                if k > 0:
                    self._set_deck(t0 + k * hs)
                v.substep(hs, t0 + k * hs)
        v.finish(h)
        thrust = v.f1 + v.f2 + v.f3 + v.f4
        if thrust > self.max_thrust_n:
            self.max_thrust_n = thrust
        t = t0 + h
        self.t_s = t
        self._set_deck(t)
        if t + 1e-9 >= self._next_sensor_s:
            self._sample_sensors(t)
        # resting: enough gear points down on one surface (the land detector's "landed")
        c = v.contact
        if c.n_active == 0:
            self.resting_on = None
            if not self._watching:
                self._watching = True
                v.monitor = self.monitor
        else:
            need = 3 if c.n_gear >= 3 else c.n_gear
            counts = c.n_gear_contacts
            if counts[0] >= need:
                self.resting_on = 'pad' if self._over_pad_now() else 'deck'
            elif counts[1] >= need:
                self.resting_on = self.ground.kind
            else:
                self.resting_on = None
        if self._contact is None and self.monitor.first is not None:
            self._contact = self._first_contact()

    def _over_pad_now(self) -> bool:
        v = self.vehicle
        if self.ship is None:
            cx, cy, _, _, _ = self._deck_now
            return abs(v.x - cx) <= self.pad_half_x and abs(v.y - cy) <= self.pad_half_y
        x, y, _ = self.pad_state().to_deck((v.x, v.y, v.z))
        return abs(x) <= self.pad_half_x and abs(y) <= self.pad_half_y

    def _first_contact(self) -> ContactEvent:
        f = self.monitor.first
        assert f is not None
        v = self.vehicle
        svz = self.deck_surface.vz if f.surface in ('pad', 'deck', 'edge') else 0.0
        rec = self.monitor.record(v.body)
        return ContactEvent(kind=f.surface, t_s=f.t_s, touchdown_speed_mps=f.normal_speed_mps,
                            horizontal_error_m=rec.horizontal_error_m, tilt_rad=f.tilt_rad,
                            vehicle_vz_mps=v.vz, surface_vz_mps=svz,
                            position_m=(v.x, v.y, v.z), lateral_speed_mps=f.lateral_speed_mps)

    @property
    def contact(self) -> ContactEvent | None:
        """The first contact of the landing, or None."""
        return self._contact

    @property
    def landing_done(self) -> bool:
        """The landing can be scored: settled (disarmed, still), or a crash no later event
        can undo (:attr:`TouchdownMonitor.done`)."""
        return self.monitor.done

    def landing_record(self) -> LandingRecord:
        """The touchdown monitor's record now, with the scenario's outcome rules applied."""
        return self.monitor.record(self.vehicle.body)

    # --- sensors (docs/world/sensors.md) -------------------------------------------------------

    def _init_sensors(self, camera_rng: random.Random, camera_normal: Normal) -> None:
        """The seed's honest sensors (:class:`SensorSuite`), each on its own clock.

        The clocks start before t = 0 (two periods plus the latency of the slowest sensor,
        rounded up to whole seconds), sampling the start state, so at t = 0 every sensor has
        delivered (the autopilot was streaming before the landing began)."""
        sp = self.scenario.sensors
        if not self.scenario.randomize.gps_bias:
            lp = sp.local_position
            sp = replace(sp, local_position=replace(
                lp, horizontal=replace(lp.horizontal, bias_std_m=0.0)))
        timings = (sp.imu.timing, sp.attitude.timing, sp.local_position.timing,
                   sp.lidar.timing, sp.true_camera.timing)
        for tp in timings:
            if tp.rate_hz > 1.0 / self.physics_dt_s + 1e-9:
                raise ValueError(
                    f'a sensor rate_hz of {tp.rate_hz:g} exceeds the physics rate '
                    f'{1.0 / self.physics_dt_s:g} Hz: it cannot be realised')
        # whole seconds: without a random phase a clock then ticks on multiples of its period
        lead = float(math.ceil(max(2.0 / tp.rate_hz + tp.latency_s + 5.0 * tp.latency_jitter_s
                                   for tp in timings)))
        suite = SensorSuite(sp, self.seed, self.params.gravity_mps2, start_s=-lead)
        self.sensor_suite = suite
        self.sensor_params = sp
        cam_t = suite.camera_timing
        self.camera = Camera(sp.camera, camera_rng, camera_normal, cam_t.period_s)
        # a frame is rendered once all its rows are exposed (rolling readout, jitter)
        tc = sp.true_camera
        self._frame_margin_s = 0.5 * tc.rolling_readout_s + 4.0 * tc.exposure_jitter_s
        self._lidar_mount = sp.lidar.mount_offset_m
        self._latest_imu: tuple[tuple[float, float, float], tuple[float, float, float]] = (
            (0.0, 0.0, self.params.gravity_mps2), (0.0, 0.0, 0.0))
        self._latest_attitude: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._latest_position: tuple[tuple[float, float, float],
                                     tuple[float, float, float]] = ((0.0, 0.0, 0.0),
                                                                    (0.0, 0.0, 0.0))
        self._latest_range: float | None = None
        self._latest_frame: tuple[float, list[Block]] = (math.nan, [])
        #: the sensors whose delivered samples queue for :meth:`delivered` (none by default)
        self.queued: frozenset[str] = frozenset()
        self.inbox: dict[str, list] = {name: [] for name in SENSOR_STREAMS}
        self._next_sensor_s = -math.inf
        t = -lead
        self.queued = frozenset(SENSOR_STREAMS)
        while t < 0.0:    # the start state, sampled on every clock until t = 0
            t = min(0.0, t + self.physics_dt_s)
            self._sample_sensors(t)
        self.queued = frozenset()
        for box in self.inbox.values():   # the stack, running already, has the last one
            del box[:-1]

    def idle_to(self, t_s: float) -> None:
        """Move the clock to ``t_s`` without physics (the vehicle and its motion frozen, the
        deck moving), sampling and delivering the sensors on the way: for tests of the
        sensor and fault streams over long spans."""
        self.t_s = t_s
        self._set_deck(t_s)
        self._sample_sensors(t_s)

    def _sample_sensors(self, t_now: float) -> None:
        """Every sample due by ``t_now`` (taken from the state now: at most one physics tick
        old), then every sample delivered by then (faults act on delivery). A clock instant
        within 1 ns of now counts as now (the sub-step times are sums of floats)."""
        t = t_now + 1e-9
        s = self.sensor_suite
        v = self.vehicle
        tm_imu, tm_att, tm_lp, tm_li, tm_cam = (s.imu_timing, s.attitude_timing,
                                                s.local_position_timing, s.lidar_timing,
                                                s.camera_timing)
        r = None
        while tm_imu.next_sample_s <= t:
            ts = tm_imu.take()
            if r is None:
                r = rot_body_to_world(v.roll, v.pitch, v.yaw)
            tm_imu.push(ts, s.imu.sample((v.ax, v.ay, v.az), r, body_rates_from_euler(
                v.roll, v.pitch, v.roll_rate, v.pitch_rate, v.yaw_rate)))
        while tm_att.next_sample_s <= t:
            tm_att.push(tm_att.take(), s.attitude.sample(v.roll, v.pitch, v.yaw))
        while tm_lp.next_sample_s <= t:
            tm_lp.push(tm_lp.take(), s.local_position.sample((v.x, v.y, v.z),
                                                             (v.vx, v.vy, v.vz)))
        while tm_li.next_sample_s <= t:
            ts = tm_li.take()
            if r is None:
                r = rot_body_to_world(v.roll, v.pitch, v.yaw)
            ox, oy, oz = self._lidar_mount
            origin = (v.x + r[0][0] * ox + r[0][1] * oy + r[0][2] * oz,
                      v.y + r[1][0] * ox + r[1][1] * oy + r[1][2] * oz,
                      v.z + r[2][0] * ox + r[2][1] * oy + r[2][2] * oz)
            tm_li.push(ts, s.lidar.sample(origin, (-r[0][2], -r[1][2], -r[2][2]),
                                          self._lidar_surfaces()))
        margin = self._frame_margin_s
        while tm_cam.next_sample_s + margin <= t:
            tk = tm_cam.take()
            tm_cam.push(tk, self._render_frame(tk, t))
        queued = self.queued
        inbox = self.inbox
        nxt = math.inf
        for name, tm in (('imu', tm_imu), ('attitude', tm_att), ('local_position', tm_lp),
                         ('lidar', tm_li), ('camera', tm_cam)):
            if tm.pending():
                for stamp, value in tm.pop(t):
                    value = self._deliver(name, value, t, stamp)
                    if name in queued:
                        inbox[name].append((stamp, value))
            ns = tm.next_sample_s
            if name == 'camera':
                ns += margin
            if ns < nxt:
                nxt = ns
            nd = tm.next_delivery_s()
            if nd < nxt:
                nxt = nd
        self._next_sensor_s = nxt

    def _deliver(self, name: str, value: Any, t: float, stamp: float) -> Any:
        """A sample arriving at ``t``: the faults that act on the link or the reading, then
        the latest value of that sensor."""
        fs = self.faults
        if name == 'imu':
            self._latest_imu = value
        elif name == 'attitude':
            self._latest_attitude = value
        elif name == 'local_position':
            if fs is not None and fs.gps:
                off = fs.gps_offset(t)
                if off is not None:
                    pos = value[0]
                    value = ((pos[0] + off[0], pos[1] + off[1], pos[2] + off[2]), value[1])
            self._latest_position = value
        elif name == 'lidar':
            if fs is not None and fs.has_lidar:
                lp = self.sensor_params.lidar
                value = fs.lidar(t, value, lp.min_range_m, lp.max_range_m)
            self._latest_range = value
        elif name == 'camera':
            self._latest_frame = (stamp, value)
        return value

    def _lidar_surfaces(self) -> list[LidarSurface]:
        """What the lidar beam can meet now: the pad (and the ship's deck around it) and the
        ground or the sea."""
        lp = self.sensor_params.lidar
        if self.ship is None:
            cx, cy, ztop, _, _ = self._deck_now
            return [horizontal_rectangle(cx, cy, ztop, self.pad_half_x, self.pad_half_y,
                                         lp.pad_reflectivity),
                    ground_plane(lp.ground_reflectivity)]
        s = self.deck_surface
        n = (s.nx, s.ny, s.nz)
        u = (s.ux, s.uy, s.uz)
        ps = self.pad_state()
        return [LidarSurface(ps.position_m, n, u, self.pad_half_x, self.pad_half_y,
                             lp.pad_reflectivity),
                LidarSurface((s.cx, s.cy, s.cz), n, u, s.half_u, s.half_w,
                             lp.deck_reflectivity),
                ground_plane(lp.ground_reflectivity)]

    def _render_frame(self, t_k: float, t: float) -> list[Block]:
        """The Pixy frame of nominal time ``t_k`` rendered at ``t`` (after its last row):
        the beacon's row from the pose at ``t_k``, that row's exposure time, the pose and the
        deck at that time (extrapolated back from now), through the seed's true camera."""
        cm = self.sensor_suite.camera
        cm.start_frame()
        cam_true = cm.camera
        beacon = self._beacon_at(t_k)
        pos, r = self._pose_back(t - t_k)
        d = (beacon[0] - pos[0], beacon[1] - pos[1], beacon[2] - pos[2])
        uv = cam_true.project_optical(*cam_true.optical(r, d[0], d[1], d[2]))
        row = uv[1] if uv is not None else 0.5 * cam_true.height_px
        # a beacon off the sensor has no row of its own: the nearest row (the readout bounds
        # every exposure; unbounded, a point far outside the view read an exposure seconds
        # away and was drawn from a pose extrapolated that far: phantom detections)
        row = min(max(row, 0.0), cam_true.height_px - 1.0)
        te = t_k + cm.exposure_offset_s(row)
        beacon = self._beacon_at(te)
        pos, r = self._pose_back(t - te)
        fs = self.faults
        cam = self.camera
        if fs is None or not fs.has_camera:
            return cam.frame(te, pos, r, beacon, true_camera=cam_true)
        # faults act on the exposure time; the base noise streams are drawn as without them
        blocks = cam.frame(te, pos, r, beacon, show_beacon=not fs.beacon_hidden(te),
                           true_camera=cam_true)
        if fs.blobs:
            extra = fs.false_blobs(te, cam, pos, r, beacon)
            if extra:
                blocks.extend(extra)
                blocks.sort(key=lambda b: -b[3] * b[4])   # Pixy sends the largest first
        if fs.dropout and fs.camera_empty(te):
            return []
        return blocks

    def _pose_back(self, lag_s: float) -> tuple[tuple[float, float, float], Mat3]:
        """Camera position and body rotation ``lag_s`` ago (linear extrapolation)."""
        v = self.vehicle
        r = rot_body_to_world(v.roll - v.roll_rate * lag_s, v.pitch - v.pitch_rate * lag_s,
                              v.yaw - v.yaw_rate * lag_s)
        ox, oy, oz = self.camera.params.mount_offset_m
        return ((v.x - v.vx * lag_s + r[0][0] * ox + r[0][1] * oy + r[0][2] * oz,
                 v.y - v.vy * lag_s + r[1][0] * ox + r[1][1] * oy + r[1][2] * oz,
                 v.z - v.vz * lag_s + r[2][0] * ox + r[2][1] * oy + r[2][2] * oz), r)

    def delivered(self, name: str) -> list[tuple[float, Any]]:
        """Every ``(stamp, payload)`` of sensor ``name`` (:data:`SENSOR_STREAMS`) delivered
        since the last call, oldest first, for the sensors in :attr:`queued` (the in-process
        runner's way of reading: each sample reaches the stack once, stamped).
        Payloads: ``imu`` (specific force FLU, rate FLU), ``attitude`` (roll, pitch, yaw),
        ``local_position`` (position ENU, velocity ENU), ``lidar`` (m or None), ``camera``
        (Pixy blocks)."""
        box = self.inbox[name]
        out = list(box)
        box.clear()
        return out

    def read_camera(self) -> tuple[float, list[Block]]:
        """The last Pixy frame delivered: (stamp, [(signature, x, y, w, h), ...])."""
        return self._latest_frame

    def _beacon_at(self, t_s: float) -> tuple[float, float, float]:
        """The beacon (pad centre on its top) at ``t_s``."""
        if self.deck is not None:
            cx, cy, ztop, _, _ = self.deck.state(t_s)
            return cx, cy, ztop
        return self.deck_motion.pad_state(t_s).position_m

    def true_lidar_range(self) -> float | None:
        """The lidar's true range now (:func:`~deck_simulator.sensors.lidar_true_range`;
        on a ship: to the tilted deck, else the sea).

        Only the third column of R = :func:`rot_body_to_world` is needed (the ray is
        −R e3), computed with the same expressions (so the same bits) without the rest of
        the matrix."""
        v = self.vehicle
        roll, pitch, yaw = v.roll, v.pitch, v.yaw
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        dx, dy, dz = -(cy * sp * cr + sy * sr), -(sy * sp * cr - cy * sr), -(cp * cr)
        if self.ship is not None:
            return self._ray_to_deck(v.x, v.y, v.z, dx, dy, dz)
        dcx, dcy, ztop, _, _ = self._deck_now
        return lidar_range_along(v.x, v.y, v.z, dx, dy, dz, dcx, dcy, ztop, self.pad_half_x,
                                 self.pad_half_y)

    def _ray_to_deck(self, x: float, y: float, z: float, dx: float, dy: float,
                     dz: float) -> float | None:
        """Range along the unit direction from (x, y, z) to the deck's top (its rectangle,
        tilted and moving: the pose now), else to the sea (z = 0); None pointing up."""
        s = self.deck_surface
        ox, oy, oz = x - s.cx, y - s.cy, z - s.cz
        hn = ox * s.nx + oy * s.ny + oz * s.nz
        dn = dx * s.nx + dy * s.ny + dz * s.nz
        if hn > 0.0 and dn < -1e-9:
            r = hn / -dn
            px, py, pz = ox + r * dx, oy + r * dy, oz + r * dz
            if (abs(px * s.ux + py * s.uy + pz * s.uz) <= s.half_u
                    and abs(px * s.wx + py * s.wy + pz * s.wz) <= s.half_w):
                return r
        if dz >= -1e-9:
            return None
        if z <= 0.0:
            return 0.0
        return z / -dz

    def read_ship_telemetry(self) -> list[tuple[float, ShipMessage]]:
        """The ship's MAVLink messages arrived by now, ``(t_arrival_s, message)``."""
        link = self.ship_link
        return link.poll(self.t_s) if link is not None else []

    def read_lidar(self) -> float | None:
        """The last LIDAR-Lite range delivered (m along body −z), None without a return."""
        return self._latest_range

    def read_local_position(self) -> tuple[tuple[float, float, float],
                                           tuple[float, float, float]]:
        """The last EKF local position and velocity delivered, ENU."""
        return self._latest_position

    def read_attitude(self) -> tuple[float, float, float]:
        """The last attitude estimate delivered (roll, pitch, yaw; the autopilot's)."""
        return self._latest_attitude

    def read_imu(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The last IMU sample delivered: specific force and body rate, FLU."""
        return self._latest_imu

    def read_accel_world(self) -> tuple[float, float, float]:
        """Vehicle acceleration in ENU with gravity removed: the last IMU sample rotated by
        the last attitude estimate (:func:`accel_world_through`)."""
        r, p, y = self._latest_attitude
        return accel_world_through(self._latest_imu[0], r, p, y, self.params.gravity_mps2)

    # --- truth and outcome ---------------------------------------------------------------

    def truth(self) -> Truth:
        v = self.vehicle
        t = self.t_s
        d = self.deck
        if d is not None:
            cx, cy, ztop, dvz, daz = self._deck_now
            over = abs(v.x - cx) <= self.pad_half_x and abs(v.y - cy) <= self.pad_half_y
            surface = ztop if over and v.z > ztop else 0.0
            beacon = (cx, cy, ztop)
            dvel = (d.drift_x, d.drift_y)
            rpy = (0.0, 0.0, 0.0)
        else:
            ps = self.pad_state()
            beacon = ps.position_m
            ztop, dvz, daz = beacon[2], ps.velocity_mps[2], ps.accel_mps2[2]
            over = self._over_pad_now()
            surface = self._surface_below(v.x, v.y, v.z)
            dvel = (ps.velocity_mps[0], ps.velocity_mps[1])
            rpy = ps.rpy_rad
        g = self.gust
        wind = (self.wind_mean[0] + g[0], self.wind_mean[1] + g[1], g[2])
        if self.faults is not None and self.faults.wind:
            ws = self.faults.wind_step(t)
            if ws is not None:
                wind = (wind[0] + ws[0], wind[1] + ws[1], wind[2] + ws[2])
        return Truth(
            t_s=t, position_m=(v.x, v.y, v.z), velocity_mps=(v.vx, v.vy, v.vz),
            accel_mps2=(v.ax, v.ay, v.az), roll_rad=v.roll, pitch_rad=v.pitch, yaw_rad=v.yaw,
            euler_rates_radps=(v.roll_rate, v.pitch_rate, v.yaw_rate),
            beacon_position_m=beacon, deck_height_m=ztop, deck_vz_mps=dvz,
            deck_az_mps2=daz, deck_velocity_mps=dvel, over_pad=over,
            surface_height_m=surface, height_above_surface_m=v.z - surface,
            gamma=v.gamma, thrust_n=v.thrust_n, wind_mps=wind, resting_on=self.resting_on,
            deck_rpy_rad=rpy, armed=self.armed)

    def outcome(self) -> Outcome:
        """The landing record mapped to the runner's outcome fields."""
        rec = self.landing_record()
        f = rec.first
        if f is None:
            v = self.vehicle
            b = v.body
            tilt = math.acos(max(-1.0, min(1.0, b.r22)))
            return Outcome(False, False, False, 'none', self.t_s, rec.horizontal_error_m, 0.0,
                           tilt, self.max_thrust_n, 'no contact')
        return Outcome(
            landed_on_deck=rec.outcome == 'deck', crash=rec.crash,
            fallback=rec.outcome == 'fallback', contact_kind=f.surface, t_s=f.t_s,
            horizontal_error_m=rec.horizontal_error_m, touchdown_speed_mps=f.normal_speed_mps,
            tilt_rad=f.tilt_rad, max_thrust_n=self.max_thrust_n,
            reason='; '.join(rec.reasons), landing=rec.outcome,
            lateral_speed_mps=f.lateral_speed_mps, impacts=len(rec.impacts),
            max_impact_speed_mps=max(i.normal_speed_mps for i in rec.impacts),
            bounces=rec.bounces, max_bounce_height_m=rec.max_bounce_height_m,
            settled=rec.settled)
