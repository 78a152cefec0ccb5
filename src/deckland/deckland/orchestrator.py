"""A small process orchestrator standing in for ``ros2 launch`` (not available here).

The graph is a YAML list of nodes; each node runs as its own process with ``--ros-args``
(``-r __node:=NAME``, ``-p key:=value`` and ``-r from:=to``). Output lines are prefixed with
the node's name. A node that exits is reported (and respawned if its entry says so). ``stop``
sends SIGINT to every child, then SIGTERM, then SIGKILL, all within ``stop_timeout_s``.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import os
import signal
import subprocess
import sys
import threading
import time
from typing import IO, Any

import yaml


@dataclass
class NodeSpec:
    """One node of the graph."""

    name: str
    package: str
    module: str = 'node'
    parameters: dict[str, Any] = field(default_factory=dict)
    remappings: dict[str, str] = field(default_factory=dict)
    respawn: bool = False
    sim_only: bool = False
    hardware_only: bool = False
    log_level: str = ''
    params_file: str = ''

    def command(self, python: str = sys.executable) -> list[str]:
        """The process's argv: run ``<package>.<module>.main()`` with ROS arguments."""
        code = (f'import sys; from {self.package}.{self.module} import main; '
                'sys.exit(main() or 0)')
        argv = [python, '-c', code, '--ros-args', '-r', f'__node:={self.name}']
        for key, value in self.parameters.items():
            argv += ['-p', f'{key}:={_ros_value(value)}']
        for src, dst in self.remappings.items():
            argv += ['-r', f'{src}:={dst}']
        if self.params_file:
            argv += ['--params-file', self.params_file]
        if self.log_level:
            argv += ['--log-level', self.log_level]
        return argv


def _ros_value(value: Any) -> str:
    """Render a parameter value as a ``-p`` literal (YAML syntax, as ros2 run expects)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value if value else "''"
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(_ros_value(v) for v in value) + ']'
    return repr(value)


def load_graph(path: str, substitutions: dict[str, Any], hardware: bool) -> dict[str, Any]:
    """Read a graph YAML, fill ``{placeholders}`` and keep the nodes for this mode."""
    with open(path) as fh:
        raw = yaml.safe_load(fh)
    if not isinstance(raw, dict) or not isinstance(raw.get('nodes'), list):
        raise ValueError(f'{path}: a graph needs a list under "nodes"')
    nodes = []
    for entry in raw['nodes']:
        unknown = set(entry) - set(NodeSpec.__dataclass_fields__)
        if unknown:
            raise ValueError(f'{path}: node {entry.get("name")!r} has unknown keys {unknown}')
        spec = NodeSpec(**entry)
        if (hardware and spec.sim_only) or (not hardware and spec.hardware_only):
            continue
        spec.parameters = {k: _substitute(v, substitutions) for k, v in spec.parameters.items()}
        nodes.append(spec)
    raw['nodes'] = nodes
    return raw


def _substitute(value: Any, subs: dict[str, Any]) -> Any:
    if isinstance(value, str) and value.startswith('{') and value.endswith('}'):
        key = value[1:-1]
        if key not in subs:
            raise ValueError(f'graph placeholder {value} has no value')
        return subs[key]
    return value


class ManagedProcess:
    """One child process with prefixed output and optional respawn."""

    def __init__(self, spec: NodeSpec, out: IO[str], env: dict[str, str]):
        self.spec = spec
        self.out = out
        self.env = env
        self.proc: subprocess.Popen | None = None
        self.exit_codes: list[int] = []
        self._reader: threading.Thread | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            self.spec.command(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=self.env, text=True, bufsize=1,
            start_new_session=True)
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        prefix = f'[{self.spec.name}] '
        for line in self.proc.stdout:
            self.out.write(prefix + line)
            self.out.flush()

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, sig)

    def join_output(self, timeout: float = 1.0) -> None:
        if self._reader is not None:
            self._reader.join(timeout)


class Orchestrator:
    """Starts the graph's nodes, watches them, and stops them all on request."""

    def __init__(self, nodes: list[NodeSpec], out: IO[str] = sys.stdout,
                 env: dict[str, str] | None = None, stop_timeout_s: float = 5.0):
        self.out = out
        self.env = dict(os.environ if env is None else env)
        self.env.setdefault('PYTHONUNBUFFERED', '1')
        self.stop_timeout_s = stop_timeout_s
        self.procs = [ManagedProcess(n, out, self.env) for n in nodes]
        self.crashed: list[tuple[str, int]] = []

    def start(self) -> None:
        for p in self.procs:
            p.start()
            self.log(f'started {p.spec.name} (pid {p.proc.pid})')

    def log(self, text: str) -> None:
        self.out.write(f'[deckland up] {text}\n')
        self.out.flush()

    def check(self) -> list[str]:
        """Report children that exited; respawn those that ask for it. Returns the dead."""
        dead = []
        for p in self.procs:
            code = p.poll()
            if code is None:
                continue
            p.exit_codes.append(code)
            if p.spec.respawn:
                self.log(f'{p.spec.name} exited with {code}; respawning')
                p.start()
            else:
                if (p.spec.name, code) not in self.crashed:
                    self.crashed.append((p.spec.name, code))
                    self.log(f'{p.spec.name} exited with status {code}')
                dead.append(p.spec.name)
        return dead

    def stop(self) -> float:
        """SIGINT, then SIGTERM, then SIGKILL; all children gone within the timeout."""
        start = time.monotonic()
        deadline = start + self.stop_timeout_s
        for sig, share in ((signal.SIGINT, 0.5), (signal.SIGTERM, 0.8), (signal.SIGKILL, 1.0)):
            for p in self.procs:
                p.signal(sig)
            until = start + self.stop_timeout_s * share
            while time.monotonic() < min(until, deadline):
                if all(p.poll() is not None for p in self.procs):
                    break
                time.sleep(0.02)
            if all(p.poll() is not None for p in self.procs):
                break
        for p in self.procs:
            if p.proc is not None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.proc.wait(timeout=max(0.0, deadline - time.monotonic()) + 0.5)
            p.join_output(0.5)
        return time.monotonic() - start
