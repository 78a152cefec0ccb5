"""ROS 2 node ``deck_simulator``: the simulated world on the wall clock, emulating the hardware.

The world (:class:`deck_simulator.world.World`, paper (1)-(4) and Tables 2-3) runs in its own
thread on an absolute wall-clock schedule (:class:`TickSchedule`): tick k is due at
``start + k · tick_s``; the thread sleeps until that deadline, then advances the world by
exactly ``tick_s × realtime_factor`` in sub-steps of ``1 / physics_rate_hz``. The schedule
never drifts (``next += tick_s``, not ``now + tick_s``); a late tick is caught up by stepping
the next ticks at once; only a stall longer than ``MAX_TICK_WALL_S`` is given up (the sim then
slows down instead). Telemetry due at a tick's start goes out right at its deadline, so the
emulated autopilot streams ATTITUDE/HIGHRES_IMU at a steady 100 Hz like a real Pixhawk.
Towards the rest of the graph it looks like the real hardware over the same wires:

* the Pixhawk: a PX4-like MAVLink endpoint (:class:`deck_simulator.px4_emulator.Px4Emulator`)
  on UDP, streaming HEARTBEAT, ATTITUDE, LOCAL_POSITION_NED, DISTANCE_SENSOR, HIGHRES_IMU and
  EXTENDED_SYS_STATE and taking SET_ATTITUDE_TARGET / COMMAND_LONG from ``mavlink_bridge``;
* the Pixy: every 50 Hz camera frame is one UDP datagram of Pixy v1 bytes
  (:func:`pixy_driver.protocol.encode_frame`) sent to ``pixy_driver``'s UDP port.

Outside OFFBOARD (before it is engaged, and on the emulator's offboard-loss failsafe) the
vehicle is flown by :class:`AutopilotEmulation`, a stand-in for PX4's position controller built
from the project's own cores. Ground truth goes to ``sim/truth/*`` and the landing's outcome
(campaign fields, JSON) to the latched ``sim/outcome``.

Layering: :class:`AutopilotEmulation` and :class:`SimulationLoop` do not touch rclpy (they are
stepped with sim time and testable without ROS); :class:`DeckSimulatorNode` only adds the
wall-clock thread, the sockets' lifetime, parameters and topics.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, replace
import ipaddress
import json
import math
import random
import re
import socket
import sys
import threading
import time

from deckland_common.frames import euler_to_quaternion, mat_t_vec, rot_body_to_world
from deckland_common.params import ParameterError, ParamSpec, in_range, one_of
from deckland_common.ros_node import (
    LATCHED_QOS,
    RELIABLE_QOS,
    declare_and_validate,
    run_node,
    s_to_stamp,
)
from dob_altitude.pid import PidAltitudeController, PidParams
from dob_altitude.types import AltitudeInput
from landing_planner.horizontal import HorizontalController, HorizontalParams
from mavlink_bridge.conversions import ThrustCalibration
from mavlink_bridge.signing import load_signing_key
from nav_msgs.msg import Odometry
from pixy_driver.protocol import block_in_range, encode_frame
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.node import Node
from std_msgs.msg import String

from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
from deck_simulator.scenario import Scenario, load_scenario
from deck_simulator.world import Truth, World

#: planner modes that do not count as "landing triggered" (time_to_land_s starts at the first
#: mode outside this set; TAKEOFF is a take-off, not a landing trigger)
NOT_LANDING_MODES = frozenset({'IDLE', 'HOLD', 'TAKEOFF'})
AUTOPILOT_CONTROL_HZ = 100.0     # PX4's position/velocity loop rate stand-in
MAX_TICK_WALL_S = 0.1            # a longer stall is not caught up (the sim slows down instead)
#: a GIL switch interval of 1 ms (CPython's default is 5 ms) so the world thread wakes on time
#: even while an executor thread of this process runs Python code
SWITCH_INTERVAL_S = 0.001

_URL_RE = re.compile(r'^(udpin|udpout|udp):([^:]+):(\d{1,5})$')


def parse_mavlink_url(url: str) -> tuple[str, str, int]:
    """``'udpin:HOST:PORT'`` / ``'udp:HOST:PORT'`` (listen there) or ``'udpout:HOST:PORT'``
    (send there) → ``(mode, host, port)`` with mode ``'in'`` or ``'out'``; ValueError if bad.

    The same syntax as pymavlink's, seen from the autopilot: the bridge's default
    ``udpin:127.0.0.1:14540`` pairs with our default ``udpout:127.0.0.1:14540`` (PX4 SITL
    sends to 14540), and the bridge's ``udpout:H:P`` (``deckland up``) pairs with our
    ``udpin:H:P``.
    """
    m = _URL_RE.match(url.strip())
    if m is None:
        raise ValueError(f"expected 'udpin:HOST:PORT' or 'udpout:HOST:PORT', got {url!r}")
    kind, host, port_s = m.groups()
    port = int(port_s)
    if host != 'localhost':
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise ValueError(f'host must be an IPv4 literal or localhost, got {host!r}') \
                from None
    mode = 'out' if kind == 'udpout' else 'in'
    if not (0 <= port <= 65535) or (mode == 'out' and port == 0):
        raise ValueError(f'bad UDP port {port} in {url!r}')
    return mode, ('127.0.0.1' if host == 'localhost' else host), port


class UdpLink:
    """Non-blocking UDP transport for :class:`Px4Emulator` (send/receive/set_peer/close).

    ``remote`` is None until a peer is known (udpin before the companion's first packet):
    sends are then dropped and counted in ``dropped_no_peer`` instead of spraying a guessed
    port. The emulator calls :meth:`set_peer` with the source of every valid packet.
    """

    def __init__(self, bind: tuple[str, int], remote: tuple[str, int] | None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind(bind)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.remote = remote
        self.send_errors = 0
        self.dropped_no_peer = 0

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def send(self, data: bytes) -> None:
        if self.remote is None:
            self.dropped_no_peer += 1
            return
        try:
            self.sock.sendto(data, self.remote)
        except OSError:
            self.send_errors += 1   # nobody listening (ECONNREFUSED), socket closed, ...

    def receive(self) -> list[tuple[bytes, object]]:
        out = []
        for _ in range(1000):
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                if self.sock.fileno() < 0:
                    break
                continue   # a late ICMP error surfaces on recv: skip it
            out.append((data, addr))
        return out

    def set_peer(self, addr: object) -> None:
        self.remote = addr

    def close(self) -> None:
        self.sock.close()


def make_mavlink_link(url: str) -> UdpLink:
    """The emulator's socket for ``mavlink_url`` (see :func:`parse_mavlink_url`)."""
    mode, host, port = parse_mavlink_url(url)
    if mode == 'in':
        return UdpLink((host, port), None)
    bind_host = '127.0.0.1' if ipaddress.IPv4Address(host).is_loopback else '0.0.0.0'
    return UdpLink((bind_host, 0), (host, port))


# --- MAVLink link faults on the wire ------------------------------------------------------

#: scenario fault types the graph applies on the MAVLink wire (``node_kill`` is a real SIGKILL
#: of a node process by ``deckland up``, so it is not applied here a second time)
WIRE_FAULT_TYPES = ('mavlink_link_loss', 'mavlink_loss', 'mavlink_latency')
DOWNLINK_MODES = ('none', 'cut', 'all')


class ImpairedLink:
    """A lossy radio/serial link between the bridge and the emulated autopilot (no rclpy).

    Wraps the emulator's byte transport (same ``send``/``receive``/``set_peer``/``close``
    interface) and applies the scenario's MAVLink faults datagram by datagram at the
    simulator's time ``world.t_s`` (the fault windows of :class:`deck_simulator.faults.FaultSet`,
    world time; a ``trigger_height_m`` window is opened by the world itself):

    * ``mavlink_link_loss``: every datagram in the window is dropped (``*_cut``); the
      emulator's own COM_OF_LOSS_T timeout then triggers its offboard-loss failsafe;
    * ``mavlink_loss``: each datagram is dropped with ``probability`` (``*_lost``);
    * ``mavlink_latency``: each datagram is held back ``latency_s`` (``*_delayed``), FIFO and
      never reordered (a datagram behind a delayed one waits for it, as in
      :meth:`World.command_link`).

    Uplink (bridge → autopilot: setpoints, commands, heartbeats) is always impaired.
    ``downlink`` says what happens to telemetry (autopilot → bridge): ``'none'`` untouched,
    ``'cut'`` (default) only the link-loss cut (a dead radio is dead both ways), ``'all'`` loss
    and latency as well. Random draws come from ``random.Random(f'{seed}:mavlink_wire:up')``
    and ``...:down`` (one draw per datagram and active loss fault), so they never shift the
    world's streams. Held datagrams are released on the next ``send``/``receive`` call at or
    after their due time (the emulator polls at 100 Hz: ≤ 10 ms quantisation).
    """

    def __init__(self, inner, world: World, seed: int, downlink: str = 'cut') -> None:
        if downlink not in DOWNLINK_MODES:
            raise ValueError(f'ImpairedLink.downlink must be one of {DOWNLINK_MODES}, '
                             f'got {downlink!r}')
        fs = world.faults
        if fs is None:
            raise ValueError('ImpairedLink needs a world with faults')
        self.inner = inner
        self.world = world
        self.downlink = downlink
        self._cut = [a for a in fs.link_cut if a.name == 'mavlink_link_loss']
        self._loss = [a for a in fs.link_loss if a.name == 'mavlink_loss']
        self._lat = [a for a in fs.link_latency if a.name == 'mavlink_latency']
        self._rng_up = random.Random(f'{seed}:mavlink_wire:up')
        self._rng_down = random.Random(f'{seed}:mavlink_wire:down')
        self._rx_queue: list[tuple[float, bytes, object]] = []
        self._tx_queue: list[tuple[float, bytes]] = []
        self.counters: dict[str, int] = {
            'rx': 0, 'rx_cut': 0, 'rx_lost': 0, 'rx_delayed': 0,
            'tx': 0, 'tx_cut': 0, 'tx_lost': 0, 'tx_delayed': 0}

    @staticmethod
    def wire_faults(world: World) -> list:
        """The world's run-time faults this link applies (empty: nothing to wrap)."""
        fs = world.faults
        if fs is None:
            return []
        return [a for a in fs.all if a.name in WIRE_FAULT_TYPES]

    def _fate(self, t: float, rng: random.Random, cut_only: bool) -> float | str:
        """'cut' / 'lost' or the delay in seconds (0 = now) of a datagram sent at t."""
        for a in self._cut:
            if a.on <= t < a.off:
                return 'cut'
        if cut_only:
            return 0.0
        for a in self._loss:
            if a.on <= t < a.off and rng.random() < a.spec.probability:
                return 'lost'
        delay = 0.0
        for a in self._lat:
            if a.on <= t < a.off and a.spec.latency_s > delay:
                delay = a.spec.latency_s
        return delay

    # --- transport interface (as UdpLink / MemoryLink.End) --------------------------------

    @property
    def local_address(self):
        return getattr(self.inner, 'local_address', None)

    def _flush_tx(self, t: float) -> None:
        q = self._tx_queue
        n = 0
        while n < len(q) and q[n][0] <= t + 1e-9:
            self.inner.send(q[n][1])
            n += 1
        if n:
            del q[:n]

    def send(self, data: bytes) -> None:
        t = self.world.t_s
        self._flush_tx(t)
        self.counters['tx'] += 1
        if self.downlink == 'none':
            self.inner.send(data)
            return
        fate = self._fate(t, self._rng_down, self.downlink == 'cut')
        if fate == 'cut' or fate == 'lost':
            self.counters['tx_' + fate] += 1
            return
        if fate > 0.0 or self._tx_queue:
            self.counters['tx_delayed'] += fate > 0.0
            self._tx_queue.append((t + fate, bytes(data)))
            return
        self.inner.send(data)

    def receive(self) -> list[tuple[bytes, object]]:
        t = self.world.t_s
        self._flush_tx(t)
        q = self._rx_queue
        n = 0
        while n < len(q) and q[n][0] <= t + 1e-9:
            n += 1
        out = [(d, a) for _, d, a in q[:n]]
        del q[:n]
        for data, addr in self.inner.receive():
            self.counters['rx'] += 1
            fate = self._fate(t, self._rng_up, False)
            if fate == 'cut' or fate == 'lost':
                self.counters['rx_' + fate] += 1
                continue
            if fate > 0.0 or q:
                self.counters['rx_delayed'] += fate > 0.0
                q.append((t + fate, data, addr))
                continue
            out.append((data, addr))
        return out

    def set_peer(self, addr: object) -> None:
        self.inner.set_peer(addr)

    def close(self) -> None:
        self.inner.close()


# --- autopilot emulation -------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class AutopilotParams:
    """The PX4-position-controller stand-in flown outside OFFBOARD (on the truth)."""

    altitude: PidParams = field(default_factory=PidParams)
    horizontal: HorizontalParams = field(default_factory=HorizontalParams)
    land_speed_mps: float = 0.7       # MPC_LAND_SPEED
    rotor_height_m: float = 0.05      # rotor plane above the body origin, for γ̄ of (4)
    return_speed_mps: float = 1.0     # RTL: horizontal speed toward home
    return_alt_m: float = 0.0         # RTL: climb to at least this world altitude first
    home_radius_m: float = 0.3        # RTL: within this of home and braked → land there
    braked_mps: float = 0.15          # ... "braked" = horizontal speed below this

    def __post_init__(self) -> None:
        if not (isinstance(self.return_alt_m, int | float) and math.isfinite(self.return_alt_m)
                and self.return_alt_m >= 0.0):
            raise ValueError(f'AutopilotParams.return_alt_m must be a finite number >= 0, '
                             f'got {self.return_alt_m!r}')
        for name in ('land_speed_mps', 'rotor_height_m', 'return_speed_mps', 'home_radius_m',
                     'braked_mps'):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f'AutopilotParams.{name} must be a finite number > 0, '
                                 f'got {v!r}')

    @classmethod
    def for_scenario(cls, scenario: Scenario, land_speed_mps: float = 0.7,
                     return_speed_mps: float = 1.0,
                     return_alt_m: float = 0.0) -> AutopilotParams:
        """Gains of the shipped PID matched to the scenario's vehicle (mass, g, thrust range)."""
        vp = scenario.vehicle
        weight = vp.mass_kg * vp.gravity_mps2
        alt = replace(PidParams.profile('default'), mass_kg=vp.mass_kg,
                      gravity_mps2=vp.gravity_mps2, prop_radius_m=vp.prop_radius_m,
                      thrust_min_n=0.1 * weight, thrust_max_n=vp.thrust_to_weight * weight)
        hor = replace(HorizontalParams(), gravity_mps2=vp.gravity_mps2)
        return cls(altitude=alt, horizontal=hor, land_speed_mps=land_speed_mps,
                   rotor_height_m=vp.rotor_height_m, return_speed_mps=return_speed_mps,
                   return_alt_m=return_alt_m)


class AutopilotEmulation:
    """What PX4 flies when the companion is not in control (pure, stepped with ``dt_s``).

    ``kind`` is :attr:`Px4Emulator.command().kind`:

    * ``'hold'`` (POSCTL/LOITER, the start state, the 'hold' failsafe): hold the position and
      heading captured when hold was entered (at t = 0 the scenario's start hover);
    * ``'land'`` / ``'failsafe_land'``: hold x, y and heading of the switch, descend at
      ``land_speed_mps`` (the height reference ramps down; it keeps ramping after contact, so
      the thrust falls to its minimum until the emulator's land detector disarms);
    * ``'failsafe_return'`` (AUTO.RTL, PX4's offboard-loss "Return"): climb to
      ``return_alt_m`` if lower, brake to rest, then the held point slews to ``home``
      (where OFFBOARD was engaged) at ``return_speed_mps``; within ``home_radius_m`` of it
      and braked, descend
      there as ``'land'`` does. The same behaviour as the in-process World's ``'return'``
      failsafe (``World._failsafe_command``), flown here by the PX4 stand-in's controllers;
    * ``'idle'``: disarmed, zero thrust.

    Vertical: :class:`dob_altitude.pid.PidAltitudeController` on the *true* world altitude
    (e_z of (7), ė_z of (8); γ̄ of (4) from the true rotor-plane height above the surface
    below). Horizontal: :class:`landing_planner.horizontal.HorizontalController` on the true
    position. The real PX4 flies on its EKF estimate; truth is good enough for a stand-in whose
    only job is to keep the vehicle where the mission starts.
    """

    def __init__(self, params: AutopilotParams) -> None:
        self.params = params
        self.altitude = PidAltitudeController(params.altitude)
        self.horizontal = HorizontalController(params.horizontal)
        self.kind: str | None = None
        self.braked = False       # RTL: braked to rest, flying home
        self.returned = False     # RTL: home reached, descending there
        self.target_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.target_yaw_rad = 0.0
        self.rejected: dict[str, int] = {'nan': 0}

    def _enter(self, kind: str, truth: Truth) -> None:
        self.kind = kind
        self.braked = self.returned = False
        self.target_m = truth.position_m
        if kind == 'failsafe_return':
            x, y, z = truth.position_m
            self.target_m = (x, y, max(z, self.params.return_alt_m))
        self.target_yaw_rad = truth.yaw_rad
        self.altitude.reset()
        self.horizontal.reset()

    def release(self) -> None:
        """The companion flies (OFFBOARD): the next hold/land re-captures its target."""
        self.kind = 'offboard'

    def command(self, kind: str, truth: Truth, dt_s: float,
                home: tuple[float, float] | None = None) -> tuple[float, float, float, float]:
        """(roll, pitch, yaw, thrust_n) for the emulator's ``kind`` at ``truth``; ``home`` is
        the RTL target (the emulator's ``home_m``; None → return where the failsafe began)."""
        if kind not in ('hold', 'land', 'failsafe_land', 'failsafe_return'):
            self.kind = kind
            return 0.0, 0.0, truth.yaw_rad, 0.0
        landing = kind in ('land', 'failsafe_land')
        if kind != self.kind and not (landing and self.kind in ('land', 'failsafe_land')):
            self._enter(kind, truth)
        self.kind = kind
        p = self.params
        x, y, z = truth.position_m
        vx, vy, vz = truth.velocity_mps
        tx, ty, tz = self.target_m
        z_d_dot = 0.0
        if kind == 'failsafe_return' and not self.braked:
            # PX4: brake first, then start back from where the vehicle came to rest
            tx, ty = x, y
            self.target_m = (tx, ty, tz)
            self.braked = math.hypot(vx, vy) <= p.braked_mps
        elif kind == 'failsafe_return' and not self.returned:
            hx, hy = home if home is not None else (tx, ty)
            ex, ey = hx - tx, hy - ty
            n = math.hypot(ex, ey)
            step = p.return_speed_mps * dt_s
            if n > step:
                ex, ey = ex * step / n, ey * step / n
            tx, ty = tx + ex, ty + ey
            self.target_m = (tx, ty, tz)
            if (math.hypot(x - hx, y - hy) <= p.home_radius_m
                    and math.hypot(vx, vy) <= p.braked_mps):
                self.returned = True
        landing = landing or self.returned
        if landing:
            # straight down at the land speed; the reference stops 1 m below the surface so the
            # integral stays bounded while resting
            tz = max(tz - p.land_speed_mps * dt_s, truth.surface_height_m - 1.0)
            self.target_m = (tx, ty, tz)
            z_d_dot = -p.land_speed_mps
        roll, pitch = self.horizontal.step((tx, ty), (0.0, 0.0), (x, y), (vx, vy), truth.yaw_rad,
                                           dt_s)
        inp = AltitudeInput(z_m=z, z_dot_mps=vz, z_d_m=tz, z_d_dot_mps=z_d_dot,
                            z_d_ddot_mps2=0.0, roll_rad=truth.roll_rad, pitch_rad=truth.pitch_rad,
                            rotor_height_m=truth.height_above_surface_m + p.rotor_height_m)
        thrust = self.altitude.step(inp, dt_s).thrust_n
        out = (roll, pitch, self.target_yaw_rad, thrust)
        if not all(map(math.isfinite, out)):
            self.rejected['nan'] += 1
            return 0.0, 0.0, self.target_yaw_rad, self.params.altitude.mass_kg * \
                self.params.altitude.gravity_mps2
        return out


# --- the simulation loop (sim time, no rclpy) ---------------------------------------------

def body_rates(roll: float, pitch: float, droll: float, dpitch: float,
               dyaw: float) -> tuple[float, float, float]:
    """Z-Y-X Euler rates → body rates (p, q, r) FLU: ω = W(φ, θ) (φ̇, θ̇, ψ̇)."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    return (droll - sp * dyaw, cr * dpitch + sr * cp * dyaw, -sr * dpitch + cr * cp * dyaw)


def _json_number(v: float) -> float | None:
    return v if math.isfinite(v) else None


class SimulationLoop:
    """World + emulator + Pixy wire + autopilot emulation + outcome, stepped in sim time.

    ``advance(dt_s)`` runs as many ``1 / physics_rate_hz`` sub-steps as fit (the remainder is
    carried over) and returns ``(truth_samples, outcome_or_None)``. Per sub-step, at the rates
    of the scenario's sensors: telemetry into the emulator (``imu.rate_hz``; lidar at
    ``lidar.rate_hz``), a Pixy datagram (``camera.rate_hz``), the emulator's input and the
    vehicle command (``AUTOPILOT_CONTROL_HZ``), truth samples (``truth_rate_hz``).
    ``on_planner_mode`` may be called from another thread.
    """

    def __init__(self, scenario: Scenario, seed: int, emulator: Px4Emulator, pixy_send,
                 physics_rate_hz: float = 400.0, truth_rate_hz: float = 50.0,
                 link_downlink: str = 'cut') -> None:
        self.scenario = scenario
        self.seed = seed
        self.world = World(scenario, seed, physics_dt_s=1.0 / physics_rate_hz)
        self.emulator = emulator
        # the scenario's MAVLink faults act on the wire (ImpairedLink); the autopilot's
        # failsafe settings (COM_OF_LOSS_T, MPC_LAND_SPEED) are the first such fault's keys
        self.link: ImpairedLink | None = None
        wire = ImpairedLink.wire_faults(self.world)
        fs = self.world.faults
        if fs is not None and fs.has_link:     # the wire faults are link faults too
            # a scenario fault that cuts the command path (on the wire, or a node_kill of a
            # command-path node: the orchestrator kills the process) carries the autopilot's
            # failsafe settings: COM_OF_LOSS_T, MPC_LAND_SPEED, and 'return' → AUTO.RTL
            spec = fs.link_spec
            action = 'return' if spec.action == 'return' else emulator.params.offboard_loss_action
            emulator.params = replace(emulator.params,
                                      offboard_loss_timeout_s=spec.loss_timeout_s,
                                      land_speed_mps=spec.land_speed_mps,
                                      offboard_loss_action=action)
        if wire:
            self.link = ImpairedLink(emulator.transport, self.world, seed, link_downlink)
            emulator.set_transport(self.link)
        self.pixy_send = pixy_send
        spec = fs.link_spec if fs is not None else None
        self.autopilot = AutopilotEmulation(AutopilotParams.for_scenario(
            scenario, emulator.params.land_speed_mps,
            return_speed_mps=spec.return_speed_mps if spec is not None else 1.0,
            return_alt_m=spec.min_alt_m if spec is not None else 0.0))
        self.h_s = 1.0 / physics_rate_hz
        sp = scenario.sensors
        self._periods = {'telemetry': 1.0 / sp.imu.rate_hz, 'lidar': 1.0 / sp.lidar.rate_hz,
                         'camera': 1.0 / sp.camera.rate_hz, 'control': 1.0 / AUTOPILOT_CONTROL_HZ,
                         'truth': 1.0 / truth_rate_hz}
        self._due = dict.fromkeys(self._periods, 0.0)
        self._pending_s = 0.0
        self._range_m: float | None = None
        self._g = scenario.vehicle.gravity_mps2
        self._lock = threading.Lock()
        self.mode = ''
        self.trigger_t_s: float | None = None
        self.searches = 0
        self.outcome: dict | None = None
        self.counters = {'substeps': 0, 'pixy_frames': 0, 'pixy_blocks_dropped': 0,
                         'pixy_send_errors': 0, 'offboard_steps': 0, 'autopilot_steps': 0}
        self.rejected: dict[str, int] = {'bad_dt': 0, 'bad_mode': 0}
        # the vehicle hovers armed in POSCTL at the start (PX4 after a manual take-off)
        self._take('lidar', 0.0)
        self._range_m = self.world.read_lidar()
        self._take('telemetry', 0.0)
        self._telemetry(0.0)
        emulator.armed = True
        self.last_kind = emulator.command().kind

    # --- inputs from other threads -------------------------------------------------------

    def on_planner_mode(self, name: str) -> None:
        """``planner/mode``: the landing trigger (first mode outside IDLE/HOLD/TAKEOFF) and
        the number of entries into SEARCH, both at the current sim time."""
        if not isinstance(name, str) or not name.strip():
            self.rejected['bad_mode'] += 1
            return
        name = name.strip().upper()
        with self._lock:
            if name == 'SEARCH' and self.mode != 'SEARCH':
                self.searches += 1
            if self.trigger_t_s is None and name not in NOT_LANDING_MODES:
                self.trigger_t_s = self.world.t_s
            self.mode = name

    # --- stepping ------------------------------------------------------------------------

    def advance(self, dt_s: float) -> tuple[list[Truth], dict | None]:
        if not (isinstance(dt_s, int | float) and math.isfinite(dt_s) and dt_s >= 0.0):
            self.rejected['bad_dt'] += 1
            return [], None
        self._pending_s += dt_s
        n = int(self._pending_s / self.h_s + 1e-9)
        self._pending_s = max(0.0, self._pending_s - n * self.h_s)
        samples: list[Truth] = []
        new_outcome = None
        for _ in range(n):
            out = self._substep(samples)
            if out is not None:
                new_outcome = out
        return samples, new_outcome

    def _take(self, name: str, t: float) -> bool:
        if t + 1e-9 < self._due[name]:
            return False
        nxt = self._due[name] + self._periods[name]
        self._due[name] = nxt if nxt > t + 1e-9 else t + self._periods[name]
        return True

    def _substep(self, samples: list[Truth]) -> dict | None:
        world = self.world
        t = world.t_s
        if self._take('lidar', t):
            self._range_m = world.read_lidar()
        if self._take('telemetry', t):
            self._telemetry(t)
        if self._take('camera', t):
            self._camera()
        if self._take('control', t):
            self._control(t)
        world.step(self.h_s)
        self.counters['substeps'] += 1
        t = world.t_s
        if self._take('truth', t):
            samples.append(world.truth())
        if self.outcome is None:
            return self._check_outcome(t)
        return None

    def _telemetry(self, t: float) -> None:
        world = self.world
        pos, vel = world.read_local_position()
        roll, pitch, yaw = world.read_attitude()
        ax, ay, az = world.read_accel_world()
        tr = world.truth()
        rates = body_rates(tr.roll_rad, tr.pitch_rad, *tr.euler_rates_radps)
        # specific force in body FLU (REP-145): Rᵀ (a + g e3)
        accel_body = mat_t_vec(rot_body_to_world(tr.roll_rad, tr.pitch_rad, tr.yaw_rad),
                               (ax, ay, az + self._g))
        self.emulator.publish_state(t, pos, vel, roll, pitch, yaw, rates, accel_body,
                                    self._range_m, world.resting_on is not None)

    def _camera(self) -> None:
        _stamp, blocks = self.world.read_camera()
        keep = [b for b in blocks if block_in_range(*b)]
        self.counters['pixy_blocks_dropped'] += len(blocks) - len(keep)
        try:
            self.pixy_send(encode_frame(keep))
            self.counters['pixy_frames'] += 1
        except (OSError, ValueError):
            self.counters['pixy_send_errors'] += 1

    def _control(self, t: float) -> None:
        emu = self.emulator
        emu.update(t)       # bytes from the wire: setpoints, commands (bad ones are counted)
        cmd = emu.command()
        self.last_kind = cmd.kind
        if cmd.kind == 'offboard':
            self.autopilot.release()
            self.world.set_command(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad, cmd.thrust_n)
            self.counters['offboard_steps'] += 1
            return
        roll, pitch, yaw, thrust = self.autopilot.command(cmd.kind, self.world.truth(),
                                                          self._periods['control'], emu.home_m)
        self.world.set_command(roll, pitch, yaw, thrust)
        self.counters['autopilot_steps'] += 1

    def _check_outcome(self, t: float) -> dict | None:
        world = self.world
        with self._lock:
            trigger, searches, mode = self.trigger_t_s, self.searches, self.mode
        if world.contact is not None:
            o = world.outcome()
            out = {
                'seed': self.seed, 'scenario': self.scenario.name,
                'landed_on_deck': o.landed_on_deck,
                'success': o.landed_on_deck and not o.crash,
                'crash': o.crash, 'fallback': o.fallback, 'contact_kind': o.contact_kind,
                'horizontal_error_m': _json_number(o.horizontal_error_m),
                'touchdown_speed_mps': _json_number(o.touchdown_speed_mps),
                'time_to_land_s': None if trigger is None else _json_number(o.t_s - trigger),
                'searches': searches, 'max_thrust_n': _json_number(o.max_thrust_n),
                'final_mode': mode, 'reason': o.reason, 'sim_time_s': o.t_s,
            }
        else:
            deadline = (trigger if trigger is not None else 0.0) + self.scenario.timeout_s
            if t < deadline:
                return None
            since = 'the landing trigger' if trigger is not None else 'the start (no trigger)'
            out = {
                'seed': self.seed, 'scenario': self.scenario.name, 'landed_on_deck': False,
                'success': False, 'crash': False, 'fallback': False, 'contact_kind': 'none',
                'horizontal_error_m': None, 'touchdown_speed_mps': None,
                'time_to_land_s': None, 'searches': searches,
                'max_thrust_n': _json_number(world.max_thrust_n), 'final_mode': mode,
                'reason': 'timeout', 'sim_time_s': t,
                'detail': f'no touchdown within {self.scenario.timeout_s:g} s of {since}',
            }
        self.outcome = out
        return out


def outcome_json(outcome: dict) -> str:
    """The ``sim/outcome`` payload (strict JSON: non-finite numbers are null)."""
    return json.dumps(outcome, allow_nan=False, sort_keys=True)


# --- the wall-clock schedule (pure) ---------------------------------------------------------

class TickSchedule:
    """Absolute fixed-rate deadlines on a monotonic clock (pure: the caller passes ``now_s``).

    Tick k is due at ``anchor + k · period_s``. :meth:`wait_s` says how long to sleep until the
    next deadline (≤ 0: due now); :meth:`tick` accounts one tick run at ``now_s`` and returns
    its deadline. Deadlines advance by ``period_s`` whatever the work took, so there is no
    drift and a late tick is followed by catch-up ticks with no sleep in between. If a tick is
    run more than ``max_lag_s`` after its deadline (a stall), the backlog is dropped, the
    schedule is re-anchored at ``now_s`` and the stall is counted in ``overruns`` with the
    dropped ticks in ``ticks_dropped``; ``late`` counts ticks run more than ``late_s`` after
    their deadline (jitter diagnostics).
    """

    __slots__ = ('_next_s', 'late', 'late_s', 'max_lag_s', 'overruns', 'period_s', 'ticks',
                 'ticks_dropped')

    def __init__(self, period_s: float, max_lag_s: float, now_s: float,
                 late_s: float = 0.002) -> None:
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ValueError(f'TickSchedule.period_s must be finite and > 0, got {period_s!r}')
        if not (math.isfinite(max_lag_s) and max_lag_s >= period_s):
            raise ValueError(f'TickSchedule.max_lag_s must be finite and >= period_s, '
                             f'got {max_lag_s!r}')
        self.period_s = period_s
        self.max_lag_s = max_lag_s
        self.late_s = late_s
        self._next_s = now_s
        self.ticks = 0
        self.late = 0
        self.overruns = 0
        self.ticks_dropped = 0

    @property
    def next_s(self) -> float:
        """Deadline of the next tick."""
        return self._next_s

    def wait_s(self, now_s: float) -> float:
        """Seconds until the next deadline (≤ 0 when it is due)."""
        return self._next_s - now_s

    def tick(self, now_s: float) -> float:
        """Account the tick run at ``now_s`` (call it when :meth:`wait_s` ≤ 0); returns the
        deadline the tick stands for (``now_s`` itself after a stall)."""
        lag = now_s - self._next_s
        if lag > self.max_lag_s:
            self.overruns += 1
            self.ticks_dropped += int(lag / self.period_s + 1e-9)  # due, not run
            self._next_s = now_s
        elif lag > self.late_s:
            self.late += 1
        deadline = self._next_s
        self._next_s = deadline + self.period_s
        self.ticks += 1
        return deadline


# --- the ROS adapter -----------------------------------------------------------------------

def _is_ipv4(value: str) -> bool:
    try:
        ipaddress.IPv4Address(value)
    except ValueError:
        return False
    return True


def _url_ok(value: str) -> bool:
    try:
        parse_mavlink_url(value)
    except ValueError:
        return False
    return True


PARAMS = [
    ParamSpec('scenario', 'paper', 'built-in scenario name or path to a scenario YAML file',
              lambda v: v.strip() != '', 'must not be empty'),
    ParamSpec('seed', 1, 'seed of every random stream of the world', lambda v: v >= 0,
              'must be >= 0'),
    ParamSpec('mavlink_url', 'udpout:127.0.0.1:14540',
              "emulated autopilot's MAVLink socket: 'udpout:HOST:PORT' sends to the bridge "
              "listening there (bridge default 'udpin:127.0.0.1:14540'); 'udpin:HOST:PORT' "
              "listens for a bridge configured 'udpout:HOST:PORT'", _url_ok,
              "must be 'udpin:IPV4:PORT' or 'udpout:IPV4:PORT'"),
    ParamSpec('pixy_udp_address', '127.0.0.1', "where pixy_driver listens (its "
              "'udp_bind_address')", _is_ipv4, 'must be an IPv4 literal'),
    in_range('pixy_udp_port', 14600, 1, 65535, "pixy_driver's 'udp_port'"),
    ParamSpec('realtime_factor', 1.0, 'sim seconds per wall second', lambda v: 0.0 < v <= 20.0,
              'must be in (0, 20]'),
    ParamSpec('physics_rate_hz', 400.0, 'physics sub-step rate (the Pixhawk attitude loop runs '
              'at 400 Hz)', lambda v: 400.0 <= v <= 4000.0, 'must be in [400, 4000]'),
    ParamSpec('truth_rate_hz', 50.0, 'rate of sim/truth/vehicle and sim/truth/apron',
              lambda v: 0.0 < v <= 400.0, 'must be in (0, 400]'),
    ParamSpec('tick_s', 0.01, 'wall-clock period of the simulation thread (absolute '
              'deadlines); keep it a divisor of the sensor periods (10 ms: IMU 100 Hz, camera '
              'and lidar 50 Hz) so telemetry leaves at a deadline',
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
        self.emulator: Px4Emulator | None = None
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
        vp = scenario.vehicle
        # the autopilot maps normalised thrust to the *vehicle's* newtons: hover at 1/(T/W)
        thrust = ThrustCalibration(mass_kg=vp.mass_kg, gravity_mps2=vp.gravity_mps2,
                                   hover_thrust_norm=1.0 / vp.thrust_to_weight)
        try:
            link = make_mavlink_link(p['mavlink_url'])
        except OSError as exc:
            raise ParameterError(f"parameter 'mavlink_url' = {p['mavlink_url']!r}: cannot "
                                 f'open the socket: {exc}') from None
        self.emulator = Px4Emulator(EmulatorParams(
            offboard_loss_action=p['offboard_loss_action'], thrust=thrust), transport=link)
        if p['signing_key_file']:
            # signing timestamps: 10 µs units since 2015-01-01 (wall clock, as PX4 with RTC)
            self.emulator.setup_signing(load_signing_key(p['signing_key_file']),
                                        int(max(time.time() - 1420070400.0, 0.0) * 1e5))
        self._pixy_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        pixy_addr = (p['pixy_udp_address'], p['pixy_udp_port'])
        sock = self._pixy_sock

        def pixy_send(data: bytes) -> None:
            sock.sendto(data, pixy_addr)

        self.sim = SimulationLoop(scenario, p['seed'], self.emulator, pixy_send,
                                  p['physics_rate_hz'], p['truth_rate_hz'],
                                  p['mavlink_fault_downlink'])
        self.schedule: TickSchedule | None = None
        self.thread_errors = 0
        self._outcome_msg: str | None = None
        self._warned: dict[str, int] = {}
        self.pub_vehicle = self.create_publisher(Odometry, 'sim/truth/vehicle', RELIABLE_QOS)
        self.pub_apron = self.create_publisher(Odometry, 'sim/truth/apron', RELIABLE_QOS)
        self.pub_outcome = self.create_publisher(String, 'sim/outcome', LATCHED_QOS)
        self.create_subscription(String, 'planner/mode', self._on_mode, LATCHED_QOS)
        self.create_timer(1.0, self._report_rejections)
        local = link.local_address
        self.get_logger().info(
            f"scenario {scenario.name!r} seed {p['seed']}: MAVLink {p['mavlink_url']} "
            f'(local {local[0]}:{local[1]}), Pixy -> {pixy_addr[0]}:{pixy_addr[1]}, '
            f"x{p['realtime_factor']:g} real time")

    # --- callbacks -----------------------------------------------------------------------

    def _on_mode(self, msg: String) -> None:
        self.sim.on_planner_mode(msg.data)

    def _report_rejections(self) -> None:
        """Log (once per change) what was rejected from the wire or by the cores."""
        counts = {f'mavlink.{k}': v for k, v in self.emulator.rejected.items()}
        counts.update({f'world.{k}': v for k, v in self.sim.world.rejected.items()})
        counts.update({f'sim.{k}': v for k, v in self.sim.rejected.items()})
        counts['pixy.blocks_dropped'] = self.sim.counters['pixy_blocks_dropped']
        counts['pixy.send_errors'] = self.sim.counters['pixy_send_errors']
        counts['schedule.overruns'] = self.overruns     # stalls > MAX_TICK_WALL_S, not caught up
        if self.sim.link is not None:   # datagrams the scenario's MAVLink faults took
            lc = self.sim.link.counters
            counts.update({f'link.{k}': v for k, v in lc.items()
                           if k.endswith(('_cut', '_lost', '_delayed'))})
        grown = {k: v for k, v in counts.items() if v > self._warned.get(k, 0)}
        if grown:
            self._warned.update(grown)
            self.get_logger().warning(f'rejected/dropped so far: {grown}')

    # --- the wall-clock thread -----------------------------------------------------------

    @property
    def ticks(self) -> int:
        """Ticks run by the world thread."""
        return self.schedule.ticks if self.schedule is not None else 0

    @property
    def overruns(self) -> int:
        """Stalls longer than ``MAX_TICK_WALL_S`` (their backlog was not caught up)."""
        return self.schedule.overruns if self.schedule is not None else 0

    def _run(self) -> None:
        """The world thread: tick k at ``start + k · tick_s`` (absolute, see TickSchedule);
        each tick advances the world by ``tick_s × realtime_factor``."""
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
            text = outcome_json(outcome)
            self._outcome_msg = text
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
        # twist in base_link (REP-105), like vehicle/odom
        tw = od.twist.twist
        r = rot_body_to_world(tr.roll_rad, tr.pitch_rad, tr.yaw_rad)
        tw.linear.x, tw.linear.y, tw.linear.z = mat_t_vec(r, tr.velocity_mps)
        tw.angular.x, tw.angular.y, tw.angular.z = body_rates(tr.roll_rad, tr.pitch_rad,
                                                              *tr.euler_rates_radps)
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
        if self.emulator is not None:
            with contextlib.suppress(Exception):
                self.emulator.close()
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


__all__ = ['PARAMS', 'AutopilotEmulation', 'AutopilotParams', 'DeckSimulatorNode',
           'ImpairedLink', 'SimulationLoop', 'TickSchedule', 'UdpLink', 'body_rates', 'main',
           'make_mavlink_link', 'outcome_json', 'parse_mavlink_url']
