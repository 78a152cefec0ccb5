"""The simulator's hardware emulation stepped in sim time, and its wall-clock schedule (pure).

:class:`SimulationLoop` is everything the simulator node does between its timer and its
publishers: the world, the autopilot the world flies (the emulated PX4 on the MAVLink wire, or
a real firmware in lockstep such as PX4 SITL), the scenario's link faults on the wire, the Pixy
datagrams, truth samples and the outcome record.
:class:`TickSchedule` gives the node's thread absolute fixed-rate deadlines. No rclpy: the
node (``deck_simulator.node``) only adds the thread, the sockets, parameters and topics.
"""

from __future__ import annotations

from collections.abc import Callable
import math
import threading
from typing import Any

from deckland_common.frames import mat_t_vec, rot_body_to_world
from pixy_driver.protocol import block_in_range, encode_frame

from deck_simulator.autopilot import Autopilot, EmulatedAutopilot, with_link_fault
from deck_simulator.link import ImpairedLink
from deck_simulator.outcome import landing_outcome, outcome_dict
from deck_simulator.px4_emulator import Px4Emulator
from deck_simulator.scenario import Scenario
from deck_simulator.ship_link import ShipEncoder
from deck_simulator.world import Truth, World

#: planner modes that do not count as "landing triggered" (time_to_land_s starts at the first
#: mode outside this set; TAKEOFF is a take-off, not a landing trigger)
NOT_LANDING_MODES = frozenset({'IDLE', 'HOLD', 'TAKEOFF'})
AUTOPILOT_INPUT_HZ = 100.0     # the emulator reads the wire at PX4's control rate
#: the outcome waits this long after the first contact at most (as the runner's
#: ``settle_after_contact_s``): settling needs the land detector's disarm and 1 s still
SETTLE_CAP_S = 10.0


def body_rates(roll: float, pitch: float, droll: float, dpitch: float,
               dyaw: float) -> tuple[float, float, float]:
    """Z-Y-X Euler rates → body rates (p, q, r) FLU: ω = W(φ, θ) (φ̇, θ̇, ψ̇)."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    return (droll - sp * dyaw, cr * dpitch + sr * cp * dyaw, -sr * dpitch + cr * cp * dyaw)


def body_twist(tr: Truth) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The true twist in ``base_link`` (REP-105): (Rᵀ v, body rates)."""
    r = rot_body_to_world(tr.roll_rad, tr.pitch_rad, tr.yaw_rad)
    return (mat_t_vec(r, tr.velocity_mps),
            body_rates(tr.roll_rad, tr.pitch_rad, *tr.euler_rates_radps))


class SimulationLoop:
    """World + autopilot + MAVLink link faults + Pixy wire + outcome, stepped in sim time.

    Two autopilot backends, one loop. Emulated (``emulator`` given): the world flies one
    :class:`~deck_simulator.autopilot.EmulatedAutopilot` (the emulator is its MAVLink face; a
    scenario link fault's settings configure it, with no hold before the failsafe action and
    no automatic re-engagement: the bridge asks for OFFBOARD itself); the vehicle starts
    armed, in the air, in POSCTL. Firmware (``firmware(world)`` returns the world's
    :class:`~deck_simulator.autopilot.Autopilot`, e.g. ``px4_hil.Px4Hil``, attached to the
    world; ``emulator`` None): the firmware talks MAVLink to the companion itself; with wire
    faults ``relay = (companion_side, firmware_side)`` transports carry that link through
    the scenario's faults. ``advance(dt_s)`` runs as many ``1 / physics_rate_hz`` sub-steps as
    fit (the remainder is carried over) and returns ``(truth_samples, outcome_or_None)``; per
    sub-step: telemetry into the emulator at the IMU's rate (``sensors.imu.timing.rate_hz``:
    the latest sample every sensor has delivered, on its own clock and latency), each Pixy
    frame as a datagram when the world delivers it, the emulator's input
    (``AUTOPILOT_INPUT_HZ``) or the relay, truth samples (``truth_rate_hz``), then
    ``world.step`` (the autopilot ticks in there). ``on_planner_mode`` may be called from
    another thread.
    """

    def __init__(self, scenario: Scenario, seed: int, emulator: Px4Emulator | None,
                 pixy_send: Callable[[bytes], None], physics_rate_hz: float = 400.0,
                 truth_rate_hz: float = 50.0, link_downlink: str = 'cut',
                 firmware: Callable[[World], Autopilot] | None = None,
                 relay: tuple[Any, Any] | None = None,
                 ship_send: Callable[[bytes], None] | None = None) -> None:
        if (emulator is None) == (firmware is None):
            raise ValueError('SimulationLoop: give either an emulator or a firmware backend')
        self.scenario = scenario
        self.seed = seed
        self.world = world = World(scenario, seed, physics_dt_s=1.0 / physics_rate_hz)
        self.emulator = emulator
        fs = world.faults
        self.link: ImpairedLink | None = None
        self.relay: tuple[Any, Any] | None = None
        self.autopilot: Any
        if emulator is not None:
            params = emulator.params.autopilot_params()
            if fs is not None and fs.has_link:   # COM_OF_LOSS_T, MPC_LAND_SPEED, RTL, ...
                params = with_link_fault(params, fs.link_spec)
            self.autopilot = EmulatedAutopilot(params, world)
            world.attach_autopilot(self.autopilot)
            emulator.use_autopilot(self.autopilot)
            # the scenario's MAVLink faults act on the wire; a node_kill is a real kill
            if ImpairedLink.wire_faults(fs):
                self.link = ImpairedLink(emulator.transport, world, seed, link_downlink)
                emulator.set_transport(self.link)
        else:
            assert firmware is not None
            self.autopilot = firmware(world)
            world.attach_autopilot(self.autopilot)
            if fs is not None:   # the firmware boots and takes off first: faults count
                fs.start_at(None)   # from the landing trigger
            if relay is not None:
                companion, fw = relay
                if ImpairedLink.wire_faults(fs):
                    self.link = companion = ImpairedLink(companion, world, seed, link_downlink)
                self.relay = (companion, fw)
        self.pixy_send = pixy_send
        # the ship's own MAVLink stream (deck_simulator.ship_link), when the scenario has one
        self.ship_send = ship_send if world.ship_link is not None else None
        self._ship_encoder: ShipEncoder | None = None
        if self.ship_send is not None and scenario.ship_telemetry is not None:
            st = scenario.ship_telemetry
            self._ship_encoder = ShipEncoder(st.sysid, st.compid)
        self.h_s = 1.0 / physics_rate_hz
        sp = scenario.sensors
        world.queued = frozenset(('camera',))
        self._periods = {'telemetry': 1.0 / sp.imu.timing.rate_hz,
                         'control': 1.0 / AUTOPILOT_INPUT_HZ, 'truth': 1.0 / truth_rate_hz}
        self._due = dict.fromkeys(self._periods, 0.0)
        self._pending_s = 0.0
        self._lock = threading.Lock()
        self.mode = ''
        self.trigger_t_s: float | None = None
        self.searches = 0
        self.outcome: dict | None = None
        self.counters = {'substeps': 0, 'pixy_frames': 0, 'pixy_blocks_dropped': 0,
                         'pixy_send_errors': 0, 'offboard_steps': 0, 'autopilot_steps': 0,
                         'relayed_up': 0, 'relayed_down': 0, 'ship_messages': 0,
                         'ship_send_errors': 0}
        self.rejected: dict[str, int] = {'bad_dt': 0, 'bad_mode': 0}
        self.last_kind = 'firmware'
        self._faults_dormant = emulator is None and fs is not None
        if emulator is not None:
            # the vehicle hovers armed in POSCTL at the start (PX4 after a manual take-off)
            self._take('telemetry', 0.0)
            self._telemetry(0.0)
            self.autopilot.start_in_air(0.0)
            self.last_kind = self.autopilot.kind

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

    def rejection_counts(self) -> dict[str, int]:
        """What was rejected (the wire, the world, this loop, the autopilot) or dropped (Pixy
        blocks out of range, send errors, datagrams the scenario's MAVLink faults took)."""
        counts = ({f'mavlink.{k}': v for k, v in self.emulator.rejected.items()}
                  if self.emulator is not None else {})
        counts.update({f'world.{k}': v for k, v in self.world.rejected.items()})
        counts.update({f'sim.{k}': v for k, v in self.rejected.items()})
        counts.update({f'autopilot.{k}': v for k, v in self.autopilot.rejected.items()})
        counts['pixy.blocks_dropped'] = self.counters['pixy_blocks_dropped']
        counts['pixy.send_errors'] = self.counters['pixy_send_errors']
        if self.link is not None:
            counts.update({f'link.{k}': v for k, v in self.link.counters.items()
                           if k.endswith(('_cut', '_lost', '_delayed'))})
        return counts

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
        if self.emulator is not None and self._take('telemetry', t):
            self._telemetry(t)
        if world.inbox['camera']:
            for _stamp, blocks in world.delivered('camera'):
                self._camera(blocks)
        if self.emulator is not None:
            if self._take('control', t):
                self._control(t)
        else:
            if self._faults_dormant and self.trigger_t_s is not None \
                    and world.faults is not None:
                self._faults_dormant = False
                world.faults.start_at(self.trigger_t_s)
            if self.relay is not None:
                self._relay()
        if self._ship_encoder is not None:
            self._ship()
        world.step(self.h_s)      # the autopilot flies the non-offboard modes in here
        self.counters['substeps'] += 1
        t = world.t_s
        if self._take('truth', t):
            samples.append(world.truth())
        if self.outcome is None:
            return self._check_outcome(t)
        return None

    def _telemetry(self, t: float) -> None:
        world = self.world
        emulator = self.emulator
        assert emulator is not None   # telemetry is scheduled only with the emulator
        # the latest sample each sensor has delivered (the model latency stands for the
        # serial link loopback UDP does not have); IMU: specific force and rate, body FLU
        pos, vel = world.read_local_position()
        roll, pitch, yaw = world.read_attitude()
        accel_body, rates = world.read_imu()
        emulator.publish_state(t, pos, vel, roll, pitch, yaw, rates, accel_body,
                               world.read_lidar(), world.resting_on is not None)

    def _ship(self) -> None:
        """The ship's messages that arrived by now (the link model's latency and loss),
        sent as MAVLink datagrams."""
        enc, send = self._ship_encoder, self.ship_send
        assert enc is not None and send is not None
        for _t, msg in self.world.read_ship_telemetry():
            try:
                send(enc.encode(msg))
                self.counters['ship_messages'] += 1
            except (OSError, ValueError):
                self.counters['ship_send_errors'] += 1

    def _camera(self, blocks: list) -> None:
        keep = [b for b in blocks if block_in_range(*b)]
        self.counters['pixy_blocks_dropped'] += len(blocks) - len(keep)
        try:
            self.pixy_send(encode_frame(keep))
            self.counters['pixy_frames'] += 1
        except (OSError, ValueError):
            self.counters['pixy_send_errors'] += 1

    def _relay(self) -> None:
        """The companion <-> firmware link (every sub-step), through the wire faults."""
        relay = self.relay
        assert relay is not None
        companion, fw = relay
        for data, addr in companion.receive():
            companion.set_peer(addr)
            fw.send(data)
            self.counters['relayed_up'] += 1
        for data, addr in fw.receive():
            fw.set_peer(addr)
            companion.send(data)
            self.counters['relayed_down'] += 1

    def _control(self, t: float) -> None:
        emulator = self.emulator
        assert emulator is not None
        emulator.update(t)   # bytes from the wire: setpoints, commands (bad ones counted)
        self.last_kind = kind = self.autopilot.kind
        self.counters['offboard_steps' if kind == 'offboard' else 'autopilot_steps'] += 1

    def _check_outcome(self, t: float) -> dict | None:
        world = self.world
        with self._lock:
            trigger, searches, mode = self.trigger_t_s, self.searches, self.mode
        c = world.contact
        if c is not None:
            # the landing is scored once settled or crashed (or SETTLE_CAP_S after contact)
            if not world.landing_done and t - c.t_s < SETTLE_CAP_S:
                return None
            out = outcome_dict(landing_outcome(world, self.seed, trigger, searches, mode, ''))
        else:
            deadline = (trigger if trigger is not None else 0.0) + self.scenario.timeout_s
            if t < deadline:
                return None
            since = 'the landing trigger' if trigger is not None else 'the start (no trigger)'
            out = outcome_dict(
                landing_outcome(world, self.seed, trigger, searches, mode, 'timeout'),
                detail=f'no touchdown within {self.scenario.timeout_s:g} s of {since}')
        self.outcome = out
        return out


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


__all__ = ['AUTOPILOT_INPUT_HZ', 'NOT_LANDING_MODES', 'SETTLE_CAP_S', 'SimulationLoop',
           'TickSchedule', 'body_rates', 'body_twist']
