"""Pure monitors the bridge core feeds (no sockets, no rclpy; times in seconds).

* :class:`SetpointStats` — the bridge's *own* SET_ATTITUDE_TARGET stream: rate and largest gap
  per diagnostics window, largest gap since the stream started (PX4 falls back to its
  offboard-loss action when a gap exceeds ``COM_OF_LOSS_T``).
* :class:`HoverThrustEstimator` — the normalised thrust that hovers, measured from PX4's own
  ATTITUDE_TARGET while PX4 itself holds a hover (PX4 v1.16 publishes its hover-thrust
  estimate on no MAVLink message; the thrust its position controller commands in a steady
  hover is that estimate plus the integrator, i.e. what the vehicle needs).
"""

from __future__ import annotations

import math


class SetpointStats:
    """Rate and gaps of the setpoints the bridge sent (call :meth:`on_sent` per setpoint).

    :meth:`window` returns ``(rate_hz, max_gap_s)`` over the time since the previous call and
    starts a new window; the gap counted for a window includes the time from the last
    setpoint to the end of the window (a stream that stopped shows its silence at once).
    """

    __slots__ = ('_count', '_last_s', '_max_gap_s', '_window_start_s', 'max_gap_total_s',
                 'sent')

    def __init__(self) -> None:
        self.sent = 0
        self.max_gap_total_s = 0.0
        self._count = 0
        self._last_s = math.nan
        self._max_gap_s = 0.0
        self._window_start_s = math.nan

    def on_sent(self, t_s: float) -> None:
        last = self._last_s
        if not math.isnan(last) and t_s >= last:
            gap = t_s - last
            if gap > self._max_gap_s:
                self._max_gap_s = gap
            if gap > self.max_gap_total_s:
                self.max_gap_total_s = gap
        self._last_s = t_s
        self._count += 1
        self.sent += 1
        if math.isnan(self._window_start_s):
            self._window_start_s = t_s

    def window(self, t_s: float) -> tuple[float, float]:
        """``(rate_hz, max_gap_s)`` since the last call (NaN rate before any setpoint)."""
        start, n = self._window_start_s, self._count
        if math.isnan(start) or not t_s > start:
            rate = math.nan
        else:
            rate = n / (t_s - start)
        gap = self._max_gap_s
        if not math.isnan(self._last_s) and t_s - self._last_s > gap:
            gap = t_s - self._last_s          # silent until now
        self._count = 0
        self._max_gap_s = 0.0
        self._window_start_s = t_s if not math.isnan(start) else math.nan
        return rate, gap


class HoverThrustEstimator:
    """Hover thrust from the autopilot's commanded collective in its own steady hover.

    Feed :meth:`on_sample` with ATTITUDE_TARGET.thrust (the norm of PX4's thrust vector), the
    tilt (cos φ cos θ from ATTITUDE) and the vertical speed, only while PX4 flies (armed, in
    the air, not OFFBOARD: in OFFBOARD ATTITUDE_TARGET echoes the bridge's own setpoints).
    A sample is the vertical component ``thrust · cos φ cos θ``; it is kept when |v_z| <
    ``max_vz_mps`` and the tilt is below ``max_tilt_rad``. The estimate is the mean over the
    last ``window_s``; it is :attr:`valid` once the window is covered by samples whose spread
    (max − min) is below ``max_spread`` — a climb, a gust or a mode change restarts it.
    """

    __slots__ = ('_cos_tilt_min', '_samples', 'estimate', 'max_spread', 'max_vz_mps',
                 'window_s')

    def __init__(self, window_s: float = 4.0, max_vz_mps: float = 0.15,
                 max_tilt_rad: float = 0.17, max_spread: float = 0.05) -> None:
        for name, v in (('window_s', window_s), ('max_vz_mps', max_vz_mps),
                        ('max_tilt_rad', max_tilt_rad), ('max_spread', max_spread)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f'HoverThrustEstimator.{name} = {v!r}: must be a finite '
                                 'number > 0')
        self.window_s = float(window_s)
        self.max_vz_mps = float(max_vz_mps)
        self.max_spread = float(max_spread)
        self._cos_tilt_min = math.cos(max_tilt_rad)
        self._samples: list[tuple[float, float]] = []
        self.estimate = math.nan

    @property
    def valid(self) -> bool:
        return not math.isnan(self.estimate)

    def reset(self) -> None:
        self._samples = []
        self.estimate = math.nan

    def on_sample(self, t_s: float, thrust_norm: float, cos_tilt: float, vz_mps: float) -> bool:
        """One ATTITUDE_TARGET sample; returns True when it was kept. A sample outside the
        hover conditions restarts the window (the previous valid estimate is kept)."""
        if not all(map(math.isfinite, (t_s, thrust_norm, cos_tilt, vz_mps))):
            return False
        s = self._samples
        if s and t_s < s[-1][0]:
            return False
        if not (0.0 < thrust_norm < 1.0) or abs(vz_mps) > self.max_vz_mps or \
                cos_tilt < self._cos_tilt_min:
            s.clear()
            return False
        s.append((t_s, thrust_norm * cos_tilt))
        while s and s[0][0] < t_s - self.window_s:
            del s[0]
        vals = [v for _, v in s]
        if t_s - s[0][0] >= 0.9 * self.window_s and max(vals) - min(vals) <= self.max_spread:
            self.estimate = sum(vals) / len(vals)
        return True
