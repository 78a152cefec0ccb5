"""``deckland plot``: the paper's Figures 7, 8 and 9 (section 4.2) from a bag or a run's CSV.

More in the package README, "Module notes" (`deckland.plot`).
"""

from __future__ import annotations

import argparse
import bisect
from collections.abc import Iterable, Mapping, Sequence
import csv
from dataclasses import dataclass, field
import itertools
import json
import math
import os
from pathlib import Path
import sys
from typing import Any

from deckland_common.frames import (
    mat_vec,
    quaternion_to_euler,
    rot_body_to_world,
    world_to_body_xy,
)

#: Planner modes that are not a landing (the trigger is the first mode outside this set).
NOT_LANDING_MODES = frozenset({'IDLE', 'HOLD', 'TAKEOFF'})
#: Planner mode names in ``deckland_common.contract.Mode`` order (the runner's ``mode`` column
#: stores the index into ``list(Mode)``).
MODE_NAMES = ('IDLE', 'TAKEOFF', 'APPROACH', 'ALIGN', 'DESCEND', 'FINAL', 'SEARCH',
              'FALLBACK', 'HOLD', 'LANDED')

#: Topics read from a bag (relative names) and their expected message types.
TOPICS: dict[str, str] = {
    'vehicle/odom': 'nav_msgs/msg/Odometry',
    'vehicle/range': 'sensor_msgs/msg/Range',
    'apron/state': 'deckland_interfaces/msg/ApronState',
    'apron/odom': 'nav_msgs/msg/Odometry',
    'altitude/state': 'deckland_interfaces/msg/AltitudeState',
    'control/thrust': 'geometry_msgs/msg/WrenchStamped',
    'planner/mode': 'std_msgs/msg/String',
    'sim/truth/vehicle': 'nav_msgs/msg/Odometry',
    'sim/truth/apron': 'nav_msgs/msg/Odometry',
    'sim/outcome': 'std_msgs/msg/String',
}

#: Every series a :class:`LandingSeries` may hold, with its meaning (README-plot.md table).
SERIES: dict[str, str] = {
    'x': 'vehicle x, ENU [m] (vehicle/odom; CSV x)',
    'y': 'vehicle y, ENU [m]',
    'z': 'vehicle altitude, ENU [m]',
    'x_true': 'vehicle x, simulator truth [m] (sim/truth/vehicle; CSV x_true)',
    'y_true': 'vehicle y, simulator truth [m]',
    'z_true': 'vehicle altitude, simulator truth [m]',
    'apron_x': 'apron x, estimate [m] (apron/odom)',
    'apron_y': 'apron y, estimate [m]',
    'apron_x_true': 'apron (beacon) x, truth [m] (sim/truth/apron)',
    'apron_y_true': 'apron (beacon) y, truth [m]',
    'deck_z_true': 'deck (pad top) height, truth [m] (sim/truth/apron z; CSV deck_z)',
    'range': 'lidar range [m] (vehicle/range; NaN = no return)',
    'height_est': 'height above the surface below, estimate [m] (apron/state; CSV height_est)',
    'height_true': 'height above the surface below, truth [m] (CSV height_true)',
    'surface_z_est': 'surface height z_s, estimate [m] (apron/state; NaN while invalid)',
    'visible': 'beacon detected in the latest frame, 0/1 (apron/state; CSV visible)',
    'tracked': 'horizontal estimate valid, 0/1',
    'rel_x_body': 'apron minus vehicle, heading frame forward [m] (NaN while untracked)',
    'rel_y_body': 'apron minus vehicle, heading frame left [m]',
    'rel_vx_body': 'relative velocity, heading frame forward [m/s]',
    'rel_vy_body': 'relative velocity, heading frame left [m/s]',
    'rel_x_body_true': 'truth of rel_x_body [m]',
    'rel_y_body_true': 'truth of rel_y_body [m]',
    'rel_vx_body_true': 'truth of rel_vx_body [m/s]',
    'rel_vy_body_true': 'truth of rel_vy_body [m/s]',
    'sigma': 'sliding variable σ (14) (altitude/state; CSV sigma)',
    'd_hat': 'disturbance estimate d̂ (18) [m/s²]',
    'thrust': 'collective thrust u_z (16) [N] (control/thrust force.z; CSV thrust)',
    'z_d': 'reference height above the surface [m] (CSV z_d)',
}

#: CSV column -> series name (columns not listed here are ignored).
CSV_COLUMNS: dict[str, str] = {
    'x': 'x', 'y': 'y', 'z': 'z', 'x_true': 'x_true', 'y_true': 'y_true', 'z_true': 'z_true',
    'deck_z': 'deck_z_true', 'height_est': 'height_est', 'height_true': 'height_true',
    'z_d': 'z_d', 'thrust': 'thrust', 'sigma': 'sigma', 'd_hat': 'd_hat',
    'visible': 'visible', 'tracked': 'tracked', 'rel_x_body': 'rel_x_body',
    'rel_y_body': 'rel_y_body', 'rel_vx_body': 'rel_vx_body', 'rel_vy_body': 'rel_vy_body',
    'rel_x_body_true': 'rel_x_body_true', 'rel_y_body_true': 'rel_y_body_true',
    'rel_vx_body_true': 'rel_vx_body_true', 'rel_vy_body_true': 'rel_vy_body_true',
    'apron_x': 'apron_x', 'apron_y': 'apron_y', 'apron_x_true': 'apron_x_true',
    'apron_y_true': 'apron_y_true', 'range': 'range', 'surface_z_est': 'surface_z_est',
}
_REL_BODY = ('rel_x_body', 'rel_y_body', 'rel_vx_body', 'rel_vy_body')

#: Touchdown in a trace: the first sample whose truth height above the surface is at or below
#: ``gear_height_m`` (0.15 m, docs/interfaces.md: contact) plus 1 mm (the simulator's resting
#: height reads 0.15001 m; 1 mm is at most 5 ms early at the 0.2 m/s final closing speed).
CONTACT_HEIGHT_M = 0.15 + 0.001


class PlotError(Exception):
    """The source cannot be plotted (missing, unreadable, or holds no known data)."""


# ================================================================================ the data


@dataclass
class LandingSeries:
    """Named time series of one landing, times in seconds from the landing trigger.

    ``series[name] = (t_s, values)`` (two equal-length lists, ``t_s`` non-decreasing); names
    are those of :data:`SERIES`. ``trigger_s`` is the trigger in the source's own clock,
    ``modes`` the planner mode changes ``(t_s, name)``, ``touchdown_s`` the touchdown (or
    None) and ``touchdown_source`` where it came from. ``rejected`` counts dropped samples.
    """

    source: str
    trigger_s: float
    trigger_source: str
    series: dict[str, tuple[list[float], list[float]]] = field(default_factory=dict)
    modes: list[tuple[float, str]] = field(default_factory=list)
    touchdown_s: float | None = None
    touchdown_source: str = 'none'
    rejected: dict[str, int] = field(default_factory=dict)

    def get(self, name: str) -> tuple[list[float], list[float]] | None:
        """``(t_s, values)`` of ``name`` or None when the source had none."""
        pair = self.series.get(name)
        return pair if pair is not None and pair[0] else None

    def value_at(self, name: str, t_s: float) -> float:
        """Linear interpolation of ``name`` at ``t_s`` (NaN outside its span or if absent)."""
        pair = self.get(name)
        return math.nan if pair is None else _interp(pair[0], pair[1], t_s)


class _Collector:
    """Accumulates absolute-time samples; :meth:`finish` shifts them to the trigger."""

    def __init__(self) -> None:
        self.data: dict[str, tuple[list[float], list[float]]] = {}
        self.modes: list[tuple[float, str]] = []
        self.rejected: dict[str, int] = {}
        self.t_min = math.inf

    def reject(self, why: str) -> None:
        self.rejected[why] = self.rejected.get(why, 0) + 1

    def add(self, name: str, t: float, value: float, allow_nan: bool = False) -> None:
        if not math.isfinite(t):
            self.reject('bad_time')
            return
        if not (math.isfinite(value) or (allow_nan and math.isnan(value))):
            self.reject('nan')
            return
        ts, vs = self.data.setdefault(name, ([], []))
        ts.append(t)
        vs.append(value)
        self.t_min = min(self.t_min, t)

    def mode(self, t: float, name: str) -> None:
        if not math.isfinite(t):
            self.reject('bad_time')
            return
        name = name.strip().upper()
        if not self.modes or self.modes[-1][1] != name:
            self.modes.append((t, name))
        self.t_min = min(self.t_min, t)

    def finish(self, source: str, touchdown_rel_s: float | None = None,
               touchdown_source: str = 'none', contact_height: str | None = None
               ) -> LandingSeries:
        """Shift to the trigger; touchdown: ``touchdown_rel_s`` (already relative) if given,
        else the truth contact in series ``contact_height`` (height above the surface at or
        below :data:`CONTACT_HEIGHT_M` after the trigger), else the first LANDED mode."""
        for ts, vs in self.data.values():
            if any(b < a for a, b in itertools.pairwise(ts)):
                order = sorted(range(len(ts)), key=ts.__getitem__)   # stable
                ts[:], vs[:] = [ts[i] for i in order], [vs[i] for i in order]
        self.modes.sort(key=lambda m: m[0])
        trigger = next((t for t, m in self.modes if m not in NOT_LANDING_MODES), None)
        if trigger is not None:
            trigger_source = 'planner mode ' + next(
                m for t, m in self.modes if m not in NOT_LANDING_MODES)
        else:
            trigger = self.t_min if math.isfinite(self.t_min) else 0.0
            trigger_source = 'start of data (no landing mode)'
        out = LandingSeries(source, trigger, trigger_source, rejected=dict(self.rejected))
        for name, (ts, vs) in self.data.items():
            out.series[name] = ([t - trigger for t in ts], list(vs))
        out.modes = [(t - trigger, m) for t, m in self.modes]
        pair = out.get(contact_height) if contact_height else None
        contact = None if pair is None else next(
            (t for t, h in zip(*pair, strict=True) if t >= 0.0 and h <= CONTACT_HEIGHT_M), None)
        if touchdown_rel_s is not None and math.isfinite(touchdown_rel_s):
            out.touchdown_s, out.touchdown_source = float(touchdown_rel_s), touchdown_source
        elif contact is not None:
            out.touchdown_s = contact
            out.touchdown_source = f'truth height <= {CONTACT_HEIGHT_M:.3f} m'
        else:
            landed = next((t for t, m in out.modes if m == 'LANDED' and t >= 0.0), None)
            if landed is not None:
                out.touchdown_s, out.touchdown_source = landed, 'planner mode LANDED'
        return out


def _interp(ts: Sequence[float], vs: Sequence[float], t: float) -> float:
    """Linear interpolation in a sorted sample list; NaN outside [ts[0], ts[-1]]."""
    n = len(ts)
    if n == 0 or t < ts[0] or t > ts[-1]:
        return math.nan
    i = bisect.bisect_left(ts, t)
    if i < n and ts[i] == t:
        return vs[i]
    t0, t1 = ts[i - 1], ts[i]
    if t1 <= t0:
        return vs[i]
    a = (t - t0) / (t1 - t0)
    return vs[i - 1] + a * (vs[i] - vs[i - 1])


# ==================================================================================== bags


def resolve_topics(bag_topics: Iterable[str], namespace: str | None = None) -> dict[str, str]:
    """Map each known relative name of :data:`TOPICS` to the bag's topic.

    With ``namespace`` (e.g. ``/uav1``) the topic must be exactly ``namespace/name``. Without
    it ``/name`` is taken when present, otherwise a unique topic ending in ``/name`` (one
    namespaced vehicle); an ambiguous suffix match is left out.
    """
    names = [t if t.startswith('/') else '/' + t for t in bag_topics]
    out: dict[str, str] = {}
    for rel in TOPICS:
        if namespace is not None:
            want = '/' + '/'.join(p for p in (namespace.strip('/'), rel) if p)
            if want in names:
                out[rel] = want
            continue
        if '/' + rel in names:
            out[rel] = '/' + rel
            continue
        hits = [t for t in names if t.endswith('/' + rel)]
        if len(hits) == 1:
            out[rel] = hits[0]
    return out


def _stamp_ns(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def series_from_bag(bag_dir: str | os.PathLike[str], namespace: str | None = None,
                    time_source: str = 'log') -> LandingSeries:
    """Read the landing's time series from a rosbag2 bag (see :data:`TOPICS`).

    ``time_source``: ``'log'`` (default) uses the recorder's receive time of every message,
    one clock for all topics; ``'header'`` uses ``header.stamp`` where the message has one
    (topics without a header keep the log time, so only use it when both clocks agree).
    Raises :class:`PlotError` if the bag cannot be read or holds none of the known topics.
    """
    from deckland.ros import bag as bagmod
    from deckland.ros import rosio

    if time_source not in ('log', 'header'):
        raise ValueError(f"time_source must be 'log' or 'header', got {time_source!r}")
    path = Path(bag_dir)
    if not path.is_dir():
        raise PlotError(f'{path} is not a bag directory')
    try:
        info = bagmod.bag_info(path)
    except Exception as exc:  # rosbags/mcap raise many types on a corrupt bag
        raise PlotError(f'cannot read bag {path}: {exc}') from exc
    types = {t.name: t.msgtype for t in info.topics}
    resolved = resolve_topics(types, namespace)
    if not resolved:
        raise PlotError(f'{path}: none of the known topics ({", ".join(TOPICS)}) is in the bag '
                        f'(it has: {", ".join(sorted(types)) or "nothing"})')
    col = _Collector()
    ref_ns = int(info.start_ns)
    for rel, topic in list(resolved.items()):
        if types.get(topic) != TOPICS[rel]:
            col.reject('wrong_type')
            print(f'plot: {topic} has type {types.get(topic)}, expected {TOPICS[rel]}; '
                  'ignored', file=sys.stderr)
            del resolved[rel]
    by_topic = {topic: rel for rel, topic in resolved.items()}
    store = rosio.typestore()
    truth_v: list[tuple[float, float, float, float, float, float]] = []  # t x y yaw vx vy
    truth_a: tuple[list[float], list[float], list[float], list[float], list[float]] = (
        [], [], [], [], [])                                               # t x y vx vy
    outcome: dict[str, Any] | None = None
    try:
        messages = bagmod.iter_messages(path, list(by_topic))
        for topic, msgtype, t_ns, data in messages:
            rel = by_topic.get(topic if topic.startswith('/') else '/' + topic)
            if rel is None:
                continue
            try:
                msg = store.deserialize_cdr(data, msgtype)
            except Exception:  # a truncated or foreign CDR payload
                col.reject('decode')
                continue
            if time_source == 'header' and hasattr(msg, 'header'):
                t_ns = _stamp_ns(msg)
            t = (t_ns - ref_ns) * 1e-9   # integer difference first: no loss at 1.7e9 s
            if rel == 'sim/outcome':
                try:
                    parsed = json.loads(msg.data)
                except ValueError:
                    col.reject('bad_outcome')
                    continue
                if isinstance(parsed, dict):
                    outcome = parsed
                continue
            _add_message(col, rel, t, msg, truth_v, truth_a)
    except PlotError:
        raise
    except Exception as exc:
        raise PlotError(f'cannot read bag {path}: {exc}') from exc
    _add_relative_truth(col, truth_v, truth_a)
    touchdown, td_source = None, 'none'
    if outcome is not None:
        ttl = outcome.get('time_to_land_s')
        if isinstance(ttl, int | float) and math.isfinite(ttl):
            touchdown, td_source = float(ttl), 'sim/outcome time_to_land_s'
    out = col.finish(str(path), touchdown, td_source)
    out.trigger_s += ref_ns * 1e-9
    return out


def _add_message(col: _Collector, rel: str, t: float, msg: Any,
                 truth_v: list[tuple[float, ...]],
                 truth_a: tuple[list[float], ...]) -> None:
    if rel == 'planner/mode':
        col.mode(t, str(msg.data))
    elif rel == 'vehicle/odom':
        p = msg.pose.pose.position
        col.add('x', t, float(p.x))
        col.add('y', t, float(p.y))
        col.add('z', t, float(p.z))
    elif rel == 'vehicle/range':
        r = float(msg.range)
        # REP-117: +inf = no return, -inf = too close; both shown as a gap (NaN)
        col.add('range', t, r if math.isfinite(r) else math.nan, allow_nan=not math.isnan(r))
    elif rel == 'apron/odom':
        p = msg.pose.pose.position
        col.add('apron_x', t, float(p.x))
        col.add('apron_y', t, float(p.y))
    elif rel == 'apron/state':
        _add_apron_state(col, t, msg)
    elif rel == 'altitude/state':
        col.add('sigma', t, float(msg.sigma))
        col.add('d_hat', t, float(msg.d_hat_mps2))
    elif rel == 'control/thrust':
        col.add('thrust', t, float(msg.wrench.force.z))
    elif rel == 'sim/truth/vehicle':
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        vals = (float(p.x), float(p.y), float(p.z), float(q.w), float(q.x), float(q.y),
                float(q.z))
        lin = msg.twist.twist.linear
        vb = (float(lin.x), float(lin.y), float(lin.z))
        if not all(math.isfinite(v) for v in (*vals, *vb)):
            col.reject('nan')
            return
        col.add('x_true', t, vals[0])
        col.add('y_true', t, vals[1])
        col.add('z_true', t, vals[2])
        roll, pitch, yaw = quaternion_to_euler(*vals[3:])
        # the twist of sim/truth/vehicle is in base_link (REP-105): back to ENU
        vw = mat_vec(rot_body_to_world(roll, pitch, yaw), vb)
        truth_v.append((t, vals[0], vals[1], yaw, vw[0], vw[1]))
    elif rel == 'sim/truth/apron':
        p, v = msg.pose.pose.position, msg.twist.twist.linear
        vals = (float(p.x), float(p.y), float(p.z), float(v.x), float(v.y))
        if not all(math.isfinite(x) for x in vals):
            col.reject('nan')
            return
        col.add('apron_x_true', t, vals[0])
        col.add('apron_y_true', t, vals[1])
        col.add('deck_z_true', t, vals[2])
        for lst, x in zip(truth_a, (t, vals[0], vals[1], vals[3], vals[4]), strict=True):
            lst.append(x)


def _add_apron_state(col: _Collector, t: float, msg: Any) -> None:
    from deckland_common.messages import apron_state_from_msg

    s, reason, _ = apron_state_from_msg(msg)
    if s is None:
        col.reject('nan' if reason == 'non_finite' else reason)
        return
    col.add('visible', t, 1.0 if s.visible else 0.0)
    col.add('tracked', t, 1.0 if s.tracked else 0.0)
    rel = (*s.rel_position_body_m, *s.rel_velocity_body_mps)
    for name, value in zip(_REL_BODY, rel, strict=True):
        # an untracked estimate is meaningless (zeros or stale): a gap, not a value
        col.add(name, t, value if s.tracked else math.nan, allow_nan=True)
    v = s.vertical
    col.add('height_est', t, v.height_m if v.valid else math.nan, allow_nan=True)
    col.add('surface_z_est', t, v.surface_height_m if v.valid else math.nan, allow_nan=True)


def _add_relative_truth(col: _Collector, truth_v: list[tuple[float, ...]],
                        truth_a: tuple[list[float], ...]) -> None:
    """Figure 8 truth: (beacon − vehicle) and (apron velocity − vehicle velocity), rotated into
    the heading frame {B} with the vehicle's true yaw (frames.world_to_body_xy), i.e. the
    quantities the estimator's (23)-(24) measure, at each vehicle truth sample (the apron
    truth interpolated to it)."""
    ta = truth_a[0]
    if not ta:
        return
    for t, vx, vy, yaw, vvx, vvy in truth_v:
        ax = _interp(ta, truth_a[1], t)
        if math.isnan(ax):
            continue
        ay = _interp(ta, truth_a[2], t)
        avx = _interp(ta, truth_a[3], t)
        avy = _interp(ta, truth_a[4], t)
        rx, ry = world_to_body_xy(ax - vx, ay - vy, yaw)
        rvx, rvy = world_to_body_xy(avx - vvx, avy - vvy, yaw)
        col.add('rel_x_body_true', t, rx)
        col.add('rel_y_body_true', t, ry)
        col.add('rel_vx_body_true', t, rvx)
        col.add('rel_vy_body_true', t, rvy)


# ============================================================================= traces (CSV)


def series_from_trace(trace: Mapping[str, Sequence[float]],
                      source: str = 'trace') -> LandingSeries:
    """Time series from a runner trace (``RunResult.trace`` or a parsed CSV).

    ``trace['t']`` is required; other columns are mapped with :data:`CSV_COLUMNS`; ``mode``
    holds the index into ``deckland_common.contract.Mode``. Touchdown: the first sample (after
    the trigger) whose truth height above the surface is at or below
    :data:`CONTACT_HEIGHT_M` (the simulator's contact), else the first LANDED mode (the
    planner's detection, later by its confirmation time). Raises :class:`PlotError`
    without ``t`` or without any known column.
    """
    if 't' not in trace:
        raise PlotError(f'{source}: no time column "t"')
    known = [c for c in trace if c in CSV_COLUMNS or c == 'mode']
    if not known:
        raise PlotError(f'{source}: none of the known columns ({", ".join(CSV_COLUMNS)}, '
                        'mode) is present')
    ts = [_to_float(v) for v in trace['t']]
    col = _Collector()
    tracked = [_to_float(v) for v in trace['tracked']] if 'tracked' in trace else None
    for name in known:
        values = trace[name]
        if len(values) != len(ts):
            raise PlotError(f'{source}: column {name!r} has {len(values)} rows, t has {len(ts)}')
        if name == 'mode':
            for t, v in zip(ts, values, strict=True):
                f = _to_float(v)
                i = round(f) if math.isfinite(f) else -1
                if 0 <= i < len(MODE_NAMES):
                    col.mode(t, MODE_NAMES[i])
                else:
                    col.reject('bad_mode')
            continue
        target = CSV_COLUMNS[name]
        gap_ok = target in _REL_BODY or target in ('range', 'height_est', 'surface_z_est')
        for i, (t, v) in enumerate(zip(ts, values, strict=True)):
            f = _to_float(v)
            if target in _REL_BODY and tracked is not None and not tracked[i] > 0.5:
                f = math.nan
            col.add(target, t, f, allow_nan=gap_ok)
    return col.finish(source, contact_height='height_true')


def _to_float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def series_from_csv(path: str | os.PathLike[str]) -> LandingSeries:
    """Read the CSV ``deckland sim --csv`` writes (header row = column names)."""
    p = Path(path)
    try:
        with p.open(newline='') as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if not header:
                raise PlotError(f'{p}: empty CSV')
            header = [h.strip() for h in header]
            cols: dict[str, list[float]] = {h: [] for h in header}
            for row in reader:
                if not row:
                    continue
                if len(row) != len(header):
                    raise PlotError(f'{p}: a row has {len(row)} fields, header has '
                                    f'{len(header)}')
                for h, v in zip(header, row, strict=True):
                    cols[h].append(_to_float(v))
    except OSError as exc:
        raise PlotError(f'cannot read {p}: {exc}') from exc
    return series_from_trace(cols, str(p))


# ================================================================================= figures

_Line = tuple[str, str, str, str]          # series name, legend label, colour, line style
_T = 'time since landing trigger [s]'

#: Panels of every figure: file -> ((panel id, y label, lines, step plot), ...).
FIGURES: dict[str, tuple[tuple[str, str, tuple[_Line, ...], bool], ...]] = {
    'figure7.png': (
        ('7a', '(a) x [m]', (('x', 'vehicle (estimate)', 'C0', '-'),
                             ('x_true', 'vehicle (truth)', 'C0', '--'),
                             ('apron_x', 'apron (estimate)', 'C3', '-'),
                             ('apron_x_true', 'apron (truth)', 'C3', '--')), False),
        ('7b', '(b) y [m]', (('y', 'vehicle (estimate)', 'C0', '-'),
                             ('y_true', 'vehicle (truth)', 'C0', '--'),
                             ('apron_y', 'apron (estimate)', 'C3', '-'),
                             ('apron_y_true', 'apron (truth)', 'C3', '--')), False),
        ('7c', '(c) altitude [m]', (('z', 'altitude (estimate)', 'C0', '-'),
                                    ('z_true', 'altitude (truth)', 'C0', '--'),
                                    ('height_est', 'height above surface (estimate)', 'C1',
                                     '-'),
                                    ('range', 'lidar range', 'C2', ':')), False),
        ('7d', '(d) visibility', (('visible', 'beacon visible', 'C3', '-'),
                                  ('tracked', 'tracked', 'C7', '--')), True),
    ),
    'figure8.png': tuple(
        (f'8{letter}', f'({letter}) {label}', ((key, 'estimate', 'C0', '-'),
                                               (key + '_true', 'truth', 'C3', '--')), False)
        for letter, key, label in zip('abcd', _REL_BODY, (
            'x_B relative [m]', 'y_B relative [m]', 'vx_B relative [m/s]',
            'vy_B relative [m/s]'), strict=True)),
    'figure9.png': (
        ('9a', '(a) σ', (('sigma', 'σ (14)', 'C0', '-'),), False),
        ('9b', '(b) u_z [N]', (('thrust', 'u_z (16)', 'C0', '-'),), False),
    ),
    'heave.png': (
        ('heave', 'height [m]', (('z_true', 'vehicle altitude (truth)', 'C0', '--'),
                                 ('z', 'vehicle altitude (estimate)', 'C0', '-'),
                                 ('deck_z_true', 'deck height (truth)', 'C3', '--'),
                                 ('surface_z_est', 'surface height (estimate)', 'C3', '-')),
         False),
    ),
}
FIGURE_FILES = tuple(FIGURES)
_LAYOUT = {'figure7.png': ((2, 2), (11, 7)), 'figure8.png': ((2, 2), (11, 7)),
           'figure9.png': ((2, 1), (9, 6)), 'heave.png': ((1, 1), (9, 4.5))}


def empty_panels(data: LandingSeries) -> list[str]:
    """Panel ids of :data:`FIGURES` that have no series in ``data`` (drawn as "no data")."""
    return [pid for panels in FIGURES.values() for pid, _, lines, _ in panels
            if all(data.get(name) is None for name, *_ in lines)]


def write_figures(data: LandingSeries, out_dir: str | os.PathLike[str], *,
                  pre_trigger_s: float = 0.0, title: str = '', dpi: int = 110) -> list[Path]:
    """Draw :data:`FIGURES` into ``out_dir`` (created) and return the PNG paths.

    Every panel without data says "no data" (:func:`empty_panels`); the figures are always
    written. The x axis starts ``pre_trigger_s`` before the trigger (t = 0) and ends at the
    last sample; the touchdown is a dotted vertical line (and a marker on the deck).
    """
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    if not (pre_trigger_s >= 0.0 and math.isfinite(pre_trigger_s)):
        raise ValueError(f'pre_trigger_s must be finite and >= 0, got {pre_trigger_s!r}')
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_end = max((p[0][-1] for p in data.series.values() if p[0]), default=1.0)
    if data.touchdown_s is not None:
        t_end = max(t_end, data.touchdown_s)
    xlim = (-pre_trigger_s, max(t_end, -pre_trigger_s + 1e-3))
    suptitle = title or Path(data.source).name
    td = data.touchdown_s
    paths = []
    for name, panels in FIGURES.items():
        (rows, cols), size = _LAYOUT[name]
        fig, axs = plt.subplots(rows, cols, figsize=size, squeeze=False)
        axes = list(axs.flat)
        for ax, (_, ylabel, lines, step) in zip(axes, panels, strict=True):
            _lines(ax, data, lines, ylabel, step)
            ax.set_xlim(*xlim)
            ax.grid(True, alpha=0.3)
            if td is not None and ax.has_data():
                ax.axvline(td, color='k', ls=':', lw=1.0)
        for ax in axes[-cols:]:
            ax.set_xlabel(_T)
        if name == 'figure7.png' and axes[3].has_data():
            axes[3].set_ylim(-0.1, 1.1)
            axes[3].set_yticks([0, 1])
        if name == 'figure9.png' and axes[0].has_data():
            axes[0].axhline(0.0, color='k', lw=0.6)
        if name == 'heave.png' and td is not None and axes[0].has_data():
            ax = axes[0]
            deck = data.value_at('deck_z_true', td)
            if math.isnan(deck):
                deck = data.value_at('surface_z_est', td)
            if not math.isnan(deck):
                ax.plot([td], [deck], 'kv', ms=8)
            right = td > 0.5 * (xlim[0] + xlim[1])    # keep the label inside the axes
            ax.annotate(f'touchdown {td:.2f} s\n({data.touchdown_source})',
                        xy=(td, 0.03), xycoords=('data', 'axes fraction'),
                        xytext=(-4 if right else 4, 0), textcoords='offset points',
                        ha='right' if right else 'left', fontsize=8)
            ax.set_title('deck heave and vehicle height', fontsize=10)
        fig.suptitle(suptitle, fontsize=10)
        fig.tight_layout()
        path = out / name
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        paths.append(path)
    return paths


def _lines(ax: Any, data: LandingSeries, specs: Sequence[_Line], ylabel: str,
           step: bool = False) -> None:
    """Plot each available series of ``specs``; "no data" if none is available."""
    drawn = 0
    for name, label, color, style in specs:
        pair = data.get(name)
        if pair is None:
            continue
        if step:
            ax.step(pair[0], pair[1], where='post', color=color, ls=style, lw=1.2, label=label)
        else:
            ax.plot(pair[0], pair[1], color=color, ls=style, lw=1.2, label=label)
        drawn += 1
    ax.set_ylabel(ylabel)
    if drawn:
        ax.legend(fontsize=8, loc='best')
    else:
        ax.text(0.5, 0.5, 'no data', transform=ax.transAxes, ha='center', va='center',
                fontsize=14, color='0.4')


# ===================================================================================== CLI


def register(sub: Any) -> None:
    """Add ``plot`` (figures from a bag directory or from ``--trace RUN.csv``) to ``sub``."""
    p = sub.add_parser('plot', help="the paper's Figures 7-9 and deck heave from a bag or CSV")
    p.add_argument('bag', nargs='?', metavar='BAG_DIR', help='rosbag2 bag directory')
    p.add_argument('--trace', metavar='RUN.csv', help='CSV written by deckland sim --csv')
    p.add_argument('--out', required=True, metavar='DIR', help='directory for the PNG files')
    p.add_argument('--namespace', default=None, metavar='NS',
                   help='topic namespace in the bag (default: /, else a unique suffix match)')
    p.add_argument('--time', choices=('log', 'header'), default='log',
                   help='bag timestamps: recorder receive time (default) or header.stamp')
    p.add_argument('--pre', type=float, default=0.0, metavar='S',
                   help='also show S seconds before the landing trigger')
    p.add_argument('--title', default='', help='figure title (default: the source name)')
    p.set_defaults(func=_cmd_plot)


def _cmd_plot(args: argparse.Namespace) -> int:
    if (args.bag is None) == (args.trace is None):
        print('plot: give exactly one of BAG_DIR or --trace RUN.csv', file=sys.stderr)
        return 2
    if not (math.isfinite(args.pre) and args.pre >= 0.0):
        print('plot: --pre must be >= 0', file=sys.stderr)
        return 2
    try:
        if args.trace is not None:
            data = series_from_csv(args.trace)
        else:
            data = series_from_bag(args.bag, args.namespace, args.time)
        paths = write_figures(data, args.out, pre_trigger_s=args.pre, title=args.title)
    except PlotError as exc:
        print(f'plot: {exc}', file=sys.stderr)
        return 1
    empty = empty_panels(data)
    print(f'time origin: {data.trigger_source}; touchdown: '
          + (f'{data.touchdown_s:.2f} s ({data.touchdown_source})'
             if data.touchdown_s is not None else 'none'), file=sys.stderr)
    if empty:
        print(f'panels without data: {", ".join(empty)}', file=sys.stderr)
    if data.rejected:
        print(f'rejected samples: {data.rejected}', file=sys.stderr)
    for path in paths:
        print(f'wrote {path}')
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m deckland.plot ...`` (same as ``deckland plot ...``)."""
    parser = argparse.ArgumentParser(prog='deckland')
    register(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['plot', *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)


if __name__ == '__main__':
    sys.exit(main())
