"""In-process closed-loop landing runs: the simulator plus the loop cores the nodes run.

One run is the paper's mission (section 4.2): hovering at the start, landing triggered at
t = 0, GPS approach to the landing area, search if needed, precision landing, touchdown and
disarm — or a fallback. Physics at 400 Hz, the stack's loops at ``control_hz``; every sensor
sample reaches the stack when the world delivers it (its own clock, latency and stamp:
docs/world/sensors.md), deterministically for a seed, without ROS. Each node of the graph
(docs/interfaces.md) is its loop core here (``apron_estimator.loop``, ``landing_planner.loop``,
``dob_altitude.loop``), fed in the order its inputs arrive in one control tick.
"""

from __future__ import annotations

from bisect import insort
from dataclasses import asdict, dataclass, field
import math
from typing import Any

from apron_estimator.camera import CameraParams
from apron_estimator.estimator import ApronEstimator, EstimatorParams
from apron_estimator.loop import EstimatorLoop
from deck_simulator.outcome import RunOutcome, landing_outcome
from deck_simulator.scenario import Scenario
from deck_simulator.sensor_imu import accel_world_through
from deck_simulator.world import SENSOR_STREAMS, World
from deckland_common.contract import Mode, PixyBlock, VehicleDescription
from dob_altitude.adapter import make_controller
from dob_altitude.loop import AltitudeLoop
from landing_planner.horizontal import HorizontalController, HorizontalParams
from landing_planner.loop import PlannerLoop
from landing_planner.planner import LandingPlanner, PlannerParams
from mavlink_bridge.core import LinkMonitor, LinkMonitorParams
from mavlink_bridge.ship import DeckOdomAssembler, ShipDecodeParams, ShipTelemetryDecoder

CONTROLLERS = ('dob', 'pid', 'constant-rate')


@dataclass(frozen=True)
class RunConfig:
    """How one run is flown (the scenario says what the world does)."""

    controller: str = 'dob'
    gains_profile: str = 'default'
    physics_hz: int = 400
    control_hz: int = 100     # the companion's loops (estimator publish, planner, altitude)
    # end of run: the landing scored (settled or crashed) or this long after the first contact
    settle_after_contact_s: float = 10.0
    record: bool = False
    surface_accel_ff: bool = False
    dob_overrides: tuple[tuple[str, float], ...] = ()
    pid_overrides: tuple[tuple[str, float], ...] = ()
    planner_overrides: tuple[tuple[str, float], ...] = ()
    horizontal_overrides: tuple[tuple[str, float], ...] = ()
    # mavlink_bridge's LinkMonitor on the simulated TIMESYNC (World.timesync_rtt_s): stop
    # commanding when the link is too slow, the autopilot's failsafe takes over (None: off)
    link_monitor: LinkMonitorParams | None = field(default_factory=LinkMonitorParams)

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ValueError(f'controller must be one of {CONTROLLERS}, got {self.controller!r}')
        if self.physics_hz % self.control_hz:
            raise ValueError(f'physics_hz ({self.physics_hz}) must be a multiple of control_hz '
                             f'({self.control_hz}): the loop rate cannot be realised')
        if self.physics_hz < 400:
            raise ValueError('physics_hz must be >= 400 (the Pixhawk attitude loop rate)')


def config_fields(config: RunConfig) -> dict[str, Any]:
    """``config`` as plain data (a worker rebuilds it after loading the compiled cores)."""
    return asdict(config)


def config_from_fields(fields: dict[str, Any]) -> RunConfig:
    """The inverse of :func:`config_fields` (validated again by the constructors)."""
    monitor = fields.get('link_monitor')
    return RunConfig(**{**fields, 'link_monitor':
                        None if monitor is None else LinkMonitorParams(**monitor)})


@dataclass
class RunResult(RunOutcome):
    """Outcome of one run (a campaign's per-run record): the simulator's outcome record
    (:class:`deck_simulator.outcome.RunOutcome`) plus what the runner knows."""

    controller: str = ''
    link_degraded_s: float = math.nan  # when the LinkMonitor stopped the commands (NaN: never)
    link_latency_s: float = math.nan   # its one-way latency estimate at the end
    trace: dict[str, list[float]] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        out = asdict(self)
        out.pop('trace')
        return out


def vehicle_description(scenario: Scenario) -> VehicleDescription:
    """The scenario's vehicle as the stack is told about it (``deckland up`` passes the same
    to the altitude controller and the bridge): mass, and hover at 1 / thrust-to-weight."""
    vp = scenario.vehicle
    return VehicleDescription.from_thrust_to_weight(vp.mass_kg, vp.thrust_to_weight,
                                                    vp.gravity_mps2)


def make_altitude_controller(config: RunConfig, vehicle: VehicleDescription | None = None):
    """The altitude controller a run uses (the dob_altitude node makes the same choice)."""
    mass = (vehicle or VehicleDescription()).mass_kg
    if config.controller == 'dob':
        return make_controller('dob', config.gains_profile,
                               {'mass_kg': mass, **dict(config.dob_overrides)})
    return make_controller('pid', config.gains_profile,
                           {'mass_kg': mass, **dict(config.pid_overrides)})


def nominal_camera(scenario: Scenario) -> CameraParams:
    """The estimator's camera: the scenario's nominal ``sensors.camera`` (what an operator
    calibrated), not the per-seed true camera the world renders through."""
    c, lens = scenario.sensors.camera, scenario.sensors.true_camera
    (mx, my, mz), (mr, mp, myaw) = c.mount_offset_m, c.mount_rpy_rad
    return CameraParams(fov_x_deg=c.fov_x_deg, fov_y_deg=c.fov_y_deg,
                        width_px=float(c.width_px), height_px=float(c.height_px),
                        cx_px=c.principal_point_px[0], cy_px=c.principal_point_px[1],
                        mount_x_m=mx, mount_y_m=my, mount_z_m=mz, mount_roll_rad=mr,
                        mount_pitch_rad=mp, mount_yaw_rad=myaw,
                        # the lens's published characterisation (each unit deviates from it)
                        k1=lens.k1, k2=lens.k2, p1=lens.p1, p2=lens.p2)


def planner_params_for(scenario: Scenario, config: RunConfig) -> PlannerParams:
    """The planner is told only what an operator knows: where the landing area is."""
    ax, ay = scenario.landing_area_m
    profile = 'constant_rate' if config.controller == 'constant-rate' else 'deck_relative'
    return PlannerParams(landing_area_m=(float(ax), float(ay)), descent_profile=profile,
                         **dict(config.planner_overrides))


TRACE_FIELDS = (
    't', 'x', 'y', 'z', 'x_true', 'y_true', 'z_true', 'deck_z', 'height_est', 'height_true',
    'closing_est', 'closing_true', 'z_d', 'thrust', 'sigma', 'd_hat', 'visible', 'tracked',
    'rel_x_body', 'rel_y_body', 'rel_vx_body', 'rel_vy_body', 'rel_x_body_true', 'rel_y_body_true',
    'mode',
)


def run_landing(scenario: Scenario, seed: int, config: RunConfig | None = None) -> RunResult:
    """Fly one seeded landing of ``scenario`` and return its outcome."""
    config = config or RunConfig()
    world = World(scenario, seed, 1.0 / config.physics_hz)
    world.queued = frozenset(SENSOR_STREAMS)
    gravity = scenario.vehicle.gravity_mps2
    dt_ctrl = 1.0 / config.control_hz
    # the estimator is configured with the nominal camera; the world's differs per seed
    estimator = EstimatorLoop(ApronEstimator(EstimatorParams(
        camera=nominal_camera(scenario))))
    planner = PlannerLoop(LandingPlanner(planner_params_for(scenario, config)),
                          HorizontalController(HorizontalParams(
                              **dict(config.horizontal_overrides))), period_s=dt_ctrl)
    # in-process the altitude loop flies through an invalid vertical estimate on the
    # filter's prediction (the node withholds): the campaigns' behaviour, kept
    altitude = AltitudeLoop(make_altitude_controller(config, vehicle_description(scenario)),
                            period_s=dt_ctrl, surface_accel_ff=config.surface_accel_ff,
                            require_valid_vertical=False)
    # --- mavlink_bridge's link monitor: TIMESYNC requests through the world's link --------
    monitor = LinkMonitor(config.link_monitor) if config.link_monitor is not None else None
    replies: list[tuple[float, float]] = []   # (t_received, t_sent), sorted
    commanding = True

    ship_rx = ship_receiver(scenario)

    trace: dict[str, list[float]] = {k: [] for k in TRACE_FIELDS} if config.record else {}
    modes = list(Mode)

    dt = 1.0 / config.physics_hz
    ctrl_div = config.physics_hz // config.control_hz
    n_steps = math.ceil(scenario.timeout_s * config.physics_hz)

    t_contact = None
    mode = Mode.IDLE
    started = False
    settle_s = config.settle_after_contact_s
    landed = Mode.LANDED
    disarmed = False
    enabled = True
    # bound once: the loop below runs physics_hz times per simulated second
    world_step = world.step
    delivered = world.delivered
    camera_box = world.inbox['camera']
    est_attitude, est_position = estimator.on_attitude, estimator.on_local_position
    est_accel, est_lidar, est_publish = estimator.on_accel, estimator.on_lidar, estimator.publish
    plan_pose, plan_velocity, plan_apron = planner.on_pose, planner.on_velocity, planner.on_apron
    alt_attitude, alt_reference, alt_apron = (altitude.on_attitude, altitude.on_reference,
                                              altitude.on_apron)
    roll, pitch, yaw = world.read_attitude()
    pos, _vel = world.read_local_position()
    autopilot = world.autopilot

    for k in range(n_steps + 1):
        t = k * dt
        ctrl = k % ctrl_div == 0
        if ctrl:
            # --- mavlink_bridge: vehicle state from the autopilot -------------------------
            if monitor is not None and commanding:
                while replies and replies[0][0] <= t + 1e-9:
                    t_rx, t_tx = replies.pop(0)
                    monitor.on_timesync(t_tx, t_rx)
                commanding = not monitor.degraded
                if monitor.poll(t):
                    rtt = world.timesync_rtt_s(t)
                    if rtt is not None:
                        insort(replies, (t + rtt, t))
            # --- every sample delivered since the last tick, with its own stamp -----------
            for stamp, att in delivered('attitude'):
                roll, pitch, yaw = att
                est_attitude(t, stamp, roll, pitch, yaw)
                alt_attitude(t, stamp, roll, pitch)
            for stamp, (f_body, _rate) in delivered('imu'):
                # the estimator node's world acceleration: IMU through the attitude estimate
                est_accel(t, stamp, accel_world_through(f_body, roll, pitch, yaw, gravity))
            for stamp, (pos, vel) in delivered('local_position'):
                est_position(t, stamp, pos, vel)
                plan_pose(t, stamp, pos, roll, pitch, yaw)
                plan_velocity(t, stamp, vel)
            for stamp, rng in delivered('lidar'):
                est_lidar(t, stamp, rng)
            if ship_rx is not None:
                ship_rx.feed(t, world.read_ship_telemetry(), estimator)
            # the autopilot's land detector (EXTENDED_SYS_STATE, as the bridge relays it)
            if autopilot is not None:
                planner.on_landed(autopilot.landed)
        if camera_box:
            # --- pixy_driver: each frame when it arrives, stamped at its exposure -----------
            for stamp, blocks in delivered('camera'):
                estimator.on_camera(t, stamp, [PixyBlock(*b) for b in blocks])
        if ctrl:
            # --- apron_estimator -> landing_planner -> dob_altitude -----------------------
            apron = est_publish(t)
            if not started:
                planner.start_landing(t)
                started = True
            tick = plan_apron(t, apron, dt_ctrl) if apron is not None else planner.watchdog(t)
            alt_out = None
            if tick is not None:
                out = tick.output
                mode = out.mode
                if out.thrust_enabled is not enabled:    # control/enabled: latched, on change
                    enabled = out.thrust_enabled
                    altitude.on_enabled(enabled)
                if tick.publish_reference:
                    alt_reference(t, tick.stamp_s, out.vertical_mode, out.z_d_m,
                                  out.z_d_dot_mps, out.z_d_ddot_mps2)
                if apron is not None:
                    alt_out = alt_apron(t, apron, None, dt_ctrl)
                # the bridge streams only what it receives; disabled = disarmed (0 N)
                command = tick.command
                if commanding and command is not None and (alt_out is not None
                                                           or not enabled):
                    thrust = alt_out.thrust_n if alt_out is not None else 0.0
                    world.command_link(t, command[0], command[1], out.yaw_rad, thrust)
            if config.record and tick is not None and apron is not None:
                truth = world.truth()
                _record(trace, t, pos, truth, apron.vertical, apron, tick.output,
                        alt_out or altitude.last_output, modes.index(mode))
            if mode is landed and not disarmed:
                # the bridge asks the autopilot to disarm once the planner has landed, again
                # until it is accepted (PX4 refuses in the air; its land detector disarms too)
                disarmed = world.disarm(t) or not world.armed
        world_step(dt)
        if t_contact is None and world.contact is not None:
            t_contact = world.t_s
        if t_contact is not None and (world.landing_done or world.t_s - t_contact >= settle_s):
            break

    rec = landing_outcome(world, seed, 0.0, planner.planner.searches, mode.name,
                          f'no touchdown within {scenario.timeout_s:.0f} s (mode {mode.name})')
    result = RunResult(**asdict(rec), controller=config.controller)
    if monitor is not None:
        result.link_degraded_s = monitor.degraded_since_s
        result.link_latency_s = monitor.latency_s
    if config.record:
        result.trace = trace
    return result


class ShipReceiver:
    """The bridge's ship-telemetry side in-process: decode (mavlink_bridge.ship), assemble
    ``deck/odom``, hand it to the estimator loop — what the graph does over UDP and a topic."""

    def __init__(self, sysid: int, decode: ShipDecodeParams) -> None:
        self.sysid = sysid
        self.decoder = ShipTelemetryDecoder(decode)
        self.assembler = DeckOdomAssembler()

    def feed(self, now_s: float, messages: list[tuple[float, Any]],
             estimator: EstimatorLoop) -> None:
        for t_rx, msg in messages:
            sample = self.decoder.on_message(t_rx, self.sysid, msg)
            odom = self.assembler.on_sample(sample) if sample is not None else None
            if odom is not None:
                estimator.on_deck_odom(now_s, odom.t_s, odom.position_m, odom.velocity_mps,
                                       odom.attitude_valid, odom.rpy_rad, odom.yaw_rate_radps,
                                       odom.rates_flu_radps)


def ship_receiver(scenario: Scenario) -> ShipReceiver | None:
    """The receiver of the scenario's ship telemetry (the operator knows the ship's system
    id and the local frame's geodetic origin), None without telemetry."""
    st = scenario.ship_telemetry
    if st is None:
        return None
    return ShipReceiver(st.sysid, ShipDecodeParams(
        ship_sysid=st.sysid, origin_lat_deg=st.origin_lat_deg, origin_lon_deg=st.origin_lon_deg,
        origin_alt_m=st.origin_alt_m))


def _record(trace, t, pos, truth, vert, apron, out, alt_out, mode_index) -> None:
    nan = math.nan
    from deckland_common.frames import world_to_body_xy
    vx, vy, vz = truth.position_m
    bx, by = truth.beacon_position_m[0], truth.beacon_position_m[1]
    rbx, rby = world_to_body_xy(bx - vx, by - vy, truth.yaw_rad)
    row = {
        't': t, 'x': pos[0], 'y': pos[1], 'z': pos[2], 'x_true': vx, 'y_true': vy,
        'z_true': vz, 'deck_z': truth.deck_height_m, 'height_est': vert.height_m,
        'height_true': truth.height_above_surface_m, 'closing_est': vert.closing_speed_mps,
        'closing_true': truth.velocity_mps[2] - truth.deck_vz_mps, 'z_d': out.z_d_m,
        'thrust': alt_out.thrust_n if alt_out is not None else nan,
        'sigma': alt_out.sigma if alt_out is not None else nan,
        'd_hat': alt_out.d_hat_mps2 if alt_out is not None else nan,
        'visible': float(apron.visible),
        'tracked': float(apron.tracked), 'rel_x_body': apron.rel_position_body_m[0],
        'rel_y_body': apron.rel_position_body_m[1], 'rel_vx_body': apron.rel_velocity_body_mps[0],
        'rel_vy_body': apron.rel_velocity_body_mps[1], 'rel_x_body_true': rbx,
        'rel_y_body_true': rby, 'mode': float(mode_index),
    }
    for key, value in row.items():
        trace[key].append(value)
