"""In-process closed-loop landing runs: the simulator plus the same cores the nodes run.

One run is the paper's mission (section 4.2): hovering at the start, landing triggered at
t = 0, GPS approach to the landing area, search if needed, precision landing, touchdown and
disarm — or a fallback. Everything is stepped in lock-step at the real rates (physics 400 Hz,
estimator/planner/controllers 100 Hz, camera 50 Hz with its latency), deterministically for a
seed, without ROS. The wiring here mirrors the node graph (docs/interfaces.md): each block
below corresponds to one node's callback.
"""

from __future__ import annotations

from bisect import insort
from dataclasses import asdict, dataclass, field
import math
from typing import Any

from apron_estimator.estimator import ApronEstimator, EstimatorParams
from apron_estimator.types import PixyBlock
from deck_simulator.outcome import RunOutcome, landing_outcome
from deck_simulator.scenario import Scenario
from deck_simulator.world import World
from dob_altitude.adapter import altitude_input, make_controller, parse_vertical_frame
from landing_planner.horizontal import HorizontalController, HorizontalParams
from landing_planner.planner import LandingPlanner, PlannerParams
from landing_planner.types import Mode, VehicleState
from mavlink_bridge.core import LinkMonitor, LinkMonitorParams

CONTROLLERS = ('dob', 'pid', 'constant-rate')


@dataclass(frozen=True)
class RunConfig:
    """How one run is flown (the scenario says what the world does)."""

    controller: str = 'dob'
    gains_profile: str = 'default'
    physics_hz: int = 400
    control_hz: int = 100
    camera_hz: int = 50
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
        if self.physics_hz % self.control_hz or self.physics_hz % self.camera_hz:
            raise ValueError('physics_hz must be a multiple of control_hz and camera_hz')
        if self.physics_hz < 400:
            raise ValueError('physics_hz must be >= 400 (the Pixhawk attitude loop rate)')


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


def make_altitude_controller(config: RunConfig):
    """The altitude controller a run uses (the dob_altitude node makes the same choice)."""
    if config.controller == 'dob':
        return make_controller('dob', config.gains_profile, dict(config.dob_overrides))
    return make_controller('pid', config.gains_profile, dict(config.pid_overrides))


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
    world = World(scenario, seed)
    estimator = ApronEstimator(EstimatorParams())
    planner = LandingPlanner(planner_params_for(scenario, config))
    altitude = make_altitude_controller(config)
    vframe = 'surface'
    vmode = None   # the planner's last vertical_mode string
    horizontal = HorizontalController(HorizontalParams(**dict(config.horizontal_overrides)))
    # --- mavlink_bridge's link monitor: TIMESYNC requests through the world's link --------
    monitor = LinkMonitor(config.link_monitor) if config.link_monitor is not None else None
    replies: list[tuple[float, float]] = []   # (t_received, t_sent), sorted
    commanding = True

    trace: dict[str, list[float]] = {k: [] for k in TRACE_FIELDS} if config.record else {}
    modes = list(Mode)

    dt = 1.0 / config.physics_hz
    ctrl_div = config.physics_hz // config.control_hz
    cam_div = config.physics_hz // config.camera_hz
    dt_ctrl = 1.0 / config.control_hz
    n_steps = math.ceil(scenario.timeout_s * config.physics_hz)

    t_contact = None
    mode = Mode.IDLE
    started = False
    settle_s = config.settle_after_contact_s
    landed = Mode.LANDED
    disarmed = False
    # bound once: the loop below runs physics_hz times per simulated second
    world_step = world.step
    planner_step = planner.step
    altitude_step = altitude.step
    horizontal_step = horizontal.step

    for k in range(n_steps + 1):
        t = k * dt
        ctrl = k % ctrl_div == 0
        frame = world.read_camera() if k % cam_div == 0 else None
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
            pos, vel = world.read_local_position()
            roll, pitch, yaw = world.read_attitude()
            estimator.on_attitude(t, roll, pitch, yaw)
            estimator.on_local_position(t, pos, vel)
            estimator.on_accel(t, world.read_accel_world())
            estimator.on_lidar(t, world.read_lidar())
        if frame is not None:
            # --- pixy_driver: the frame arrives now, stamped at its (earlier) exposure -------
            estimator.on_camera(frame[0], [PixyBlock(*b) for b in frame[1]])
        if ctrl:
            # --- apron_estimator -> landing_planner -------------------------------------
            apron = estimator.state(t)
            if not started:
                planner.start_landing(t)
                started = True
            vehicle = VehicleState(t, pos, vel, roll, pitch, yaw)
            out = planner_step(t, dt_ctrl, vehicle, apron)
            mode = out.mode
            roll_cmd, pitch_cmd = horizontal_step(out.setpoint_m, out.velocity_ff_mps,
                                                  (pos[0], pos[1]), (vel[0], vel[1]), yaw,
                                                  dt_ctrl, precise=out.precise_xy)
            # --- dob_altitude ------------------------------------------------------------
            vert = apron.vertical
            if out.vertical_mode != vmode:   # parse only when the planner's mode changes
                vmode = out.vertical_mode
                new_frame = parse_vertical_frame(vmode)
                if new_frame != vframe:  # the node resets on a frame switch too
                    altitude.reset()
                    vframe = new_frame
            inp = altitude_input(vert, out.z_d_m, out.z_d_dot_mps, out.z_d_ddot_mps2, vframe,
                                 roll, pitch, surface_accel_ff=config.surface_accel_ff)
            alt_out = altitude_step(inp, dt_ctrl)
            thrust = alt_out.thrust_n if out.thrust_enabled else 0.0
            if commanding:   # else the bridge has stopped streaming (LinkMonitor)
                world.command_link(t, roll_cmd, pitch_cmd, out.yaw_rad, thrust)
            if config.record:
                truth = world.truth()
                _record(trace, t, pos, truth, vert, apron, out, alt_out, modes.index(mode))
            if mode is landed and not disarmed:
                # the bridge asks the autopilot to disarm once the planner has landed, again
                # until it is accepted (PX4 refuses in the air; its land detector disarms too)
                disarmed = world.disarm(t) or not world.armed
        world_step(dt)
        if t_contact is None and world.contact is not None:
            t_contact = world.t_s
        if t_contact is not None and (world.landing_done or world.t_s - t_contact >= settle_s):
            break

    rec = landing_outcome(world, seed, 0.0, planner.searches, mode.name,
                          f'no touchdown within {scenario.timeout_s:.0f} s (mode {mode.name})')
    result = RunResult(**asdict(rec), controller=config.controller)
    if monitor is not None:
        result.link_degraded_s = monitor.degraded_since_s
        result.link_latency_s = monitor.latency_s
    if config.record:
        result.trace = trace
    return result


def _record(trace, t, pos, truth, vert, apron, out, alt_out, mode_index) -> None:
    from deckland_common.frames import world_to_body_xy
    vx, vy, vz = truth.position_m
    bx, by = truth.beacon_position_m[0], truth.beacon_position_m[1]
    rbx, rby = world_to_body_xy(bx - vx, by - vy, truth.yaw_rad)
    row = {
        't': t, 'x': pos[0], 'y': pos[1], 'z': pos[2], 'x_true': vx, 'y_true': vy,
        'z_true': vz, 'deck_z': truth.deck_height_m, 'height_est': vert.height_m,
        'height_true': truth.height_above_surface_m, 'closing_est': vert.closing_speed_mps,
        'closing_true': truth.velocity_mps[2] - truth.deck_vz_mps, 'z_d': out.z_d_m,
        'thrust': alt_out.thrust_n,
        'sigma': alt_out.sigma, 'd_hat': alt_out.d_hat_mps2, 'visible': float(apron.visible),
        'tracked': float(apron.tracked), 'rel_x_body': apron.rel_position_body_m[0],
        'rel_y_body': apron.rel_position_body_m[1], 'rel_vx_body': apron.rel_velocity_body_mps[0],
        'rel_vy_body': apron.rel_velocity_body_mps[1], 'rel_x_body_true': rbx,
        'rel_y_body_true': rby, 'mode': float(mode_index),
    }
    for key, value in row.items():
        trace[key].append(value)
