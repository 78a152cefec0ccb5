"""What every firmware-in-the-loop process shares: lifecycle, ports, CPU, a GCS operator.

:class:`SitlProcess` is one firmware process in a fresh temporary working directory: spawned
niced and tied to its parent's life (``setpriv --pdeathsig``), its console captured to a log,
waited on by regex, killed with its process group and cleaned up on :meth:`~SitlProcess.stop`
(logs kept on request). :class:`GcsOperator` is a ground station on the firmware's GCS link:
heartbeats at 1 Hz, the mode/arming/landed-state/position it reports, acknowledgements, texts
and parameter reads. PX4 (:mod:`.px4`, :mod:`.mission`) and ArduCopter (:mod:`.ardupilot`)
fill in only what differs: the command line, the ports, the transport and the mode names.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import contextlib
import json
import math
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from typing import Any
import weakref

from deckland.graph.orchestrator import die_with_parent
from deckland.sitl import SitlStartError


def cleanup(pid: int, workdir: str) -> None:
    """Last-resort clean-up of a process never stopped (garbage-collected or at exit)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal.SIGKILL)
    shutil.rmtree(workdir, ignore_errors=True)


def udp_free(port: int) -> bool:
    """Nobody holds UDP ``port`` on the loopback."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


def tcp_free(port: int, *, reuse_address: bool = False) -> bool:
    """Nobody listens on TCP ``port``; with ``reuse_address`` (as ArduPilot binds it) the
    TIME_WAIT connections of an earlier process on the port do not count."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        if reuse_address:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


def proc_cpu_s(pid: int) -> float:
    """CPU time (user + system, s) of process ``pid`` so far (its threads included); NaN
    when it is gone."""
    try:
        fields = pathlib.Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


class SitlProcess:
    """One firmware process (a context manager, or :meth:`start` / :meth:`stop`).

    Subclasses set :attr:`NAME` (for messages), :attr:`LOG_NAME` (the console log in the
    working directory), :attr:`PREFIX` (of the directory), :attr:`START_ERROR`, and implement
    :meth:`_spawn` (take an instance, then :meth:`_popen`), :meth:`_ports_of` and optionally
    :meth:`_keep_logs`. ``nice``: the process's niceness (the machine is shared);
    ``keep_log_dir``: where :meth:`stop` copies the logs before the directory goes.
    """

    NAME = 'firmware'
    LOG_NAME = 'console.log'
    PREFIX = 'deckland-sitl-'
    START_ERROR: type[SitlStartError] = SitlStartError
    #: signals :meth:`stop` sends the process group, each followed by a wait of 2 s
    STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGKILL)

    def __init__(self, *, instance: int | None = None, nice: int = 0,
                 keep_log_dir: pathlib.Path | None = None) -> None:
        self.preferred_instance = instance
        self.nice = int(nice)
        self.keep_log_dir = keep_log_dir
        self.instance: int | None = None
        self.workdir: pathlib.Path | None = None
        self.proc: subprocess.Popen | None = None
        self.started_s = float('nan')
        self._log: Any = None
        self._finalizer: weakref.finalize | None = None

    def __enter__(self) -> Any:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _ports_of(self, instance: int) -> dict[str, int]:
        raise NotImplementedError

    @property
    def ports(self) -> dict[str, int]:
        if self.instance is None:
            raise RuntimeError(f'{type(self).__name__} not started')
        return self._ports_of(self.instance)

    @property
    def log_path(self) -> pathlib.Path:
        assert self.workdir is not None
        return self.workdir / self.LOG_NAME

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors='replace')
        except OSError:
            return ''

    def start(self) -> None:
        """Make the working directory and spawn the process (returns at once;
        :meth:`wait_for_log` waits for a line that says it is up)."""
        if self.proc is not None:
            raise RuntimeError(f'{type(self).__name__} already started')
        self.workdir = pathlib.Path(tempfile.mkdtemp(prefix=self.PREFIX))
        try:
            self._spawn()
        except BaseException:
            self.stop()
            raise

    def _spawn(self) -> None:
        raise NotImplementedError

    def _popen(self, cmd: list[str], cwd: pathlib.Path, env: dict[str, str] | None = None
               ) -> None:
        """Start ``cmd`` niced, in its own session, its console to :attr:`log_path`."""
        assert self.workdir is not None
        if self.nice:
            cmd = ['nice', '-n', str(self.nice), *cmd]
        # SIGKILL to the firmware when the thread that started it dies (a killed test run
        # must not leave it holding its instance's ports)
        cmd = die_with_parent(cmd, 'KILL')
        self._log = open(self.log_path, 'wb')  # noqa: SIM115 (closed in stop())
        self.started_s = time.monotonic()
        self.proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                                     stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        self._finalizer = weakref.finalize(self, cleanup, self.proc.pid, str(self.workdir))

    def wait_for_log(self, pattern: str, timeout_s: float) -> float:
        """Seconds from the spawn until ``pattern`` (a regex) appears in the console output;
        :attr:`START_ERROR` when the process exits or the timeout passes first."""
        rx = re.compile(pattern)
        end = time.monotonic() + timeout_s
        while True:
            text = self.log_text()
            if rx.search(text):
                return time.monotonic() - self.started_s
            if self.proc is None or self.proc.poll() is not None:
                rc = self.proc.returncode if self.proc else '?'
                raise self.START_ERROR(f'{self.NAME} exited ({rc}) before {pattern!r}; its '
                                       f'log ends:\n{text[-2000:]}')
            if time.monotonic() > end:
                raise self.START_ERROR(f'{self.NAME} not at {pattern!r} after {timeout_s:g} '
                                       f's; its log ends:\n{text[-2000:]}')
            time.sleep(0.05)

    def cpu_s(self) -> float:
        """CPU time (user + system, s) of the process so far (its threads included)."""
        return float('nan') if self.proc is None else proc_cpu_s(self.proc.pid)

    def kill(self) -> None:
        """Kill the process now, keeping the directory (a crash or a reboot in a test)."""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=2.0)

    def _release(self) -> None:
        """Give the instance back (a lock held for the process's life)."""

    def _keep_logs(self, dest: pathlib.Path) -> None:
        with contextlib.suppress(OSError):
            shutil.copy2(self.log_path, dest / self.LOG_NAME)

    def stop(self) -> None:
        """Kill the process group, release the instance and remove the working directory
        (the logs copied to ``keep_log_dir`` first). Safe to call more than once."""
        proc, self.proc = self.proc, None
        if self._finalizer is not None:
            self._finalizer.detach()
            self._finalizer = None
        if proc is not None:
            for sig in self.STOP_SIGNALS:
                if proc.poll() is not None:
                    break
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, sig)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=2.0)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)   # stray members of the group
        if self._log is not None:
            self._log.close()
            self._log = None
        self._release()
        if self.workdir is not None:
            if self.keep_log_dir is not None:
                dest = pathlib.Path(self.keep_log_dir)
                dest.mkdir(parents=True, exist_ok=True)
                self._keep_logs(dest)
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None


class UdpWriter:
    """pymavlink's output "file" for a UDP peer (send errors dropped: the peer may be gone)."""

    def __init__(self, sock: socket.socket, addr: tuple[str, int]) -> None:
        self.sock, self.addr = sock, addr

    def write(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            self.sock.sendto(data, self.addr)


class GcsOperator:
    """A ground station on a firmware's GCS link, in a thread of its own: a heartbeat at 1 Hz
    and what an operator sees — :attr:`armed`, :attr:`mode`, :attr:`landed_state`,
    :attr:`local_ned`, :attr:`home_ned`, :attr:`origin`, :attr:`modes` (monotonic time, mode
    name, armed) on every change, :attr:`texts`, :attr:`acks`, :attr:`params` (name →
    (value, MAV_PARAM_TYPE)). Subclasses give the transport (:meth:`_recv`, :meth:`write`)
    and the firmware's heartbeat (:meth:`_mode_of`) and parameter encoding
    (:meth:`_param_of`); the thread starts with :meth:`_start`."""

    THREAD_NAME = 'gcs_operator'

    def __init__(self, system_id: int) -> None:
        from pymavlink.dialects.v20 import common as mavlink
        self._mavlink = mavlink
        self.target = system_id
        self.mav = mavlink.MAVLink(self, srcSystem=255, srcComponent=190)
        self.rx = mavlink.MAVLink(None)
        self.rx.robust_parsing = True
        self.heartbeats = 0
        self.armed = False
        self.mode = ''
        self.landed_state = 0
        self.local_ned: tuple[float, float, float] | None = None
        self.origin: tuple[int, int, int] | None = None
        self.home_ned: tuple[float, float, float] | None = None
        self.modes: list[tuple[float, str, bool]] = []
        self.texts: list[tuple[float, str]] = []
        self.acks: list[tuple[float, int, int]] = []
        self.params: dict[str, tuple[float, int]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=self.THREAD_NAME, daemon=True)

    def _start(self) -> None:
        self._thread.start()

    def write(self, data: bytes) -> None:      # pymavlink's file
        raise NotImplementedError

    def _recv(self) -> bytes | None:
        """The next datagram/segment (None: nothing within ~50 ms, or not connected)."""
        raise NotImplementedError

    def _mode_of(self, m: Any) -> str | None:
        """The mode name of a HEARTBEAT from the autopilot, None for anyone else's."""
        raise NotImplementedError

    def _param_of(self, m: Any) -> float:
        return float(m.param_value)

    def _on_heartbeat(self) -> None:
        """Called before the autopilot's first heartbeat is counted."""

    def _run(self) -> None:
        mavlink = self._mavlink
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 1.0
                self.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                        0, 0, mavlink.MAV_STATE_ACTIVE)
            data = self._recv()
            if not data:
                continue
            try:
                msgs = self.rx.parse_buffer(data) or []
            except Exception:
                continue
            for m in msgs:
                self._on_message(time.monotonic(), m)

    def _on_message(self, now: float, m: Any) -> None:
        from mavlink_bridge.conversions import MAV_MODE_FLAG_SAFETY_ARMED
        kind = m.get_type()
        if kind == 'HEARTBEAT':
            mode = self._mode_of(m)
            if mode is None:
                return
            if self.heartbeats == 0:
                self._on_heartbeat()
            self.heartbeats += 1
            armed = bool(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            if mode != self.mode or armed != self.armed or not self.modes:
                self.modes.append((now, mode, armed))
            self.mode, self.armed = mode, armed
        elif kind == 'EXTENDED_SYS_STATE':
            self.landed_state = int(m.landed_state)
        elif kind == 'LOCAL_POSITION_NED':
            self.local_ned = (float(m.x), float(m.y), float(m.z))
        elif kind == 'HOME_POSITION':
            self.home_ned = (float(m.x), float(m.y), float(m.z))
        elif kind == 'GPS_GLOBAL_ORIGIN':
            self.origin = (int(m.latitude), int(m.longitude), int(m.altitude))
        elif kind == 'STATUSTEXT':
            self.texts.append((now, str(m.text)))
        elif kind == 'COMMAND_ACK':
            self.acks.append((now, int(m.command), int(m.result)))
        elif kind == 'PARAM_VALUE':
            self.params[str(m.param_id)] = (self._param_of(m), int(m.param_type))

    def command(self, cmd: int, *params: float) -> None:
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.target, 1, cmd, 0, *p)

    def read_params(self, names, timeout_s: float = 5.0) -> dict[str, float]:
        """The autopilot's values of ``names`` (PARAM_REQUEST_READ, repeated for the ones
        still missing every 0.3 s)."""
        names = list(names)
        for name in names:
            self.params.pop(name, None)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            missing = [n for n in names if n not in self.params]
            if not missing:
                break
            for name in missing:
                self.mav.param_request_read_send(self.target, 1, name.encode('ascii'), -1)
                time.sleep(0.005)
            time.sleep(0.3)
        return {n: self.params[n][0] for n in names if n in self.params}

    def _close_transport(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._close_transport()


def measure_main(prog: str, doc: str | None, runs: dict[str, Callable[[float], dict]],
                 argv: list[str] | None = None) -> int:
    """The command line of the SITL measurement scripts: ``[WHAT ...] [--seconds S]
    [--out FILE]``; each measurement's JSON printed as it ends, all of them to ``--out``."""
    ap = argparse.ArgumentParser(prog=prog, description=doc)
    ap.add_argument('what', nargs='*', help=f'{", ".join(runs)} (default: all of them)')
    ap.add_argument('--seconds', type=float, default=20.0)
    ap.add_argument('--out', type=pathlib.Path)
    args = ap.parse_args(argv)
    bad = set(args.what) - set(runs)
    if bad:
        ap.error(f'unknown measurement(s) {sorted(bad)}: choose from {", ".join(runs)}')
    if not (math.isfinite(args.seconds) and args.seconds > 0.0):
        ap.error('--seconds must be > 0')
    res: dict = {'load_before': os.getloadavg()[0]}
    for what in args.what or list(runs):
        res[what] = runs[what](args.seconds)
        print(what, json.dumps(res[what]), flush=True)
    res['load_after'] = os.getloadavg()[0]
    text = json.dumps(res, indent=2, sort_keys=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + '\n')
    print(text)
    return 0
