"""A tiny kinematic stand-in for vehicle, deck and estimator, used by the planner tests.

It is deliberately simple and independent of deck_simulator: the vehicle's vertical motion
tracks the planner's reference exactly as an ideal altitude loop would (first-order on the
height error, with the reference rate and the surface rate fed forward), the horizontal motion
is a point mass driven by the tilt of model (2) through a first-order attitude lag, and the
"estimator" reports truth (optionally with a GPS bias and a blocked camera).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from deckland_common.contract import ApronState, Mode, PlannerOutput, VehicleState, VerticalState
from deckland_common.frames import mat_vec, rot_body_to_world
from landing_planner.horizontal import HorizontalController, HorizontalParams
from landing_planner.planner import LandingPlanner, PlannerParams

G = 9.81


def make_vertical(height=2.0, closing=0.0, surface=0.0, epoch=0, rebase=0.0,
                  valid=True) -> VerticalState:
    return VerticalState(valid=valid, height_m=height, closing_speed_mps=closing,
                         vehicle_altitude_m=height + surface, vehicle_vz_mps=closing,
                         surface_height_m=surface, surface_vz_mps=0.0, surface_accel_mps2=0.0,
                         surface_epoch=epoch, last_rebase_m=rebase)


def make_apron(t, vehicle_xy=(0.0, 0.0), beacon_xy=None, vertical=None,
               beacon_v=(0.0, 0.0)) -> ApronState:
    """ApronState as the estimator would report it; beacon_xy None = not tracked."""
    vertical = vertical or make_vertical()
    if beacon_xy is None:
        z = (0.0, 0.0)
        return ApronState(t, False, False, math.inf, z, z, z, z, z, z, z, vertical)
    rel = (beacon_xy[0] - vehicle_xy[0], beacon_xy[1] - vehicle_xy[1])
    return ApronState(t, True, True, 0.0, rel, beacon_v, (0.01, 0.01), rel, beacon_v,
                      tuple(beacon_xy), beacon_v, vertical)


def make_vehicle(t, xy=(0.0, 0.0), z=2.0, v=(0.0, 0.0, 0.0), yaw=0.0,
                 landed=False) -> VehicleState:
    return VehicleState(t_s=t, position_m=(xy[0], xy[1], z), velocity_mps=v, roll_rad=0.0,
                        pitch_rad=0.0, yaw_rad=yaw, landed=landed)


@dataclass
class StandIn:
    """Vehicle + heaving deck + perfect-ish estimator, stepped at ``dt_s``."""

    params: PlannerParams = field(default_factory=PlannerParams)
    start_xy: tuple[float, float] = (-3.0, 1.5)
    start_height_m: float = 2.0
    beacon_xy: tuple[float, float] = (0.0, 0.0)
    deck_half_m: float = 0.5           # square pad around the beacon
    deck_base_m: float = 0.6           # mean deck top height
    heave_amp_m: float = 0.15
    heave_period_s: float = 6.0
    half_fov_rad: float = math.radians(30.0)
    gps_bias_m: tuple[float, float] = (0.0, 0.0)
    camera_blocked: object = None      # callable t -> bool
    vertical_gain: float = 3.0         # 1/s, ideal altitude loop bandwidth
    tilt_lag_s: float = 0.08
    yaw_rad: float = 0.4
    dt_s: float = 0.01

    def __post_init__(self) -> None:
        self.planner = LandingPlanner(self.params)
        self.hctl = HorizontalController(HorizontalParams())
        self.t = 0.0
        self.x, self.y = self.start_xy
        self.vx = self.vy = 0.0
        self.roll = self.pitch = 0.0
        self.z = self.surface(self.x, self.y, 0.0) + self.start_height_m
        self.vz = 0.0
        self.contact = None            # (t, on_pad, rel speed, horizontal error)
        self.epoch = 0
        self.last_rebase = 0.0
        self._last_surface_kind = self._kind(self.x, self.y)
        self._t_seen = -math.inf
        self.log: list[tuple[float, PlannerOutput, float, float, float]] = []
        self.outputs: list[PlannerOutput] = []

    # --- world ----------------------------------------------------------------------------
    def deck(self, t):
        w = 2.0 * math.pi / self.heave_period_s
        return (self.deck_base_m + self.heave_amp_m * math.sin(w * t),
                self.heave_amp_m * w * math.cos(w * t))

    def _kind(self, x, y):
        return (abs(x - self.beacon_xy[0]) <= self.deck_half_m
                and abs(y - self.beacon_xy[1]) <= self.deck_half_m)

    def surface(self, x, y, t):
        return self.deck(t)[0] if self._kind(x, y) else 0.0

    def surface_vz(self, x, y, t):
        return self.deck(t)[1] if self._kind(x, y) else 0.0

    # --- sensing (the estimator stand-in) -------------------------------------------------
    def sense(self, nan_vehicle=False):
        t = self.t
        surf = self.surface(self.x, self.y, t)
        kind = self._kind(self.x, self.y)
        if kind != self._last_surface_kind:
            old = self.deck(t)[0] if self._last_surface_kind else 0.0
            self.epoch += 1
            self.last_rebase = surf - old
            self._last_surface_kind = kind
        h = self.z - surf
        closing = self.vz - self.surface_vz(self.x, self.y, t)
        vert = VerticalState(True, h, closing, self.z, self.vz, surf,
                             self.surface_vz(self.x, self.y, t), 0.0, self.epoch,
                             self.last_rebase)
        gx, gy = self.x + self.gps_bias_m[0], self.y + self.gps_bias_m[1]
        rel = (self.beacon_xy[0] - self.x, self.beacon_xy[1] - self.y)
        beacon_below = self.z - self.deck(t)[0]
        visible = (beacon_below > 0.05
                   and math.hypot(*rel) <= beacon_below * math.tan(self.half_fov_rad)
                   and not (self.camera_blocked and self.camera_blocked(t)))
        if visible:
            self._t_seen = t
        tracked = t - self._t_seen <= 0.3
        rv = (-self.vx, -self.vy)
        apron = ApronState(t, tracked, visible, t - self._t_seen, rel, rv, (0.01, 0.01), rel,
                           rv, (gx + rel[0], gy + rel[1]), (0.0, 0.0), vert)
        pos = (math.nan, gy, self.z) if nan_vehicle else (gx, gy, self.z)
        vehicle = VehicleState(t, pos, (self.vx, self.vy, self.vz), self.roll, self.pitch,
                               self.yaw_rad)
        return vehicle, apron

    # --- one control + physics step -------------------------------------------------------
    def step(self, nan_vehicle=False) -> PlannerOutput:
        dt = self.dt_s
        vehicle, apron = self.sense(nan_vehicle)
        out = self.planner.step(self.t, dt, vehicle, apron)
        self.outputs.append(out)
        gx, gy = self.x + self.gps_bias_m[0], self.y + self.gps_bias_m[1]
        roll_c, pitch_c = self.hctl.step(out.setpoint_m, out.velocity_ff_mps, (gx, gy),
                                         (self.vx, self.vy), self.yaw_rad, dt)
        k = dt / (self.tilt_lag_s + dt)
        self.roll += k * (roll_c - self.roll)
        self.pitch += k * (pitch_c - self.pitch)
        # model (2) with u_z cφ cθ = m g (altitude loop holds the vertical balance)
        r3 = mat_vec(rot_body_to_world(self.roll, self.pitch, self.yaw_rad), (0.0, 0.0, 1.0))
        ax, ay = G * r3[0] / r3[2], G * r3[1] / r3[2]
        surf = self.surface(self.x, self.y, self.t)
        svz = self.surface_vz(self.x, self.y, self.t)
        if self.contact is None:
            if out.vertical_mode == 'world_rate':
                vz = out.z_d_dot_mps + self.vertical_gain * (out.z_d_m - self.z)
            else:
                h = self.z - surf
                vz = svz + out.z_d_dot_mps + self.vertical_gain * (out.z_d_m - h)
            self.vx += ax * dt
            self.vy += ay * dt
            self.x += self.vx * dt
            self.y += self.vy * dt
            self.vz = vz
            self.z += vz * dt
        self.t = round(self.t + dt, 9)
        surf = self.surface(self.x, self.y, self.t)
        svz = self.surface_vz(self.x, self.y, self.t)
        if self.contact is None and self.z <= surf + self.params.gear_height_m:
            self.contact = (self.t, self._kind(self.x, self.y), self.vz - svz,
                            math.hypot(self.x - self.beacon_xy[0], self.y - self.beacon_xy[1]))
        if self.contact is not None:   # sits on the surface, moves with it
            self.z = surf + self.params.gear_height_m
            self.vz = svz
            self.vx = self.vy = 0.0
        self.log.append((self.t, out, self.x, self.y, self.z))
        return out

    def run(self, t_end_s, until_mode: Mode | None = None, **kw) -> PlannerOutput:
        out = None
        while self.t < t_end_s:
            out = self.step(**kw)
            if until_mode is not None and out.mode is until_mode:
                break
        return out

    def modes(self) -> list[Mode]:
        seq: list[Mode] = []
        for out in self.outputs:
            if not seq or seq[-1] is not out.mode:
                seq.append(out.mode)
        return seq


DT = 0.01


AREA = (0.0, 0.0)


class Driver:
    """Steps a planner at 100 Hz with a vehicle that sits exactly where it is told."""

    def __init__(self, params=None, xy=AREA, height=2.0):
        self.p = LandingPlanner(params or PlannerParams(landing_area_m=AREA))
        self.t = 0.0
        self.xy = xy
        self.height = height
        self.closing = 0.0
        self.beacon = None          # None = not tracked
        self.epoch = 0
        self.rebase = 0.0
        self.valid = True
        self.surface = 0.0
        self.landed_flag = False
        self.out = None

    def step(self):
        vert = make_vertical(self.height, self.closing, self.surface, self.epoch, self.rebase,
                             self.valid)
        apron = make_apron(self.t, self.xy, self.beacon, vert)
        veh = make_vehicle(self.t, self.xy, self.height + self.surface, landed=self.landed_flag)
        self.out = self.p.step(self.t, DT, veh, apron)
        self.t = round(self.t + DT, 9)
        return self.out

    def run(self, duration, until=None):
        end = self.t + duration
        while self.t < end - 1e-9:
            self.step()
            if until is not None and self.out.mode is until:
                break
        return self.out


def aligned_driver(**kw):
    d = Driver(PlannerParams(landing_area_m=AREA, **kw))
    d.beacon = (0.05, 0.0)
    d.p.start_landing(0.0)
    d.run(0.05)
    assert d.out.mode is Mode.ALIGN
    return d
