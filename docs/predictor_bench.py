"""Deck-motion predictor on the built-in heave models: error against horizon, interval
coverage, commit windows, the broken-prediction detector, and the cost per call.

    .venv/bin/python docs/predictor_bench.py                # writes docs/results/predictor.json
    .venv/bin/python docs/predictor_bench.py --quick        # shorter runs, prints only
    .venv/bin/python docs/predictor_bench.py --compiled     # + cost with the mypyc-built cores

Input: the vertical filter (apron_estimator.vertical) on simulated sensors at the simulator's
default noise (deck_simulator.sensors), the vehicle hovering 1.4 m above the deck's mean.
Errors are against the true deck, so they include the estimator's own. CPU time of this
process (robust to other load). docs/predictor.md quotes the JSON.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import json
import math
import os
import pathlib
import platform
import random
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
HORIZONS_S = (0.25, 0.5, 1.0, 2.0)
DT_S = 0.01

Heave = Callable[[float], tuple[float, float, float]]


# -- signals ---------------------------------------------------------------------------------
def heave_model(name: str, seed: int, duration_s: float) -> Heave:
    """The built-in heave models (deck_simulator.deck) by name, phases drawn from the seed."""
    from deck_simulator import deck

    rng = random.Random(f'{seed}:heave')
    if name == 'paper_triangle':          # paper Table 3: 300 mm stroke at 90 mm/s
        return deck.TriangleHeave(0.30, 0.09, rng.random()).state
    if name == 'sine':                    # HeaveSpec's sine defaults: 0.25 m, 6 s
        return deck.SineHeave(0.25, 6.0, rng.uniform(0.0, 2 * math.pi)).state
    if name == 'sine_0.2m_4s':            # the harsh unseen sine (docs/results/scenarios)
        return deck.SineHeave(0.2, 4.0, rng.uniform(0.0, 2 * math.pi)).state
    if name == 'two_tone':                # two incommensurate periods
        a = deck.SineHeave(0.15, 5.0, rng.uniform(0.0, 2 * math.pi))
        b = deck.SineHeave(0.08, 2.3, rng.uniform(0.0, 2 * math.pi))

        def two(t: float) -> tuple[float, float, float]:
            za, va, aa = a.state(t)
            zb, vb, ab = b.state(t)
            return za + zb, va + vb, aa + ab
        return two
    if name in ('sea_state_3', 'sea_state_4'):   # the built-in scenarios' JONSWAP heave
        hs, tp = (0.5, 6.0) if name == 'sea_state_3' else (1.0, 7.0)
        return deck.SeaStateHeave(hs, tp, 'jonswap', rng, duration_s + 5.0).state
    raise ValueError(f'unknown heave {name!r}')


MODELS = ('paper_triangle', 'sine', 'sine_0.2m_4s', 'two_tone', 'sea_state_3', 'sea_state_4')


def estimated_stream(heave: Heave, seed: int, duration_s: float,
                     steps: tuple[tuple[float, float, float], ...] = (),
                     perturb: Callable[[float], float] | None = None) -> list[tuple]:
    """The vertical filter's surface estimate at 100 Hz over a heaving deck.

    Sensors at deck_simulator.sensors' defaults: lidar 2 cm at 100 Hz (LidarParams), GPS
    altitude 5 cm + a 10 cm / 60 s Gauss-Markov bias and vertical speed 5 cm/s at 10 Hz
    (GpsParams), accelerometer 0.1 m/s² at 100 Hz (ImuParams); the filter at its defaults.

    Rows ``(t, surface_height_m, surface_epoch, last_rebase_m, valid, z_true, vz_true)``.
    ``steps``: (t0, t1, dz) — the surface under the lidar is dz higher in [t0, t1) (a
    raised structure moving with the deck: the filter re-bases twice). ``perturb(t)``: an
    extra deck displacement (the true deck includes it).
    """
    from apron_estimator.vertical import VerticalFilter

    rng = random.Random(f'{seed}:sensors')
    vf = VerticalFilter()
    zv, vv, bias = 2.0, 0.0, 0.0
    rows = []
    eps = 1e-5
    for k in range(round(duration_s / DT_S)):
        t = k * DT_S
        av = -0.5 * vv - (zv - 2.0) + rng.gauss(0.0, 0.6)     # hover with some motion
        vv += av * DT_S
        zv += vv * DT_S
        zd, vd, _ = heave(t)
        if perturb is not None:
            dz = perturb(t)
            vd += (perturb(t + eps) - perturb(t - eps)) / (2 * eps)
            zd += dz
        zd += 0.6
        step = sum(s for t0, t1, s in steps if t0 <= t < t1)
        vf.on_accel(t, av + rng.gauss(0.0, 0.1))
        if k % 10 == 0:
            bias += -bias / 60.0 * 0.1 + rng.gauss(0.0, 0.1 * math.sqrt(2 * 0.1 / 60.0))
            vf.on_altitude(t, zv + bias + rng.gauss(0.0, 0.05), vv + rng.gauss(0.0, 0.05))
        vf.on_lidar(t, zv - (zd + step) + rng.gauss(0.0, 0.02))
        s = vf.state(t)
        rows.append((t, s.surface_height_m, s.surface_epoch, s.last_rebase_m, s.valid, zd, vd))
    return rows


def feed(pred, row) -> bool:
    t, z, epoch, rebase, valid, _, _ = row
    return bool(valid) and pred.on_surface(t, z, int(epoch), rebase)


# -- measurements ----------------------------------------------------------------------------
def horizon_errors(rows: list[tuple], every_s: float = 0.5) -> dict:
    """RMS error and ±1.96σ coverage per horizon, against the true deck."""
    from landing_planner.deck_predictor import DeckPredictor

    pred = DeckPredictor()
    acc = {h: {'ez': [], 'ev': [], 'sz': [], 'sv': [], 'cz': 0, 'cv': 0} for h in HORIZONS_S}
    nxt = 0.0
    ready_s = math.nan
    for _i, row in enumerate(rows):
        feed(pred, row)
        if not pred.ready:
            continue
        if math.isnan(ready_s):
            ready_s = row[0]
        if row[0] < nxt:
            continue
        nxt = row[0] + every_s
        snap = pred.heave.snapshot()
        i0 = round(snap.origin_s / DT_S)
        if i0 >= len(rows):
            continue
        z0 = snap.at(snap.origin_s).value
        for h in HORIZONS_S:
            j = round((row[0] + h) / DT_S)
            if j >= len(rows):
                continue
            p = snap.at(row[0] + h)
            ez = (p.value - z0) - (rows[j][5] - rows[i0][5])
            ev = p.rate - rows[j][6]
            a = acc[h]
            a['ez'].append(ez)
            a['ev'].append(ev)
            a['sz'].append(p.sigma_value)
            a['sv'].append(p.sigma_rate)
            a['cz'] += abs(ez) <= 1.96 * p.sigma_value
            a['cv'] += abs(ev) <= 1.96 * p.sigma_rate
    out: dict = {'ready_after_s': round(ready_s, 2), 'frequency_hz': pred.heave.frequency_hz(),
                 'rejected': dict(pred.heave.rejected), 'restarts': pred.heave.restarts,
                 'rebases': pred.heave.rebases}
    for h, a in acc.items():
        n = len(a['ez'])
        out[f'{h}s'] = {
            'n': n,
            'height_rms_m': _rms(a['ez']), 'height_sigma_mean_m': _mean(a['sz']),
            'height_coverage_95': round(a['cz'] / n, 3) if n else math.nan,
            'rate_rms_mps': _rms(a['ev']), 'rate_sigma_mean_mps': _mean(a['sv']),
            'rate_coverage_95': round(a['cv'] / n, 3) if n else math.nan,
        }
    zs = [r[5] for r in rows]
    vs = [r[6] for r in rows]
    out['deck_sigma_m'] = _std(zs)
    out['deck_rate_sigma_mps'] = _std(vs)
    return out


def fly_plan(rows: list[tuple], i0: int, plan, snap=None) -> tuple[int, float]:
    """The plan flown against the true deck from row i0: (contact row, relative normal
    speed). With feed-forward the vehicle follows the predicted path of ``snap``."""
    from landing_planner.commit_window import _lag_factor

    b = _lag_factor(plan.follow_lag_s, DT_S)
    bff = _lag_factor(plan.feedforward_lag_s, DT_S)
    h, vf, vm, u = plan.height_m, plan.vehicle_vz_mps, plan.vehicle_vz_mps, 0.0
    i = i0
    while h > 0.0 and i < len(rows) - 1:
        vd = rows[i][6]
        if plan.feedforward and snap is not None:
            p = snap.at(rows[i][0])
            vp = p.rate if p.valid else snap.rates[-1]
            vm += bff * (vp - vm)
            u += b * ((vd - vp) - u)
            vf = vm + u
        else:
            vf += b * (vd - vf)
        h += (vf - plan.closing_speed_mps - vd) * DT_S
        i += 1
    return i, plan.closing_speed_mps + rows[i][6] - vf


PLANS = {
    # the stack's final descent: deck-relative at 0.08 m/s (planner final_speed_mps) from a
    # 0.15 m hold, following the measured deck with ~0.25 s of lag (estimator + loop)
    'follow': {'height_m': 0.15, 'closing_speed_mps': 0.08, 'follow_lag_s': 0.25},
    # the same with the predicted deck velocity fed forward
    'feedforward': {'height_m': 0.15, 'closing_speed_mps': 0.08, 'follow_lag_s': 0.25,
                    'feedforward': True},
    # hover at a world height 5 cm above the deck's crests, then a deck-blind world-frame
    # descent at 0.1 m/s timed onto a crest (height_m is set from CREST_M at each commit)
    'world': {'height_m': 0.05, 'closing_speed_mps': 0.1, 'follow_lag_s': math.inf,
              'hold_world': True},
}
#: Highest deck excursion above the mean the 'world' plan hovers over (+ 5 cm); the sea
#: states have no such bound within a 3 s descent (their crests reach 2 Hs).
CREST_M = {'paper_triangle': 0.15, 'sine': 0.25, 'sine_0.2m_4s': 0.2, 'two_tone': 0.23}


def windows(rows: list[tuple], plan_name: str, crest_m: float = 0.0,
            every_s: float = 0.25) -> dict:
    """How often a commit is offered, and what the offered commits meet on the true deck."""
    from landing_planner.commit_window import DescentPlan, find_window
    from landing_planner.deck_predictor import DeckPredictor

    pred = DeckPredictor()
    spec = PLANS[plan_name]
    vfollow = 0.0
    bl = 1.0 - math.exp(-DT_S / 0.25)
    n_eval = n_now = 0
    speeds: list[float] = []
    deck_speeds: list[float] = []
    nxt = 0.0
    for i, row in enumerate(rows):
        vfollow += bl * (row[6] - vfollow)
        feed(pred, row)
        if not pred.ready or row[0] < nxt or i > len(rows) - 600:
            continue
        nxt = row[0] + every_s
        vz = 0.0 if math.isinf(spec['follow_lag_s']) else vfollow
        kw = dict(spec)
        if kw.get('hold_world'):
            kw['height_m'] = crest_m + 0.05 - (row[5] - 0.6)
        plan = DescentPlan(vehicle_vz_mps=vz, **kw)
        snap = pred.snapshot()
        w = find_window(row[0], snap, plan)
        n_eval += 1
        if w.commit_now:
            n_now += 1
            j, r = fly_plan(rows, i, plan, snap.heave)
            speeds.append(r)
            deck_speeds.append(abs(rows[j][6]))
    over = sum(1 for s in speeds if s > 0.15)
    return {'evaluations': n_eval, 'commit_now_fraction': round(n_now / max(n_eval, 1), 3),
            'commits': n_now, 'true_speed_p50_mps': _pct(speeds, 50),
            'true_speed_p95_mps': _pct(speeds, 95),
            'true_speed_max_mps': round(max(speeds), 4) if speeds else math.nan,
            'over_0.15_fraction': round(over / max(n_now, 1), 4),
            'deck_speed_at_contact_mean_mps': _mean(deck_speeds)}


def monitor_false_alarms(rows: list[tuple], every_s: float = 1.0) -> dict:
    """Arm the monitor at regular times on a nominal deck and watch each full horizon."""
    from landing_planner.commit_window import PredictionMonitor
    from landing_planner.deck_predictor import DeckPredictor

    pred = DeckPredictor()
    mons: list[PredictionMonitor] = []
    armed = alarms = 0
    nxt = 0.0
    for row in rows:
        feed(pred, row)
        for m in mons:
            m.update(row[0], pred)
        done = [m for m in mons if m.broken or m.expired]
        alarms += sum(1 for m in done if m.broken)
        mons = [m for m in mons if not (m.broken or m.expired)]
        if pred.ready and row[0] >= nxt:
            nxt = row[0] + every_s
            m = PredictionMonitor()
            if m.arm(pred):
                mons.append(m)
                armed += 1
    return {'armed': armed, 'false_alarms': alarms,
            'false_alarm_rate': round(alarms / max(armed, 1), 4)}


PERTURBATIONS = {
    # the deck sinks 10 cm in 0.2 s (a sudden settle) at t = 150 s
    'step_0.1m': lambda t: 0.0 if t < 150.0 else -0.1 * min(1.0, (t - 150.0) / 0.2),
    # an extra 0.1 m/s upward drift from t = 150 s (the deck departs from its rhythm)
    'drift_0.1mps': lambda t: 0.0 if t < 150.0 else 0.1 * (t - 150.0),
}


def detection_delay(name: str, seed: int, duration_s: float, which: str) -> dict:
    """Monitors armed every 0.5 s before the perturbation (t = 150 s): time from it to the
    alarm of each monitor whose horizon covers it."""
    from landing_planner.commit_window import PredictionMonitor
    from landing_planner.deck_predictor import DeckPredictor

    t_p = 150.0
    rows = estimated_stream(heave_model(name, seed, duration_s), seed, duration_s,
                            perturb=PERTURBATIONS[which])
    pred = DeckPredictor()
    mons: list[PredictionMonitor] = []
    delays: list[float] = []
    missed = early = 0
    arm_at = [t_p - 2.0 + 0.5 * i for i in range(5)]
    for row in rows:
        feed(pred, row)
        t = row[0]
        for m in mons:
            m.update(t, pred)
        for m in mons:
            if m.broken:
                if m.t_broken_s >= t_p:
                    delays.append(m.t_broken_s - t_p)
                else:
                    early += 1
            elif m.expired:
                missed += 1
        mons = [m for m in mons if not (m.broken or m.expired)]
        if pred.ready and arm_at and t >= arm_at[0]:
            arm_at.pop(0)
            m = PredictionMonitor()
            if m.arm(pred):
                mons.append(m)
        if t > t_p + 4.0:
            break
    return {'monitors': len(delays) + missed + early, 'detected': len(delays),
            'missed': missed, 'early_alarms': early, 'delay_p50_s': _pct(delays, 50),
            'delay_max_s': round(max(delays), 3) if delays else math.nan}


def cost(duration_s: float) -> dict:
    """CPU µs per call on a sea-state stream (the most active signal)."""
    from landing_planner.commit_window import (
        DescentPlan,
        PredictionMonitor,
        find_window,
    )
    from landing_planner.deck_predictor import DeckPredictor

    from landing_planner import deck_predictor as dp_mod

    rows = estimated_stream(heave_model('sea_state_4', 3, duration_s), 3, duration_s)
    samples = [(r[0], r[1], int(r[2]), r[3]) for r in rows if r[4]]
    pred = DeckPredictor()
    t0 = time.process_time()
    for t, z, e, rb in samples:
        pred.on_surface(t, z, e, rb)
    per_sample = (time.process_time() - t0) / len(samples) * 1e6
    cells = pred.heave.cells
    plan = DescentPlan(0.15, 0.08, 0.25, 0.0)
    t_now = samples[-1][0]
    reps = 50
    t0 = time.process_time()
    for _ in range(reps):
        snap = pred.snapshot()
    t_snap = (time.process_time() - t0) / reps * 1e6
    t0 = time.process_time()
    for _ in range(reps):
        find_window(t_now, snap, plan)
    t_find = (time.process_time() - t0) / reps * 1e6
    t0 = time.process_time()
    for _ in range(reps):
        pred.heave.forecast(t_now + 1.0)
    t_fc = (time.process_time() - t0) / reps * 1e6
    mon = PredictionMonitor()
    mon.arm(pred)
    t0 = time.process_time()
    for _ in range(reps):
        mon.update(t_now, pred)
    t_mon = (time.process_time() - t0) / reps * 1e6
    return {'compiled': not dp_mod.__file__.endswith('.py'),
            'on_surface_mean_us': round(per_sample, 1),
            'grid_update_us': round(per_sample * len(samples) / max(cells, 1), 1),
            'samples_per_grid_value': round(len(samples) / max(cells, 1), 1),
            'snapshot_us': round(t_snap, 1), 'find_window_us': round(t_find, 1),
            'forecast_us': round(t_fc, 1), 'monitor_update_us': round(t_mon, 1)}


def _compile_into(stage: pathlib.Path) -> None:
    for pkg in ('deckland_common', 'landing_planner'):
        shutil.copytree(ROOT / 'src' / pkg / pkg, stage / pkg)
    mods = ['landing_planner/deck_predictor.py', 'landing_planner/commit_window.py']
    (stage / 'mypy.ini').write_text('[mypy]\nignore_missing_imports = True\n'
                                    'follow_imports = silent\n')
    (stage / 'setup.py').write_text(
        'from setuptools import setup\nfrom mypyc.build import mypycify\n'
        f'setup(name="bench", ext_modules=mypycify({mods!r}, opt_level="3", '
        'multi_file=True, group_name="bench_predictor"))\n')
    env = dict(os.environ, CFLAGS='-ffp-contract=off')
    subprocess.run([sys.executable, 'setup.py', 'build_ext', '--inplace'], cwd=stage, env=env,
                   check=True, capture_output=True)


# -- helpers ---------------------------------------------------------------------------------
def _rms(xs: list[float]) -> float:
    return round(math.sqrt(sum(x * x for x in xs) / len(xs)), 4) if xs else math.nan


def _mean(xs: list[float]) -> float:
    return round(sum(xs) / len(xs), 4) if xs else math.nan


def _std(xs: list[float]) -> float:
    m = sum(xs) / len(xs)
    return round(math.sqrt(sum((x - m) ** 2 for x in xs) / len(xs)), 4)


def _pct(xs: list[float], q: float) -> float:
    from deckland_common.stats import percentile

    return round(percentile(xs, q), 4) if xs else math.nan


def _nulls(x):
    """NaN → null (strict JSON)."""
    if isinstance(x, dict):
        return {k: _nulls(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nulls(v) for v in x]
    return None if isinstance(x, float) and math.isnan(x) else x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--quick', action='store_true', help='120 s runs, print only')
    ap.add_argument('--compiled', action='store_true', help='cost with mypyc-built cores')
    ap.add_argument('--out', default=str(ROOT / 'docs' / 'results' / 'predictor.json'))
    args = ap.parse_args(argv)
    if args.compiled:
        stage = pathlib.Path(tempfile.mkdtemp(prefix='bench_predictor_'))
        _compile_into(stage)
        sys.path.insert(0, str(stage))
        for mod in [m for m in sys.modules if m.startswith(('landing_planner',
                                                              'deckland_common'))]:
            del sys.modules[mod]
        result = cost(60.0)
        print(json.dumps(result))
        out = pathlib.Path(args.out)
        if out.is_file():                 # merged into the report of the last full run
            report = json.loads(out.read_text())
            report['cost_compiled'] = result
            out.write_text(json.dumps(_nulls(report), indent=1) + '\n')
        return 0
    duration = 120.0 if args.quick else 400.0
    seed = 1
    report: dict = {'command': 'python docs/predictor_bench.py' + (' --quick' if args.quick
                                                                   else ''),
                    'duration_s': duration, 'seed': seed, 'python': platform.python_version(),
                    'models': {}}
    for name in MODELS:
        rows = estimated_stream(heave_model(name, seed, duration), seed, duration)
        entry = {'horizons': horizon_errors(rows)}
        entry['windows'] = {p: windows(rows, p, CREST_M.get(name, 0.0)) for p in PLANS
                            if p != 'world' or name in CREST_M}
        entry['monitor'] = monitor_false_alarms(rows)
        report['models'][name] = entry
        print(name, json.dumps(entry), flush=True)
    # the same triangle with the surface stepping 0.25 m under the lidar for 30 s
    rows = estimated_stream(heave_model('paper_triangle', seed, duration), seed, duration,
                            steps=((60.0, 90.0, 0.25),))
    report['paper_triangle_rebased'] = {'horizons': horizon_errors(rows)}
    report['detection'] = {f'{n}/{w}': detection_delay(n, seed, max(duration, 200.0), w)
                           for n in ('paper_triangle', 'sine', 'sea_state_3')
                           for w in PERTURBATIONS}
    print(json.dumps(report['detection']), flush=True)
    report['cost'] = cost(60.0)
    print(json.dumps(report['cost']), flush=True)
    if not args.quick:
        pathlib.Path(args.out).write_text(json.dumps(_nulls(report), indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
