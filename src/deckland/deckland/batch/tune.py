"""``deckland tune``: a documented, equal-effort gain sweep for the altitude controllers.

Both controllers are tuned the same way so that neither baseline is weakened: the same
scenarios, the same seeds, the same number of grid points and the same cost,

    J = p95 touchdown speed [m/s] + 2 · (1 − success rate) + 0.5 · crash rate,

averaged over the scenarios. The DOB grid scales (K, Λ, Γ) of (14)-(19); the PID grid scales
(k_p, k_i, k_d) around its default, which is the DOB's small-signal equivalent. The report lists
every grid point so the choice can be checked.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
import sys
from typing import Any

from deckland.batch import backends
from deckland.batch.accel import add_cores_argument
from deckland.batch.backends import CampaignError, LocalPool, RayBackend
from deckland.batch.campaign import run_campaign
from deckland.batch.runner import RunConfig

#: Multipliers applied to each of the three gains (3 × 3 × 3 = 27 points per controller).
SCALES = (0.6, 1.0, 1.6)
GAINS = {'dob': ('k', 'lam', 'gamma_obs'), 'pid': ('kp', 'ki', 'kd')}


def cost(report: dict[str, Any]) -> float:
    speed = report['touchdown_speed_mps']['p95']
    speed = 1.0 if speed is None else speed
    return speed + 2.0 * (1.0 - report['success_rate']) + 0.5 * report['crash_rate']


def base_gains(controller: str, profile: str) -> dict[str, float]:
    from dob_altitude.adapter import make_controller
    ctrl = make_controller(controller, profile, {})
    return {name: float(getattr(ctrl.params, name)) for name in GAINS[controller]}


def sweep(controller: str, scenarios: list[str], runs: int, seed: int, workers: int,
          profile: str = 'default', scales=SCALES,
          backend: LocalPool | RayBackend | None = None, chunk: int = 0) -> dict[str, Any]:
    """Every grid point on every scenario, flown on ``backend`` (default: a local pool)."""
    base = base_gains(controller, profile)
    names = GAINS[controller]
    points = []
    for combo in itertools.product(scales, repeat=len(names)):
        gains = {n: round(base[n] * s, 4) for n, s in zip(names, combo, strict=True)}
        key = 'dob_overrides' if controller == 'dob' else 'pid_overrides'
        config = RunConfig(controller=controller, gains_profile=profile,
                           **{key: tuple(gains.items())})
        per_scenario = {}
        for scenario in scenarios:
            report, _ = run_campaign(scenario, runs, seed, config, workers=workers,
                                     progress=False, backend=backend, chunk=chunk)
            per_scenario[scenario] = {
                'cost': round(cost(report), 4), 'success_rate': report['success_rate'],
                'crash_rate': report['crash_rate'],
                'touchdown_speed_p95': report['touchdown_speed_mps']['p95'],
                'max_thrust_n': report['max_thrust_n']}
        mean = sum(v['cost'] for v in per_scenario.values()) / len(per_scenario)
        points.append({'gains': gains, 'scales': combo, 'cost': round(mean, 4),
                       'scenarios': per_scenario})
        print(f'{controller} {gains} cost {mean:.4f}', flush=True)
    points.sort(key=lambda p: p['cost'])
    return {'controller': controller, 'profile': profile, 'base': base,
            'scenarios': scenarios, 'runs': runs, 'seed': seed,
            'cost': 'p95 touchdown speed + 2 (1 - success) + 0.5 crash, mean over scenarios',
            'best': points[0], 'points': points}


def _cmd_tune(args: argparse.Namespace) -> int:
    backend = backends.from_args(args)
    try:
        print(f'deckland: {backend.describe()}', file=sys.stderr)
        result = sweep(args.controller, args.scenarios, args.runs, args.seed, args.workers,
                       args.profile, backend=backend, chunk=args.chunk)
    except CampaignError as exc:
        print(f'deckland: {exc}', file=sys.stderr)
        return 1
    finally:
        backend.close()
    best = result['best']
    print(f'best {args.controller}: {best["gains"]} cost {best["cost"]}')
    if args.out:
        path = pathlib.Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=2) + '\n')
        print(f'wrote {path}')
    return 0


def register(sub) -> None:
    p = sub.add_parser('tune', help='equal-effort gain sweep of an altitude controller')
    p.add_argument('--controller', choices=tuple(GAINS), default='dob')
    p.add_argument('--scenarios', nargs='+', default=['paper', 'sea_state_4'])
    p.add_argument('--runs', type=int, default=40)
    p.add_argument('--seed', type=int, default=101, help='tuning seeds (keep apart from reports)')
    p.add_argument('--profile', default='default')
    p.add_argument('--workers', type=int, default=0,
                   help='processes, or CPUs of a private ray cluster (default: all cores)')
    backends.add_arguments(p)
    p.add_argument('--out', help='write the whole sweep as JSON')
    add_cores_argument(p)
    p.set_defaults(func=_cmd_tune)
