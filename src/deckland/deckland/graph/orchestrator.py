"""A small process orchestrator standing in for ``ros2 launch`` (not available here).

More in the package README, "Module notes" (`deckland.graph.orchestrator`).
"""

from __future__ import annotations

import collections
from collections.abc import Iterable
import contextlib
from dataclasses import dataclass, field
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from typing import IO, Any

from deckland_common.readiness import READY_FD_ENV, parse_ready_line
import yaml

#: Upper bound of the respawn back-off.
MAX_BACKOFF_S = 30.0
LOG_LEVELS = ('', 'debug', 'info', 'warn', 'error', 'fatal')

_NODE_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_]*')
_MODULE = re.compile(r'[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*')
_PARAM_NAME = re.compile(r'[A-Za-z][A-Za-z0-9_]*(\.[A-Za-z][A-Za-z0-9_]*)*')
_TOPIC = re.compile(r'~?/?[A-Za-z_{][A-Za-z0-9_/{}~]*')
_BAD_CHARS = re.compile(r'[\x00-\x1f\x7f]')


def _check(cond: bool, where: str, rule: str, value: Any) -> None:
    if not cond:
        raise ValueError(f'{where} {rule}, got {value!r}')


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def launcher_code(module: str, call: str) -> str:
    """The ``-c`` program of a node process: ``from MODULE import main; sys.exit(CALL)``.

    A stop that comes while the node still imports (a failed start stops every node) exits
    quietly with 128 + SIGINT instead of a KeyboardInterrupt traceback; ``main`` then runs
    with Python's default handler (the nodes install their own).
    """
    return ('import signal, sys; signal.signal(signal.SIGINT, lambda *_: sys.exit(130)); '
            f'from {module} import main; '
            f'signal.signal(signal.SIGINT, signal.default_int_handler); sys.exit({call})')


@dataclass
class NodeSpec:
    """One node of the graph (validated at construction: ``ValueError`` names the field)."""

    name: str
    package: str
    module: str = 'node'
    parameters: dict[str, Any] = field(default_factory=dict)
    remappings: dict[str, str] = field(default_factory=dict)
    respawn: bool = False
    respawn_limit: int = 3
    respawn_delay_s: float = 1.0
    sim_only: bool = False
    hardware_only: bool = False
    log_level: str = ''
    params_file: str = ''

    def __post_init__(self) -> None:
        where = f'node {self.name!r}:'
        _check(isinstance(self.name, str) and _NODE_NAME.fullmatch(self.name) is not None,
               f'{where} name', 'must be a ROS node name ([A-Za-z][A-Za-z0-9_]*)', self.name)
        for key in ('package', 'module'):
            value = getattr(self, key)
            _check(isinstance(value, str) and _MODULE.fullmatch(value) is not None,
                   f'{where} {key}', 'must be a dotted Python identifier', value)
        for key in ('respawn', 'sim_only', 'hardware_only'):
            _check(isinstance(getattr(self, key), bool), f'{where} {key}', 'must be true/false',
                   getattr(self, key))
        _check(isinstance(self.respawn_limit, int) and not isinstance(self.respawn_limit, bool)
               and self.respawn_limit >= 0, f'{where} respawn_limit', 'must be an integer >= 0',
               self.respawn_limit)
        _check(_is_number(self.respawn_delay_s) and math.isfinite(self.respawn_delay_s)
               and self.respawn_delay_s >= 0, f'{where} respawn_delay_s',
               'must be a finite number >= 0', self.respawn_delay_s)
        _check(not (self.sim_only and self.hardware_only), f'{where} sim_only',
               'and hardware_only cannot both be true', True)
        _check(self.log_level in LOG_LEVELS, f'{where} log_level', f'must be one of {LOG_LEVELS}',
               self.log_level)
        _check(isinstance(self.params_file, str) and not _BAD_CHARS.search(self.params_file),
               f'{where} params_file', 'must be a path without control characters',
               self.params_file)
        _check(isinstance(self.parameters, dict), f'{where} parameters', 'must be a mapping',
               self.parameters)
        for key, value in self.parameters.items():
            _check(isinstance(key, str) and _PARAM_NAME.fullmatch(key) is not None,
                   f'{where} parameter name', 'must be a ROS parameter name', key)
            _ros_value(value, f'{where} parameters.{key}')   # raises on unsupported values
        _check(isinstance(self.remappings, dict), f'{where} remappings', 'must be a mapping',
               self.remappings)
        for src, dst in self.remappings.items():
            for v in (src, dst):
                _check(isinstance(v, str) and _TOPIC.fullmatch(v) is not None,
                       f'{where} remapping', 'must be a ROS topic or service name', v)

    def command(self, python: str = sys.executable) -> list[str]:
        """The process's argv: run ``<package>.<module>.main()`` with ROS arguments.

        No shell is involved; ``package`` and ``module`` are validated identifiers (the only
        text in the ``-c`` program) and every parameter value is a quoted YAML literal.
        """
        code = launcher_code(f'{self.package}.{self.module}', 'main() or 0')
        argv = [python, '-c', code, '--ros-args', '-r', f'__node:={self.name}']
        for key, value in self.parameters.items():
            argv += ['-p', f'{key}:={_ros_value(value, key)}']
        for src, dst in self.remappings.items():
            argv += ['-r', f'{src}:={dst}']
        if self.params_file:
            argv += ['--params-file', self.params_file]
        if self.log_level:
            argv += ['--log-level', self.log_level]
        return argv


def _ros_value(value: Any, where: str = 'value') -> str:
    """Render a parameter value as a ``-p`` YAML literal that rcl reads back unchanged.

    Strings are always single-quoted (``'`` doubled), so ``'true'``, ``'1'``, ``'x # y'`` or
    ``"__import__('os')"`` stay the same strings; floats use YAML's ``.inf``/``.nan``.
    """
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return '.nan'
        if math.isinf(value):
            return '.inf' if value > 0 else '-.inf'
        return repr(value)
    if isinstance(value, str):
        _check(not _BAD_CHARS.search(value), where, 'must not contain control characters',
               value)
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, list | tuple):
        kinds = {type(v) for v in value}
        _check(len(kinds) <= 1 and all(isinstance(v, bool | int | float | str) for v in value),
               where, 'must be a list of one scalar type', value)
        return '[' + ','.join(_ros_value(v, where) for v in value) + ']'
    raise ValueError(f'{where} must be a bool, number, string or list of them, got {value!r}')


def load_graph(path: str, substitutions: dict[str, Any], hardware: bool) -> dict[str, Any]:
    """Read a graph YAML, fill ``{placeholders}`` and keep the nodes for this mode.

    Returns the YAML mapping with ``nodes`` replaced by validated :class:`NodeSpec` objects.
    """
    with open(path) as fh:
        raw = yaml.safe_load(fh)
    if not isinstance(raw, dict) or not isinstance(raw.get('nodes'), list):
        raise ValueError(f'{path}: a graph needs a list under "nodes"')
    unknown_top = set(raw) - {'nodes', 'wait_for_topics'}
    if unknown_top:
        raise ValueError(f'{path}: unknown top-level keys {sorted(unknown_top)}')
    wait = raw.get('wait_for_topics', [])
    if not isinstance(wait, list) or not all(
            isinstance(t, str) and _TOPIC.fullmatch(t) for t in wait):
        raise ValueError(f'{path}: wait_for_topics must be a list of topic names, got {wait!r}')
    nodes, names = [], set()
    for i, entry in enumerate(raw['nodes']):
        if not isinstance(entry, dict):
            raise ValueError(f'{path}: nodes[{i}] must be a mapping, got {entry!r}')
        unknown = set(entry) - set(NodeSpec.__dataclass_fields__)
        if unknown:
            raise ValueError(f'{path}: node {entry.get("name")!r} has unknown keys '
                             f'{sorted(unknown)}')
        entry = dict(entry)
        params = entry.get('parameters') or {}
        if not isinstance(params, dict):
            raise ValueError(f'{path}: node {entry.get("name")!r} parameters must be a mapping')
        entry['parameters'] = {k: _substitute(v, substitutions) for k, v in params.items()}
        entry['remappings'] = entry.get('remappings') or {}
        try:
            spec = NodeSpec(**entry)
        except TypeError as exc:   # a missing name/package
            raise ValueError(f'{path}: nodes[{i}]: {exc}') from None
        except ValueError as exc:
            raise ValueError(f'{path}: {exc}') from None
        if spec.name in names:
            raise ValueError(f'{path}: node name {spec.name!r} is used twice')
        names.add(spec.name)
        if (hardware and spec.sim_only) or (not hardware and spec.hardware_only):
            continue
        nodes.append(spec)
    raw['nodes'] = nodes
    raw['wait_for_topics'] = list(wait)
    return raw


def _substitute(value: Any, subs: dict[str, Any]) -> Any:
    """A value that is exactly ``{key}`` becomes ``subs[key]`` (no other templating)."""
    if isinstance(value, str) and value.startswith('{') and value.endswith('}'):
        key = value[1:-1]
        if key not in subs:
            raise ValueError(f'graph placeholder {value} has no value')
        return subs[key]
    return value


def describe_status(code: int) -> str:
    """``Popen.returncode`` in words: ``status 1`` or ``killed by SIGKILL``."""
    if code < 0:
        try:
            return f'killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'killed by signal {-code}'
    return f'exit status {code}'


def die_with_parent(cmd: list[str], sig: str = 'TERM') -> list[str]:
    """``cmd`` run so that the kernel sends it ``sig`` when the thread that started it dies
    (PR_SET_PDEATHSIG through util-linux ``setpriv``; ``cmd`` unchanged where it is missing).

    A supervisor killed outright (SIGKILL, OOM) otherwise leaves its children running
    unsupervised: nodes still commanding with no one to respawn or record them, a firmware
    still holding its ports. The exec keeps the pid, so pids reported stay the children's.
    """
    setpriv = shutil.which('setpriv')
    return [setpriv, '--pdeathsig', sig, '--', *cmd] if setpriv else cmd


def members(spec: NodeSpec) -> list[str]:
    """The ROS node names a process runs: its components when composed, else its name."""
    return [c.name for c in getattr(spec, 'components', ())] or [spec.name]


@dataclass(frozen=True, slots=True)
class ExitEvent:
    """A child that ended by itself or by fault injection (not by :meth:`Orchestrator.stop`)."""

    node: str
    pid: int
    status: int              # Popen.returncode (negative: killed by that signal)
    injected: bool           # killed on purpose (node_kill fault)
    action: str              # 'respawn' | 'gave up' | 'not respawned' | 'held'
    log_tail: tuple[str, ...]
    nodes: tuple[str, ...] = ()   # the ROS nodes that went with it (composed: all of them)

    def as_dict(self) -> dict[str, Any]:
        return {'node': self.node, 'pid': self.pid, 'status': self.status,
                'description': describe_status(self.status), 'injected': self.injected,
                'action': self.action, 'log_tail': list(self.log_tail),
                'nodes': list(self.nodes or (self.node,))}


class ManagedProcess:
    """One child process: prefixed output, the tail of its log, respawn bookkeeping."""

    def __init__(self, spec: NodeSpec, out: IO[str], env: dict[str, str],
                 out_lock: threading.Lock, tail_lines: int = 15,
                 pass_fds: tuple[int, ...] = ()):
        self.spec = spec
        self.pass_fds = pass_fds
        self.out = out
        self.env = env
        self.proc: subprocess.Popen | None = None
        self.exit_codes: list[int] = []
        self.pids: list[int] = []
        self.tail: collections.deque[str] = collections.deque(maxlen=tail_lines)
        self.respawns = 0
        self.respawn_at: float | None = None   # monotonic time of a pending respawn
        self.held = False                      # killed by fault injection, stays down
        self.kill_pending = False              # the next exit is the injected kill
        self._out_lock = out_lock
        self._reader: threading.Thread | None = None

    def start(self) -> None:
        # a node's life is bounded by its supervisor's: SIGTERM (a clean stop) if it dies
        self.proc = subprocess.Popen(
            die_with_parent(self.spec.command()), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=self.env, text=True, bufsize=1, errors='replace',
            start_new_session=True, pass_fds=self.pass_fds)
        self.pids.append(self.proc.pid)
        self.respawn_at = None
        self._reader = threading.Thread(target=self._pump, args=(self.proc,), daemon=True,
                                        name=f'out-{self.spec.name}')
        self._reader.start()

    def _pump(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        prefix = f'[{self.spec.name}] '
        with contextlib.suppress(ValueError, OSError):
            for line in proc.stdout:
                self.tail.append(line.rstrip('\n'))
                with self._out_lock:
                    self.out.write(prefix + line)
                    self.out.flush()

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, sig)

    def join_output(self, timeout: float = 1.0) -> None:
        if self._reader is not None:
            self._reader.join(timeout)


class Orchestrator:
    """Starts the graph's nodes, watches them (report, respawn), injects kills, stops them all.

    ``clock`` (monotonic seconds) is only used for respawn back-off; tests may pass their own.
    Call :meth:`check` periodically (``deckland up`` does every 0.1 s).
    """

    def __init__(self, nodes: list[NodeSpec], out: IO[str] = sys.stdout,
                 env: dict[str, str] | None = None, stop_timeout_s: float = 5.0,
                 tail_lines: int = 15, clock=time.monotonic, pass_fds: Iterable[int] = ()):
        if not stop_timeout_s > 0:
            raise ValueError(f'stop_timeout_s must be > 0, got {stop_timeout_s!r}')
        names = [n.name for n in nodes] + [m for n in nodes for m in members(n)
                                            if m != n.name]
        if len(set(names)) != len(names):
            raise ValueError(f'node names must be unique, got {names}')
        self.out = out
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault('PYTHONUNBUFFERED', '1')
        self.stop_timeout_s = stop_timeout_s
        self.clock = clock
        self._out_lock = threading.Lock()
        self._ready_r, self._ready_w = os.pipe()
        self.env[READY_FD_ENV] = str(self._ready_w)
        fds = tuple(sorted({*pass_fds, self._ready_w}))
        self.procs = [ManagedProcess(n, out, self.env, self._out_lock, tail_lines, fds)
                      for n in nodes]
        #: node name -> {'pid', 'problem'} of its latest readiness line (respawns replace it)
        self.ready: dict[str, dict[str, Any]] = {}
        self._ready_cond = threading.Condition()
        self._ready_thread = threading.Thread(target=self._read_ready, daemon=True,
                                              name='ready-pipe')
        self._ready_thread.start()
        #: process and ROS node names -> their process (composed nodes share one)
        self.by_name = {name: p for p in self.procs for name in {p.spec.name, *members(p.spec)}}
        self.exits: list[ExitEvent] = []
        self.stopping = False

    # --- life cycle ----------------------------------------------------------------------

    def start(self) -> None:
        for p in self.procs:
            p.start()
            self.log(f'started {p.spec.name} (pid {p.proc.pid})')

    def _read_ready(self) -> None:
        """Collect the readiness lines (a line is one atomic pipe write, < PIPE_BUF)."""
        with os.fdopen(self._ready_r, 'r', errors='replace') as fh:
            for line in fh:
                msg = parse_ready_line(line)
                if msg is None or msg['node'] not in self.by_name:
                    continue
                with self._ready_cond:
                    self.ready[msg['node']] = {'pid': msg['pid'], 'problem': msg['problem']}
                    self._ready_cond.notify_all()
                if msg['problem']:
                    self.log(f"{msg['node']} is up without its device: {msg['problem']}")

    def is_ready(self, name: str) -> bool:
        """The running process of ``name`` has reported ready (a respawn must report again)."""
        p = self.by_name[name]
        info = self.ready.get(name)
        return info is not None and p.alive() and info['pid'] in p.pids[-1:]

    def wait_ready(self, timeout_s: float, abort=None) -> list[str]:
        """Wait until every node has reported ready; return those that have not.

        ``abort()`` (optional) is polled at least every 0.1 s and ends the wait early.
        """
        deadline = time.monotonic() + timeout_s
        with self._ready_cond:
            while True:
                missing = [m for p in self.procs for m in members(p.spec)
                           if not self.is_ready(m)]
                left = deadline - time.monotonic()
                if not missing or left <= 0 or (abort is not None and abort()):
                    return missing
                self._ready_cond.wait(min(0.1, left))

    def device_problems(self) -> dict[str, str]:
        """``node -> problem`` of the nodes that came up without their device."""
        return {n: r['problem'] for n, r in self.ready.items() if r['problem']}

    def log(self, text: str) -> None:
        with self._out_lock:
            self.out.write(f'[deckland up] {text}\n')
            self.out.flush()

    @property
    def crashed(self) -> list[tuple[str, int]]:
        """``(node, status)`` of the exits that were not injected (crashes, unexpected exits);
        :attr:`exits` has the details (log tail, action)."""
        return [(e.node, e.status) for e in self.exits if not e.injected]

    def pids(self) -> list[int]:
        """Every child pid ever started (respawns included)."""
        return [pid for p in self.procs for pid in p.pids]

    def alive(self) -> list[str]:
        return [p.spec.name for p in self.procs if p.alive()]

    def check(self) -> list[ExitEvent]:
        """Report children that exited since the last call, run due respawns.

        Returns the new exit events. A node with ``respawn: true`` is started again after
        ``respawn_delay_s · 2^k`` (k = respawns so far, capped at :data:`MAX_BACKOFF_S`) until
        ``respawn_limit`` respawns are used up; a held (fault-killed) node stays down.
        """
        now = self.clock()
        new: list[ExitEvent] = []
        for p in self.procs:
            if p.proc is None:
                continue
            code = p.proc.poll()
            if code is not None and p.respawn_at is None and len(p.exit_codes) < len(p.pids):
                p.exit_codes.append(code)
                if self.stopping and not p.kill_pending:
                    continue       # stopped by stop(): expected, not an event
                p.join_output(0.2)
                injected = p.kill_pending
                p.kill_pending = False
                if p.held:
                    action = 'held'
                elif self.stopping or not p.spec.respawn:
                    action = 'not respawned'
                elif p.respawns >= p.spec.respawn_limit:
                    action = 'gave up'
                else:
                    action = 'respawn'
                    delay = min(MAX_BACKOFF_S, p.spec.respawn_delay_s * 2.0 ** p.respawns)
                    p.respawn_at = now + delay
                event = ExitEvent(p.spec.name, p.proc.pid, code, injected, action,
                                  tuple(p.tail), tuple(members(p.spec)))
                self.exits.append(event)
                new.append(event)
                self._report(event, p)
            if (p.respawn_at is not None and now >= p.respawn_at and not self.stopping
                    and not p.held):
                p.respawns += 1
                p.start()
                self.log(f'respawned {p.spec.name} (pid {p.proc.pid}, respawn {p.respawns} '
                         f'of {p.spec.respawn_limit})')
        return new

    def _report(self, e: ExitEvent, p: ManagedProcess) -> None:
        what = 'was killed (fault injection)' if e.injected else 'died'
        self.log(f'{e.node} (pid {e.pid}) {what}: {describe_status(e.status)}')
        if e.nodes and e.nodes != (e.node,):
            self.log(f'{e.node}: composed nodes lost with it: {", ".join(e.nodes)}')
        if not e.injected:
            for line in e.log_tail[-10:]:
                self.log(f'  {e.node} | {line}')
        if e.action == 'respawn':
            self.log(f'{e.node}: respawning in {p.respawn_at - self.clock():.1f} s '
                     f'({p.respawns + 1} of {p.spec.respawn_limit})')
        elif e.action == 'gave up':
            self.log(f'{e.node}: respawn limit {p.spec.respawn_limit} reached; not respawned')

    # --- fault injection -----------------------------------------------------------------

    def kill(self, name: str, sig: int = signal.SIGKILL) -> bool:
        """Kill node ``name`` (its process group) and hold it down until :meth:`release`."""
        p = self.by_name.get(name)
        if p is None:
            raise KeyError(f'no node {name!r} in the graph ({sorted(self.by_name)})')
        p.held = True
        p.respawn_at = None
        if not p.alive():
            return False
        p.kill_pending = True
        where = name if p.spec.name == name else f'{name} (composed in {p.spec.name})'
        self.log(f'fault injection: {describe_status(-sig).replace("killed by", "sending")} '
                 f'to {where} (pid {p.proc.pid})')
        p.signal(sig)
        return True

    def release(self, name: str) -> None:
        """End a kill fault: start the node again now (if it is down)."""
        p = self.by_name[name]
        p.held = False
        if not p.alive() and not self.stopping:
            self.check()     # record the kill's exit first
            p.start()
            self.log(f'fault injection over: restarted {name} (pid {p.proc.pid})')

    # --- shutdown ------------------------------------------------------------------------

    def stop(self) -> float:
        """SIGINT, then SIGTERM, then SIGKILL to every process group; all gone in the timeout.

        Returns the time it took (s).
        """
        self.stopping = True
        start = time.monotonic()
        deadline = start + self.stop_timeout_s
        for sig, share in ((signal.SIGINT, 0.5), (signal.SIGTERM, 0.8), (signal.SIGKILL, 0.9)):
            for p in self.procs:
                p.signal(sig)
            until = start + self.stop_timeout_s * share
            while time.monotonic() < until:
                if not any(p.alive() for p in self.procs):
                    break
                time.sleep(0.02)
            if not any(p.alive() for p in self.procs):
                break
        for p in self.procs:
            if p.proc is not None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            # the children's own children (same process group) go with the group
            with contextlib.suppress(ProcessLookupError, PermissionError):
                if p.proc is not None:
                    os.killpg(p.proc.pid, signal.SIGKILL)
            p.join_output(0.3)
        return time.monotonic() - start

    def close(self) -> None:
        """Release the readiness pipe (after :meth:`stop`)."""
        with contextlib.suppress(OSError):
            os.close(self._ready_w)   # the reader sees EOF once no child holds it either
        self._ready_thread.join(timeout=1.0)
