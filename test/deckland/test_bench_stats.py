"""deckland bench: the pure parts (percentiles, /proc parsing, MAVLink parsing, stamp chain)."""

import math
import os
import random

from deckland.graph.bench import (
    LOOP_PERIOD_S,
    build_report,
    cpu_percent,
    format_table,
    iter_mavlink_frames,
    loop_jitter,
    match_chain,
    parse_proc_stat,
    read_cpu_ticks,
    set_attitude_target_boot_ms,
    stamp_ms,
    summarize_ms,
)
import pytest


def test_summarize_converts_to_ms_and_is_strict_json_when_empty():
    s = summarize_ms([0.001, 0.002, 0.003])
    assert s['p50'] == pytest.approx(2.0) and s['max'] == pytest.approx(3.0) and s['n'] == 3
    assert summarize_ms([]) == {'p50': None, 'p99': None, 'max': None, 'n': 0}


# --- loop jitter ------------------------------------------------------------------------------

def test_jitter_is_the_lateness_against_the_period_and_gaps_are_counted():
    t, arrivals = 100.0, []
    for dt in [0.010] * 50 + [0.012, 0.008, 0.020, 0.5, 0.010, 0.001, 0.009]:
        t += dt
        arrivals.append(t)
    rng = random.Random(3)
    rng.shuffle(arrivals)                         # arrival order is restored by sorting
    jit, gaps = loop_jitter(arrivals, LOOP_PERIOD_S, max_gap_s=0.1)
    assert gaps == 1                              # the 0.5 s stream interruption
    assert len(jit) == len(arrivals) - 2
    # late: 12 ms → 2 ms, 20 ms → 10 ms; early (8 ms, and a 1 ms extra setpoint of the same
    # instant) is not jitter
    assert sorted(jit)[-2:] == pytest.approx([0.002, 0.010], abs=1e-9)
    assert sum(1 for j in jit if j < 1e-9) == len(jit) - 2


# --- /proc ------------------------------------------------------------------------------------

def test_proc_stat_parsing_survives_spaces_and_parentheses_in_comm():
    fields = ['S', '1', '2', '3', '0', '-1', '4194560', '10', '0', '0', '0', '1234', '567',
              '0', '0', '20', '0', '3', '0', '99']
    text = '4242 (weird) name (x)) ' + ' '.join(fields) + '\n'
    assert parse_proc_stat(text) == (1234, 567)
    with pytest.raises(ValueError):
        parse_proc_stat('4242 no parenthesis 1 2 3')
    with pytest.raises(ValueError):
        parse_proc_stat('4242 (short) S 1 2')


def test_cpu_ticks_of_this_process_grow_with_work_and_percent_formula():
    clk = os.sysconf('SC_CLK_TCK')
    t0 = read_cpu_ticks(os.getpid())
    x = 0
    end = os.times().elapsed + 0.3
    while os.times().elapsed < end:     # burn CPU; ticks can only grow
        x += 1
    t1 = read_cpu_ticks(os.getpid())
    assert t0 is not None and t1 is not None and t1 > t0
    assert read_cpu_ticks(2 ** 22 + 12345) is None        # no such process
    assert cpu_percent(100, 150, 1.0, 100) == pytest.approx(50.0)
    assert cpu_percent(100, 300, 2.0, 100) == pytest.approx(100.0)  # one full core
    assert cpu_percent(None, 300, 2.0, clk) is None


# --- MAVLink on the wire ------------------------------------------------------------------------

def _mav(version: int):
    os.environ['MAVLINK20'] = '1'
    from pymavlink.dialects.v10 import common as v1
    from pymavlink.dialects.v20 import common as v2
    mod = v2 if version == 2 else v1
    return mod, mod.MAVLink(None, srcSystem=1, srcComponent=191)


@pytest.mark.parametrize('version', [1, 2])
def test_set_attitude_target_time_boot_ms_from_real_pymavlink_frames(version):
    _mod, m = _mav(version)
    buf = b'\x00\x13garbage'
    buf += m.heartbeat_encode(18, 8, 0, 0, 4).pack(m)
    values = [0, 1, 255, 65536, 0xFFFFFFFF, stamp_ms(1795304375.598213)]
    for v in values:
        buf += m.set_attitude_target_encode(v, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                            0.5).pack(m)
    assert set_attitude_target_boot_ms(buf) == values
    ids = [mid for mid, _ in iter_mavlink_frames(buf)]
    assert ids == [0] + [82] * len(values)
    # a truncated last frame is not reported
    assert set_attitude_target_boot_ms(buf[:-3]) == values[:-1]


def test_stamp_ms_wraps_modulo_2_32():
    t = 1795304375.598213       # ROS wall-clock stamps are ~1.8e12 ms, above 2**32
    assert stamp_ms(t) == round(t * 1000.0) % 2 ** 32
    assert 0 <= stamp_ms(t) < 2 ** 32


# --- the stamp chain ------------------------------------------------------------------------

def _synthetic_pipeline(seed=11, n_states=400, t0=1795304000.0):
    """Frames at 50 Hz, apron states at 100 Hz carrying the latest frame that had arrived,
    one setpoint per state after a known control delay. Returns the inputs and the truth."""
    rng = random.Random(seed)
    frames = [t0 + 0.02 * i + rng.uniform(0.0, 0.001) for i in range(n_states // 2 + 2)]
    cam_delay = 0.020                                    # exposure -> driver publication
    states, setpoints, truth_first = [], [], {}
    for k in range(n_states):
        t_s = t0 + 0.005 + 0.01 * k + rng.uniform(0.0, 0.002)
        seen = [f for f in frames if f + cam_delay <= t_s]
        cam = seen[-1] if seen else -math.inf
        states.append((t_s, cam))
        arrival = t_s + rng.uniform(0.001, 0.009)
        setpoints.append((arrival, stamp_ms(t_s)))
        if seen and cam not in truth_first:
            truth_first[cam] = arrival - cam
    return frames, states, setpoints, truth_first


def test_chain_recovers_first_use_latency_of_every_frame():
    frames, states, setpoints, truth = _synthetic_pipeline()
    rng = random.Random(5)
    shuffled = list(setpoints)
    rng.shuffle(shuffled)
    m = match_chain(shuffled, states, frames)
    assert m.counts['setpoints'] == len(setpoints)
    assert m.counts['no_camera_yet'] >= 1             # states before the first frame arrived
    assert m.counts['no_apron_state'] == 0 and m.counts['frame_not_seen'] == 0
    assert m.first_use_latency_s == pytest.approx([truth[f] for f in sorted(truth)], abs=1e-9)
    # every latency contains the 20 ms camera delay, and data age >= first-use latency
    assert min(m.first_use_latency_s) >= 0.020
    assert min(m.data_age_s) >= min(m.first_use_latency_s) - 1e-12
    for (to_state, to_mav), lat in zip(m.stages_s, m.first_use_latency_s, strict=True):
        assert to_state + to_mav == pytest.approx(lat, abs=1e-9)
        assert 0.001 <= to_mav <= 0.009 + 1e-9


def test_chain_counts_what_it_cannot_match_and_tolerates_1ms_rounding():
    frames, states, setpoints, _ = _synthetic_pipeline(n_states=60)
    last_arrival, last_ms = setpoints[-1]
    bad = [(last_arrival + 0.01, (last_ms + 5) & 0xFFFFFFFF),      # no such apron state
           (last_arrival + 0.02, (last_ms + 1) & 0xFFFFFFFF)]      # a 1 ms rounding difference
    m = match_chain(setpoints + bad, states, frames)
    assert m.counts['no_apron_state'] == 1
    assert m.counts['matched'] == len(setpoints) + 1 - m.counts['no_camera_yet']
    # an apron state pointing at a frame the bench never saw
    states2 = [(t, c + 0.0005 if math.isfinite(c) else c) for t, c in states]
    m2 = match_chain(setpoints, states2, frames)
    assert m2.counts['matched'] == 0 and m2.counts['frame_not_seen'] > 0
    assert m2.first_use_latency_s == []


def test_chain_window_excludes_setpoints_and_frames_outside_it():
    frames, states, setpoints, _ = _synthetic_pipeline()
    lo, hi = frames[50], frames[150]
    m = match_chain(setpoints, states, frames, (lo, hi))
    assert any(not lo <= a <= hi for a, _ in setpoints)   # the window does cut
    assert m.counts['setpoints'] == sum(1 for a, _ in setpoints if lo <= a <= hi)
    assert m.counts['before_window_frame'] >= 1
    assert len(m.first_use_latency_s) <= m.counts['frames_in_window']


# --- the report -------------------------------------------------------------------------------

def test_report_keys_totals_and_targets():
    frames, states, setpoints, _ = _synthetic_pipeline()
    m = match_chain(setpoints, states, frames)
    jit, gaps = loop_jitter([a for a, _ in setpoints])
    cpu = {'deck_simulator': 30.0, 'pixy_driver': 2.0, 'dob_altitude': 10.0, 'ghost': None}
    r = build_report(m, jit, gaps, cpu, 0.02, 4.0)
    assert set(r) >= {'e2e_latency_ms', 'loop_jitter_ms', 'cpu_percent', 'duration_s',
                      'samples'}
    assert set(r['e2e_latency_ms']) >= {'p50', 'p99'}
    assert r['cpu_percent']['total_without_sim'] == pytest.approx(12.0)   # sim excluded
    assert 'ghost' not in r['cpu_percent']
    assert r['samples'] == len(m.first_use_latency_s)
    assert r['stack_latency_ms']['p50'] == pytest.approx(r['e2e_latency_ms']['p50'] - 20.0)
    assert r['targets']['cpu_total_without_sim_percent']['met'] is True
    assert r['targets']['stack_latency_p99_ms']['met'] is (r['stack_latency_ms']['p99'] <= 10.0)
    text = format_table(r)
    assert 'total_without_sim' in text and 'e2e latency' in text
