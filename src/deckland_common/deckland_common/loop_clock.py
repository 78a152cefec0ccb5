"""A fixed-rate loop clock phase-locked to a reference event (pure: no rclpy, no sleeping).

More in the package README, "Module notes" (`deckland_common.loop_clock`).
"""

from __future__ import annotations

from dataclasses import dataclass
import math


@dataclass(frozen=True, slots=True)
class PhaseLockParams:
    """Loop clock parameters (seconds), validated at construction."""

    period_s: float = 0.01       # loop period (100 Hz)
    lead_s: float = 0.001        # wanted time from a reference event to the next tick
    max_slew_s: float = 0.0002   # largest phase correction per reference event
    max_wait_s: float = 0.003    # an event further than this before the next tick goes at once
    max_lag_s: float = 0.05      # a tick later than this re-anchors the schedule at "now"

    def __post_init__(self) -> None:
        for name in ('period_s', 'lead_s', 'max_slew_s', 'max_wait_s', 'max_lag_s'):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f'PhaseLockParams.{name} must be a finite number, got {v!r}')
        if self.period_s <= 0.0:
            raise ValueError(f'PhaseLockParams.period_s must be > 0, got {self.period_s!r}')
        if not 0.0 <= self.lead_s < self.period_s / 2.0:
            raise ValueError(f'PhaseLockParams.lead_s must be in [0, period_s/2), got '
                             f'{self.lead_s!r}')
        if not 0.0 <= self.max_slew_s <= self.period_s / 10.0:
            raise ValueError(f'PhaseLockParams.max_slew_s must be in [0, period_s/10] (a '
                             f'regular stream), got {self.max_slew_s!r}')
        if not self.lead_s <= self.max_wait_s < self.period_s:
            raise ValueError(f'PhaseLockParams.max_wait_s must be in [lead_s, period_s), got '
                             f'{self.max_wait_s!r}')
        if self.max_lag_s < self.period_s:
            raise ValueError(f'PhaseLockParams.max_lag_s must be >= period_s, got '
                             f'{self.max_lag_s!r}')


class PhaseLockedLoop:
    """Absolute-deadline loop clock, phase-locked to reference events (module doc)."""

    __slots__ = ('events', 'next_s', 'overruns', 'params', 'skipped', 'ticks')

    def __init__(self, params: PhaseLockParams, start_s: float) -> None:
        if not math.isfinite(start_s):
            raise ValueError(f'PhaseLockedLoop start_s must be finite, got {start_s!r}')
        self.params = params
        self.next_s = start_s + params.period_s   #: the next deadline
        self.ticks = 0
        self.events = 0
        self.skipped = 0       #: deadlines passed over after a late tick (no catch-up burst)
        self.overruns = 0      #: re-anchors after a stall longer than max_lag_s

    def wait_s(self, now_s: float) -> float:
        """Seconds until the next deadline (0 when due)."""
        d = self.next_s - now_s
        return d if d > 0.0 else 0.0

    def tick(self, now_s: float) -> float:
        """Account the tick run at ``now_s`` (call once the deadline is due); returns the
        deadline it stands for. Missed deadlines are skipped, never run as a burst: a control
        loop wants the newest data once, not several steps on the same data."""
        p = self.params
        deadline = self.next_s
        self.ticks += 1
        late = now_s - deadline
        if late > p.max_lag_s:
            self.overruns += 1
            self.next_s = now_s + p.period_s
            return deadline
        nxt = deadline + p.period_s
        if nxt <= now_s:
            missed = math.floor((now_s - deadline) / p.period_s)
            self.skipped += missed
            nxt = deadline + (missed + 1) * p.period_s
        self.next_s = nxt
        return deadline

    def phase_error_s(self, t_s: float) -> float:
        """How much later than wanted the next tick falls after an event at ``t_s``:
        (time to the next tick − ``lead_s``) wrapped into [−period/2, period/2)."""
        p = self.params
        err = (self.next_s - t_s) - p.lead_s
        half = p.period_s / 2.0
        return (err + half) % p.period_s - half

    def on_event(self, t_s: float) -> bool:
        """A reference event at ``t_s``: move the next deadline by at most ``max_slew_s``
        toward ``t_s + lead_s``. Returns True when the event should be published at once
        (the next tick is more than ``max_wait_s`` away), False when that tick will carry it.
        """
        p = self.params
        self.events += 1
        err = self.phase_error_s(t_s)
        s = p.max_slew_s
        self.next_s -= s if err > s else (-s if err < -s else err)
        return self.next_s - t_s > p.max_wait_s
