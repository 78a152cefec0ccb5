"""Pure input checks shared by the node adapters (no rclpy)."""

from __future__ import annotations

import math


def stamp_verdict(stamp_s: float, last_s: float | None, now_s: float,
                  timeout_s: float) -> str | None:
    """Why a message stamp must be rejected, or None when it is acceptable.

    Reasons: ``'non_finite'``; ``'out_of_order'`` (older than the last accepted stamp);
    ``'stale_stamp'`` (older than ``now − timeout``); ``'future_stamp'`` (later than
    ``now + timeout``: one such stamp would otherwise make every later message look out of
    order).
    """
    if not math.isfinite(stamp_s):
        return 'non_finite'
    if last_s is not None and stamp_s < last_s:
        return 'out_of_order'
    if now_s - stamp_s > timeout_s:
        return 'stale_stamp'
    if stamp_s - now_s > timeout_s:
        return 'future_stamp'
    return None
