"""Arrival times of stream bytes, to stamp parsed frames (pure, no rclpy).

A serial reader gets bytes in chunks; the parser emits a frame only when the next frame starts
(see :mod:`pixy_driver.protocol`). :class:`ArrivalLog` remembers, for the last few reads, the
stream offset reached and the time of that read, so a frame can be stamped with the arrival of
its own last byte (``PixyFrame.end_offset``) rather than with the arrival of the bytes that
closed it, one frame period later.
"""

from __future__ import annotations

from collections import deque
import math


class ArrivalLog:
    """Bounded log of ``(total_bytes_after_read, t_s)`` pairs, in stream order."""

    def __init__(self, capacity: int = 256) -> None:
        if not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f'ArrivalLog.capacity must be an int >= 1, got {capacity!r}')
        self._log: deque[tuple[int, float]] = deque(maxlen=capacity)
        self.rejected = {'nan': 0, 'out_of_order': 0}

    def record(self, total_bytes: int, t_s: float) -> None:
        """A read ended at stream offset ``total_bytes`` at time ``t_s``."""
        if not math.isfinite(t_s):
            self.rejected['nan'] += 1
            return
        if self._log:
            last_total, last_t = self._log[-1]
            if total_bytes < last_total or t_s < last_t:
                self.rejected['out_of_order'] += 1
                return
        self._log.append((total_bytes, t_s))

    def time_of(self, offset: int) -> float | None:
        """Time of the read that delivered the byte just before ``offset``.

        None when nothing was recorded; the oldest time when the offset fell out of the log;
        the newest time when the offset is beyond the last record.
        """
        log = self._log
        if not log:
            return None
        t_found = None
        for total, t_s in reversed(log):
            if total >= offset:
                t_found = t_s
            else:
                break
        return t_found if t_found is not None else log[-1][1]
