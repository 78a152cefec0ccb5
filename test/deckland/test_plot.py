"""deckland plot: time-series extraction from a synthetic bag / CSV against known signals,
the figures written as valid PNGs, missing topics, and the error paths."""

import json
import math
from pathlib import Path
import random
import struct

from deckland.batch.runner import TRACE_FIELDS, RunConfig, run_landing
from deckland.ros import bag
from deckland_common.contract import ApronState, VerticalState
from deckland_common.frames import euler_to_quaternion, rot_body_to_world
from deckland_common.messages import fill_apron_state
from geometry_msgs.msg import WrenchStamped
from nav_msgs.msg import Odometry
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Range
from std_msgs.msg import String

from deckland import cli, plot
from deckland_interfaces.msg import AltitudeState
from deckland_interfaces.msg import ApronState as ApronStateMsg

# ----------------------------------------------------------------------- the synthetic landing
# Time τ is seconds from the trigger; the bag starts 2 s before it (planner IDLE -> APPROACH).
T_TRIGGER_S = 1_700_000_100.0           # absolute recorder time of the trigger
YAW = math.pi / 2                        # nose north
HEAVE_A_M, HEAVE_T_S, DECK_MEAN_M = 0.3, 6.0, 1.0
TOUCHDOWN_S = 9.5                        # sim/outcome time_to_land_s
LANDED_S = 10.0                          # planner mode LANDED


def deck_z(tau):
    """Sine heave of the pad top."""
    return DECK_MEAN_M + HEAVE_A_M * math.sin(2 * math.pi * tau / HEAVE_T_S)


def deck_vz(tau):
    return HEAVE_A_M * 2 * math.pi / HEAVE_T_S * math.cos(2 * math.pi * tau / HEAVE_T_S)


def vehicle_xyz(tau):
    """Ramp descent from 5 m at 0.3 m/s while flying east at 0.5 m/s."""
    return 0.5 * tau, 0.0, 5.0 - 0.3 * tau


VEHICLE_V = (0.5, 0.0, -0.3)


def beacon_xy(tau):
    """Beacon drifting east at 0.1 m/s, 1 m south of the vehicle's track."""
    return 2.0 + 0.1 * tau, -1.0


BEACON_V = (0.1, 0.0)


def expected_rel_body(tau):
    """Beacon minus vehicle in the heading frame, worked by hand for yaw = +90° (nose north):
    forward = north, left = west. The beacon is 1 m south (behind: x_B = -1) and
    2 - 0.4 τ m east (to the right: y_B = -(2 - 0.4 τ)). Relative velocity east -0.4 m/s ->
    left +0.4 m/s."""
    return -1.0, -(2.0 - 0.4 * tau), 0.0, 0.4


def ns(tau):
    return round((T_TRIGGER_S + tau) * 1e9)


def stamp(msg, tau):
    t = T_TRIGGER_S + tau
    msg.header.stamp.sec = int(t)
    msg.header.stamp.nanosec = round((t - int(t)) * 1e9) % 1_000_000_000
    return msg


def odom(tau, xyz, quat=(1.0, 0.0, 0.0, 0.0), twist=(0.0, 0.0, 0.0)):
    m = stamp(Odometry(), tau)
    p = m.pose.pose.position
    p.x, p.y, p.z = xyz
    q = m.pose.pose.orientation
    q.w, q.x, q.y, q.z = quat
    lin = m.twist.twist.linear
    lin.x, lin.y, lin.z = twist
    return m


def apron_state(tau, tracked, visible, rel_body, height, surface, valid=True):
    v = VerticalState(valid, height, 0.0, height + surface, 0.0, surface, 0.0, 0.0, 0, 0.0)
    z = (0.0, 0.0)
    s = ApronState(T_TRIGGER_S + tau, tracked, visible, 0.0, z, z, z, rel_body[:2],
                   rel_body[2:], z, z, v)
    return fill_apron_state(ApronStateMsg(), s, 'map')


def make_bag(path, topics=None, outcome=True, extra=None):
    """Write the synthetic landing (τ from -2 to 12 s) with BagWriter; ``topics`` limits it."""
    writer = bag.BagWriter(path)
    msgs = []   # (tau, topic, type, msg)

    def put(tau, topic, msgtype, msg):
        if topics is None or topic in topics:
            msgs.append((tau, topic, msgtype, msg))

    for tau, mode in ((-2.0, 'IDLE'), (0.0, 'APPROACH'), (5.0, 'DESCEND'), (LANDED_S, 'LANDED')):
        put(tau, '/planner/mode', 'std_msgs/msg/String', String(data=mode))
    quat = euler_to_quaternion(0.0, 0.0, YAW)
    r = rot_body_to_world(0.0, 0.0, YAW)
    v_body = tuple(sum(r[i][j] * VEHICLE_V[i] for i in range(3)) for j in range(3))  # Rᵀ v
    for k in range(-100, 601):            # 50 Hz truth and 50 Hz everything else
        tau = k * 0.02
        x, y, z = vehicle_xyz(tau)
        bx, by = beacon_xy(tau)
        put(tau, '/sim/truth/vehicle', 'nav_msgs/msg/Odometry', odom(tau, (x, y, z), quat, v_body))
        put(tau, '/sim/truth/apron', 'nav_msgs/msg/Odometry',
            odom(tau, (bx, by, deck_z(tau)), twist=(*BEACON_V, deck_vz(tau))))
        put(tau, '/vehicle/odom', 'nav_msgs/msg/Odometry', odom(tau, (x + 0.05, y, z), quat))
        rng = math.inf if k % 10 == 0 else z - deck_z(tau)       # a lost return every 0.2 s
        put(tau, '/vehicle/range', 'sensor_msgs/msg/Range', stamp(Range(range=rng), tau))
        tracked = tau >= 3.0
        put(tau, '/apron/state', 'deckland_interfaces/msg/ApronState',
            apron_state(tau, tracked, tracked and k % 5 != 0, expected_rel_body(tau),
                        z - deck_z(tau), deck_z(tau)))
        ov = stamp(AltitudeState(), tau)
        ov.sigma, ov.d_hat_mps2 = math.exp(-tau) if tau >= 0 else 1.0, 0.1
        put(tau, '/altitude/state', 'deckland_interfaces/msg/AltitudeState', ov)
        w = stamp(WrenchStamped(), tau)
        w.wrench.force.z = 15.0 + math.sin(tau)
        put(tau, '/control/thrust', 'geometry_msgs/msg/WrenchStamped', w)
        put(tau, '/apron/odom', 'nav_msgs/msg/Odometry', odom(tau, (bx + 0.1, by, 0.0)))
    if outcome:
        put(TOUCHDOWN_S + 0.1, '/sim/outcome', 'std_msgs/msg/String',
            String(data=json.dumps({'time_to_land_s': TOUCHDOWN_S, 'success': True})))
    for item in extra or ():
        msgs.append(item)
    for _, topic, msgtype, _ in msgs:
        writer.add_topic(topic, msgtype, [])
    for tau, topic, _, msg in sorted(msgs, key=lambda m: m[0]):
        writer.write(topic, ns(tau), serialize_message(msg))
    writer.close()
    return Path(path)


@pytest.fixture(scope='module')
def full_bag(tmp_path_factory):
    return make_bag(tmp_path_factory.mktemp('bags') / 'landing')


@pytest.fixture(scope='module')
def full_series(full_bag):
    return plot.series_from_bag(full_bag)


def png_size(path):
    """(width, height) from the PNG signature and IHDR chunk; fails on anything else."""
    data = Path(path).read_bytes()
    assert data[:8] == b'\x89PNG\r\n\x1a\n', f'{path} is not a PNG'
    assert data[12:16] == b'IHDR'
    assert data[-8:-4] == b'IEND'
    return struct.unpack('>II', data[16:24])


def near(a, b, tol=1e-6):
    return abs(a - b) <= tol


# ------------------------------------------------------------------------------- extraction

def test_time_origin_is_the_first_landing_mode(full_series):
    s = full_series
    assert near(s.trigger_s, T_TRIGGER_S, 1e-6)
    assert s.trigger_source == 'planner mode APPROACH'
    assert [m for _, m in s.modes] == ['IDLE', 'APPROACH', 'DESCEND', 'LANDED']
    assert near(s.modes[0][0], -2.0) and near(s.modes[1][0], 0.0)
    t, _ = s.get('z_true')
    assert near(t[0], -2.0) and near(t[-1], 12.0)


def test_vehicle_and_deck_truth_match_the_signals(full_series):
    s = full_series
    for name, fn in (('x_true', lambda tau: vehicle_xyz(tau)[0]),
                     ('z_true', lambda tau: vehicle_xyz(tau)[2]),
                     ('x', lambda tau: vehicle_xyz(tau)[0] + 0.05),
                     ('deck_z_true', deck_z),
                     ('apron_x_true', lambda tau: beacon_xy(tau)[0]),
                     ('apron_x', lambda tau: beacon_xy(tau)[0] + 0.1)):
        t, v = s.get(name)
        assert len(t) == 701, name
        assert max(abs(vi - fn(ti)) for ti, vi in zip(t, v, strict=True)) < 1e-6, name
    # the heave is a sine of the right amplitude and period: peak at τ = T/4
    assert near(s.value_at('deck_z_true', HEAVE_T_S / 4), DECK_MEAN_M + HEAVE_A_M, 1e-6)
    assert near(s.value_at('deck_z_true', 3 * HEAVE_T_S / 4), DECK_MEAN_M - HEAVE_A_M, 1e-6)


def test_relative_truth_in_the_heading_frame(full_series):
    """Figure 8 truth: beacon minus vehicle rotated by the true yaw; the velocity from the
    body-frame twist of sim/truth/vehicle (REP-105) and the map-frame apron twist."""
    s = full_series
    for k, name in enumerate(('rel_x_body_true', 'rel_y_body_true', 'rel_vx_body_true',
                              'rel_vy_body_true')):
        t, v = s.get(name)
        assert len(t) == 701
        err = max(abs(vi - expected_rel_body(ti)[k]) for ti, vi in zip(t, v, strict=True))
        assert err < 1e-6, (name, err)


def test_estimate_series_from_apron_state(full_series):
    s = full_series
    t, v = s.get('rel_y_body')
    for ti, vi in zip(t, v, strict=True):
        if ti < 3.0 - 1e-9:
            assert math.isnan(vi)            # untracked -> a gap
        else:
            assert near(vi, expected_rel_body(ti)[1], 1e-9)
    t, v = s.get('visible')
    assert sum(v) == sum(1 for k in range(150, 601) if k % 5 != 0)
    t, v = s.get('surface_z_est')
    assert max(abs(vi - deck_z(ti)) for ti, vi in zip(t, v, strict=True)) < 1e-9


def test_range_gaps_and_control_signals(full_series):
    s = full_series
    t, v = s.get('range')
    assert len(t) == 701
    assert sum(math.isnan(x) for x in v) == 71          # +inf (no return) -> NaN gap
    for ti, vi in zip(t, v, strict=True):
        if not math.isnan(vi):
            assert near(vi, vehicle_xyz(ti)[2] - deck_z(ti), 1e-5)   # float32 range
    assert near(s.value_at('sigma', 2.0), math.exp(-2.0), 1e-9)
    assert near(s.value_at('thrust', 1.0), 15.0 + math.sin(1.0), 1e-9)


def test_touchdown_from_outcome_else_landed_mode(full_series, tmp_path):
    assert full_series.touchdown_s == TOUCHDOWN_S
    assert full_series.touchdown_source == 'sim/outcome time_to_land_s'
    s = plot.series_from_bag(make_bag(tmp_path / 'b', outcome=False))
    assert near(s.touchdown_s, LANDED_S) and s.touchdown_source == 'planner mode LANDED'


def test_header_time_source(tmp_path):
    """Header stamps 0.25 s later than the log time shift only the headered topics."""
    path = tmp_path / 'hdr'
    writer = bag.BagWriter(path)
    writer.add_topic('/planner/mode', 'std_msgs/msg/String', [])
    writer.add_topic('/control/thrust', 'geometry_msgs/msg/WrenchStamped', [])
    writer.write('/planner/mode', ns(0.0), serialize_message(String(data='APPROACH')))
    for k in range(10):
        w = stamp(WrenchStamped(), k * 0.1 + 0.25)
        w.wrench.force.z = float(k)
        writer.write('/control/thrust', ns(k * 0.1), serialize_message(w))
    writer.close()
    log = plot.series_from_bag(path)
    hdr = plot.series_from_bag(path, time_source='header')
    assert near(log.get('thrust')[0][3], 0.3, 1e-6)
    assert near(hdr.get('thrust')[0][3], 0.55, 1e-6)
    with pytest.raises(ValueError, match='time_source'):
        plot.series_from_bag(path, time_source='wall')


def test_bad_messages_are_counted_not_plotted(tmp_path):
    bad_state = apron_state(1.0, True, True, (0.0, 0.0, 0.0, 0.0), 1.0, 0.0)
    bad_state.vertical.height_m = math.nan                       # NaN in a decoded field
    nan_odom = odom(1.0, (math.nan, 0.0, 1.0))
    path = make_bag(tmp_path / 'bad', topics={'/planner/mode', '/vehicle/odom'}, extra=[
        (1.01, '/apron/state', 'deckland_interfaces/msg/ApronState', bad_state),
        (1.01, '/sim/truth/vehicle', 'nav_msgs/msg/Odometry', nan_odom),
        (1.02, '/sim/outcome', 'std_msgs/msg/String', String(data='{not json'))])
    s = plot.series_from_bag(path)
    assert s.rejected == {'nan': 2, 'bad_outcome': 1}
    assert s.get('visible') is None and s.get('x_true') is None
    assert all(math.isfinite(v) for v in s.get('x')[1])


def test_wrong_type_on_a_known_topic_is_ignored(tmp_path):
    path = make_bag(tmp_path / 'wt', topics={'/planner/mode'}, extra=[
        (0.5, '/control/thrust', 'std_msgs/msg/String', String(data='12.0'))])
    s = plot.series_from_bag(path)
    assert s.rejected == {'wrong_type': 1} and s.get('thrust') is None


def test_resolve_topics_namespace_and_suffix():
    r = plot.resolve_topics(['/uav1/vehicle/odom', '/uav1/planner/mode', '/other'])
    assert r == {'vehicle/odom': '/uav1/vehicle/odom', 'planner/mode': '/uav1/planner/mode'}
    two = ['/uav1/vehicle/odom', '/uav2/vehicle/odom']
    assert plot.resolve_topics(two) == {}                       # ambiguous: left out
    assert plot.resolve_topics(two, '/uav2') == {'vehicle/odom': '/uav2/vehicle/odom'}
    assert plot.resolve_topics(['/vehicle/odom', '/x/vehicle/odom']) == {
        'vehicle/odom': '/vehicle/odom'}


# --------------------------------------------------------------------------------- the CLI

def test_plot_command_writes_the_figures(full_bag, tmp_path, capsys):
    out = tmp_path / 'fig'
    assert cli_main(['plot', str(full_bag), '--out', str(out)]) == 0
    sizes = {}
    for name in plot.FIGURE_FILES:
        w, h = png_size(out / name)
        sizes[name] = (w, h)
        assert 600 <= w <= 2000 and 300 <= h <= 1500, (name, w, h)
        assert (out / name).stat().st_size > 15_000          # drawn lines, not a blank page
    assert sizes['figure7.png'] == (1210, 770)               # 11 x 7 in at 110 dpi
    assert plot.empty_panels(plot.series_from_bag(full_bag)) == []
    assert 'time origin: planner mode APPROACH' in capsys.readouterr().err


def test_missing_topics_give_no_data_panels(tmp_path, capsys):
    path = make_bag(tmp_path / 'partial', topics={'/vehicle/odom'}, outcome=False)
    s = plot.series_from_bag(path)
    assert s.trigger_source.startswith('start of data')
    assert near(s.get('x')[0][0], 0.0)                         # origin = first sample
    assert set(plot.empty_panels(s)) == {'7d', '8a', '8b', '8c', '8d', '9a', '9b'}
    out = tmp_path / 'fig'
    assert cli_main(['plot', str(path), '--out', str(out)]) == 0
    for name in plot.FIGURE_FILES:
        png_size(out / name)
    assert 'panels without data: 7d, 8a' in capsys.readouterr().err


def test_no_known_topic_is_an_error(tmp_path, capsys):
    path = tmp_path / 'foreign'
    writer = bag.BagWriter(path)
    writer.add_topic('/chatter', 'std_msgs/msg/String', [])
    writer.write('/chatter', ns(0.0), serialize_message(String(data='hi')))
    writer.close()
    out = tmp_path / 'fig'
    assert cli_main(['plot', str(path), '--out', str(out)]) == 1
    err = capsys.readouterr().err
    assert 'none of the known topics' in err and '/chatter' in err
    assert not out.exists()
    assert cli_main(['plot', str(tmp_path / 'nope'), '--out', str(out)]) == 1
    assert cli_main(['plot', '--out', str(out)]) == 2                    # no source
    assert cli_main(['plot', str(path), '--trace', 'x.csv', '--out', str(out)]) == 2


def cli_main(argv):
    """``deckland plot`` through the real top-level parser (plot registered as the integrator
    will, without editing cli.py)."""
    import argparse

    if 'deckland.plot' in cli.TOOL_MODULES:
        return cli.main(argv)
    parser = argparse.ArgumentParser(prog='deckland')
    sub = parser.add_subparsers(dest='command')
    plot.register(sub)
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


# ------------------------------------------------------------------------------ CSV / trace

def write_csv(path, rows):
    """The format of ``deckland sim --csv`` (header of TRACE_FIELDS, '.5g' values)."""
    with open(path, 'w') as fh:
        fh.write(','.join(TRACE_FIELDS) + '\n')
        for row in rows:
            fh.write(','.join(f'{row[k]:.5g}' for k in TRACE_FIELDS) + '\n')


def synthetic_rows():
    """100 Hz; hovering (IDLE index 0) for 1 s, APPROACH (index 2) from t = 1, never LANDED;
    the truth height reaches the gear at τ = 7.005."""
    rng = random.Random(7)
    rows = []
    for k in range(0, 1001):
        t = k * 0.01
        tau = t - 1.0
        h = max(0.15, 0.15 + 0.5 * (7.005 - tau)) if tau > 0 else 3.65
        rows.append(dict.fromkeys(TRACE_FIELDS, 0.0) | {
            't': t, 'z_true': deck_z(tau) + h, 'z': deck_z(tau) + h + rng.gauss(0, 0.01),
            'deck_z': deck_z(tau), 'height_true': h, 'height_est': h,
            'sigma': math.exp(-max(tau, 0.0)), 'thrust': 14.0, 'tracked': float(tau > 2.0),
            'visible': float(tau > 2.0), 'rel_x_body': 0.3, 'rel_x_body_true': 0.31,
            'mode': 0.0 if tau < 0 else 2.0})
    return rows


def test_csv_trace_series_and_figures(tmp_path):
    path = tmp_path / 'run.csv'
    write_csv(path, synthetic_rows())
    s = plot.series_from_csv(path)
    assert near(s.trigger_s, 1.0) and s.trigger_source == 'planner mode APPROACH'
    t, v = s.get('deck_z_true')
    assert near(t[0], -1.0) and near(t[-1], 9.0)
    assert max(abs(vi - deck_z(ti)) for ti, vi in zip(t, v, strict=True)) < 1e-4   # .5g
    assert near(s.value_at('sigma', 1.5), math.exp(-1.5), 1e-4)
    # untracked estimate -> gap; no LANDED mode -> touchdown from the truth height
    t, v = s.get('rel_x_body')
    assert all(math.isnan(x) for ti, x in zip(t, v, strict=True) if ti <= 2.0)
    assert near(s.touchdown_s, 7.01, 1e-6)     # h <= 0.151 m from τ = 7.003: next sample
    assert s.touchdown_source.startswith('truth height')
    # what the runner's trace lacks is "no data", not zeros
    assert {'7a', '7b'}.isdisjoint(plot.empty_panels(s))
    assert s.get('apron_x') is None and s.get('rel_vx_body_true') is None
    out = tmp_path / 'fig'
    assert cli_main(['plot', '--trace', str(path), '--out', str(out)]) == 0
    for name in plot.FIGURE_FILES:
        png_size(out / name)


def test_csv_errors(tmp_path):
    empty = tmp_path / 'empty.csv'
    empty.write_text('')
    with pytest.raises(plot.PlotError, match='empty'):
        plot.series_from_csv(empty)
    foreign = tmp_path / 'foreign.csv'
    foreign.write_text('t,foo\n0,1\n')
    with pytest.raises(plot.PlotError, match='known columns'):
        plot.series_from_csv(foreign)
    ragged = tmp_path / 'ragged.csv'
    ragged.write_text('t,z\n0,1\n1\n')
    with pytest.raises(plot.PlotError, match='fields'):
        plot.series_from_csv(ragged)
    assert cli_main(['plot', '--trace', str(tmp_path / 'missing.csv'),
                     '--out', str(tmp_path / 'o')]) == 1


def test_in_process_run_trace():
    """A real seeded landing of the paper scenario: the trigger is t = 0 of the run, the
    touchdown is LANDED, the deck truth is the scenario's heave and σ is recorded."""
    result = run_landing(_paper(), 3, RunConfig(record=True))
    assert result.contact_kind != 'none', result.reason
    s = plot.series_from_trace(result.trace, 'run')
    assert s.trigger_s == 0.0 and s.trigger_source.startswith('planner mode')
    # the trace's truth height crosses gear height later than the world's first contact: the
    # lowest foot of a slightly tilted body touches first (1 deg over the 0.2 m arm: ~3.5 mm, at
    # the final descent's few cm/s about 0.1 s), plus the 100 Hz trace period
    assert s.touchdown_source.startswith('truth height')
    assert -0.006 <= s.touchdown_s - result.time_to_land_s <= 0.15, (
        s.touchdown_s, result.time_to_land_s)
    # the planner's LANDED (if the run reached it) comes no earlier than the contact
    landed = [t for t, m in s.modes if m == 'LANDED']
    assert not landed or landed[0] >= s.touchdown_s - 1e-9
    t, v = s.get('deck_z_true')
    assert len(t) == len(result.trace['t'])
    assert max(v) > min(v)                                     # the deck heaves
    assert s.get('sigma') is not None and s.get('thrust') is not None


def _paper():
    from deck_simulator.scenario import load_scenario

    return load_scenario('paper')
