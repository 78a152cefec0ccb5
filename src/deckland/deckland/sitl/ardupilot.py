"""ArduCopter SITL as a managed process: find it, start it in a fresh directory, stop, clean up.

:func:`find_ardupilot` resolves the binary (``$DECKLAND_ARDUPILOT_SITL``, else
``../shared/ardupilot-sitl`` next to the repository, as CI has it). :class:`ArduPilotSitl`
starts one instance: a temporary working directory of its own (``eeprom.bin``, ``logs/``,
``terrain/``), a free instance number (its TCP MAVLink and UDP physics ports, held by a lock
file for the process's life), the parameters given written to a defaults file after
``copter.parm``, and always kills the process group and removes the directory on
:meth:`~ArduPilotSitl.stop` (the dataflash logs kept on request).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import weakref

from deckland.sitl.px4 import _cleanup, _udp_free

#: ArduPilot SITL ports add 10 per instance (``-I``); 0-9 are used here
MAX_INSTANCE = 9
#: ArduPilot's example home (CMAC, Canberra), lat, lon, alt (m AMSL), heading (deg)
CMAC_HOME = (-35.363261, 149.165230, 584.0, 353.0)
#: what the mission needs of ArduCopter 4.5 in SITL (FACTS.md, ArduCopter section; the
#: mavlink_bridge README "Autopilot set-up"): thrust (not climb rate) in SET_ATTITUDE_TARGET,
#: arming checks off (SITL's "Accels inconsistent" right after boot), no tilt boost of our
#: body-axis thrust, a stale setpoint flown at most 1 s, and LAND when the companion's
#: heartbeat stops for FS_GCS_TIMEOUT (5 s): the GCS failsafe on the bridge (system id 1)
MISSION_PARAMS: dict[str, float] = {'GUID_OPTIONS': 8, 'ARMING_CHECK': 0, 'ATC_ANGLE_BOOST': 0,
                                    'GUID_TIMEOUT': 1.0, 'FS_GCS_ENABLE': 5, 'SYSID_MYGCS': 1}

_REPO_ROOT = pathlib.Path(__file__).resolve().parents[4]


class ArduPilotNotFoundError(RuntimeError):
    """No ``arducopter`` at ``$DECKLAND_ARDUPILOT_SITL`` or ``../shared/ardupilot-sitl``."""


class ArduPilotStartError(RuntimeError):
    """ArduCopter did not come up (the message carries the end of its output)."""


def find_ardupilot(env: dict[str, str] | None = None) -> pathlib.Path | None:
    """The ``arducopter`` SITL binary, or None.

    ``$DECKLAND_ARDUPILOT_SITL`` first: the binary itself, a folder holding it (the shared
    copy) or an ArduPilot ``build/sitl`` folder (``bin/arducopter``); set but wrong is an
    error naming what is missing, not a silent fallback. Then ``../shared/ardupilot-sitl``
    relative to the repository root."""
    env = os.environ if env is None else env
    given = env.get('DECKLAND_ARDUPILOT_SITL', '').strip()
    root = pathlib.Path(given).expanduser() if given else (
        _REPO_ROOT.parent / 'shared' / 'ardupilot-sitl')
    for cand in (root, root / 'arducopter', root / 'bin' / 'arducopter'):
        if cand.is_file() and os.access(cand, os.X_OK):
            return cand.resolve()
    if given:
        raise ArduPilotNotFoundError(
            f'DECKLAND_ARDUPILOT_SITL={given}: no executable arducopter there (build '
            'ArduCopter 4.5 with `./waf configure --board sitl && ./waf copter` and point it '
            'at build/sitl/bin/arducopter)')
    return None


def find_defaults(binary: pathlib.Path) -> pathlib.Path | None:
    """``copter.parm`` beside the binary (the shared copy) or in the ArduPilot tree it was
    built in (``Tools/autotest/default_params/copter.parm``), or None."""
    for d in (binary.parent, *binary.parents):
        for cand in (d / 'copter.parm', d / 'Tools' / 'autotest' / 'default_params' /
                     'copter.parm'):
            if cand.is_file():
                return cand
    return None


def ports(instance: int) -> dict[str, int]:
    """ArduPilot SITL's ports for ``instance`` (each + 10 × instance): SERIAL0 on TCP 5760
    (the one a client must connect to before it boots), SERIAL1/2 on 5762/5763, the JSON
    physics servo output to UDP 9002 (answers come back to its source port, 9003), RC input
    UDP 5501."""
    k = 10 * instance
    return {'mavlink_tcp': 5760 + k, 'serial1_tcp': 5762 + k, 'serial2_tcp': 5763 + k,
            'physics_udp': 9002 + k, 'sim_in_udp': 9003 + k, 'rc_in_udp': 5501 + k}


def _tcp_listenable(port: int) -> bool:
    """Nobody listens on ``port`` (as ArduPilot binds it, with SO_REUSEADDR: the TIME_WAIT
    connections of a previous instance on the same port do not count)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


def _lock_path(i: int) -> str:
    return f'/tmp/deckland-ardupilot-lock-{i}'


def _try_lock(i: int) -> int | None:
    """An fd holding the instance's exclusive lock (other test sessions and developers run
    SITL on the same machine), or None when it is taken or its ports are busy."""
    try:
        fd = os.open(_lock_path(i), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    p = ports(i)
    if all(_tcp_listenable(p[k]) for k in ('mavlink_tcp', 'serial1_tcp', 'serial2_tcp')) and \
            all(_udp_free(p[k]) for k in ('physics_udp', 'sim_in_udp', 'rc_in_udp')):
        return fd
    os.close(fd)
    return None


def _format_param(v: float) -> str:
    return repr(float(v)) if isinstance(v, float) else str(int(v))


class ArduPilotSitl:
    """One ArduCopter SITL process (a context manager, or :meth:`start` / :meth:`stop`).

    ``model``: ``'quad'`` (ArduPilot's built-in physics) or ``'JSON'`` (an external physics
    program on UDP :attr:`ports` ``['physics_udp']``, :mod:`deck_simulator.ardupilot_json`).
    ``params``: set at boot, after ``copter.parm`` (ArduPilot's SITL defaults) — they win;
    :data:`MISSION_PARAMS` are included unless ``mission_params=False``. ``nice``: the
    process's niceness (the machine is shared). ``keep_log_dir``: the dataflash logs
    (``logs/*.BIN``) and the console output are copied there at :meth:`stop`.
    """

    def __init__(self, model: str = 'quad', params: dict[str, float] | None = None, *,
                 binary: pathlib.Path | None = None, defaults: pathlib.Path | None = None,
                 home: tuple[float, float, float, float] = CMAC_HOME, speedup: float = 1.0,
                 instance: int | None = None, nice: int = 0, mission_params: bool = True,
                 keep_log_dir: pathlib.Path | None = None) -> None:
        found = binary if binary is not None else find_ardupilot()
        if found is None:
            raise ArduPilotNotFoundError(
                'ArduCopter SITL not found: set DECKLAND_ARDUPILOT_SITL to an arducopter SITL '
                'binary (or provide ../shared/ardupilot-sitl)')
        self.binary = pathlib.Path(found)
        self.defaults = defaults if defaults is not None else find_defaults(self.binary)
        if not re.fullmatch(r'[A-Za-z0-9_:.+-]{1,40}', model):
            raise ValueError(f'ArduPilotSitl.model = {model!r}: not a SITL model name')
        self.model = model
        merged = dict(MISSION_PARAMS) if mission_params else {}
        merged.update(params or {})
        for k, v in merged.items():
            if not re.fullmatch(r'[A-Z0-9_]{1,16}', k):
                raise ValueError(f'ArduPilotSitl.params: {k!r} is not an ArduPilot parameter '
                                 'name')
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f'ArduPilotSitl.params[{k!r}] = {v!r}: must be a number')
        self.params = merged
        if not (len(home) == 4 and -90.0 < home[0] < 90.0 and -180.0 <= home[1] <= 180.0):
            raise ValueError(f'ArduPilotSitl.home = {home!r}: (lat, lon, alt_m, heading_deg)')
        self.home = tuple(float(v) for v in home)
        if not (isinstance(speedup, int | float) and 0.0 < speedup <= 100.0):
            raise ValueError(f'ArduPilotSitl.speedup = {speedup!r}: must be in (0, 100]')
        self.speedup = float(speedup)
        self.preferred_instance = instance
        self.nice = int(nice)
        self.keep_log_dir = keep_log_dir
        self.instance: int | None = None
        self.workdir: pathlib.Path | None = None
        self.proc: subprocess.Popen | None = None
        self.started_s = float('nan')
        self._lock_fd: int | None = None
        self._log = None

    # --- lifecycle ---------------------------------------------------------------------

    def __enter__(self) -> ArduPilotSitl:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def ports(self) -> dict[str, int]:
        if self.instance is None:
            raise RuntimeError('ArduPilotSitl not started')
        return ports(self.instance)

    @property
    def connection(self) -> str:
        """pymavlink device string of SERIAL0 (``tcp:127.0.0.1:5760`` for instance 0)."""
        return f"tcp:127.0.0.1:{self.ports['mavlink_tcp']}"

    @property
    def log_path(self) -> pathlib.Path:
        assert self.workdir is not None
        return self.workdir / 'arducopter.log'

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors='replace')
        except OSError:
            return ''

    def start(self) -> None:
        """Make the working directory, take a free instance and spawn ArduCopter (returns at
        once; it waits for a client on :attr:`connection` before it boots)."""
        if self.proc is not None:
            raise RuntimeError('ArduPilotSitl already started')
        self.workdir = pathlib.Path(tempfile.mkdtemp(prefix='deckland-ardupilot-'))
        try:
            self._spawn()
        except BaseException:
            self.stop()
            raise

    def _take_instance(self) -> int:
        pref = self.preferred_instance
        order = ([pref] if pref is not None else []) + [
            i for i in range(MAX_INSTANCE + 1) if i != pref]
        for i in order:
            if 0 <= i <= MAX_INSTANCE:
                fd = _try_lock(i)
                if fd is not None:
                    self._lock_fd = fd
                    return i
        raise ArduPilotStartError('no free ArduPilot SITL instance (0-9): every lock or port '
                                  'is taken')

    def _spawn(self) -> None:
        assert self.workdir is not None
        self.instance = self._take_instance()
        parm = self.workdir / 'deckland.parm'
        parm.write_text(''.join(f'{k} {_format_param(v)}\n' for k, v in self.params.items()))
        defaults = ([str(self.defaults)] if self.defaults is not None else []) + [str(parm)]
        lat, lon, alt, hdg = self.home
        cmd = [str(self.binary), '--model', self.model, '--speedup', f'{self.speedup:g}',
               '--defaults', ','.join(defaults), '-I', str(self.instance),
               '--home', f'{lat:.7f},{lon:.7f},{alt:g},{hdg:g}', '-w']
        if self.nice:
            cmd = ['nice', '-n', str(self.nice), *cmd]
        setpriv = shutil.which('setpriv')
        if setpriv:
            # SIGKILL to ArduCopter when the thread that started it dies (a killed test run
            # must not leave it holding the instance's ports; PR_SET_PDEATHSIG)
            cmd = [setpriv, '--pdeathsig', 'KILL', '--', *cmd]
        self._log = open(self.log_path, 'wb')  # noqa: SIM115 (closed in stop())
        self.started_s = time.monotonic()
        self.proc = subprocess.Popen(cmd, cwd=self.workdir, stdin=subprocess.DEVNULL,
                                     stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        self._finalizer = weakref.finalize(self, _cleanup, self.proc.pid, str(self.workdir))

    def wait_for_log(self, pattern: str, timeout_s: float) -> float:
        """Seconds from the spawn until ``pattern`` (a regex) appears in ArduCopter's output;
        ArduPilotStartError when it exits or the timeout passes first."""
        rx = re.compile(pattern)
        end = time.monotonic() + timeout_s
        while True:
            text = self.log_text()
            if rx.search(text):
                return time.monotonic() - self.started_s
            if self.proc is None or self.proc.poll() is not None:
                rc = self.proc.returncode if self.proc else '?'
                raise ArduPilotStartError(f'ArduCopter exited ({rc}) before {pattern!r}; its '
                                          f'output ends:\n{text[-2000:]}')
            if time.monotonic() > end:
                raise ArduPilotStartError(f'ArduCopter not at {pattern!r} after {timeout_s:g} '
                                          f's; its output ends:\n{text[-2000:]}')
            time.sleep(0.05)

    def wait_listening(self, timeout_s: float = 10.0) -> float:
        """Seconds from the spawn until SERIAL0 accepts connections ("Waiting for
        connection")."""
        return self.wait_for_log(r'Serial port 0 on TCP port|Waiting for connection', timeout_s)

    def cpu_s(self) -> float:
        """CPU time (user + system, s) of the ArduCopter process so far."""
        if self.proc is None:
            return float('nan')
        try:
            fields = pathlib.Path(f'/proc/{self.proc.pid}/stat').read_text().rsplit(')', 1)[1]
        except OSError:
            return float('nan')
        f = fields.split()
        return (int(f[11]) + int(f[12])) / os.sysconf('SC_CLK_TCK')

    def kill(self) -> None:
        """Kill the process now, keeping the directory (a crash or a reboot in a test)."""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=2.0)

    def stop(self) -> None:
        """Kill ArduCopter (SIGTERM, then SIGKILL to its process group), release the
        instance and remove the working directory (logs copied to ``keep_log_dir`` first).
        Safe to call more than once."""
        proc, self.proc = self.proc, None
        fin = getattr(self, '_finalizer', None)
        if fin is not None:
            fin.detach()
        if proc is not None:
            for sig in (signal.SIGTERM, signal.SIGKILL):
                if proc.poll() is not None:
                    break
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, sig)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=2.0)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        if self.workdir is not None:
            if self.keep_log_dir is not None:
                dest = pathlib.Path(self.keep_log_dir)
                dest.mkdir(parents=True, exist_ok=True)
                for log in (self.workdir / 'logs').glob('*.BIN'):
                    shutil.copy2(log, dest / log.name)
                with contextlib.suppress(OSError):
                    shutil.copy2(self.log_path, dest / 'arducopter.log')
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None
