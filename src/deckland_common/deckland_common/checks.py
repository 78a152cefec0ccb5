"""Input gating shared by the loop cores of the nodes (pure, no rclpy).

:func:`stamp_verdict` judges a message stamp against the node clock; :class:`InputGuard` is
the bookkeeping every loop core has: inputs rejected and outputs withheld, counted by reason,
with optional hooks through which a node logs them (``deckland_common.ros_node.GuardedNode``);
:func:`finite` is the finiteness test they use.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from deckland_common.frames import normalised_quaternion


def finite(x: float) -> bool:
    """``x`` is neither NaN nor ±inf: x − x is 0 only for a finite x (a plain float test, which
    the compiled cores run natively; ``math.isfinite`` is a Python call there)."""
    return x - x == 0.0


def stamp_verdict(stamp_s: float, last_s: float, now_s: float, timeout_s: float) -> str:
    """Why a message stamp must be rejected, or '' when it is acceptable.

    ``last_s`` is the last accepted stamp (``-inf``: none yet). Reasons: ``'non_finite'``;
    ``'out_of_order'`` (older than ``last_s``); ``'stale_stamp'`` (older than
    ``now − timeout``); ``'future_stamp'`` (later than ``now + timeout``: one such stamp would
    otherwise make every later message look out of order).
    """
    if not finite(stamp_s):
        return 'non_finite'
    if stamp_s < last_s:
        return 'out_of_order'
    if now_s - stamp_s > timeout_s:
        return 'stale_stamp'
    if stamp_s - now_s > timeout_s:
        return 'future_stamp'
    return ''


class InputGuard:
    """Counters of a loop core: ``rejected`` inputs and ``withheld`` outputs, by reason.

    ``withheld_reason`` is the reason of the latest withheld output ('' once an output went
    out again). ``on_reject(reason, what)`` is called for every rejection and
    ``on_withhold(reason)`` when the withholding reason changes (a node logs them; None in
    the in-process runner and the replays).
    """

    def __init__(self, rejected: Iterable[str], withheld: Iterable[str]) -> None:
        self.rejected: dict[str, int] = dict.fromkeys(rejected, 0)
        self.withheld: dict[str, int] = dict.fromkeys(withheld, 0)
        self.withheld_reason = 'starting'
        self.on_reject: Callable[[str, str], None] | None = None
        self.on_withhold: Callable[[str], None] | None = None

    def reject(self, reason: str, what: str) -> str:
        """Count one rejected input; returns ``reason``."""
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        hook = self.on_reject
        if hook is not None:
            hook(reason, what)
        return reason

    def withhold(self, reason: str) -> None:
        """Count one withheld output."""
        self.withheld[reason] = self.withheld.get(reason, 0) + 1
        hook = self.on_withhold
        if hook is not None and reason != self.withheld_reason:
            hook(reason)
        self.withheld_reason = reason

    def check_stamp(self, stamp_s: float, last_s: float, now_s: float, timeout_s: float,
                    what: str) -> bool:
        """:func:`stamp_verdict`; a bad stamp is rejected (counted) and False returned."""
        reason = stamp_verdict(stamp_s, last_s, now_s, timeout_s)
        if not reason:
            return True
        self.reject(reason, what)
        return False

    def unit_quaternion(self, q: tuple[float, float, float, float],
                        what: str) -> tuple[float, float, float, float] | None:
        """A received orientation (w, x, y, z) scaled to unit norm, or None, counted as
        ``non_finite`` or, off unit by more than ``frames.QUATERNION_NORM_TOLERANCE``,
        ``bad_quaternion``."""
        qn = normalised_quaternion(q[0], q[1], q[2], q[3])
        if qn is None:
            numbers = finite(q[0]) and finite(q[1]) and finite(q[2]) and finite(q[3])
            self.reject('bad_quaternion' if numbers else 'non_finite', what)
        return qn
