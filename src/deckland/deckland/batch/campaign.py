"""``deckland campaign`` and ``deckland sim``: many seeded landings, one report.

More in the package README, "Module notes" (`deckland.batch.campaign`).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time
from typing import Any

from deckland_common.stats import percentile, wilson_interval

from deckland.batch import accel, backends
from deckland.batch.backends import CampaignError, Chunk, LocalPool, RayBackend
from deckland.batch.runner import CONTROLLERS, RunConfig, RunResult, run_landing

SEED_STRIDE = 100_000
#: the run classes counted in a report (deck_simulator.outcome.classify)
OUTCOMES = ('deck', 'failed', 'fallback', 'hold', 'crash', 'unstable')

#: Report keys that say how a campaign was run, not what was flown: two reports of the same
#: scenario, controller and seeds are identical but for these, whatever backend flew them.
HOW_RUN_KEYS = ('wall_time_s', 'realtime_factor', 'realtime_factor_per_worker', 'workers',
                'backend')


def run_seed(campaign_seed: int, index: int) -> int:
    """The seed of run ``index`` in a campaign seeded ``campaign_seed``."""
    return campaign_seed * SEED_STRIDE + index


def summarize(results: list[RunResult], scenario: str, controller: str, seed: int,
              wall_time_s: float, workers: int = 1, cores: str | None = None,
              backend: str = 'local') -> dict[str, Any]:
    """Aggregate run outcomes into the campaign report (see module docstring).

    ``cores``: what the workers flew (default: this process's); ``backend``: where.
    """
    n = len(results)
    on_pad = [r for r in results if r.landed_on_deck]
    errors = [r.horizontal_error_m for r in on_pad]
    speeds = [r.touchdown_speed_mps for r in on_pad]
    touched = [r for r in results if r.contact_kind != 'none']
    times = [r.time_to_land_s for r in touched]
    sim_time = sum(r.sim_time_s for r in results)
    successes = sum(r.success for r in results)
    lo, hi = wilson_interval(successes, n)
    bounced = [r for r in touched if r.bounces > 0]

    def stats(xs, keys=('p50', 'p95', 'max')):
        out = {}
        for key in keys:
            value = max(xs) if (key == 'max' and xs) else (
                math.nan if key == 'max' else percentile(xs, float(key[1:])))
            out[key] = _json_float(value)
        return out

    return {
        'scenario': scenario,
        'controller': controller,
        'runs': n,
        'seed': seed,
        'success_rate': successes / n if n else 0.0,
        'fallback_rate': sum(r.fallback for r in results) / n if n else 0.0,
        'crash_rate': sum(r.crash for r in results) / n if n else 0.0,
        'horizontal_error_m': stats(errors),
        'touchdown_speed_mps': stats(speeds),
        'time_to_land_s': stats(times, ('p50', 'p95')),
        'searches_mean': (sum(r.searches for r in results) / n) if n else 0.0,
        'max_thrust_n': _json_float(max((r.max_thrust_n for r in results), default=math.nan)),
        'wall_time_s': round(wall_time_s, 3),
        'realtime_factor': round(sim_time / wall_time_s, 1) if wall_time_s > 0 else 0.0,
        'workers': workers,
        'realtime_factor_per_worker': (round(sim_time / wall_time_s / workers, 1)
                                       if wall_time_s > 0 else 0.0),
        'backend': backend,
        'cores': cores or accel.cores(),
        'failures': [{'seed': r.seed, 'reason': r.reason, 'outcome': r.outcome}
                     for r in results if not r.success],
        'outcomes': {k: sum(r.outcome == k for r in results) for k in OUTCOMES},
        'success_ci95': [round(lo, 4), round(hi, 4)],
        'first_contact': {
            'runs': len(touched),
            'normal_speed_mps': stats([r.touchdown_speed_mps for r in touched]),
            'lateral_speed_mps': stats([r.lateral_speed_mps for r in touched]),
            'tilt_rad': stats([r.tilt_rad for r in touched]),
        },
        'impacts': {
            'runs_with_later_impacts': sum(r.impacts > 1 for r in touched),
            'later_impacts': sum(max(0, r.impacts - 1) for r in touched),
            'max_speed_mps': stats([r.max_impact_speed_mps for r in touched]),
        },
        'bounces': {
            'runs': len(bounced),
            'total': sum(r.bounces for r in touched),
            'max_height_m': stats([r.max_bounce_height_m for r in bounced]),
        },
        'settled_rate': (sum(r.settled for r in touched) / len(touched)) if touched else 0.0,
    }


def _json_float(x: float) -> float | None:
    return None if not math.isfinite(x) else round(x, 4)


#: Seeds per chunk at most: a Ray task costs ~2 ms, a run ~50-160 ms (FACTS.md).
MAX_CHUNK = 100


def chunk_size(runs: int, workers: int) -> int:
    """Seeds per chunk: about 8 chunks per worker (balance), at most `MAX_CHUNK`."""
    return max(1, min(MAX_CHUNK, math.ceil(runs / (8 * max(1, workers)))))


def make_chunks(scenario: str, runs: int, seed: int, config: RunConfig,
                size: int) -> list[Chunk]:
    """The campaign's seeds in consecutive chunks, with what a worker needs to fly them."""
    from deck_simulator.scenario import builtin_names
    text = None if scenario in builtin_names() else pathlib.Path(scenario).read_text('utf-8')
    from deckland.batch.runner import config_fields
    blob = config_fields(config)
    seeds = [run_seed(seed, i) for i in range(runs)]
    return [Chunk(k, scenario, text, blob, tuple(seeds[i:i + size]),
                  accel.status().get('dir'))
            for k, i in enumerate(range(0, runs, size))]


def run_campaign(scenario: str, runs: int, seed: int, config: RunConfig, workers: int = 0,
                 progress: bool = True, backend: LocalPool | RayBackend | None = None,
                 chunk: int = 0) -> tuple[dict[str, Any], list[RunResult]]:
    """Fly ``runs`` seeded landings on ``backend`` (default: a local pool of ``workers``).

    Returns (report, per-run results sorted by seed). Raises `CampaignError` naming the seeds
    of a chunk that failed for good; a report never silently lacks a run.
    """
    from deck_simulator.scenario import load_scenario
    scen = load_scenario(scenario)  # fail early on a bad scenario, before any worker starts
    if runs < 1:
        raise ValueError(f'runs must be >= 1, got {runs}')
    backend = backend or LocalPool(workers)
    chunks = make_chunks(scenario, runs, seed, config, chunk or chunk_size(runs, backend.workers))
    start = time.perf_counter()
    results: list[RunResult] = []
    cores = set()
    label = f'{scen.name}/{config.controller}'
    for done in backend.map(chunks):
        results.extend(done.results)
        cores.add(done.cores)
        if progress:
            _progress(label, len(results), runs, start)
    wall = time.perf_counter() - start
    if progress:
        sys.stderr.write('\n')
    results.sort(key=lambda r: r.seed)
    flown = [r.seed for r in results]
    expected = [s for c in chunks for s in c.seeds]
    if flown != expected:   # cannot happen with a correct backend; never report a gap
        missing = sorted(set(expected) - set(flown))
        raise CampaignError(f'campaign incomplete: {len(flown)} results for {runs} runs, '
                            f'{len(missing)} seeds missing (first {missing[:5]})')
    report = summarize(results, scen.name, config.controller, seed, wall,
                       backend.used(len(chunks)), cores='+'.join(sorted(cores)),
                       backend=backend.name)
    return report, results


def _progress(label: str, done: int, total: int, start: float) -> None:
    width = 30
    filled = int(width * done / total)
    elapsed = time.perf_counter() - start
    eta = elapsed / done * (total - done) if done else 0.0
    sys.stderr.write(f'\r{label:<24} [{"#" * filled}{"." * (width - filled)}] '
                     f'{done}/{total}  {elapsed:5.1f}s  eta {eta:5.1f}s')
    sys.stderr.flush()


def format_table(reports: list[dict[str, Any]]) -> str:
    """Side-by-side summary of one or more campaign reports."""
    rows = [
        ('success', lambda r: f'{100 * r["success_rate"]:.1f} %'),
        ('  95 % interval', lambda r: '{:.1f}-{:.1f} %'.format(*(100 * x for x in
                                                                 r['success_ci95']))),
        ('failed', lambda r: f'{100 * r["outcomes"]["failed"] / max(1, r["runs"]):.1f} %'),
        ('fallback', lambda r: f'{100 * r["fallback_rate"]:.1f} %'),
        ('crash', lambda r: f'{100 * r["crash_rate"]:.1f} %'),
        ('1st contact runs', lambda r: f'{r["first_contact"]["runs"]}'),
        ('1st normal p95 [m/s]', lambda r: _fmt(r['first_contact']['normal_speed_mps']['p95'])),
        ('1st normal max [m/s]', lambda r: _fmt(r['first_contact']['normal_speed_mps']['max'])),
        ('1st lateral p95 [m/s]',
         lambda r: _fmt(r['first_contact']['lateral_speed_mps']['p95'])),
        ('1st tilt p95 [deg]', lambda r: _fmt_deg(r['first_contact']['tilt_rad']['p95'])),
        ('later impacts (runs)', lambda r: f'{r["impacts"]["runs_with_later_impacts"]}'),
        ('bounces (runs)', lambda r: f'{r["bounces"]["runs"]}'),
        ('settled', lambda r: f'{100 * r["settled_rate"]:.1f} %'),
        ('error p50 [m]', lambda r: _fmt(r['horizontal_error_m']['p50'])),
        ('error p95 [m]', lambda r: _fmt(r['horizontal_error_m']['p95'])),
        ('error max [m]', lambda r: _fmt(r['horizontal_error_m']['max'])),
        ('td speed p50 [m/s]', lambda r: _fmt(r['touchdown_speed_mps']['p50'])),
        ('td speed p95 [m/s]', lambda r: _fmt(r['touchdown_speed_mps']['p95'])),
        ('td speed max [m/s]', lambda r: _fmt(r['touchdown_speed_mps']['max'])),
        ('time p50 [s]', lambda r: _fmt(r['time_to_land_s']['p50'], 1)),
        ('time p95 [s]', lambda r: _fmt(r['time_to_land_s']['p95'], 1)),
        ('searches/run', lambda r: f'{r["searches_mean"]:.2f}'),
        ('max thrust [N]', lambda r: _fmt(r['max_thrust_n'], 1)),
        ('realtime factor', lambda r: f'{r["realtime_factor"]:.0f}'),
        ('wall time [s]', lambda r: f'{r["wall_time_s"]:.1f}'),
    ]
    head = f'{"scenario " + reports[0]["scenario"]:<22}' + ''.join(
        f'{r["controller"]:>16}' for r in reports)
    lines = [head, f'{"runs":<22}' + ''.join(f'{r["runs"]:>16}' for r in reports)]
    for name, fn in rows:
        lines.append(f'{name:<22}' + ''.join(f'{fn(r):>16}' for r in reports))
    return '\n'.join(lines)


def _fmt(x, digits=3) -> str:
    return '-' if x is None else f'{x:.{digits}f}'


def _fmt_deg(x) -> str:
    return '-' if x is None else f'{math.degrees(x):.1f}'


def write_plots(per_controller: dict[str, list[RunResult]], out_dir: pathlib.Path,
                scenario: str) -> list[pathlib.Path]:
    """PNG distributions of touchdown error and speed per controller."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for key, label, unit in (('horizontal_error_m', 'horizontal error at touchdown', 'm'),
                             ('touchdown_speed_mps', 'touchdown speed (relative)', 'm/s')):
        fig, ax = plt.subplots(figsize=(7, 4))
        for controller, results in per_controller.items():
            xs = [getattr(r, key) for r in results if r.landed_on_deck]
            if xs:
                ax.hist(xs, bins=30, alpha=0.5, label=f'{controller} (n={len(xs)})')
        ax.set_xlabel(f'{label} [{unit}]')
        ax.set_ylabel('runs')
        ax.set_title(f'{scenario}: {label}')
        ax.legend()
        fig.tight_layout()
        path = out_dir / f'{scenario}_{key}.png'
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def _cmd_campaign(args: argparse.Namespace) -> int:
    if args.autopilot != 'in-process':   # the graph through a firmware, one mission at a time
        from deckland.sitl.campaign import cmd_sitl_campaign
        return cmd_sitl_campaign(args)
    controllers = list(CONTROLLERS) if args.compare else [args.controller]
    reports, per_controller = [], {}
    backend = backends.from_args(args)
    try:
        if not args.quiet:
            print(f'deckland: {backend.describe()}', file=sys.stderr)
        for controller in controllers:
            config = RunConfig(controller=controller, gains_profile=args.profile)
            report, results = run_campaign(args.scenario, args.runs, args.seed, config,
                                           progress=not args.quiet, backend=backend,
                                           chunk=args.chunk)
            reports.append(report)
            per_controller[controller] = results
    except CampaignError as exc:
        print(f'deckland: {exc}', file=sys.stderr)
        return 1
    finally:
        backend.close()
    print(format_table(reports))
    for report in reports:
        for failure in report['failures'][:10]:
            print(f'  {report["controller"]} failed seed {failure["seed"]}: {failure["reason"]}')
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        payload = reports[0] if len(reports) == 1 else {'compare': reports}
        out.write_text(json.dumps(payload, indent=2) + '\n')
        print(f'wrote {out}')
    if args.plots:
        for path in write_plots(per_controller, pathlib.Path(args.plots), reports[0]['scenario']):
            print(f'wrote {path}')
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    from deck_simulator.scenario import load_scenario
    scenario = load_scenario(args.scenario)
    config = RunConfig(controller=args.controller, gains_profile=args.profile,
                       record=bool(args.csv))
    result = run_landing(scenario, args.seed, config)
    print(json.dumps(result.summary(), indent=2, default=_json_default))
    if args.csv:
        path = pathlib.Path(args.csv)
        path.parent.mkdir(parents=True, exist_ok=True)
        keys = list(result.trace)
        with path.open('w') as fh:
            fh.write(','.join(keys) + '\n')
            for row in zip(*(result.trace[k] for k in keys), strict=True):
                fh.write(','.join(f'{v:.9g}' for v in row) + '\n')
        print(f'wrote {path}')
    return 0 if result.success else 1


def _json_default(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return str(x)


def register(sub) -> None:
    p = sub.add_parser('campaign', help='run many seeded simulated landings and summarise')
    p.add_argument('--scenario', default='paper', help='built-in name or YAML file')
    p.add_argument('--runs', type=int, default=100)
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--controller', choices=CONTROLLERS, default='dob')
    p.add_argument('--profile', default='default', help="gains profile ('default' or 'paper')")
    p.add_argument('--compare', action='store_true', help='run every controller on the same seeds')
    p.add_argument('--workers', type=int, default=0,
                   help='processes, or CPUs of a private ray cluster (default: all cores)')
    backends.add_arguments(p)
    p.add_argument('--out', help='write the JSON report here')
    p.add_argument('--plots', help='write PNG distributions into this directory')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    accel.add_cores_argument(p)
    from deckland.sitl.campaign import add_arguments as add_sitl_arguments
    add_sitl_arguments(p)
    p.set_defaults(func=_cmd_campaign)

    s = sub.add_parser('sim', help='fly one seeded simulated landing in-process')
    s.add_argument('--scenario', default='paper')
    s.add_argument('--seed', type=int, default=1)
    s.add_argument('--controller', choices=CONTROLLERS, default='dob')
    s.add_argument('--profile', default='default')
    s.add_argument('--csv', help='write the time series of the run to this CSV')
    accel.add_cores_argument(s)
    s.set_defaults(func=_cmd_sim)
