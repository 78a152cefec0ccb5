"""ROS 2 node ``deck_simulator``: the simulated world on the wall clock, emulating the hardware.

A thin adapter around :class:`deck_simulator.loop.SimulationLoop` (the world; its autopilot,
the emulated PX4 on the MAVLink wire or PX4 SITL in lockstep (``autopilot: px4-sitl``,
:mod:`deck_simulator.px4_hil`); the Pixy datagrams; the outcome record): parameters, sockets, a
thread that advances the loop on absolute deadlines (:class:`~deck_simulator.loop.TickSchedule`,
``tick_s × realtime_factor`` of sim time per tick, stalls over ``MAX_TICK_WALL_S`` given up),
the ``sim/truth/*`` topics stamped with the wall time each sample stands for, the latched
``sim/outcome`` JSON, and ``planner/mode`` in (the landing trigger). See the package README.
"""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
import time

from deckland_common.frames import euler_to_quaternion
from deckland_common.params import ParameterError, ParamSpec, in_range, one_of
from deckland_common.ros_node import (
    LATCHED_QOS,
    RELIABLE_QOS,
    declare_and_validate,
    run_node,
    s_to_stamp,
)
from mavlink_bridge.signing import load_signing_key
from nav_msgs.msg import Odometry
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.node import Node
from std_msgs.msg import String

from deck_simulator.ardupilot_json import ArduPilotJson, JsonParams
from deck_simulator.link import DOWNLINK_MODES
from deck_simulator.loop import SimulationLoop, TickSchedule, body_twist
from deck_simulator.outcome import outcome_json
from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator, vehicle_thrust_calibration
from deck_simulator.px4_hil import HilParams, Px4Hil
from deck_simulator.scenario import load_scenario
from deck_simulator.transport import is_ipv4, is_mavlink_url, make_mavlink_link
from deck_simulator.world import Truth

LOCKSTEP_REPORT_S = 5.0          # px4-sitl: how often the lockstep rate is logged
MAX_TICK_WALL_S = 0.1            # a longer stall is not caught up (the sim slows down instead)
#: a GIL switch interval of 1 ms (CPython's default is 5 ms) so the world thread wakes on time
#: even while an executor thread of this process runs Python code
SWITCH_INTERVAL_S = 0.001


PARAMS = [
    ParamSpec('scenario', 'paper', 'built-in scenario name or path to a scenario YAML file',
              lambda v: v.strip() != '', 'must not be empty'),
    ParamSpec('seed', 1, 'seed of every random stream of the world', lambda v: v >= 0,
              'must be >= 0'),
    one_of('autopilot', 'emulator', ('emulator', 'px4-sitl', 'ardupilot-sitl'),
           "what flies the vehicle: 'emulator' (the emulated PX4 on mavlink_url), "
           "'px4-sitl' (PX4 SITL, airframe 10016, connects to px4_sim_port) or "
           "'ardupilot-sitl' (ArduCopter SITL --model JSON, servo frames to "
           'ardupilot_physics_port; deckland up --autopilot X starts them)'),
    in_range('ardupilot_physics_port', 9002, 1, 65535, 'ardupilot-sitl: UDP port of the JSON '
             'physics (9002 + 10 x ArduPilot instance); physics_rate_hz = its SIM_RATE_HZ'),
    in_range('px4_sim_port', 4560, 1, 65535, 'px4-sitl: TCP port PX4 connects to (the '
             'Simulator MAVLink API: 4560 + PX4 instance)'),
    ParamSpec('px4_onboard_url', '', "px4-sitl: PX4's onboard link as 'udpin:HOST:PORT' "
              "(14540 + instance) to carry it through the scenario's MAVLink faults to the "
              "bridge on mavlink_url; empty = the bridge talks to PX4 directly",
              lambda v: v == '' or is_mavlink_url(v), "must be empty or 'udpin:IPV4:PORT'"),
    ParamSpec('mavlink_url', 'udpout:127.0.0.1:14540',
              "emulated autopilot's MAVLink socket: 'udpout:HOST:PORT' sends to the bridge "
              "listening there (bridge default 'udpin:127.0.0.1:14540'); 'udpin:HOST:PORT' "
              "listens for a bridge configured 'udpout:HOST:PORT'", is_mavlink_url,
              "must be 'udpin:IPV4:PORT' or 'udpout:IPV4:PORT'"),
    in_range('mavlink_fd', -1, -1, 65535, 'an inherited UDP socket already bound to the '
             'udpin mavlink_url (deckland up binds it before starting the graph); -1: bind '
             'it here'),
    ParamSpec('pixy_udp_address', '127.0.0.1', "where pixy_driver listens (its "
              "'udp_bind_address')", is_ipv4, 'must be an IPv4 literal'),
    in_range('pixy_udp_port', 14600, 1, 65535, "pixy_driver's 'udp_port'"),
    ParamSpec('ship_udp_address', '127.0.0.1', "where ship_telemetry_node listens (its "
              "'ship_url' udpin address); scenarios with ship_telemetry only", is_ipv4,
              'must be an IPv4 literal'),
    in_range('ship_udp_port', 14570, 1, 65535, "ship_telemetry_node's 'ship_url' port"),
    ParamSpec('realtime_factor', 1.0, 'sim seconds per wall second', lambda v: 0.0 < v <= 20.0,
              'must be in (0, 20]'),
    ParamSpec('physics_rate_hz', 400.0, 'physics sub-step rate (the Pixhawk attitude loop runs '
              'at 400 Hz)', lambda v: 400.0 <= v <= 4000.0, 'must be in [400, 4000]'),
    ParamSpec('truth_rate_hz', 50.0, 'rate of sim/truth/vehicle and sim/truth/apron',
              lambda v: 0.0 < v <= 400.0, 'must be in (0, 400]'),
    ParamSpec('tick_s', 0.01, 'wall-clock period of the simulation thread (absolute '
              'deadlines); keep it a divisor of the IMU period (10 ms at 100 Hz) so telemetry '
              'leaves at a deadline',
              lambda v: 0.001 <= v <= 0.05, 'must be in [0.001, 0.05]'),
    one_of('offboard_loss_action', 'land', ('land', 'hold', 'return'),
           'emulated PX4 COM_OBL_RC_ACT after offboard setpoints stop for 1 s (COM_OF_LOSS_T; '
           "a scenario command-path fault's loss_timeout_s replaces the 1 s, and its "
           "action: return selects 'return' = AUTO.RTL)"),
    one_of('mavlink_fault_downlink', 'cut', DOWNLINK_MODES,
           "scenario MAVLink faults on the telemetry (autopilot -> bridge): 'none', 'cut' "
           "(only the link-loss window, default), 'all' (also loss and latency); the uplink "
           '(bridge -> autopilot) always gets them all'),
    ParamSpec('signing_key_file', '', 'MAVLink 2 signing key of the emulated autopilot (32 '
              "raw bytes or 64 hex characters, as the bridge's): sign telemetry, drop unsigned "
              'or wrongly signed input; empty = unsigned'),
    ParamSpec('map_frame', 'map', 'world frame id (ENU)', lambda v: v.strip() != '',
              'must not be empty'),
    ParamSpec('base_frame', 'base_link', 'vehicle body frame id (FLU)',
              lambda v: v.strip() != '', 'must not be empty'),
    ParamSpec('apron_frame', 'apron', 'child frame id of sim/truth/apron',
              lambda v: v.strip() != '', 'must not be empty'),
]


class DeckSimulatorNode(Node):
    """The ``deck_simulator`` node; see the package README, section "Node"."""

    def __init__(self, **kwargs) -> None:
        super().__init__('deck_simulator', **kwargs)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pixy_sock: socket.socket | None = None
        self._ship_sock: socket.socket | None = None
        self.emulator: Px4Emulator | None = None
        self.hil: Px4Hil | ArduPilotJson | None = None   # the firmware in lockstep
        self._links: list = []
        self.px4_lost = ''
        self._lockstep_last: tuple[float, float, float] | None = None
        self._at_trigger: tuple[float, float, int, float] | None = None
        self.lockstep_rate = float('nan')
        try:
            self._setup()
        except Exception:
            self._close_io()
            self.destroy_node()
            raise
        self._thread = threading.Thread(target=self._run, name='deck_simulator', daemon=True)
        self._thread.start()

    def _setup(self) -> None:
        try:
            p = declare_and_validate(self, PARAMS)
        except InvalidParameterTypeException as exc:   # e.g. -p seed:=one
            raise ParameterError(str(exc)) from None
        self.cfg = p
        try:
            scenario = load_scenario(p['scenario'])
        except ValueError as exc:
            raise ParameterError(f"parameter 'scenario': {exc}") from None
        sp = scenario.sensors
        for name, tp in (('imu', sp.imu.timing), ('attitude', sp.attitude.timing),
                         ('local_position', sp.local_position.timing),
                         ('lidar', sp.lidar.timing), ('true_camera', sp.true_camera.timing)):
            if tp.rate_hz > p['physics_rate_hz']:   # a sensor clock samples the physics tick
                raise ParameterError(
                    f"parameter 'physics_rate_hz' = {p['physics_rate_hz']:g}: below the "
                    f"scenario's sensors.{name}.timing.rate_hz = {tp.rate_hz:g}")
        if p['autopilot'] == 'px4-sitl':
            self.sim = self._px4_loop(scenario, p)
            local, target = None, f"PX4 SITL on TCP {p['px4_sim_port']}"
        elif p['autopilot'] == 'ardupilot-sitl':
            self.sim = self._ardupilot_loop(scenario, p)
            local, target = None, f"ArduCopter SITL on UDP {p['ardupilot_physics_port']}"
        else:
            link = self._open_link('mavlink_url', p['mavlink_url'], p['mavlink_fd'])
            # the autopilot maps normalised thrust to the *vehicle's* newtons: hover at 1/(T/W)
            self.emulator = Px4Emulator(EmulatorParams(
                thrust=vehicle_thrust_calibration(scenario.vehicle),
                offboard_loss_action=p['offboard_loss_action']), transport=link)
            if p['signing_key_file']:
                # signing timestamps: 10 µs units since 2015-01-01 (wall clock, as PX4 with RTC)
                self.emulator.setup_signing(load_signing_key(p['signing_key_file']),
                                            int(max(time.time() - 1420070400.0, 0.0) * 1e5))
            self.sim = SimulationLoop(scenario, p['seed'], self.emulator, self._pixy_sender(),
                                      p['physics_rate_hz'], p['truth_rate_hz'],
                                      p['mavlink_fault_downlink'],
                                      ship_send=self._ship_sender(scenario))
            local, target = link.local_address, f"MAVLink {p['mavlink_url']}"
        self.schedule: TickSchedule | None = None
        self.thread_errors = 0
        self._warned: dict[str, int] = {}
        self.pub_vehicle = self.create_publisher(Odometry, 'sim/truth/vehicle', RELIABLE_QOS)
        self.pub_apron = self.create_publisher(Odometry, 'sim/truth/apron', RELIABLE_QOS)
        self.pub_outcome = self.create_publisher(String, 'sim/outcome', LATCHED_QOS)
        self.create_subscription(String, 'planner/mode', self._on_mode, LATCHED_QOS)
        self.create_timer(1.0, self._report_rejections)
        where = f' (local {local[0]}:{local[1]})' if local else ''
        pixy_addr = (p['pixy_udp_address'], p['pixy_udp_port'])
        self.get_logger().info(
            f"scenario {scenario.name!r} seed {p['seed']}: {target}{where}, Pixy -> "
            f"{pixy_addr[0]}:{pixy_addr[1]}, x{p['realtime_factor']:g} real time")

    def _open_link(self, name: str, url: str, fd: int = -1):
        try:
            link = make_mavlink_link(url, fd)
        except OSError as exc:
            raise ParameterError(f'parameter {name!r} = {url!r}: cannot open the socket: '
                                 f'{exc}') from None
        self._links.append(link)
        return link

    def _pixy_sender(self):
        self._pixy_sock = sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        addr = (self.cfg['pixy_udp_address'], self.cfg['pixy_udp_port'])

        def pixy_send(data: bytes) -> None:
            sock.sendto(data, addr)

        return pixy_send

    def _ship_sender(self, scenario):
        """The ship's MAVLink datagrams to ``ship_udp_address:ship_udp_port`` (None without
        ship telemetry in the scenario)."""
        if scenario.ship_telemetry is None:
            return None
        self._ship_sock = sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        addr = (self.cfg['ship_udp_address'], self.cfg['ship_udp_port'])

        def ship_send(data: bytes) -> None:
            sock.sendto(data, addr)

        return ship_send

    def _px4_loop(self, scenario, p) -> SimulationLoop:
        """PX4 SITL flies the world (lockstep on TCP ``px4_sim_port``); with
        ``px4_onboard_url`` the simulator relays PX4's onboard link to the bridge through the
        scenario's MAVLink faults."""
        relay = None
        if p['px4_onboard_url']:
            if not p['px4_onboard_url'].startswith('udpin:'):
                raise ParameterError("parameter 'px4_onboard_url' must be 'udpin:HOST:PORT' "
                                     '(where PX4 sends its onboard link)')
            # PX4 sends there unasked; the relay answers whoever sent (PX4's 14580 + i)
            relay = (self._open_link('mavlink_url', p['mavlink_url'], p['mavlink_fd']),
                     self._open_link('px4_onboard_url', p['px4_onboard_url']))

        def firmware(world) -> Px4Hil:
            try:
                self.hil = Px4Hil(world, HilParams(port=p['px4_sim_port'], seed=p['seed']))
            except ValueError as exc:
                raise ParameterError(f"parameter 'physics_rate_hz' = {p['physics_rate_hz']:g} "
                                     f'with autopilot px4-sitl: {exc}') from None
            except OSError as exc:
                raise ParameterError(f"parameter 'px4_sim_port' = {p['px4_sim_port']}: cannot "
                                     f'listen: {exc}') from None
            return self.hil

        return SimulationLoop(scenario, p['seed'], None, self._pixy_sender(),
                              p['physics_rate_hz'], p['truth_rate_hz'],
                              p['mavlink_fault_downlink'], firmware=firmware, relay=relay)

    def _ardupilot_loop(self, scenario, p) -> SimulationLoop:
        """ArduCopter SITL flies the world (its JSON physics, lockstep on UDP
        ``ardupilot_physics_port``); ArduCopter talks MAVLink to the bridge itself."""
        def firmware(world) -> ArduPilotJson:
            try:
                self.hil = ArduPilotJson(world, JsonParams(port=p['ardupilot_physics_port'],
                                                           seed=p['seed']))
            except OSError as exc:
                raise ParameterError(f"parameter 'ardupilot_physics_port' = "
                                     f"{p['ardupilot_physics_port']}: cannot bind: {exc}") \
                    from None
            return self.hil

        return SimulationLoop(scenario, p['seed'], None, self._pixy_sender(),
                              p['physics_rate_hz'], p['truth_rate_hz'],
                              p['mavlink_fault_downlink'], firmware=firmware)

    # --- callbacks -----------------------------------------------------------------------

    def _on_mode(self, msg: String) -> None:
        before = self.sim.trigger_t_s
        self.sim.on_planner_mode(msg.data)
        if before is None and self.sim.trigger_t_s is not None:
            # the world's health over the mission is reported with the outcome (px4-sitl)
            self._at_trigger = (time.monotonic(), self.sim.world.t_s, self.overruns,
                                self.hil.wait_wall_s if self.hil is not None else 0.0)

    def _report_rejections(self) -> None:
        """Log (once per change) what was rejected or dropped, and stalls not caught up."""
        counts = self.sim.rejection_counts()
        counts['schedule.overruns'] = self.overruns     # stalls > MAX_TICK_WALL_S
        grown = {k: v for k, v in counts.items() if v > self._warned.get(k, 0)}
        if grown:
            self._warned.update(grown)
            self.get_logger().warning(f'rejected/dropped so far: {grown}')
        if self.hil is not None:
            self._report_lockstep()

    def lockstep_health(self) -> dict:
        """px4-sitl, from the landing trigger to now: sim seconds per wall second, stalls
        (ticks more than MAX_TICK_WALL_S late, their backlog dropped), lockstep timeouts, and
        the share of wall time spent waiting for PX4."""
        hil = self.hil
        assert hil is not None
        now, t_sim, stalls, wait = (time.monotonic(), self.sim.world.t_s, self.overruns,
                                    hil.wait_wall_s)
        t0, s0, n0, w0 = self._at_trigger or (now, t_sim, stalls, wait)
        wall = now - t0
        return {'realtime_factor': round((t_sim - s0) / wall, 3) if wall > 0 else None,
                'stalls': stalls - n0, 'stalls_total': stalls,
                'timeouts': hil.counters['lockstep_timeouts'],
                'wait_share': round((wait - w0) / wall, 3) if wall > 0 else None}

    def _report_lockstep(self) -> None:
        """px4-sitl, every LOCKSTEP_REPORT_S: sim seconds per wall second, the share of wall
        time spent waiting for PX4, lockstep timeouts (the graph runs on the wall clock: a
        world slower than real time is a slow-motion world for it)."""
        hil, now = self.hil, time.monotonic()
        w = (now, self.sim.world.t_s, hil.wait_wall_s)
        last = self._lockstep_last
        if last is None or now - last[0] < LOCKSTEP_REPORT_S:
            if last is None:
                self._lockstep_last = w
            return
        self._lockstep_last = w
        wall = now - last[0]
        self.lockstep_rate = (w[1] - last[1]) / wall
        self.get_logger().info(
            f'lockstep: x{self.lockstep_rate:.2f} real time, waiting for the firmware '
            f'{100.0 * (w[2] - last[2]) / wall:.0f} % of the wall time, '
            f"{hil.counters['lockstep_timeouts']} timeouts, {self.overruns} stalls")

    # --- the wall-clock thread -----------------------------------------------------------

    @property
    def overruns(self) -> int:
        """Stalls longer than ``MAX_TICK_WALL_S`` (their backlog was not caught up)."""
        return self.schedule.overruns if self.schedule is not None else 0

    def _wait_for_px4(self) -> bool:
        """px4-sitl: hold the world at t = 0 until PX4 connects (False: stopped first)."""
        hil = self.hil
        if hil is None:
            return True
        log = self.get_logger()
        who = 'ArduCopter on UDP' if isinstance(hil, ArduPilotJson) else 'PX4 on TCP'
        log.info(f'waiting for {who} {hil.params.host}:{hil.params.port}')
        while not self._stop.is_set():
            if hil.accept(0.2):
                log.info(f'{who.split()[0]} connected: lockstep on the world clock')
                return True
        return False

    def _run(self) -> None:
        """The world thread: tick k at ``start + k · tick_s`` (absolute, see TickSchedule);
        each tick advances the world by ``tick_s × realtime_factor``. With PX4 the world
        waits for its connection first and stops when PX4 goes away."""
        if not self._wait_for_px4():
            return
        rtf, period = self.cfg['realtime_factor'], self.cfg['tick_s']
        sched = TickSchedule(period, MAX_TICK_WALL_S, time.monotonic())
        self.schedule = sched
        sim_dt = period * rtf
        stop = self._stop
        while True:
            delay = sched.wait_s(time.monotonic())
            if delay > 0.0:
                if stop.wait(delay):
                    break
            elif stop.is_set():
                break
            deadline = sched.tick(time.monotonic())
            try:
                t0_sim = self.sim.world.t_s
                samples, outcome = self.sim.advance(sim_dt)
                self._publish(samples, outcome, rtf, deadline, t0_sim)
            except ConnectionError as exc:   # PX4 closed the simulator link: nothing flies
                self.px4_lost = str(exc)
                self.get_logger().error(f'{exc}: the world stops at t = '
                                        f'{self.sim.world.t_s:.2f} s')
                break
            except Exception as exc:  # never let one bad tick kill the world thread
                if stop.is_set() or not self.context.ok():
                    break
                self.thread_errors += 1
                self.get_logger().error(f'simulation tick failed: {exc!r}',
                                        throttle_duration_sec=2.0)

    def _publish(self, samples: list[Truth], outcome: dict | None, rtf: float,
                 deadline_s: float, t0_sim_s: float) -> None:
        if samples:
            # a sample at sim time t stands for the wall time deadline + (t − t0) / rtf
            # (monotonic), expressed on the node clock
            offset = self.get_clock().now().nanoseconds * 1e-9 - time.monotonic()
            for tr in samples:
                stamp_s = offset + deadline_s + (tr.t_s - t0_sim_s) / rtf
                self.pub_vehicle.publish(self._vehicle_msg(tr, stamp_s))
                self.pub_apron.publish(self._apron_msg(tr, stamp_s))
        if outcome is not None:
            if self.hil is not None:
                outcome = {**outcome, 'lockstep': self.lockstep_health()}
            text = outcome_json(outcome)
            self.pub_outcome.publish(String(data=text))
            self.get_logger().info(f'outcome: {text}')

    def _vehicle_msg(self, tr: Truth, stamp_s: float) -> Odometry:
        od = Odometry()
        s_to_stamp(max(stamp_s, 0.0), od.header.stamp)
        od.header.frame_id = self.cfg['map_frame']
        od.child_frame_id = self.cfg['base_frame']
        pos = od.pose.pose.position
        pos.x, pos.y, pos.z = tr.position_m
        q = od.pose.pose.orientation
        q.w, q.x, q.y, q.z = euler_to_quaternion(tr.roll_rad, tr.pitch_rad, tr.yaw_rad)
        tw = od.twist.twist     # in base_link (REP-105), like vehicle/odom
        (tw.linear.x, tw.linear.y, tw.linear.z), (tw.angular.x, tw.angular.y, tw.angular.z) = \
            body_twist(tr)
        return od

    def _apron_msg(self, tr: Truth, stamp_s: float) -> Odometry:
        od = Odometry()
        s_to_stamp(max(stamp_s, 0.0), od.header.stamp)
        od.header.frame_id = self.cfg['map_frame']
        od.child_frame_id = self.cfg['apron_frame']
        pos = od.pose.pose.position
        pos.x, pos.y, pos.z = tr.beacon_position_m
        od.pose.pose.orientation.w = 1.0
        # the apron frame is axis-aligned with map, so its twist is the map-frame velocity
        tw = od.twist.twist.linear
        tw.x, tw.y = tr.deck_velocity_mps
        tw.z = tr.deck_vz_mps
        return od

    # --- shutdown ------------------------------------------------------------------------

    def _close_io(self) -> None:
        for closable in (self.emulator, self.hil, *self._links):
            if closable is not None:
                with contextlib.suppress(Exception):
                    closable.close()
        if self._ship_sock is not None:
            with contextlib.suppress(Exception):
                self._ship_sock.close()
        if self._pixy_sock is not None:
            with contextlib.suppress(Exception):
                self._pixy_sock.close()

    def destroy_node(self) -> None:
        """Stop and join the simulation thread, close both sockets, destroy the node."""
        stop = getattr(self, '_stop', None)
        if stop is not None:
            stop.set()
        thread = getattr(self, '_thread', None)
        if thread is not None and thread.is_alive() and thread is not threading.current_thread():
            thread.join(timeout=1.0)
        self._close_io()
        if not getattr(self, '_destroyed', False):
            self._destroyed = True
            super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``deck_simulator_node``."""
    # process-wide, so only here: the world thread must get the GIL back within ~1 ms of its
    # deadline while the executor thread runs Python code
    sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
    return run_node(DeckSimulatorNode, args)


if __name__ == '__main__':  # pragma: no cover
    raise SystemExit(main())


__all__ = ['MAX_TICK_WALL_S', 'PARAMS', 'DeckSimulatorNode', 'main']
