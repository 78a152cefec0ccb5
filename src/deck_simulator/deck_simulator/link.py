"""The MAVLink link between the companion and the autopilot, with the scenario's link faults.

:class:`LinkModel` is the one model of the link: outage (``mavlink_link_loss``, and a killed
node on the sender's side), random loss (``mavlink_loss``) and latency (``mavlink_latency``,
FIFO, never reordered) at time t, from the windows of :class:`~deck_simulator.faults.FaultSet`.
Two adapters apply it: :class:`CommandLink` in-process (the runner's commands and TIMESYNC to
the world's :class:`~deck_simulator.autopilot.EmulatedAutopilot`) and :class:`ImpairedLink` on
the wire (every datagram between the bridge and the emulated PX4 in the node graph). Random
draws come from the caller's stream, so measuring never shifts another stream's draws.
"""

from __future__ import annotations

from collections import deque
import math
import random
from typing import Any

from deck_simulator.autopilot import EmulatedAutopilot
from deck_simulator.faults import COMMAND_PATH_NODES, FaultSet

#: scenario fault types the graph applies on the MAVLink wire (``node_kill`` is a real SIGKILL
#: of a node process by ``deckland up``, so it is not applied there a second time)
WIRE_FAULT_TYPES = ('mavlink_link_loss', 'mavlink_loss', 'mavlink_latency')
DOWNLINK_MODES = ('none', 'cut', 'all')


class LinkModel:
    """Outage, loss and latency of one direction of the link at world time t (pure).

    ``silenced_by``: the nodes whose ``node_kill`` silences this channel's sender (the
    command path for the companion's commands, the bridge for TIMESYNC, none on the wire,
    where ``deckland up`` kills the real process).
    """

    def __init__(self, faults: FaultSet, silenced_by: tuple[str, ...] = ()) -> None:
        self.cuts: list[Any] = [a for a in faults.link_cut if a.name == 'mavlink_link_loss'
                                or a.spec.node in silenced_by]
        self.losses: list[Any] = faults.link_loss
        self.latencies: list[Any] = faults.link_latency

    def cut(self, t_s: float) -> bool:
        """Nothing sent at ``t_s`` gets through (outage, or the sender is dead)."""
        return any(a.on <= t_s < a.off for a in self.cuts)

    def lost(self, t_s: float, rng: random.Random | None) -> bool:
        """One draw per active loss fault (from ``rng``, or each fault's own stream if None)."""
        for a in self.losses:
            if a.on <= t_s < a.off and (a.rng if rng is None else rng).random() < \
                    a.spec.probability:
                return True
        return False

    def delay_s(self, t_s: float) -> float:
        """Latency of a packet sent at ``t_s`` (the largest active one; 0 = none)."""
        delay = 0.0
        for a in self.latencies:
            if a.on <= t_s < a.off and a.spec.latency_s > delay:
                delay = a.spec.latency_s
        return delay

    def fate(self, t_s: float, rng: random.Random | None) -> float | None:
        """None if a packet sent at ``t_s`` never arrives, else its delay (s)."""
        if self.cut(t_s) or self.lost(t_s, rng):
            return None
        return self.delay_s(t_s)


Command = tuple[float, float, float, float]


class CommandLink:
    """In-process: the companion's attitude/thrust commands and TIMESYNC requests to the
    world's autopilot through :class:`LinkModel` (what ``World.command_link`` and
    ``World.timesync_rtt_s`` use).

    Commands: a command-path ``node_kill`` cuts them, each loss fault draws from its own
    stream ``f'{seed}:fault:{i}:{type}'``, delayed ones wait in a FIFO and are delivered by
    :meth:`deliver_due` every physics sub-step. TIMESYNC: cut by the bridge's death only, loss
    drawn from ``f'{seed}:timesync'``, queued behind the commands still in flight; telemetry
    is not delayed in-process (as the wire's default ``downlink='cut'``), the autopilot answers
    at once (PX4 replies in its receive thread).
    """

    def __init__(self, faults: FaultSet, seed: int, autopilot: EmulatedAutopilot,
                 rejected: dict[str, int]) -> None:
        self.commands = LinkModel(faults, COMMAND_PATH_NODES)
        self.timesync = LinkModel(faults, ('mavlink_bridge',))
        self.autopilot = autopilot
        self.rejected = rejected
        self.stats: dict[str, int] = {'sent': 0, 'lost': 0, 'delayed': 0}
        self._queue: deque[tuple[float, Command]] = deque()
        self._last_tx_s = 0.0
        self._seed = seed
        self._timesync_rng: random.Random | None = None   # made on first use

    def send(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float,
             thrust_n: float) -> bool:
        """A command sent at ``t_s``; True unless rejected or lost (see World.command_link)."""
        if not (math.isfinite(t_s) and math.isfinite(roll_rad) and math.isfinite(pitch_rad)
                and math.isfinite(yaw_rad) and math.isfinite(thrust_n)):
            self.rejected['nan'] += 1
            return False
        ap = self.autopilot
        if not ap.active:
            self._last_tx_s = t_s
            ap.engage_offboard(t_s)
        elif t_s < self._last_tx_s:
            self.rejected['out_of_order'] += 1
            return False
        self._last_tx_s = t_s
        self.stats['sent'] += 1
        delay = self.commands.fate(t_s, None)
        if delay is None:
            self.stats['lost'] += 1
            return False
        if delay > 0.0 or self._queue:
            self.stats['delayed'] += delay > 0.0
            self._queue.append((t_s + delay, (roll_rad, pitch_rad, yaw_rad, thrust_n)))
            return True
        ap.on_setpoint(t_s, roll_rad, pitch_rad, yaw_rad, thrust_n)
        return True

    def deliver_due(self, t_s: float) -> None:
        """Hand the commands due by ``t_s`` to the autopilot (FIFO)."""
        q = self._queue
        while q and q[0][0] <= t_s + 1e-12:
            due, (roll, pitch, yaw, thrust) = q.popleft()
            self.autopilot.on_setpoint(due, roll, pitch, yaw, thrust)

    def timesync_rtt_s(self, t_s: float) -> float | None:
        """Round trip (s) of a TIMESYNC request sent at finite ``t_s``, None if lost."""
        ts = self.timesync
        if ts.cut(t_s):
            return None
        if ts.losses:
            if self._timesync_rng is None:
                self._timesync_rng = random.Random(f'{self._seed}:timesync')
            if ts.lost(t_s, self._timesync_rng):
                return None
        arrive = t_s + ts.delay_s(t_s)
        if self._queue and self._queue[-1][0] > arrive:
            arrive = self._queue[-1][0]
        if ts.cut(arrive):   # the reply leaves at `arrive`
            return None
        return arrive - t_s


class ImpairedLink:
    """The link faults on the wire: wraps the emulator's byte transport (same ``send`` /
    ``receive`` / ``set_peer`` / ``close``) and applies :class:`LinkModel` datagram by
    datagram at the world's time ``world.t_s``.

    Uplink (bridge → autopilot: setpoints, commands, heartbeats, TIMESYNC) always gets every
    wire fault. ``downlink`` (telemetry): ``'none'`` untouched, ``'cut'`` (default) only the
    link-loss cut (a dead radio is dead both ways), ``'all'`` loss and latency as well.
    Draws from ``random.Random(f'{seed}:mavlink_wire:up')`` and ``...:down``. Held datagrams
    are released on the next ``send``/``receive`` at or after their due time (the emulator
    polls at 100 Hz: ≤ 10 ms quantisation). Counters: ``rx``/``tx`` with ``_cut``, ``_lost``,
    ``_delayed``.
    """

    def __init__(self, inner: Any, world: Any, seed: int, downlink: str = 'cut') -> None:
        if downlink not in DOWNLINK_MODES:
            raise ValueError(f'ImpairedLink.downlink must be one of {list(DOWNLINK_MODES)}, '
                             f'got {downlink!r}')
        if world.faults is None:
            raise ValueError('ImpairedLink needs a world with faults')
        self.inner = inner
        self.world = world
        self.downlink = downlink
        self.model = LinkModel(world.faults)
        self._rng_up = random.Random(f'{seed}:mavlink_wire:up')
        self._rng_down = random.Random(f'{seed}:mavlink_wire:down')
        self._rx_queue: list[tuple[float, bytes, object]] = []
        self._tx_queue: list[tuple[float, bytes]] = []
        self.counters: dict[str, int] = {
            'rx': 0, 'rx_cut': 0, 'rx_lost': 0, 'rx_delayed': 0,
            'tx': 0, 'tx_cut': 0, 'tx_lost': 0, 'tx_delayed': 0}

    @staticmethod
    def wire_faults(faults: FaultSet | None) -> list[Any]:
        """The run-time faults this link applies (empty: nothing to wrap)."""
        if faults is None:
            return []
        return [a for a in faults.all if a.name in WIRE_FAULT_TYPES]

    def _fate(self, t_s: float, rng: random.Random, cut_only: bool) -> float | str:
        """'cut' / 'lost' or the delay in seconds (0 = now) of a datagram sent at t."""
        m = self.model
        if m.cut(t_s):
            return 'cut'
        if cut_only:
            return 0.0
        if m.lost(t_s, rng):
            return 'lost'
        return m.delay_s(t_s)

    @property
    def local_address(self) -> Any:
        return getattr(self.inner, 'local_address', None)

    def _flush_tx(self, t_s: float) -> None:
        q = self._tx_queue
        n = 0
        while n < len(q) and q[n][0] <= t_s + 1e-9:
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
        if isinstance(fate, str):
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
            if isinstance(fate, str):
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


__all__ = ['DOWNLINK_MODES', 'WIRE_FAULT_TYPES', 'CommandLink', 'ImpairedLink', 'LinkModel']
