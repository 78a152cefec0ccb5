"""deckland_common.loop_clock.PhaseLockedLoop: a fixed-rate clock phase-locked to events.

Pure, simulated time. What must hold: deadlines never drift (absolute schedule), the period
changes by at most max_slew_s per event (a regular stream), ticks settle lead_s after
periodic events from any starting phase, events too far from a tick are reported for
immediate publication, and a stall skips deadlines instead of bursting.
"""

import itertools

from deckland_common.loop_clock import PhaseLockedLoop, PhaseLockParams
from hypothesis import given
from hypothesis import strategies as st
import pytest

P = PhaseLockParams()   # 10 ms period, 1 ms lead, 0.2 ms slew, 3 ms max wait


def fly(loop, t_end, events, event_offset=0.0):
    """Advance simulated time to t_end: ticks exactly at their deadlines, events at the given
    times (+ offset). Returns (tick times, [(event time, publish_now)])."""
    ticks, evs = [], []
    pending = sorted(t + event_offset for t in events)
    t = 0.0
    while True:
        nxt_event = pending[0] if pending else float('inf')
        if min(loop.next_s, nxt_event) > t_end:
            return ticks, evs
        if nxt_event < loop.next_s:
            t = pending.pop(0)
            evs.append((t, loop.on_event(t)))
        else:
            t = loop.next_s
            loop.tick(t)
            ticks.append(t)


def test_free_running_ticks_are_exact_and_do_not_drift():
    loop = PhaseLockedLoop(P, 5.0)
    ticks, _ = fly(loop, 15.0, [])
    assert len(ticks) == 1000
    assert ticks[-1] == pytest.approx(5.0 + 1000 * 0.01, abs=1e-9)  # absolute schedule
    assert all(b - a == pytest.approx(0.01, abs=1e-12) for a, b in itertools.pairwise(ticks))


@given(start=st.floats(0.0, 0.01), camera_phase=st.floats(0.0, 0.02))
def test_locks_lead_s_after_50hz_events_from_any_phase(start, camera_phase):
    loop = PhaseLockedLoop(P, start)
    frames = [camera_phase + 0.02 * k for k in range(200)]      # 4 s of a 50 Hz camera
    ticks, evs = fly(loop, 4.0, frames)
    # the period never changes by more than one slew per event (one event per 2 ticks)
    for a, b in itertools.pairwise(ticks):
        assert abs((b - a) - P.period_s) <= P.max_slew_s + 1e-12
    # converged within 0.5 / slew periods (≤ 25 events = 0.5 s): every later frame is
    # followed by a tick exactly lead_s later and waits for it (not published at once)
    late = [(t, now) for t, now in evs if 1.0 < t < 3.9]
    assert len(late) >= 140
    for t, now in late:
        after = min(x for x in ticks if x >= t)
        assert after - t == pytest.approx(P.lead_s, abs=1e-9)
        assert now is False
    assert loop.skipped == 0 and loop.overruns == 0


def test_early_or_late_events_are_published_at_once():
    loop = PhaseLockedLoop(P, 0.0)          # next tick at 10 ms
    assert loop.on_event(0.0095) is False   # 0.5 ms before the tick: the tick carries it
    loop = PhaseLockedLoop(P, 0.0)
    assert loop.on_event(0.0050) is True    # 5 ms early: waiting would add 5 ms
    loop = PhaseLockedLoop(P, 0.0)
    loop.tick(0.010)                        # the tick passed; the frame came 0.3 ms late
    assert loop.on_event(0.0103) is True    # next tick ~9.7 ms away: publish now


def test_phase_error_wraps_and_the_correction_is_clamped():
    loop = PhaseLockedLoop(P, 0.0)          # next tick at 0.010
    assert loop.phase_error_s(0.0085) == pytest.approx(0.0005)   # tick 1.5 ms after: 0.5 late
    assert loop.phase_error_s(0.0102) == pytest.approx(-0.0012)  # tick just passed: wrap
    before = loop.next_s
    loop.on_event(0.0050)                   # tick 5 ms after: 4 ms too late → one slew earlier
    assert loop.next_s == pytest.approx(before - P.max_slew_s)


def test_a_stall_skips_deadlines_instead_of_bursting():
    loop = PhaseLockedLoop(P, 0.0)
    loop.tick(0.010)
    assert loop.tick(0.0355) == pytest.approx(0.020)   # 15.5 ms late: one tick, 1 skipped
    assert loop.skipped == 1
    assert loop.next_s == pytest.approx(0.040)         # back on the absolute grid
    loop.tick(0.5)                                     # beyond max_lag_s: re-anchor
    assert loop.overruns == 1 and loop.next_s == pytest.approx(0.51)


@pytest.mark.parametrize('kw', [
    {'period_s': 0.0}, {'period_s': float('nan')}, {'lead_s': 0.006}, {'lead_s': -0.001},
    {'max_slew_s': 0.002}, {'max_wait_s': 0.0005}, {'max_wait_s': 0.01}, {'max_lag_s': 0.005},
    {'lead_s': True}])
def test_bad_parameters_raise(kw):
    with pytest.raises(ValueError, match='PhaseLockParams'):
        PhaseLockParams(**kw)
