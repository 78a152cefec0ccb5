"""Benchmark of the in-process closed loop: realtime factor of seeded landings in one process.

``python -m deckland.batch.perf [--scenario paper] [--runs 20] [--seed 1] [--controller dob]
[--profile]`` prints a JSON object. The runs are the same seeds a campaign flies
(``deckland.batch.campaign.run_seed``), flown one after another in this process (no pool), so
the figure is the realtime factor of one worker. The machine may be shared: compare ratios
measured back to back, not absolute figures from different days.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from deckland.batch import accel


def measure_realtime_factor(scenario: str = 'paper', runs: int = 20, seed: int = 1,
                            controller: str = 'dob') -> dict[str, Any]:
    """Fly ``runs`` seeded landings of ``scenario`` in this process and time them.

    Returns ``{'scenario', 'controller', 'runs', 'seed', 'sim_time_s', 'wall_time_s',
    'cpu_time_s', 'realtime_factor', 'realtime_factor_cpu', 'us_per_physics_step',
    'success_rate', 'cores'}``; ``realtime_factor`` is simulated seconds per wall-clock second (one
    worker), ``realtime_factor_cpu`` the same per second of this process's CPU time (less
    sensitive to other jobs on a shared machine), ``us_per_physics_step`` the mean wall time of
    one physics step including the 100 Hz / 50 Hz blocks amortised over it.
    """
    from deck_simulator.scenario import load_scenario

    from deckland.batch.campaign import run_seed
    from deckland.batch.runner import RunConfig, run_landing

    if runs < 1:
        raise ValueError(f'runs must be >= 1, got {runs}')
    scen = load_scenario(scenario)
    config = RunConfig(controller=controller)
    sim_time = 0.0
    successes = 0
    start = time.perf_counter()
    cpu_start = time.process_time()
    for i in range(runs):
        result = run_landing(scen, run_seed(seed, i), config)
        sim_time += result.sim_time_s
        successes += bool(result.success)
    wall = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    steps = sim_time * config.physics_hz
    return {
        'scenario': scen.name,
        'controller': controller,
        'runs': runs,
        'seed': seed,
        'sim_time_s': round(sim_time, 3),
        'wall_time_s': round(wall, 3),
        'cpu_time_s': round(cpu, 3),
        'realtime_factor': round(sim_time / wall, 1) if wall > 0 else 0.0,
        'realtime_factor_cpu': round(sim_time / cpu, 1) if cpu > 0 else 0.0,
        'us_per_physics_step': round(1e6 * wall / steps, 2) if steps > 0 else 0.0,
        'success_rate': successes / runs,
        'cores': accel.cores(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m deckland.batch.perf',
                                     description=__doc__.split('\n')[0])
    parser.add_argument('--scenario', default='paper')
    parser.add_argument('--runs', type=int, default=20)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--controller', default='dob')
    parser.add_argument('--profile', action='store_true',
                        help='also print the top 25 functions by own time (cProfile) to stderr')
    accel.add_cores_argument(parser)
    args = parser.parse_args(argv)
    try:
        accel.enable(args.cores)
    except accel.AccelError as exc:
        parser.error(f'--cores compiled: {exc}')
    if args.profile:
        import cProfile
        import pstats
        prof = cProfile.Profile()
        report = prof.runcall(measure_realtime_factor, args.scenario, args.runs, args.seed,
                              args.controller)
        pstats.Stats(prof, stream=sys.stderr).sort_stats('tottime').print_stats(25)
    else:
        report = measure_realtime_factor(args.scenario, args.runs, args.seed, args.controller)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
