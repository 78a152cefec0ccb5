"""Where a campaign's runs fly: the local process pool (default) or a Ray cluster.

A campaign is cut into chunks of consecutive seeds (`Chunk`); a backend calls `run_chunk` on
each chunk wherever its workers are and yields the `ChunkResult`s as chunks finish. Chunking,
ordering and the report belong to `deckland.batch.campaign`, the same for every backend.
`run_chunk` loads the compiled cores first when the driver flies them (`accel.worker_init`,
a no-op after the first chunk in a worker), so this module imports no core at import time.
Ray is optional and imported only by `RayBackend` (see the deckland README, "Campaigns on a
Ray cluster").
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
import concurrent.futures as cf
from dataclasses import dataclass, field
import logging
import multiprocessing as mp
import os
import socket
import sys
from typing import TYPE_CHECKING, Any

from deckland.batch import accel

if TYPE_CHECKING:
    from deckland.batch.runner import RunResult

BACKENDS = ('local', 'ray')


class CampaignError(RuntimeError):
    """Runs of a campaign failed for good (after the backend's retries); names their seeds."""


@dataclass(frozen=True)
class Chunk:
    """Consecutive runs of one campaign, flown by one worker in one task."""

    index: int
    scenario: str                 # built-in name, or the label of a YAML file
    scenario_yaml: str | None     # that file's text (a worker need not see the file)
    config_fields: dict[str, Any]  # the RunConfig as plain data, rebuilt after the cores load
    seeds: tuple[int, ...]
    accel_dir: str | None         # load the compiled cores from here first (None: Python)

    def label(self) -> str:
        return f'seeds {self.seeds[0]}..{self.seeds[-1]} (chunk {self.index})'


@dataclass
class ChunkResult:
    index: int
    results: list[RunResult]
    cores: str                    # 'compiled' or 'python': what the worker flew
    worker: str = field(default='')   # host:pid


_SCENARIOS: dict[tuple[str, str | None], Any] = {}


def _scenario(name: str, text: str | None) -> Any:
    key = (name, text)
    if key not in _SCENARIOS:
        from deck_simulator.scenario import load_scenario, scenario_from_dict
        if text is None:
            _SCENARIOS[key] = load_scenario(name)
        else:   # the driver loaded the same text already: it parses and validates
            import yaml
            _SCENARIOS[key] = scenario_from_dict(yaml.safe_load(text) or {}, name)
    return _SCENARIOS[key]


def run_chunk(chunk: Chunk) -> ChunkResult:
    """Fly every seed of ``chunk`` (in this process) with the driver's cores."""
    accel.worker_init(chunk.accel_dir)
    from deckland.batch.runner import config_from_fields, run_landing
    config = config_from_fields(chunk.config_fields)
    scenario = _scenario(chunk.scenario, chunk.scenario_yaml)
    results = [run_landing(scenario, seed, config) for seed in chunk.seeds]
    where = f'{socket.gethostname()}:{os.getpid()}'
    return ChunkResult(chunk.index, results, accel.cores(), where)


ChunkFn = Callable[[Chunk], ChunkResult]


class LocalPool:
    """A process pool on this machine (fork on Linux); one process: flown in-process."""

    name = 'local'

    def __init__(self, workers: int = 0, chunk_fn: ChunkFn = run_chunk) -> None:
        if workers < 0:
            raise ValueError(f'workers must be >= 0 (0: all cores), got {workers}')
        self.workers = workers or os.cpu_count() or 1
        self.chunk_fn = chunk_fn

    def used(self, chunks: int) -> int:
        return 1 if (self.workers == 1 or chunks == 1) else min(self.workers, chunks)

    def map(self, chunks: list[Chunk]) -> Iterator[ChunkResult]:
        if self.used(len(chunks)) == 1:
            for chunk in chunks:
                yield _call(self.chunk_fn, chunk)
            return
        ctx = mp.get_context('fork' if sys.platform.startswith('linux') else 'spawn')
        with cf.ProcessPoolExecutor(self.used(len(chunks)), mp_context=ctx) as pool:
            futures = {pool.submit(self.chunk_fn, chunk): chunk for chunk in chunks}
            try:
                for future in cf.as_completed(futures):
                    exc = future.exception()
                    if isinstance(exc, cf.process.BrokenProcessPool):
                        # a worker died: every chunk it had not returned is lost with it
                        lost = [c for f, c in futures.items()
                                if not f.done() or f.exception() is not None]
                        raise CampaignError(
                            f'campaign failed: a local worker died (killed?) with '
                            f'{len(lost)} of {len(chunks)} chunks unfinished: '
                            f'{", ".join(c.label() for c in lost)}') from exc
                    if exc is not None:
                        raise _failed(futures[future], exc, len(chunks), 'no retry') from exc
                    yield future.result()
            finally:
                for future in futures:
                    future.cancel()

    def close(self) -> None:
        pass

    def describe(self) -> str:
        return f'local pool, {self.workers} processes'


def _call(fn: ChunkFn, chunk: Chunk) -> ChunkResult:
    try:
        return fn(chunk)
    except Exception as exc:
        raise _failed(chunk, exc, 1, 'no retry') from exc


def _failed(chunk: Chunk, exc: BaseException, total: int, retries: str) -> CampaignError:
    first = str(exc).strip().splitlines()
    why = f'{type(exc).__name__}: {first[-1] if first else ""}'
    return CampaignError(f'campaign failed: {chunk.label()} of {total} chunks failed '
                         f'({retries}): {why}; rerun one alone with deckland sim --seed')


def _ray_entry(fn: ChunkFn, chunk: Chunk) -> ChunkResult:
    return fn(chunk)


class RayBackend:
    """Chunks as Ray tasks (one CPU each), retried on an exception or a lost worker.

    ``address`` None starts a private single-machine cluster bound to loopback with
    ``workers`` CPUs (0: all cores); 'auto' joins the cluster `ray start` runs on this
    machine; 'HOST:PORT' joins that cluster's head. A Ray already initialised in this process
    is used as it is (and left running on `close`).
    """

    name = 'ray'

    def __init__(self, address: str | None = None, workers: int = 0, max_retries: int = 3,
                 chunk_fn: ChunkFn = run_chunk) -> None:
        if workers < 0:
            raise ValueError(f'workers must be >= 0 (0: all cores), got {workers}')
        if max_retries < 0:
            raise ValueError(f'max_retries must be >= 0, got {max_retries}')
        self.max_retries = max_retries
        self.chunk_fn = chunk_fn
        self.address = address
        os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
        if address is None:
            # advertise (and bind) 127.0.0.1, not the host's address; read when ray imports
            os.environ.setdefault('RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER', '0')
        ray = import_ray()
        self._owner = not ray.is_initialized()
        if self._owner:
            common: dict[str, Any] = {'include_dashboard': False,
                                      'logging_level': logging.WARNING}
            try:
                if address is None:
                    ray.init(address='local', num_cpus=workers or os.cpu_count() or 1,
                             **common)
                else:
                    ray.init(address=address, **common)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                where = 'start a local ray cluster' if address is None else f'join {address}'
                raise CampaignError(f'cannot {where}: {exc}') from exc
        self.workers = max(1, int(ray.cluster_resources().get('CPU', 1)))
        self._remote = ray.remote(_ray_entry)

    def used(self, chunks: int) -> int:
        return min(self.workers, chunks)

    def map(self, chunks: list[Chunk]) -> Iterator[ChunkResult]:
        ray = import_ray()
        task = self._remote.options(max_retries=self.max_retries, retry_exceptions=True)
        fn = ray.put(self.chunk_fn)
        pending = {task.remote(fn, chunk): chunk for chunk in chunks}
        try:
            while pending:
                # a bounded wait: Python gets control back every second, so Ctrl-C and a
                # test's timeout act even while a task hangs (seen once in a full test run)
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                if not ready:
                    continue
                more, _ = ray.wait([r for r in pending if r not in ready],
                                   num_returns=len(pending) - len(ready), timeout=0)
                for ref in ready + more:
                    chunk = pending.pop(ref)
                    try:
                        yield ray.get(ref)
                    except ray.exceptions.RayError as exc:
                        raise _failed(chunk, exc, len(chunks),
                                      f'{self.max_retries} retries') from None
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._owner:
            import_ray().shutdown()
            self._owner = False

    def describe(self) -> str:
        where = 'private local cluster' if self.address is None else f'cluster {self.address}'
        return f'ray, {where}, {self.workers} CPUs'


def import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise CampaignError('--backend ray needs the ray package: make setup-ray '
                            '(pip install -r requirements-ray.txt)') from exc
    return ray


def ray_available() -> bool:
    import importlib.util
    return importlib.util.find_spec('ray') is not None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--backend', choices=BACKENDS, default='local',
                        help="where the runs fly: 'local' process pool (default) or 'ray'")
    parser.add_argument('--address', default=None,
                        help="ray cluster to join: 'auto' (ray start on this machine) or "
                             'HEAD:PORT; without it a private local cluster of --workers CPUs')
    parser.add_argument('--chunk', type=int, default=0,
                        help='seeds per task (default: runs / (8 x workers), at most 100)')


def from_args(args: argparse.Namespace) -> LocalPool | RayBackend:
    """The backend the command line asks for (``--backend``, ``--address``, ``--workers``)."""
    if args.chunk < 0:
        raise SystemExit(f'deckland: --chunk must be >= 0 (0: automatic), got {args.chunk}')
    if args.workers < 0:
        raise SystemExit(f'deckland: --workers must be >= 0 (0: all cores), got {args.workers}')
    if args.backend == 'ray':
        try:
            return RayBackend(args.address, args.workers)
        except CampaignError as exc:
            raise SystemExit(f'deckland: {exc}') from None
    if args.address is not None:
        raise SystemExit('deckland: --address needs --backend ray')
    return LocalPool(args.workers)
