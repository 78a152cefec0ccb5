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

import fcntl
import os
import pathlib
import re
import shutil
import signal

from deckland.sitl import SitlNotFoundError, SitlStartError
from deckland.sitl.process import SitlProcess, tcp_free, udp_free

#: airframes used here (PX4 v1.16 ROMFS): SIH quadrotor, built-in physics; Iris for an
#: external simulator over the Simulator MAVLink API (TCP 4560 + instance)
SIH_QUADX = (10040, 'sihsim_quadx')
NONE_IRIS = (10016, 'none_iris')
MAX_INSTANCE = 9                  # PX4's port scheme: remote 14540 + i only up to 9

_REPO_ROOT = pathlib.Path(__file__).resolve().parents[4]



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
    return (all(udp_free(p[k]) for k in ('onboard_local', 'onboard_remote', 'gcs_local',
                                           'payload_local', 'gimbal_local'))
            and tcp_free(p['simulator_tcp']))


def pick_instance(preferred: int | None = None) -> int:
    """A free PX4 instance number (``preferred`` when free); RuntimeError when none is."""
    order = ([preferred] if preferred is not None else []) + [
        i for i in range(1, MAX_INSTANCE + 1) if i != preferred] + [0]
    for i in order:
        if 0 <= i <= MAX_INSTANCE and _instance_free(i):
            return i
    raise Px4StartError('no free PX4 instance (0-9): every lock or port is taken')


class Px4Sitl(SitlProcess):
    """One PX4 SITL process (use as a context manager, or call :meth:`start` / :meth:`stop`).

    ``airframe``: ``(SYS_AUTOSTART, PX4_SIM_MODEL)``, e.g. :data:`SIH_QUADX`, :data:`NONE_IRIS`.
    ``params``: PX4 parameters set at boot (``PX4_PARAM_NAME=value``; rcS applies them after
    the airframe's defaults are reset, before the airframe script's ``set-default``s, so they
    win). ``nice``: the process's niceness (the machine is shared). ``logging``: keep PX4's
    ULog (SDLOG_MODE default) — off by default (SDLOG_MODE = -1: ~25 MB and CPU per flight);
    ``keep_log_dir`` copies the ULog files there at :meth:`stop`.
    """

    NAME = 'PX4'
    LOG_NAME = 'px4.log'
    PREFIX = 'deckland-px4-'
    START_ERROR = Px4StartError
    STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)

    def __init__(self, airframe: tuple[int, str] = SIH_QUADX,
                 params: dict[str, float | int] | None = None, *, root: pathlib.Path | None
                 = None, instance: int | None = None, nice: int = 0, logging: bool = False,
                 keep_log_dir: pathlib.Path | None = None, extra_env: dict[str, str] | None
                 = None) -> None:
        super().__init__(instance=instance, nice=nice, keep_log_dir=keep_log_dir)
        found = root if root is not None else require_px4()
        self.root = pathlib.Path(found)
        self.airframe = airframe
        self.params = dict(params or {})
        for k, v in self.params.items():
            if not re.fullmatch(r'[A-Z0-9_]{1,16}', k):
                raise ValueError(f'Px4Sitl.params: {k!r} is not a PX4 parameter name')
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f'Px4Sitl.params[{k!r}] = {v!r}: must be a number')
        self.logging = bool(logging or keep_log_dir is not None)
        self.extra_env = dict(extra_env or {})

    def _ports_of(self, instance: int) -> dict[str, int]:
        return ports(instance)

    @property
    def system_id(self) -> int:
        """PX4's MAV_SYS_ID: rcS sets instance + 1."""
        return (self.instance or 0) + 1

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
        self._popen([str(bindir / 'px4'), '-d', '-i', str(self.instance),
                     str(self.root / 'etc')], cwd=rootfs, env=env)

    def _keep_logs(self, dest: pathlib.Path) -> None:
        assert self.workdir is not None
        for ulg in (self.workdir / 'rootfs' / 'log').rglob('*.ulg'):
            shutil.copy2(ulg, dest / ulg.name)
        super()._keep_logs(dest)
