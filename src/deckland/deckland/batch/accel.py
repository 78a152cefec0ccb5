"""Compiled cores for batch runs: the same Python sources, compiled by mypyc.

More in the package README, "Module notes" (`deckland.batch.accel`).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

#: Packages whose modules are compiled; each is an ament_python package under src/.
PACKAGES = ('deckland_common', 'deck_simulator', 'apron_estimator', 'landing_planner',
            'dob_altitude')

#: The modules a closed-loop run steps every tick: the cores and the nodes' loop cores.
#: Scenario loading, validation helpers, the fault injection (its frozen dataclass hierarchy
#: with class-level ``type`` names does not compile; it costs nothing in fault-free runs) and
#: everything touching rclpy stay Python.
COMPILED_MODULES = (
    'deckland_common.checks',
    'deckland_common.contract',
    'deckland_common.frames',
    'deckland_common.lens',
    'deck_simulator.autopilot',
    'deck_simulator.contact',
    'deck_simulator.deck',
    'deck_simulator.deck_motion',
    'deck_simulator.link',
    'deck_simulator.rigid_body',
    'deck_simulator.rotor_ground_effect',
    'deck_simulator.sensor_camera',
    'deck_simulator.sensor_ekf',
    'deck_simulator.sensor_imu',
    'deck_simulator.sensor_lidar',
    'deck_simulator.sensor_models',
    'deck_simulator.sensor_suite',
    'deck_simulator.sensors',
    'deck_simulator.ship',
    'deck_simulator.ship_link',
    'deck_simulator.touchdown',
    'deck_simulator.vehicle',
    'deck_simulator.world',
    'apron_estimator.camera',
    'apron_estimator.deck',
    'apron_estimator.estimator',
    'apron_estimator.horizontal',
    'apron_estimator.inputs',
    'apron_estimator.loop',
    'apron_estimator.vertical',
    'dob_altitude.adapter',
    'dob_altitude.dob',
    'dob_altitude.ground_effect',
    'dob_altitude.loop',
    'dob_altitude.pid',
    'dob_altitude.types',
    'landing_planner.commit_window',
    'landing_planner.deck_predictor',
    'landing_planner.deck_track',
    'landing_planner.horizontal',
    'landing_planner.loop',
    'landing_planner.planner',
    'landing_planner.reference',
    'landing_planner.search',
)

CORES_CHOICES = ('auto', 'python', 'compiled')
_GROUP = 'deckland_cores'
_MANIFEST = 'manifest.json'
_state: dict[str, str] = {'cores': 'python', 'reason': 'not requested'}


class AccelError(RuntimeError):
    """Compiled cores were required (`--cores compiled`) but cannot be used."""


def accel_dir() -> pathlib.Path:
    env = os.environ.get('DECKLAND_ACCEL_DIR')
    if env:
        return pathlib.Path(env)
    here = pathlib.Path(__file__).resolve()
    # editable install: <root>/src/deckland/deckland/batch/accel.py
    if len(here.parents) > 4 and here.parents[3].name == 'src':
        return here.parents[4] / 'build' / 'accel'
    return pathlib.Path.home() / '.cache' / 'deckland' / 'accel'


def _package_dir(package: str) -> pathlib.Path:
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise AccelError(f'package {package} is not installed')
    return pathlib.Path(list(spec.submodule_search_locations)[-1])


def _source(module: str) -> pathlib.Path:
    package, name = module.split('.')
    return _package_dir(package) / f'{name}.py'


def _sha256(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _python_tag() -> str:
    return f'{sys.implementation.cache_tag}{importlib.machinery.EXTENSION_SUFFIXES[0]}'


def manifest_problem(directory: pathlib.Path | None = None) -> str | None:
    """Why the build in ``directory`` cannot be used now (None: it can)."""
    directory = directory or accel_dir()
    path = directory / _MANIFEST
    if not path.is_file():
        return f'no compiled cores in {directory} (build them: deckland accel build)'
    try:
        manifest = json.loads(path.read_text())
        sources = manifest['sources']
        python = manifest['python']
    except (OSError, ValueError, KeyError) as exc:
        return f'unreadable manifest {path}: {exc}'
    if python != _python_tag():
        return f'compiled for {python}, this interpreter is {_python_tag()}'
    if sorted(sources) != sorted(COMPILED_MODULES):
        return 'the build compiled another module set (rebuild: deckland accel build)'
    for module, digest in sources.items():
        if _sha256(_source(module)) != digest:
            return f'{module} changed since the build (rebuild: deckland accel build)'
        package, name = module.split('.')
        if not list((directory / package).glob(f'{name}.*.so')) and not list(
                (directory / package).glob(f'{name}.*.pyd')):
            return f'{module}: extension missing in {directory}'
    return None


def cores() -> str:
    """'compiled' once `enable()` succeeded in this process, else 'python'."""
    return _state['cores']


def status() -> dict[str, str]:
    return dict(_state)


def enable(mode: str = 'auto', directory: pathlib.Path | None = None) -> str:
    """Load the compiled cores for the rest of this process if ``mode`` asks for them.

    ``mode``: 'python' (never), 'auto' (if a fresh build exists), 'compiled' (must; else
    `AccelError`). ``$DECKLAND_CORES`` overrides ``mode`` when set. Returns the cores in use.
    """
    mode = os.environ.get('DECKLAND_CORES') or mode
    if mode not in CORES_CHOICES:
        raise AccelError(f'cores must be one of {CORES_CHOICES}, got {mode!r}')
    if _state['cores'] == 'compiled':
        return 'compiled'
    if mode == 'python':
        _state.update(cores='python', reason='python requested')
        return 'python'
    directory = directory or accel_dir()
    problem = manifest_problem(directory)
    loaded = sorted(m for m in COMPILED_MODULES if m in sys.modules)
    if problem is None and loaded:
        problem = f'core modules already imported as Python ({", ".join(loaded[:3])}...)'
    if problem is not None:
        if mode == 'compiled':
            raise AccelError(problem)
        _state.update(cores='python', reason=problem)
        return 'python'
    for package in PACKAGES:
        # imported before the accel directory joins sys.path (whose package-named folders
        # would otherwise be taken for namespace packages)
        pkg = importlib.import_module(package)
        if not isinstance(pkg.__path__, list):
            raise AccelError(f'{package} is not a regular package ({pkg.__path__!r})')
        pkg.__path__.insert(0, str(directory / package))
    if str(directory) not in sys.path:
        sys.path.append(str(directory))     # the shared library every extension imports
    wrong = []
    for module in COMPILED_MODULES:
        mod = importlib.import_module(module)
        if not str(getattr(mod, '__file__', '')).endswith(('.so', '.pyd')):
            wrong.append(module)
    if wrong:   # cannot happen with a valid manifest; never fly a mixture silently
        raise AccelError(f'compiled cores did not load for {wrong}')
    _state.update(cores='compiled', reason=str(directory), dir=str(directory))
    return 'compiled'


def worker_init(directory: str | None) -> None:
    """Pool initializer for spawned workers: load what the parent loaded."""
    if directory:
        enable('compiled', pathlib.Path(directory))


def build(directory: pathlib.Path | None = None, jobs: int = 0, verbose: bool = False) -> dict:
    """Compile `COMPILED_MODULES` into ``directory``; return the manifest written."""
    directory = directory or accel_dir()
    import mypy.version  # build-time only dependency (requirements.txt)

    with tempfile.TemporaryDirectory(prefix='deckland-accel-') as tmp:
        stage = pathlib.Path(tmp)
        sources = {}
        for package in PACKAGES:
            (stage / package).mkdir()
            for py in sorted(_package_dir(package).glob('*.py')):
                shutil.copy2(py, stage / package / py.name)
        for module in COMPILED_MODULES:
            sources[module] = _sha256(_source(module))
        paths = [f'{m.replace(".", "/")}.py' for m in COMPILED_MODULES]
        (stage / 'mypy.ini').write_text(
            '[mypy]\nignore_missing_imports = True\nfollow_imports = silent\n')
        (stage / 'setup.py').write_text(
            'from setuptools import setup\n'
            'from mypyc.build import mypycify\n'
            f'setup(name={_GROUP!r}, ext_modules=mypycify({paths!r}, opt_level="3", '
            f'multi_file=True, group_name={_GROUP!r}))\n')
        env = dict(os.environ)
        env['CFLAGS'] = (env.get('CFLAGS', '') + ' -ffp-contract=off').strip()
        cmd = [sys.executable, 'setup.py', 'build_ext', '--inplace',
               f'--parallel={jobs or os.cpu_count() or 1}']
        proc = subprocess.run(cmd, cwd=stage, env=env, capture_output=not verbose, text=True)
        if proc.returncode != 0:
            tail = '' if verbose else (proc.stdout + proc.stderr)[-4000:]
            raise AccelError(f'mypyc build failed:\n{tail}')
        out = directory.with_name(directory.name + '.tmp')
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        for lib in stage.glob(f'{_GROUP}__mypyc.*'):
            if lib.suffix in ('.so', '.pyd'):
                shutil.copy2(lib, out / lib.name)
        for module in COMPILED_MODULES:
            package, name = module.split('.')
            (out / package).mkdir(exist_ok=True)
            built = [p for p in (stage / package).glob(f'{name}.*') if p.suffix in ('.so', '.pyd')]
            if len(built) != 1:
                raise AccelError(f'{module}: expected one extension, found {built}')
            shutil.copy2(built[0], out / package / built[0].name)
    manifest = {'python': _python_tag(), 'mypy': mypy.version.__version__,
                'cflags': '-O3 -ffp-contract=off', 'sources': sources}
    (out / _MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + '\n')
    shutil.rmtree(directory, ignore_errors=True)
    out.rename(directory)
    return manifest


def _cmd_build(args) -> int:
    try:
        manifest = build(pathlib.Path(args.dir) if args.dir else None, verbose=args.verbose)
    except AccelError as exc:
        print(exc, file=sys.stderr)
        return 1
    print(f'compiled {len(manifest["sources"])} modules into {args.dir or accel_dir()}')
    return 0


def _cmd_status(args) -> int:
    directory = pathlib.Path(args.dir) if args.dir else accel_dir()
    problem = manifest_problem(directory)
    print(f'compiled cores in {directory}: ' + ('ready' if problem is None else problem))
    return 0 if problem is None else 1


def register(sub) -> None:
    p = sub.add_parser('accel', help='build or check the compiled cores for batch runs')
    asub = p.add_subparsers(dest='accel_command', metavar='ACTION')
    asub.required = True
    b = asub.add_parser('build', help='compile the cores with mypyc (about 1-2 minutes)')
    b.add_argument('--dir', help='output directory (default: build/accel of the source tree)')
    b.add_argument('--verbose', action='store_true', help='show the compiler output')
    b.set_defaults(func=_cmd_build)
    s = asub.add_parser('status', help='exit 0 if a build matching the sources is ready')
    s.add_argument('--dir', help='accel directory to check')
    s.set_defaults(func=_cmd_status)


def add_cores_argument(parser) -> None:
    parser.add_argument(
        '--cores', choices=CORES_CHOICES, default='auto',
        help="'compiled': the mypyc build of the cores (deckland accel build), 'python': the "
             "sources, 'auto' (default): compiled when a build matches the sources")


def select_from_argv(argv: list[str], commands: tuple[str, ...]) -> None:
    """Apply ``--cores`` of a batch subcommand before anything imports a core module."""
    import argparse
    words = [w for w in argv if not w.startswith('-')]
    if not words or words[0] not in commands:
        return
    pre = argparse.ArgumentParser(add_help=False)
    add_cores_argument(pre)
    known, _ = pre.parse_known_args(argv)
    try:
        used = enable(known.cores)
    except AccelError as exc:
        raise SystemExit(f'deckland: --cores compiled: {exc}') from exc
    if used == 'python' and known.cores == 'auto' and 'DECKLAND_CORES' not in os.environ:
        print(f'deckland: Python cores ({_state["reason"]})', file=sys.stderr)
