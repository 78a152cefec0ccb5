"""Campaigns on a Ray cluster (2 CPUs, local): the local pool's report, failed tasks retried."""

import dataclasses
import functools
import importlib.util
import json
import os
import pathlib
import subprocess
import sys

import pytest

if importlib.util.find_spec('ray') is None:
    pytest.skip('ray is not installed (make setup-ray): Ray backend not tested',
                allow_module_level=True)

from deckland.batch import accel
from deckland.batch.backends import CampaignError, RayBackend, run_chunk
from deckland.batch.campaign import HOW_RUN_KEYS, run_campaign
from deckland.batch.runner import RunConfig
from deckland.batch.tune import sweep


@pytest.fixture(scope='module')
def cluster():
    """One private 2-CPU cluster for the module (start-up costs seconds).

    Started without the session's DECKLAND_CORES=python (conftest) so that a job whose driver
    flies compiled cores can load them in its workers; drivers of this process fly Python.
    """
    forced = os.environ.pop('DECKLAND_CORES', None)
    try:
        backend = RayBackend(workers=2)
    finally:
        if forced is not None:
            os.environ['DECKLAND_CORES'] = forced
    import ray
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the injected faults
    yield backend
    backend.close()


def flown(report):
    return {k: v for k, v in report.items() if k not in HOW_RUN_KEYS}


def runs_json(results):
    """Every run's summary as text (NaN fields compare equal as text, not as floats)."""
    return json.dumps([r.summary() for r in results], sort_keys=True)


def test_ray_report_is_the_local_pools(cluster, tmp_path):
    assert cluster.workers == 2
    local, local_runs = run_campaign('paper', 6, 7, RunConfig(), workers=2, progress=False)
    ray_report, ray_runs = run_campaign('paper', 6, 7, RunConfig(), progress=False,
                                        backend=cluster, chunk=2)
    assert (ray_report['backend'], local['backend']) == ('ray', 'local')
    assert ray_report['workers'] == 2
    assert flown(ray_report) == flown(local)
    assert runs_json(ray_runs) == runs_json(local_runs)
    # a scenario file travels as text in the chunk: the workers need not see the file
    scenario = tmp_path / 'windy.yaml'
    scenario.write_text('name: windy\nwind: {mean_mps: [2.0, 0.5], gust_std_mps: 0.5}\n')
    config = RunConfig(controller='pid')
    local, _ = run_campaign(str(scenario), 3, 2, config, workers=1, progress=False)
    ray_report, _ = run_campaign(str(scenario), 3, 2, config, progress=False, backend=cluster)
    assert ray_report['scenario'] == 'windy'
    assert flown(ray_report) == flown(local)


def _first_time(marker: pathlib.Path) -> bool:
    try:
        marker.touch(exist_ok=False)
    except FileExistsError:
        return False
    return True


def _flaky(marker_dir: str, chunk):
    """Chunk 0 raises on its first attempt; chunk 1's worker dies after its first landing."""
    attempts = pathlib.Path(marker_dir) / f'attempts-{chunk.index}'
    with attempts.open('a') as fh:
        fh.write('x')
    if chunk.index == 1 and _first_time(pathlib.Path(marker_dir) / 'killed'):
        run_chunk(dataclasses.replace(chunk, seeds=chunk.seeds[:1]))
        os._exit(1)
    if chunk.index == 0 and _first_time(pathlib.Path(marker_dir) / 'raised'):
        raise RuntimeError('injected failure')
    return run_chunk(chunk)


def test_a_raising_task_and_a_killed_worker_are_retried(cluster, tmp_path):
    flaky = RayBackend(max_retries=2, chunk_fn=functools.partial(_flaky, str(tmp_path)))
    assert not flaky._owner     # the module's cluster, left running on close
    report, _ = run_campaign('paper', 4, 9, RunConfig(), progress=False, backend=flaky,
                             chunk=2)
    reference, _ = run_campaign('paper', 4, 9, RunConfig(), workers=1, progress=False)
    assert flown(report) == flown(reference)
    assert (tmp_path / 'raised').exists() and (tmp_path / 'killed').exists()
    assert (tmp_path / 'attempts-0').read_text() == 'xx'    # raised, then flown
    assert (tmp_path / 'attempts-1').read_text() == 'xx'    # killed, then flown


def _broken(marker_dir: str, chunk):
    with (pathlib.Path(marker_dir) / f'attempts-{chunk.index}').open('a') as fh:
        fh.write('x')
    if chunk.index == 1:
        raise ValueError('this chunk always fails')
    return run_chunk(chunk)


def test_a_task_failing_for_good_fails_the_campaign_naming_its_seeds(cluster, tmp_path):
    broken = RayBackend(max_retries=1, chunk_fn=functools.partial(_broken, str(tmp_path)))
    with pytest.raises(CampaignError) as info:
        run_campaign('paper', 4, 3, RunConfig(), progress=False, backend=broken, chunk=2)
    message = str(info.value)
    assert 'seeds 300002..300003 (chunk 1)' in message, message
    assert 'ValueError: this chunk always fails' in message and '1 retries' in message
    assert (tmp_path / 'attempts-1').read_text() == 'xx'    # first attempt + one retry


def test_tune_sweeps_on_ray_as_on_the_local_pool(cluster):
    args = ('dob', ['paper'], 2, 5, 2)
    local = sweep(*args, scales=(1.0,))
    on_ray = sweep(*args, scales=(1.0,), backend=cluster)
    assert on_ray['points'] == local['points']


def test_cli_joins_the_cluster_and_its_workers_load_the_compiled_cores(cluster, tmp_path):
    """A second driver (`--address`) is a new Ray job: its workers load the compiled build."""
    problem = accel.manifest_problem()
    if problem is not None:
        if os.environ.get('DECKLAND_REQUIRE_ACCEL') == '1':
            pytest.fail(f'compiled cores required but not usable: {problem}')
        pytest.skip(f'no usable compiled cores ({problem}); run `make accel`')
    import ray
    address = ray.get_runtime_context().gcs_address
    out = tmp_path / 'report.json'
    env = {k: v for k, v in os.environ.items() if k != 'DECKLAND_CORES'}
    cmd = [sys.executable, '-m', 'deckland.cli', 'campaign', '--runs', '4', '--seed', '6',
           '--backend', 'ray', '--address', address, '--cores', 'compiled', '--quiet',
           '--out', str(out)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(out.read_text())
    assert (report['backend'], report['cores'], report['workers']) == ('ray', 'compiled', 2)
    local, _ = run_campaign('paper', 4, 6, RunConfig(), workers=2, progress=False)
    assert local['cores'] == 'python'
    assert ({k: v for k, v in flown(report).items() if k != 'cores'}
            == {k: v for k, v in flown(local).items() if k != 'cores'})
