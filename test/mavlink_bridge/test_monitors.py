"""LinkMonitor (mavlink_bridge.core): link latency from TIMESYNC round trips, and the bridge
core stopping its setpoint stream on a degraded link (docs/failsafe.md, "Latency")."""

from __future__ import annotations

import itertools
import math
import random

from mavlink_bridge.conversions import px4_custom_mode
from mavlink_bridge.core import BridgeCore, BridgeParams, LinkMonitor, LinkMonitorParams
import pytest


def drive(mon: LinkMonitor, rtt_of, t_end: float, dt: float = 0.01) -> list[float]:
    """Poll at 100 Hz; each request's reply arrives rtt_of(t_sent) later (None = lost).
    Returns the times at which the monitor was degraded (first entry = detection)."""
    pending: list[tuple[float, float]] = []
    seen = []
    for k in range(round(t_end / dt) + 1):
        t = k * dt
        while pending and pending[0][0] <= t + 1e-9:
            t_rx, t_tx = pending.pop(0)
            mon.on_timesync(t_tx, t_rx)
        if mon.degraded:
            seen.append(t)
        if mon.poll(t):
            rtt = rtt_of(t)
            if rtt is not None:
                pending.append((t + rtt, t))
                pending.sort()
    return seen


@pytest.mark.parametrize('field, value', [
    ('period_s', 0.0), ('max_latency_s', math.nan), ('confirm_s', -1.0), ('window', 0),
    ('window', 2.5), ('max_outstanding', 0)])
def test_bad_parameters_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        LinkMonitorParams(**{field: value})


def test_constant_latency_above_the_limit_degrades_after_window_and_confirmation():
    """rtt 0.15 s (0.15 s uplink, as fault_mavlink_latency): one-way estimate 75 ms > 60 ms.
    Replies to requests sent at 0, 0.1, 0.2, 0.3 arrive at 0.15..0.45: the window is full at
    0.45 (exceedance starts), confirmed 0.2 s later, at the reply arriving at 0.65 s."""
    mon = LinkMonitor()
    seen = drive(mon, lambda t: 0.15, 2.0)
    assert mon.degraded
    assert mon.latency_s == pytest.approx(0.075)
    assert mon.degraded_since_s == pytest.approx(0.65, abs=1e-9)
    assert seen[0] == pytest.approx(0.65, abs=1e-9)
    assert '75 ms > 60 ms' in mon.reason


def test_latency_below_the_limit_with_jitter_and_spikes_never_degrades():
    """Queueing jitter only adds delay: a 40 ms one-way link (rtt 80 ms) with exponential
    jitter and 5 % spikes of 0.4 s stays healthy (min-of-window estimate)."""
    rng = random.Random(7)

    def rtt(_t: float) -> float:
        spike = 0.4 if rng.random() < 0.05 else 0.0
        return 0.08 + rng.expovariate(1 / 0.01) + spike

    mon = LinkMonitor()
    assert drive(mon, rtt, 120.0) == []
    assert 0.04 <= mon.latency_s < 0.06
    assert mon.counters['replies'] > 1100


def test_packet_loss_is_not_latency():
    """50 % of the requests lost, no latency: never degraded (a lost request yields no
    sample; the autopilot's COM_OF_LOSS_T handles a dead link)."""
    rng = random.Random(3)
    mon = LinkMonitor()
    assert drive(mon, lambda t: None if rng.random() < 0.5 else 0.002, 60.0) == []
    assert 0.4 < mon.counters['replies'] / mon.counters['requests'] < 0.6


def test_latency_onset_mid_flight_is_detected_within_rtt_window_and_confirmation():
    mon = LinkMonitor()
    seen = drive(mon, lambda t: 0.01 if t < 5.0 else 0.2, 10.0)
    p = mon.params
    bound = 5.0 + 0.2 + (p.window - 1) * p.period_s + p.confirm_s + p.period_s + 0.01
    assert 5.0 < seen[0] <= bound


def test_degradation_latches_until_reset():
    mon = LinkMonitor()
    seen = drive(mon, lambda t: 0.3 if t < 2.0 else 0.0, 6.0)
    assert seen[-1] == pytest.approx(6.0)      # still degraded although the link recovered
    mon.reset()
    assert not mon.degraded and math.isnan(mon.latency_s)
    assert drive(mon, lambda t: 0.0, 1.0) == []


def test_bad_replies_are_rejected_and_change_nothing():
    mon = LinkMonitor()
    assert mon.poll(0.0) and not mon.poll(0.05) and mon.poll(0.1) and mon.poll(0.2)
    assert mon.on_timesync(0.0, 0.25)
    lat, rtt = mon.latency_s, mon.rtt_s
    assert not mon.on_timesync(math.nan, 0.3)
    assert not mon.on_timesync(0.1, math.inf)
    assert not mon.on_timesync(0.1, 0.24)          # received before the last reply
    assert not mon.on_timesync(0.15, 0.3)          # never requested (or forged)
    assert not mon.on_timesync(0.0, 0.3)           # answered already
    assert mon.latency_s == lat and mon.rtt_s == rtt and not mon.degraded
    assert mon.rejected == {'nan': 2, 'out_of_order': 1, 'unknown_request': 2,
                            'negative_rtt': 0}
    assert not mon.poll(math.nan)
    assert mon.rejected['nan'] == 3
    assert mon.on_timesync(0.1, 0.3)               # the good ones still count
    assert mon.counters['replies'] == 2


def test_negative_round_trip_is_rejected():
    mon = LinkMonitor()
    mon.poll(1.0)
    assert not mon.on_timesync(1.0, 0.9)
    assert mon.rejected['negative_rtt'] == 1 and math.isnan(mon.latency_s)


# --- BridgeCore ---------------------------------------------------------------------------

def linked_core() -> BridgeCore:
    """A core linked to a PX4 in OFFBOARD that has read a safe set-up (Land, 1 s, 0.5)."""
    core = BridgeCore(BridgeParams())
    core.on_heartbeat(0.0, 1, 1, 2, 12, 128, px4_custom_mode(6))
    core.on_param_value('COM_OBL_RC_ACT', 4.0, 9)
    core.on_param_value('COM_OF_LOSS_T', 1.0, 9)
    core.on_param_value('MPC_THR_HOVER', 0.5, 9)
    return core


def test_core_sends_timesync_requests_at_the_period_while_the_link_is_up():
    core = linked_core()
    sent = [t / 100 for t in range(100)
            if any(o.kind == 'timesync' for o in core.step(t / 100))]
    assert len(sent) == 10
    assert all(b - a == pytest.approx(0.1) for a, b in itertools.pairwise(sent))
    ts = next(o for o in core.step(1.0) if o.kind == 'timesync')
    assert ts.params[0] == 1.0 and ts.command == 0


def test_core_stops_streaming_on_a_slow_link_and_the_operator_can_reset():
    core = linked_core()
    t = 0.0
    sent = 0
    for k in range(200):
        t = k * 0.01
        for o in core.step(t):
            if o.kind == 'timesync':
                # the autopilot's reply comes back 0.2 s later (tc1 = its clock, ts1 echoed)
                core.on_timesync(t + 0.2, 123, round(t * 1e9))
        core.on_heartbeat(t, 1, 1, 2, 12, 128, px4_custom_mode(6))
        core.on_attitude_euler(t, t, 0.0, 0.0, 0.0)
        sent += core.on_thrust_command(t, t, 26.6) is not None
    assert core.link_monitor.degraded
    assert 'latency' in core.last_result
    assert core.on_thrust_command(t + 0.01, t + 0.01, 26.6) is None
    assert core.counters['link_degraded'] > 0
    assert 50 < sent < 100   # streamed until the detection, not after it
    ok, _ = core.request_offboard(t + 0.02)
    assert ok and not core.link_monitor.degraded
    core.on_attitude_euler(t + 0.03, t + 0.03, 0.0, 0.0, 0.0)
    assert core.on_thrust_command(t + 0.03, t + 0.03, 26.6) is not None


def test_core_ignores_timesync_requests_from_the_autopilot():
    core = linked_core()
    core.step(0.0)
    assert not core.on_timesync(0.1, 0, 0)          # tc1 == 0: a request, not a reply
    assert not core.on_timesync(0.1, 5, 'x')        # type: ignore[arg-type]
    assert core.link_monitor.counters['replies'] == 0


