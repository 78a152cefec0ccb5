"""The simulated world: vehicle truth, heaving deck, wind, sensors and touchdown (pure).

``World(scenario, seed)`` is the API of docs/interfaces.md. Every random draw comes from a
named stream of ``seed`` (``random.Random(f'{seed}:<name>')``, :func:`normal_stream` for the
Gaussian noise), so e.g. reading the camera more often never changes the GPS noise. Contact:
``pad`` (gear footprint inside the pad), ``edge`` (partly: a crash) or ``ground``; afterwards
the vehicle rests on that surface until it lifts off (not after an edge strike); only the first
contact is scored. With link faults (or a simulator node) the world also flies an autopilot
(:mod:`deck_simulator.autopilot`) every sub-step. Decisions: the package README.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import random

from deckland_common.frames import rot_body_to_world

from deck_simulator.autopilot import Autopilot, EmulatedAutopilot, in_process_params
from deck_simulator.deck import Deck, make_heave
from deck_simulator.faults import FaultSet
from deck_simulator.link import CommandLink
from deck_simulator.scenario import Scenario
from deck_simulator.sensors import (
    Block,
    Camera,
    Gps,
    Imu,
    Lidar,
    Normal,
    lidar_range_along,
    normal_stream,
)
from deck_simulator.vehicle import Vehicle

LIFTOFF_MARGIN_MPS2 = 0.2
GUST_UPDATE_S = 0.01 - 1e-9   # gusts (τ ~ s) are held over 10 ms


@dataclass(frozen=True, slots=True)
class ContactEvent:
    kind: str                       # 'pad' | 'edge' | 'ground'
    t_s: float
    touchdown_speed_mps: float      # |vehicle vz − surface vz| at contact
    horizontal_error_m: float       # vehicle centre to beacon, horizontal
    tilt_rad: float                 # acos(cos φ cos θ)
    vehicle_vz_mps: float
    surface_vz_mps: float
    position_m: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class Outcome:
    """What the runner turns into the run's outcome fields."""

    landed_on_deck: bool            # pad contact without crash
    crash: bool                     # edge, or speed > crash_speed_mps, or tilt > max_tilt_rad
    fallback: bool                  # landed on the ground (elsewhere)
    contact_kind: str               # 'pad' | 'edge' | 'ground' | 'none'
    t_s: float                      # contact time (or current time if no contact)
    horizontal_error_m: float       # at contact (or now)
    touchdown_speed_mps: float      # 0.0 without contact
    tilt_rad: float
    max_thrust_n: float             # largest collective thrust the motors produced
    reason: str


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
    deck_height_m: float                            # pad top above ground
    deck_vz_mps: float
    deck_az_mps2: float
    deck_velocity_mps: tuple[float, float]          # horizontal drift
    over_pad: bool                                  # vehicle centre above the pad rectangle
    surface_height_m: float                         # surface below the vehicle centre
    height_above_surface_m: float                   # body origin above that surface
    gamma: float                                    # true ground-effect gain (4)
    thrust_n: float                                 # collective the motors produce now
    wind_mps: tuple[float, float, float]
    resting_on: str | None                          # surface the vehicle rests on, if any


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
        heave = make_heave(sc.apron.heave, stream('heave'), sc.timeout_s + 60.0,
                           random_phase=rz.heave_phase)
        self.deck_mean_m = max(0.0, mean_h)
        self.deck = Deck(sc.apron.position_m, sc.apron.size_m, self.deck_mean_m, heave,
                         sc.apron.drift_velocity_mps)

        vp = sc.vehicle
        self.params = vp
        _, _, ztop0, _, _ = self.deck.state(0.0)
        surf0 = ztop0 if self._over_pad(start[0], start[1], 0.0) else 0.0
        hover = vp.mass_kg * vp.gravity_mps2 / vp.gamma(start[2] + vp.rotor_height_m - surf0)
        self.vehicle = Vehicle(vp, start, yaw0, hover)

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

        sp = sc.sensors
        self.camera = Camera(sp.camera, stream('camera'), noise('camera'))
        self.lidar = Lidar(sp.lidar, stream('lidar'), noise('lidar'))
        self.gps = Gps(sp.gps, stream('gps'), initial_bias=rz.gps_bias, normal=noise('gps'))
        self.imu = Imu(sp.imu, stream('imu'), noise('imu'))

        self.t_s = 0.0
        # deck state (cx, cy, z_top, vz, az) at self.t_s, kept by _substep (one evaluation
        # per sub-step serves contact, the sensors at "now" and truth())
        self._deck_now = self.deck.state(0.0)
        self.contact: ContactEvent | None = None
        self.resting_on: str | None = None
        self.max_thrust_n = self.vehicle.thrust_n
        self.rejected: dict[str, int] = {'nan': 0, 'bad_dt': 0, 'out_of_order': 0}

        # fault injection (deck_simulator.faults): nothing at all without faults
        cx0, cy0, _, _, _ = self.deck.state(0.0)
        self.faults: FaultSet | None = (FaultSet(sc.faults, seed, (cx0, cy0), self.deck_mean_m)
                                        if sc.faults else None)
        # the autopilot (deck_simulator.autopilot) and, in-process, the command link to it
        # (deck_simulator.link): only with link faults, or attached by the simulator node
        self.autopilot: Autopilot | None = None
        self.link: CommandLink | None = None
        if self.faults is not None and self.faults.has_link:
            ap = EmulatedAutopilot(in_process_params(self.faults.link_spec), self)
            self.autopilot = ap
            self.link = CommandLink(self.faults, seed, ap, self.rejected)

    # --- commands and stepping -------------------------------------------------------------

    def set_command(self, roll_rad: float, pitch_rad: float, yaw_rad: float,
                    thrust_n: float) -> None:
        """Attitude setpoint (FLU in ENU, Z-Y-X) and collective thrust u_z in newtons."""
        # one isfinite on the sum: NaN/inf anywhere makes it non-finite (finite commands would
        # need magnitudes near 1e308 to overflow it)
        if not math.isfinite(roll_rad + pitch_rad + yaw_rad + thrust_n):
            self.rejected['nan'] += 1
            return
        v = self.vehicle
        v.cmd_roll, v.cmd_pitch, v.cmd_yaw = roll_rad, pitch_rad, yaw_rad
        v.cmd_thrust = thrust_n if thrust_n > 0.0 else 0.0

    def command_link(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float,
                     thrust_n: float) -> bool:
        """Send a command over the emulated MAVLink link; True if it gets through.

        Without link faults this is :meth:`set_command`. With ``mavlink_loss`` /
        ``mavlink_latency`` / ``mavlink_link_loss`` / ``node_kill`` faults the command goes
        through :class:`~deck_simulator.link.CommandLink` to the world's
        :class:`~deck_simulator.autopilot.EmulatedAutopilot`: it may be lost (False; the
        vehicle keeps the previous command) or applied ``latency_s`` later (FIFO). The first
        accepted call engages OFFBOARD (home = here); when no command has arrived for
        ``loss_timeout_s`` the autopilot's failsafe flies (:attr:`failsafe`): hold for
        ``hold_s``, then the fault's ``action`` (land at ``land_speed_mps``, or return home
        and land); ``reengage_offboard`` lets the next command end it. A non-finite value or
        a ``t_s`` older than the previous call's is rejected (``rejected['nan']`` /
        ``['out_of_order']``, False).
        """
        link = self.link
        if link is None:
            before = self.rejected['nan']
            self.set_command(roll_rad, pitch_rad, yaw_rad, thrust_n)
            return self.rejected['nan'] == before
        return link.send(t_s, roll_rad, pitch_rad, yaw_rad, thrust_n)

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
        self.link = None

    @property
    def failsafe(self) -> str | None:
        """The autopilot's failsafe phase: None, ``'hold'``, ``'return'`` or ``'land'``."""
        ap = self.autopilot
        return ap.failsafe if ap is not None else None

    @property
    def link_stats(self) -> dict[str, int]:
        """In-process link counters ``sent``, ``lost``, ``delayed`` and the autopilot's
        ``failsafes``."""
        out = dict(self.link.stats) if self.link is not None else {
            'sent': 0, 'lost': 0, 'delayed': 0}
        out['failsafes'] = self.autopilot.failsafes if self.autopilot is not None else 0
        return out

    def surface_below_vehicle(self) -> float:
        """Height of the surface below the vehicle centre now: the pad top over the pad (and
        above it), else the ground (0)."""
        v = self.vehicle
        cx, cy, ztop, _, _ = self._deck_now
        over = abs(v.x - cx) <= self.deck.half_x and abs(v.y - cy) <= self.deck.half_y
        return ztop if over and v.z > ztop else 0.0

    def active_faults(self, t_s: float | None = None) -> tuple[str, ...]:
        """Types of the scenario faults active at ``t_s`` (default now), for logging."""
        if self.faults is None:
            return ()
        return self.faults.active(self.t_s if t_s is None else t_s)

    def step(self, dt_s: float) -> None:
        """Advance the physics by dt_s, in sub-steps of at most ``physics_dt_s``."""
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

    def _over_pad(self, x: float, y: float, t_s: float) -> bool:
        cx, cy, _, _, _ = self.deck.state(t_s)
        d = self.deck
        return abs(x - cx) <= d.half_x and abs(y - cy) <= d.half_y

    def _substep(self, h: float) -> None:
        t = self.t_s + h
        deck = self.deck
        # the deck at the end of the sub-step: contact and the resting constraint must agree
        # with truth() at the new time (the half-step offset for z_p of (4) is immaterial)
        dk = deck.state(t)
        cx, cy, ztop, dvz, daz = dk
        v = self.vehicle
        p = self.params
        ap = self.autopilot
        if ap is not None and ap.active:
            if self.link is not None:
                self.link.deliver_due(self.t_s)
            ap.tick(self.t_s, self)
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
        x0, y0 = v.x, v.y
        ox, oy = x0 - cx, y0 - cy
        hx, hy = deck.half_x, deck.half_y
        surface = ztop if (-hx <= ox <= hx and -hy <= oy <= hy and v.z > ztop) else 0.0
        fs = self.faults
        wmx, wmy = self.wind_mean
        if fs is None:
            v.step(h, surface, wmx + g[0], wmy + g[1], g[2])
        else:
            if fs.pending:
                fs.update_height(self.t_s, v.z - surface)
            wx, wy, wz = wmx + g[0], wmy + g[1], g[2]
            if fs.wind:
                ws = fs.wind_step(self.t_s)
                if ws is not None:
                    wx, wy, wz = wx + ws[0], wy + ws[1], wz + ws[2]
            v.step(h, surface, wx, wy, wz)
        thrust = v.f1 + v.f2 + v.f3 + v.f4
        if thrust > self.max_thrust_n:
            self.max_thrust_n = thrust
        self.t_s = t
        self._deck_now = dk
        resting = self.resting_on
        if resting is None:
            gear_z = v.z - p.gear_height_m
            if gear_z > ztop and gear_z > 0.0:
                return
            gw = p.gear_half_width_m
            ox, oy = v.x - cx, v.y - cy
            kind = None
            if abs(ox) < hx + gw and abs(oy) < hy + gw and gear_z <= ztop:
                kind = 'pad' if (abs(ox) <= hx - gw and abs(oy) <= hy - gw) else 'edge'
            elif gear_z <= 0.0:
                kind = 'ground'
            if kind is None:
                return
            self._touchdown(kind, t)
            resting = kind
        # resting on a surface: the contact constraint overrides the free-flight state
        if resting == 'ground':
            sz, svz, saz, svx, svy = 0.0, 0.0, 0.0, 0.0, 0.0
        else:
            sz, svz, saz, svx, svy = ztop, dvz, daz, deck.drift_x, deck.drift_y
        if resting != 'edge' and v.az > saz + LIFTOFF_MARGIN_MPS2:
            self.resting_on = None
            if v.z < sz + p.gear_height_m:
                v.z = sz + p.gear_height_m
                v.vz = max(v.vz, svz)
            return
        v.z = sz + p.gear_height_m
        v.vz, v.az = svz, saz
        v.x, v.y = x0 + svx * h, y0 + svy * h
        v.vx, v.vy, v.ax, v.ay = svx, svy, 0.0, 0.0
        v.roll = v.pitch = 0.0
        v.roll_rate = v.pitch_rate = v.yaw_rate = 0.0
        v.reset_attitude_loop()

    def _touchdown(self, kind: str, t: float) -> None:
        v = self.vehicle
        cx, cy, _, dvz, _ = self.deck.state(t)
        svz = 0.0 if kind == 'ground' else dvz
        tilt = math.acos(max(-1.0, min(1.0, math.cos(v.roll) * math.cos(v.pitch))))
        if self.contact is None:
            self.contact = ContactEvent(
                kind=kind, t_s=t, touchdown_speed_mps=abs(v.vz - svz),
                horizontal_error_m=math.hypot(v.x - cx, v.y - cy), tilt_rad=tilt,
                vehicle_vz_mps=v.vz, surface_vz_mps=svz, position_m=(v.x, v.y, v.z))
        self.resting_on = kind

    # --- sensors -----------------------------------------------------------------------------

    def read_camera(self) -> tuple[float, list[Block]]:
        """One Pixy frame: (exposure stamp, [(signature, x, y, w, h), ...]).

        The frame is exposed ``latency_s`` before now (pose extrapolated back linearly over
        the latency, deck evaluated exactly at the stamp). Call at ``sensors.camera.rate_hz``.
        """
        v = self.vehicle
        cp = self.camera.params
        lat = cp.latency_s
        stamp = self.t_s - lat
        if stamp < 0.0:
            stamp, lat = self.t_s, 0.0
        r = rot_body_to_world(v.roll - v.roll_rate * lat, v.pitch - v.pitch_rate * lat,
                              v.yaw - v.yaw_rate * lat)
        ox, oy, oz = cp.mount_offset_m
        cam = (v.x - v.vx * lat + r[0][0] * ox + r[0][1] * oy + r[0][2] * oz,
               v.y - v.vy * lat + r[1][0] * ox + r[1][1] * oy + r[1][2] * oz,
               v.z - v.vz * lat + r[2][0] * ox + r[2][1] * oy + r[2][2] * oz)
        cx, cy, ztop, _, _ = self.deck.state(stamp)
        fs = self.faults
        if fs is None or not fs.has_camera:
            return stamp, self.camera.frame(stamp, cam, r, (cx, cy, ztop))
        # faults act on the exposure time; the base noise streams are drawn as without them
        blocks = self.camera.frame(stamp, cam, r, (cx, cy, ztop),
                                   show_beacon=not fs.beacon_hidden(stamp))
        if fs.blobs:
            extra = fs.false_blobs(stamp, self.camera, cam, r, (cx, cy, ztop))
            if extra:
                blocks.extend(extra)
                blocks.sort(key=lambda b: -b[3] * b[4])   # Pixy sends the largest first
        if fs.dropout and fs.camera_empty(stamp):
            return stamp, []
        return stamp, blocks

    def true_lidar_range(self) -> float | None:
        """The lidar's true range now (:func:`~deck_simulator.sensors.lidar_true_range`).

        Only the third column of R = :func:`rot_body_to_world` is needed (the ray is
        −R e3), computed with the same expressions (so the same bits) without the rest of
        the matrix."""
        v = self.vehicle
        roll, pitch, yaw = v.roll, v.pitch, v.yaw
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        dcx, dcy, ztop, _, _ = self._deck_now
        d = self.deck
        return lidar_range_along(v.x, v.y, v.z, -(cy * sp * cr + sy * sr),
                                 -(sy * sp * cr - cy * sr), -(cp * cr), dcx, dcy, ztop,
                                 d.half_x, d.half_y)

    def read_lidar(self) -> float | None:
        """LidarLite range along body −z (m), None when there is no valid return."""
        r = self.lidar.read(self.true_lidar_range())
        fs = self.faults
        if fs is not None and fs.has_lidar:
            lp = self.lidar.params
            return fs.lidar(self.t_s, r, lp.min_range_m, lp.max_range_m)
        return r

    def read_local_position(self) -> tuple[tuple[float, float, float],
                                           tuple[float, float, float]]:
        """GPS/EKF-like local position and velocity, ENU."""
        v = self.vehicle
        pos, vel = self.gps.read(self.t_s, (v.x, v.y, v.z), (v.vx, v.vy, v.vz))
        fs = self.faults
        if fs is not None and fs.gps:
            off = fs.gps_offset(self.t_s)
            if off is not None:
                pos = (pos[0] + off[0], pos[1] + off[1], pos[2] + off[2])
        return pos, vel

    def read_attitude(self) -> tuple[float, float, float]:
        v = self.vehicle
        return self.imu.attitude(v.roll, v.pitch, v.yaw)

    def read_accel_world(self) -> tuple[float, float, float]:
        """Vehicle acceleration in ENU with gravity removed (IMU rotated by the EKF)."""
        v = self.vehicle
        return self.imu.accel(v.ax, v.ay, v.az)

    # --- truth and outcome ---------------------------------------------------------------

    def truth(self) -> Truth:
        v = self.vehicle
        d = self.deck
        t = self.t_s
        cx, cy, ztop, dvz, daz = self._deck_now
        over = abs(v.x - cx) <= d.half_x and abs(v.y - cy) <= d.half_y
        surface = ztop if over and v.z > ztop else 0.0
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
            beacon_position_m=(cx, cy, ztop), deck_height_m=ztop, deck_vz_mps=dvz,
            deck_az_mps2=daz, deck_velocity_mps=(d.drift_x, d.drift_y), over_pad=over,
            surface_height_m=surface, height_above_surface_m=v.z - surface,
            gamma=self.params.gamma(v.z + self.params.rotor_height_m - surface),
            thrust_n=v.thrust_n,
            wind_mps=wind,
            resting_on=self.resting_on)

    def outcome(self) -> Outcome:
        sc = self.scenario
        c = self.contact
        if c is None:
            v = self.vehicle
            cx, cy, _, _, _ = self.deck.state(self.t_s)
            return Outcome(False, False, False, 'none', self.t_s,
                           math.hypot(v.x - cx, v.y - cy), 0.0,
                           math.acos(max(-1.0, min(1.0, math.cos(v.roll) * math.cos(v.pitch)))),
                           self.max_thrust_n, 'no contact')
        reasons = []
        if c.kind == 'edge':
            reasons.append('edge strike')
        if c.touchdown_speed_mps > sc.crash_speed_mps:
            reasons.append(f'touchdown speed {c.touchdown_speed_mps:.2f} m/s > '
                           f'{sc.crash_speed_mps:.2f}')
        if c.tilt_rad > sc.max_tilt_rad:
            reasons.append(f'tilt {c.tilt_rad:.2f} rad > {sc.max_tilt_rad:.2f}')
        crash = bool(reasons)
        if not reasons:
            reasons.append('landed on deck' if c.kind == 'pad' else 'landed on the ground')
        return Outcome(landed_on_deck=c.kind == 'pad' and not crash, crash=crash,
                       fallback=c.kind == 'ground', contact_kind=c.kind, t_s=c.t_s,
                       horizontal_error_m=c.horizontal_error_m,
                       touchdown_speed_mps=c.touchdown_speed_mps, tilt_rad=c.tilt_rad,
                       max_thrust_n=self.max_thrust_n, reason='; '.join(reasons))
