"""The latency fault ends in the autopilot's failsafe: the simulated TIMESYNC
(World.timesync_rtt_s), the runner's link monitor, and the PX4 emulator's TIMESYNC answer."""

from __future__ import annotations

import dataclasses
import math

from deck_simulator.faults import parse_faults
from deck_simulator.px4_emulator import EmulatorParams, MemoryLink, Px4Emulator
from deck_simulator.scenario import load_scenario
from deck_simulator.world import World
from deckland.batch.runner import RunConfig, run_landing
from mavlink_bridge.core import LinkMonitor
from pymavlink.dialects.v20 import common as mavlink
import pytest

DECK_FAILSAFE = {'loss_timeout_s': 0.3, 'action': 'return', 'land_speed_mps': 0.5,
                 'min_alt_m': 2.0, 'reengage_offboard': False}


def with_faults(*entries: dict):
    return dataclasses.replace(load_scenario('paper'), faults=parse_faults(list(entries)))


# --- World.timesync_rtt_s -----------------------------------------------------------------

def test_timesync_without_link_faults_is_instant():
    w = World(load_scenario('paper'), 1)
    assert w.timesync_rtt_s(0.0) == 0.0 and w.timesync_rtt_s(3.0) == 0.0
    assert w.timesync_rtt_s(math.nan) is None and w.rejected['nan'] == 1


def test_timesync_round_trip_is_the_latency_inside_its_window():
    w = World(with_faults({'type': 'mavlink_latency', 'latency_s': 0.15, 'start_s': 2.0,
                           'end_s': 4.0}), 1)
    assert w.timesync_rtt_s(1.0) == 0.0
    assert w.timesync_rtt_s(2.0) == pytest.approx(0.15)
    assert w.timesync_rtt_s(3.99) == pytest.approx(0.15)
    assert w.timesync_rtt_s(4.0) == 0.0


def test_timesync_queues_behind_commands_still_in_flight():
    """FIFO link: a request sent just after the latency window waits for the delayed
    commands ahead of it (as command_link's queue)."""
    w = World(with_faults({'type': 'mavlink_latency', 'latency_s': 0.3, 'end_s': 1.0}), 1)
    t = 0.0
    while t < 1.0:
        w.command_link(t, 0.0, 0.0, 0.0, 26.0)
        w.step(0.01)
        t = round(t + 0.01, 10)
    # the last command (sent at 0.99 s) is applied at 1.29 s; the window is closed at 1.0 s
    assert w.timesync_rtt_s(1.0) == pytest.approx(0.29, abs=1e-6)
    assert w.timesync_rtt_s(1.5) == 0.0


def test_timesync_is_cut_by_link_loss_but_not_by_a_killed_controller():
    w = World(with_faults({'type': 'mavlink_link_loss', 'start_s': 1.0, 'end_s': 2.0}), 1)
    assert w.timesync_rtt_s(0.5) == 0.0
    assert w.timesync_rtt_s(1.5) is None
    w = World(with_faults({'type': 'node_kill', 'node': 'dob_altitude', 'start_s': 1.0}), 1)
    assert w.timesync_rtt_s(1.5) == 0.0
    w = World(with_faults({'type': 'node_kill', 'node': 'mavlink_bridge', 'start_s': 1.0}), 1)
    assert w.timesync_rtt_s(1.5) is None


def test_timesync_loss_has_its_own_stream_and_never_shifts_the_command_link():
    sc = with_faults({'type': 'mavlink_loss', 'probability': 0.3})
    a, b = World(sc, 5), World(sc, 5)
    got_a, got_b, lost_ts = [], [], 0
    for k in range(2000):
        t = k * 0.01
        got_a.append(a.command_link(t, 0.0, 0.0, 0.0, 26.0))
        lost_ts += b.timesync_rtt_s(t) is None
        got_b.append(b.command_link(t, 0.0, 0.0, 0.0, 26.0))
    assert got_a == got_b
    assert 0.25 < lost_ts / 2000 < 0.35   # binomial sd 0.01


# --- the runner ---------------------------------------------------------------------------

@pytest.mark.parametrize('seed', [100000, 100007])
def test_latency_fault_ends_in_the_autopilot_failsafe_landing(seed):
    """Every command 0.15 s late: the monitor stops the commands (one-way 75 ms > 60 ms)
    after 0.15 + 3 × 0.1 + 0.2 s; COM_OF_LOSS_T later the failsafe holds, returns home
    (the trigger point, clear of the deck) and lands on the ground at 0.5 m/s."""
    r = run_landing(load_scenario('fault_mavlink_latency'), seed)
    assert r.link_degraded_s == pytest.approx(0.65, abs=0.011)
    assert r.link_latency_s == pytest.approx(0.075)
    assert r.failsafes == 1
    assert r.outcome == 'fallback' and not r.crash
    assert r.touchdown_speed_mps == pytest.approx(0.5, abs=0.1)


def test_without_the_monitor_the_latency_fault_is_unsafe():
    """The reason for the monitor (seed 100000 of the documented campaign)."""
    r = run_landing(load_scenario('fault_mavlink_latency'), 100000,
                    RunConfig(link_monitor=None))
    assert r.outcome in ('crash', 'unstable')
    assert r.failsafes == 0


@pytest.mark.xfail(strict=False, reason=(
    'issue 12 world: seed 4 crashed (stale low thrust when the monitor stops the commands, '
    '1.49 m/s); seeds 1-10 crash 3 times on the old world (2, 8, 10) and 5 on the new '
    '(2, 4, 8, 9, 10): the claim holds on neither; for the latency work to settle. With the '
    'honest sensors seed 4 happens not to crash: not strict until the claim is settled'))
def test_latency_onset_low_over_the_deck_still_ends_safely():
    """Latency opening at 0.6 m above the deck: the stop happens mid-descent, the failsafe's
    hold climbs away; no crash."""
    sc = with_faults({'type': 'mavlink_latency', 'latency_s': 0.15, 'trigger_height_m': 0.6,
                      'duration_s': 1000.0, **DECK_FAILSAFE})
    for seed in (3, 4):
        r = run_landing(sc, seed)
        assert r.outcome in ('deck', 'fallback', 'hold'), r.summary()
        if r.failsafes:
            assert not math.isnan(r.link_degraded_s)


def test_tolerable_latency_and_nominal_runs_are_untouched():
    """rtt 0.08 s (one-way 40 ms) never stops the commands, and a nominal run is identical
    with and without the monitor (its TIMESYNC never touches the physics or the noise)."""
    sc = with_faults({'type': 'mavlink_latency', 'latency_s': 0.08, **DECK_FAILSAFE})
    r = run_landing(sc, 11)
    assert math.isnan(r.link_degraded_s) and r.failsafes == 0
    assert r.link_latency_s == pytest.approx(0.04)
    paper = load_scenario('paper')
    on = run_landing(paper, 100001).summary()
    off = run_landing(paper, 100001, RunConfig(link_monitor=None)).summary()
    assert on.pop('link_latency_s') == 0.0
    off.pop('link_latency_s')
    assert on == pytest.approx(off, nan_ok=True) and on['outcome'] == 'deck'


# --- the emulator answers TIMESYNC like PX4 -----------------------------------------------

def test_emulator_answers_timesync_requests_and_the_monitor_measures_the_round_trip():
    link = MemoryLink()
    emu = Px4Emulator(EmulatorParams(), transport=link.a)
    gcs = mavlink.MAVLink(link.b, srcSystem=1, srcComponent=191)
    mon = LinkMonitor()
    delay = 0.15   # the request is held back on the uplink, as ImpairedLink does
    in_flight: list[tuple[float, bytes]] = []
    rx = mavlink.MAVLink(None)
    for k in range(120):
        t = k * 0.01
        if mon.poll(t):
            in_flight.append((t + delay, gcs.timesync_encode(0, round(t * 1e9)).pack(gcs)))
        while in_flight and in_flight[0][0] <= t + 1e-9:
            link.a.inbox.append(in_flight.pop(0)[1])
        emu.update(t)
        for data, _ in link.b.receive():
            for msg in rx.parse_buffer(data) or []:
                if msg.get_type() == 'TIMESYNC':
                    assert msg.tc1 > 0
                    mon.on_timesync(msg.ts1 * 1e-9, t)
    assert emu.counters['timesync_rx'] == mon.counters['replies'] > 5
    assert mon.latency_s == pytest.approx(delay / 2, abs=0.006)
    assert mon.degraded
