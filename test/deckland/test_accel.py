"""The compiled cores (deckland.batch.accel, mypyc) fly exactly what the Python sources fly.

The equivalence test runs the same seeded landings in two fresh processes, one with
``--cores python`` and one with ``--cores compiled``, and compares every float of every
recorded trace bit for bit, over the built-in scenarios, every fault scenario and all three
controllers. It needs a build (``make accel``, part of ``make test``); where none is ready it
is skipped, unless ``DECKLAND_REQUIRE_ACCEL=1`` (set by ``make test``, so CI always runs it).
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

from deckland.batch import accel
import pytest

# Flown both ways: every built-in (incl. 3-D-free sea states) and fault scenario, dob; and the
# two baselines on a nominal and an irregular-heave scenario.
_FAULTS = sorted(p.stem for p in pathlib.Path(accel._package_dir('deck_simulator'), 'data')
                 .glob('fault_*.yaml'))
_MATRIX = ([(s, 'dob') for s in ('paper', 'paper_calm', 'gusty', 'sea_state_3', 'sea_state_4',
                                  'ship_ss3', 'ship_ss4', 'ship_turning')]
           + [(s, 'dob') for s in _FAULTS]
           + [(s, c) for s in ('paper', 'sea_state_4') for c in ('pid', 'constant-rate')])
_SEEDS = (100001, 200002)

_FLY = r"""
import hashlib, json, sys
from deckland.batch import accel
used = accel.enable(sys.argv[1])
from deck_simulator.scenario import load_scenario
from deckland.batch.runner import RunConfig, run_landing
out = {'cores': used, 'runs': {}}
for scenario, controller in json.loads(sys.argv[2]):
    sc = load_scenario(scenario)
    for seed in json.loads(sys.argv[3]):
        r = run_landing(sc, seed, RunConfig(controller=controller, record=True))
        trace = json.dumps({k: [float(x).hex() for x in v] for k, v in r.trace.items()},
                           sort_keys=True)
        summary = json.dumps({k: (v.hex() if isinstance(v, float) else v)
                              for k, v in r.summary().items() if k != 'trace'}, sort_keys=True,
                             default=str)
        out['runs'][f'{scenario}/{controller}/{seed}'] = [
            hashlib.sha256(trace.encode()).hexdigest(), summary, len(r.trace['t'])]
print(json.dumps(out))
"""


def _ready() -> None:
    problem = accel.manifest_problem()
    if problem is not None:
        if os.environ.get('DECKLAND_REQUIRE_ACCEL') == '1':
            pytest.fail(f'compiled cores required but not usable: {problem}')
        pytest.skip(f'no usable compiled cores ({problem}); run `make accel`')


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop('DECKLAND_CORES', None)     # conftest pins the test process to Python
    return env


@pytest.mark.slow
@pytest.mark.timeout(900)   # 46 flights per process, the truthful world costs 2x the CPU
def test_compiled_cores_fly_bit_identical_traces(tmp_path):
    _ready()
    script = tmp_path / 'fly.py'
    script.write_text(_FLY)
    args = [json.dumps(_MATRIX), json.dumps(list(_SEEDS))]
    procs = {mode: subprocess.Popen([sys.executable, str(script), mode, *args],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    env=_env())
             for mode in ('python', 'compiled')}
    out = {}
    for mode, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, stderr[-3000:]
        out[mode] = json.loads(stdout)
    assert out['python']['cores'] == 'python'
    assert out['compiled']['cores'] == 'compiled'
    py, cc = out['python']['runs'], out['compiled']['runs']
    assert len(py) == len(_MATRIX) * len(_SEEDS)
    assert all(n > 100 for _, _, n in py.values())     # real flights were recorded
    different = [k for k in py if py[k] != cc[k]]
    assert not different, f'compiled cores differ from the sources in {different}'


@pytest.mark.slow
def test_campaign_cli_with_compiled_cores_on_a_pool(tmp_path):
    """The pool workers inherit the compiled cores; the report says so and matches Python."""
    _ready()
    reports = {}
    for mode in ('compiled', 'python'):
        out = tmp_path / f'{mode}.json'
        subprocess.run([sys.executable, '-m', 'deckland.cli', 'campaign', '--scenario', 'paper',
                        '--runs', '6', '--seed', '4', '--workers', '2', '--quiet',
                        '--cores', mode, '--out', str(out)],
                       check=True, env=_env(), capture_output=True, timeout=300)
        reports[mode] = json.loads(out.read_text())
    assert reports['compiled']['cores'] == 'compiled'
    assert reports['python']['cores'] == 'python'
    assert reports['compiled']['workers'] == 2
    timing = ('wall_time_s', 'realtime_factor', 'realtime_factor_per_worker', 'cores')
    strip = [{k: v for k, v in r.items() if k not in timing} for r in reports.values()]
    assert strip[0] == strip[1]


def _fake_build(directory: pathlib.Path, **changes) -> None:
    sources = {m: accel._sha256(accel._source(m)) for m in accel.COMPILED_MODULES}
    for module in accel.COMPILED_MODULES:
        package, name = module.split('.')
        (directory / package).mkdir(parents=True, exist_ok=True)
        (directory / package / f'{name}.fake-tag.so').write_bytes(b'')
    manifest = {'python': accel._python_tag(), 'sources': sources}
    manifest.update(changes)
    (directory / 'manifest.json').write_text(json.dumps(manifest))


def test_a_build_matching_the_sources_is_accepted(tmp_path):
    _fake_build(tmp_path)
    assert accel.manifest_problem(tmp_path) is None


def test_a_stale_build_is_refused(tmp_path):
    sources = {m: accel._sha256(accel._source(m)) for m in accel.COMPILED_MODULES}
    sources['apron_estimator.vertical'] = '0' * 64       # the source changed since the build
    _fake_build(tmp_path, sources=sources)
    assert 'apron_estimator.vertical changed' in accel.manifest_problem(tmp_path)


def test_a_build_for_another_python_is_refused(tmp_path):
    _fake_build(tmp_path, python='cpython-39.cpython-39-x86_64-linux-gnu.so')
    assert 'compiled for cpython-39' in accel.manifest_problem(tmp_path)


def test_a_missing_or_partial_build_is_refused(tmp_path):
    assert 'no compiled cores' in accel.manifest_problem(tmp_path / 'none')
    _fake_build(tmp_path)
    (tmp_path / 'landing_planner' / 'planner.fake-tag.so').unlink()
    assert 'landing_planner.planner: extension missing' in accel.manifest_problem(tmp_path)


def test_enable_falls_back_or_fails_without_a_usable_build(tmp_path):
    """'auto' flies the sources and says why; 'compiled' is an error, never a silent fallback.
    Run in a fresh process: enable() changes how the cores import for the whole process."""
    code = ('import json, pathlib, sys\n'
            'from deckland.batch import accel\n'
            'd = pathlib.Path(sys.argv[1])\n'
            'auto = accel.enable("auto", d)\n'
            'try:\n'
            '    accel.enable("compiled", d); err = ""\n'
            'except accel.AccelError as e:\n'
            '    err = str(e)\n'
            'print(json.dumps([auto, accel.status()["reason"], err]))\n')
    res = subprocess.run([sys.executable, '-c', code, str(tmp_path / 'none')], env=_env(),
                         capture_output=True, text=True, check=True, timeout=60)
    auto, reason, err = json.loads(res.stdout)
    assert auto == 'python'
    assert 'no compiled cores' in reason
    assert 'no compiled cores' in err


def test_enable_refuses_once_a_core_was_imported_as_python():
    _ready()
    code = ('import apron_estimator.estimator\n'
            'from deckland.batch import accel\n'
            'try:\n'
            '    accel.enable("compiled"); print("enabled")\n'
            'except accel.AccelError as e:\n'
            '    print(e)\n')
    res = subprocess.run([sys.executable, '-c', code], env=_env(), capture_output=True,
                         text=True, check=True, timeout=60)
    assert 'already imported as Python' in res.stdout


def test_cores_are_python_in_the_test_process():
    """conftest pins DECKLAND_CORES=python: in-process tests patch and inspect the sources."""
    assert os.environ.get('DECKLAND_CORES') == 'python'
    assert accel.enable('auto') == 'python'
    import apron_estimator.vertical as vertical
    assert vertical.__file__.endswith('.py')


#: Core-package modules a compiled run may still load as Python, and why (each runs once
#: per run, not per tick).
KEPT_PYTHON = {
    'deck_simulator.scenario': 'scenario loading and validation',
    'deck_simulator.ship_params': 'the ship parameter dataclasses, read at construction',
    'deck_simulator.faults': 'fault injection: its frozen dataclass hierarchy does not '
                             'compile; nothing of it runs in a fault-free tick',
    'deck_simulator.outcome': 'the landing record, assembled once at the end',
    'deckland_common.validate': 'parameter validation at construction',
}

_LOADED = r"""
import json, sys
from deckland.batch import accel
accel.enable('compiled')
from deck_simulator.scenario import load_scenario
from deckland.batch.runner import RunConfig, run_landing
for scenario in ('paper', 'ship_ss4', 'fault_telemetry_loss', 'fault_false_blobs'):
    run_landing(load_scenario(scenario), 100001, RunConfig())
packages = set(accel.PACKAGES)
print(json.dumps(sorted(n for n, m in sys.modules.items() if '.' in n
                        and n.split('.')[0] in packages
                        and str(getattr(m, '__file__', '') or '').endswith('.py'))))
"""


def test_every_module_a_run_steps_is_compiled():
    """issue 12's speed: three planner modules (deck_track, deck_predictor, commit_window)
    and the ship link ran as Python for a tranche, unnoticed (paper 169 → 219x once
    compiled). A module a run loads as Python must be listed here with its reason."""
    _ready()
    res = subprocess.run([sys.executable, '-c', _LOADED], env=_env(), capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    loaded = set(json.loads(res.stdout.strip().splitlines()[-1]))
    assert loaded <= set(KEPT_PYTHON), sorted(loaded - set(KEPT_PYTHON))
