"""Search, retry and fallback of the landing planner (paper section 3.3, Steps 11-14).

A small machine of its own, beside the landing states: it counts the search attempts since the
last start (Step 11: another attempt, or the fallback landing of Step 14 once they are used up)
and walks the search pattern of Step 12 (hover over the centre, then a square around it,
repeated). The planner flies the legs it hands out and owns every transition and logged reason.

Pure: no rclpy, no wall clock.
"""

from __future__ import annotations

__all__ = ['SearchPattern']


class SearchPattern:
    """Attempt budget (Step 11) and square search pattern (Step 12)."""

    __slots__ = ('_t_hold', '_wp', 'attempts', 'hold_s', 'index', 'max_attempts', 'radius_m')

    def __init__(self, max_attempts: int, radius_m: float, hold_s: float) -> None:
        self.max_attempts = max_attempts
        self.radius_m = radius_m
        self.hold_s = hold_s
        self.attempts = 0
        self.index = 0
        self._wp: list[tuple[float, float]] = []
        self._t_hold: float | None = None

    def reset(self) -> None:
        """A new landing (Step 1): every attempt is available again."""
        self.attempts = 0

    def retry(self) -> bool:
        """Step 11: True starts attempt ``attempts``; False = all used, fall back (Step 14)."""
        if self.attempts < self.max_attempts:
            self.attempts += 1
            return True
        return False

    def begin(self, centre: tuple[float, float]) -> tuple[float, float]:
        """Step 12: restart the pattern around ``centre``; returns the first leg's goal."""
        c, r = centre, self.radius_m
        self._wp = [c, (c[0] + r, c[1] + r), (c[0] - r, c[1] + r),
                    (c[0] - r, c[1] - r), (c[0] + r, c[1] - r), c]
        self.index = 0
        self._t_hold = None
        return c

    def next_goal(self, t_s: float) -> tuple[float, float] | None:
        """The current leg is flown: the next goal, or None while hovering over the centre
        (``hold_s`` from the first call there)."""
        if self.index == 0:
            if self._t_hold is None:
                self._t_hold = t_s
            if t_s - self._t_hold < self.hold_s:
                return None
        self._t_hold = None
        self.index = (self.index + 1) % len(self._wp)
        return self._wp[self.index]
