"""PX4 SITL as a managed process: find it, start it in a fresh directory, stop and clean up.

:func:`find_px4` resolves the PX4 build (``$DECKLAND_PX4_SITL``, else ``../shared/px4-sitl``
next to the repository, as CI has it): a folder with ``bin/px4`` and ``etc/`` (a user's
``build/px4_sitl_default`` or the shared copy). :class:`Px4Sitl` starts one instance: a
temporary working directory of its own (parameters, dataman, logs), a free instance number
(its MAVLink and simulator ports), the parameters given as ``PX4_PARAM_*`` (PX4's rcS applies
them at boot), and always kills the process group and removes the directory on
:meth:`~Px4Sitl.stop` (the ULog kept on request).
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

from deckland.sitl import SitlNotFoundError, SitlStartError

#: airframes used here (PX4 v1.16 ROMFS): SIH quadrotor, built-in physics; Iris for an
#: external simulator over the Simulator MAVLink API (TCP 4560 + instance)
SIH_QUADX = (10040, 'sihsim_quadx')
NONE_IRIS = (10016, 'none_iris')
MAX_INSTANCE = 9                  # PX4's port scheme: remote 14540 + i only up to 9

_REPO_ROOT = pathlib.Path(__file__).resolve().parents[4]


def _cleanup(pid: int, workdir: str) -> None:
    """Last resort at interpreter exit (a Px4Sitl never stopped): kill the group, remove the
    directory."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal.SIGKILL)
    shutil.rmtree(workdir, ignore_errors=True)


class Px4NotFoundError(SitlNotFoundError):
    """No PX4 SITL build at ``$DECKLAND_PX4_SITL`` or ``../shared/px4-sitl``."""


class Px4StartError(SitlStartError):
    """PX4 did not come up (the message carries the end of its log)."""


#: a float parameter set to exactly 0.0 is sent as this: PX4 stores only values that differ
#: from the compiled default, so a 0.0 equal to it is not kept and the airframe's later
#: ``param set-default`` wins (measured: none_iris kept its CA_ROTOR1_PX = -0.1515 for a
#: requested 0.0; PX4's own rcS sets SENS_BOARD_X_OFF 0.000001 for the same reason)
ZERO_FLOAT = 1e-6


def px4_param_text(value: float | int) -> str:
    """A parameter value as ``PX4_PARAM_*`` text (floats with a '.', 0.0 as
    :data:`ZERO_FLOAT`)."""
    if isinstance(value, float):
        return repr(ZERO_FLOAT if value == 0.0 else value)
    return str(int(value))


def find_px4(env: dict[str, str] | None = None) -> pathlib.Path | None:
    """The PX4 SITL folder (with ``bin/px4`` and ``etc/init.d-posix/rcS``), or None.

    ``$DECKLAND_PX4_SITL`` first (a ``build/px4_sitl_default`` folder or a copy like the shared
    one); set but wrong is an error (Px4NotFoundError naming what is missing), not a silent
    fallback. Then ``../shared/px4-sitl`` relative to the repository root."""
    env = os.environ if env is None else env
    given = env.get('DECKLAND_PX4_SITL', '').strip()
    cands = [pathlib.Path(given).expanduser()] if given else [
        _REPO_ROOT.parent / 'shared' / 'px4-sitl']
    for root in cands:
        ok = (root / 'bin' / 'px4').is_file() and (root / 'etc' / 'init.d-posix' / 'rcS').is_file()
        if ok:
            return root.resolve()
        if given:
            raise Px4NotFoundError(
                f'DECKLAND_PX4_SITL={given}: no bin/px4 and etc/init.d-posix/rcS there (build '
                'PX4 v1.16 with `make px4_sitl_default` and point it at build/px4_sitl_default)')
    return None


def require_px4() -> pathlib.Path:
    """:func:`find_px4`, or Px4NotFoundError saying how to get PX4 SITL."""
    found = find_px4()
    if found is None:
        raise Px4NotFoundError('PX4 SITL not found: set DECKLAND_PX4_SITL to a PX4 v1.16 '
                               'build/px4_sitl_default folder (`make px4_sitl_default` at '
                               'v1.16.0), or provide ../shared/px4-sitl')
    return found


def ports(instance: int) -> dict[str, int]:
    """PX4's ports for ``instance`` (etc/init.d-posix/px4-rc.mavlink, px4-rc.mavlinksim)."""
    return {'onboard_local': 14580 + instance, 'onboard_remote': 14540 + instance,
            'gcs_local': 18570 + instance, 'simulator_tcp': 4560 + instance,
            'payload_local': 14280 + instance, 'gimbal_local': 13030 + instance}


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


def _tcp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


def _instance_free(i: int) -> bool:
    """No PX4 holds the instance's lock (``/tmp/px4_lock-i``, flock) and its ports are free
    (other developers and other test sessions run PX4 on the same machine)."""
    path = f'/tmp/px4_lock-{i}'
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
    except OSError:
        return False
    finally:
        os.close(fd)
    p = ports(i)
    return (all(_udp_free(p[k]) for k in ('onboard_local', 'onboard_remote', 'gcs_local',
                                           'payload_local', 'gimbal_local'))
            and _tcp_free(p['simulator_tcp']))


def pick_instance(preferred: int | None = None) -> int:
    """A free PX4 instance number (``preferred`` when free); RuntimeError when none is."""
    order = ([preferred] if preferred is not None else []) + [
        i for i in range(1, MAX_INSTANCE + 1) if i != preferred] + [0]
    for i in order:
        if 0 <= i <= MAX_INSTANCE and _instance_free(i):
            return i
    raise Px4StartError('no free PX4 instance (0-9): every lock or port is taken')


class Px4Sitl:
    """One PX4 SITL process (use as a context manager, or call :meth:`start` / :meth:`stop`).

    ``airframe``: ``(SYS_AUTOSTART, PX4_SIM_MODEL)``, e.g. :data:`SIH_QUADX`, :data:`NONE_IRIS`.
    ``params``: PX4 parameters set at boot (``PX4_PARAM_NAME=value``; rcS applies them after
    the airframe's defaults are reset, before the airframe script's ``set-default``s, so they
    win). ``nice``: the process's niceness (the machine is shared). ``logging``: keep PX4's
    ULog (SDLOG_MODE default) — off by default (SDLOG_MODE = -1: ~25 MB and CPU per flight);
    ``keep_log_dir`` copies the ULog files there at :meth:`stop`.
    """

    def __init__(self, airframe: tuple[int, str] = SIH_QUADX,
                 params: dict[str, float | int] | None = None, *, root: pathlib.Path | None
                 = None, instance: int | None = None, nice: int = 0, logging: bool = False,
                 keep_log_dir: pathlib.Path | None = None, extra_env: dict[str, str] | None
                 = None) -> None:
        found = root if root is not None else require_px4()
        self.root = pathlib.Path(found)
        self.airframe = airframe
        self.params = dict(params or {})
        for k, v in self.params.items():
            if not re.fullmatch(r'[A-Z0-9_]{1,16}', k):
                raise ValueError(f'Px4Sitl.params: {k!r} is not a PX4 parameter name')
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f'Px4Sitl.params[{k!r}] = {v!r}: must be a number')
        self.preferred_instance = instance
        self.nice = int(nice)
        self.logging = bool(logging or keep_log_dir is not None)
        self.keep_log_dir = keep_log_dir
        self.extra_env = dict(extra_env or {})
        self.instance: int | None = None
        self.workdir: pathlib.Path | None = None
        self.proc: subprocess.Popen | None = None
        self.started_s = float('nan')
        self._log = None

    # --- lifecycle ---------------------------------------------------------------------

    def __enter__(self) -> Px4Sitl:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def ports(self) -> dict[str, int]:
        if self.instance is None:
            raise RuntimeError('Px4Sitl not started')
        return ports(self.instance)

    @property
    def system_id(self) -> int:
        """PX4's MAV_SYS_ID: rcS sets instance + 1."""
        return (self.instance or 0) + 1

    @property
    def log_path(self) -> pathlib.Path:
        assert self.workdir is not None
        return self.workdir / 'px4.log'

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors='replace')
        except OSError:
            return ''

    def start(self) -> None:
        """Make the working directory, pick an instance and spawn PX4 (returns at once;
        :meth:`wait_for_log` waits for a line such as ``Ready for takeoff``)."""
        if self.proc is not None:
            raise RuntimeError('Px4Sitl already started')
        self.workdir = pathlib.Path(tempfile.mkdtemp(prefix='deckland-px4-'))
        try:
            self._spawn()
        except BaseException:
            self.stop()
            raise

    def _spawn(self) -> None:
        assert self.workdir is not None
        bindir = self.workdir / 'bin'
        rootfs = self.workdir / 'rootfs'
        bindir.mkdir()
        rootfs.mkdir()
        px4 = self.root / 'bin' / 'px4'
        # PX4's shell calls its modules as px4-<module> from PATH: symlinks to the binary (a
        # copied folder, like the shared one, may have lost them)
        for f in (self.root / 'bin').iterdir():
            if f.name.startswith('px4-'):
                (bindir / f.name).symlink_to(f if f.name == 'px4-alias.sh' else px4)
        (bindir / 'px4').symlink_to(px4)
        self.instance = pick_instance(self.preferred_instance)
        sys_autostart, model = self.airframe
        env = {k: v for k, v in os.environ.items() if not k.startswith('PX4_')}
        env.update(PATH=f'{bindir}:{env.get("PATH", "/usr/bin:/bin")}',
                   PX4_SYS_AUTOSTART=str(sys_autostart), PX4_SIM_MODEL=model)
        if sys_autostart == SIH_QUADX[0]:
            env['PX4_SIMULATOR'] = 'sihsim'
        params = dict(self.params)
        if not self.logging:
            params.setdefault('SDLOG_MODE', -1)
        for k, v in params.items():
            env[f'PX4_PARAM_{k}'] = px4_param_text(v)
        env.update(self.extra_env)
        cmd = [str(bindir / 'px4'), '-d', '-i', str(self.instance), str(self.root / 'etc')]
        if self.nice:
            cmd = ['nice', '-n', str(self.nice), *cmd]
        setpriv = shutil.which('setpriv')
        if setpriv:
            # SIGKILL to PX4 when the thread that started it dies (a killed test run must not
            # leave PX4 holding its instance's ports; util-linux setpriv, PR_SET_PDEATHSIG)
            cmd = [setpriv, '--pdeathsig', 'KILL', '--', *cmd]
        self._log = open(self.log_path, 'wb')  # noqa: SIM115 (closed in stop())
        self.started_s = time.monotonic()
        self.proc = subprocess.Popen(cmd, cwd=rootfs, env=env, stdin=subprocess.DEVNULL,
                                     stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        self._finalizer = weakref.finalize(self, _cleanup, self.proc.pid, str(self.workdir))

    def wait_for_log(self, pattern: str, timeout_s: float) -> float:
        """Seconds from the spawn until ``pattern`` (a regex) appears in PX4's output;
        Px4StartError when PX4 exits or the timeout passes first."""
        rx = re.compile(pattern)
        end = time.monotonic() + timeout_s
        while True:
            text = self.log_text()
            if rx.search(text):
                return time.monotonic() - self.started_s
            if self.proc is None or self.proc.poll() is not None:
                raise Px4StartError(f'PX4 exited ({self.proc.returncode if self.proc else "?"}) '
                                    f'before {pattern!r}; its log ends:\n{text[-2000:]}')
            if time.monotonic() > end:
                raise Px4StartError(f'PX4 not at {pattern!r} after {timeout_s:g} s; its log '
                                    f'ends:\n{text[-2000:]}')
            time.sleep(0.05)

    def cpu_s(self) -> float:
        """CPU time (user + system, s) of the PX4 process so far (its threads included)."""
        if self.proc is None:
            return float('nan')
        try:
            fields = pathlib.Path(f'/proc/{self.proc.pid}/stat').read_text().rsplit(')', 1)[1]
        except OSError:
            return float('nan')
        f = fields.split()
        return (int(f[11]) + int(f[12])) / os.sysconf('SC_CLK_TCK')

    def stop(self) -> None:
        """Kill PX4 (its process group: the daemon and its shell clients) and remove the
        working directory; the ULog files are copied to ``keep_log_dir`` first. Safe to call
        more than once."""
        proc, self.proc = self.proc, None
        fin = getattr(self, '_finalizer', None)
        if fin is not None:
            fin.detach()
        if proc is not None:
            for sig, wait_s in ((signal.SIGINT, 2.0), (signal.SIGTERM, 2.0),
                                (signal.SIGKILL, 2.0)):
                if proc.poll() is not None:
                    break
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, sig)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=wait_s)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)   # stray clients of the group
        if self._log is not None:
            self._log.close()
            self._log = None
        if self.workdir is not None:
            if self.keep_log_dir is not None:
                dest = pathlib.Path(self.keep_log_dir)
                dest.mkdir(parents=True, exist_ok=True)
                for ulg in (self.workdir / 'rootfs' / 'log').rglob('*.ulg'):
                    shutil.copy2(ulg, dest / ulg.name)
                with contextlib.suppress(OSError):
                    shutil.copy2(self.log_path, dest / 'px4.log')
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None
