"""Per-task cost of the campaign backends: empty chunks through the local pool and Ray.

Each backend runs ``--tasks`` chunks without seeds (the chunk and its result are pickled,
shipped and returned as in a campaign, nothing is flown) after a warm-up batch that starts
the workers; the cost per run of a campaign is this divided by the runs per chunk.
Usage: ``python docs/results/ray_overhead.py --tasks 400 --workers 2`` (prints JSON).
"""

import argparse
import dataclasses
import json
import os
import time

from deckland.batch.backends import LocalPool, RayBackend
from deckland.batch.campaign import make_chunks
from deckland.batch.runner import RunConfig


def per_task_s(backend, tasks: int) -> float:
    template = make_chunks('paper', 1, 1, RunConfig(), 1)[0]
    empty = [dataclasses.replace(template, index=k, seeds=()) for k in range(tasks)]
    list(backend.map(empty[:2 * backend.workers]))   # warm-up: workers started
    start = time.perf_counter()
    done = sum(1 for _ in backend.map(empty))
    assert done == tasks
    return (time.perf_counter() - start) / tasks


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument('--tasks', type=int, default=400)
    ap.add_argument('--workers', type=int, default=2)
    args = ap.parse_args()
    out = {'tasks': args.tasks, 'workers': args.workers,
           'load_before': os.getloadavg()}
    local = LocalPool(args.workers)
    t0 = time.perf_counter()
    ray = RayBackend(workers=args.workers)
    out['ray_start_s'] = round(time.perf_counter() - t0, 2)
    try:
        for label in ('a', 'b'):   # interleaved: the machine's load drifts
            out[f'local_{label}_ms'] = round(1e3 * per_task_s(local, args.tasks), 3)
            out[f'ray_{label}_ms'] = round(1e3 * per_task_s(ray, args.tasks), 3)
    finally:
        ray.close()
    out['load_after'] = os.getloadavg()
    print(json.dumps(out, indent=2))


if __name__ == '__main__':
    main()
