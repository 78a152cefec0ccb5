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
import socket
import threading
import time

from deckland.sitl import SitlNotFoundError, SitlStartError
from deckland.sitl.mission import Px4Mission as _Px4MissionBase
from deckland.sitl.mission import _wait
from deckland.sitl.process import GcsOperator, SitlProcess, tcp_free, udp_free

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


class ArduPilotNotFoundError(SitlNotFoundError):
    """No ``arducopter`` at ``$DECKLAND_ARDUPILOT_SITL`` or ``../shared/ardupilot-sitl``."""


class ArduPilotStartError(SitlStartError):
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
    tcp = ('mavlink_tcp', 'serial1_tcp', 'serial2_tcp')
    if all(tcp_free(p[k], reuse_address=True) for k in tcp) and \
            all(udp_free(p[k]) for k in ('physics_udp', 'sim_in_udp', 'rc_in_udp')):
        return fd
    os.close(fd)
    return None


def _format_param(v: float) -> str:
    return repr(float(v)) if isinstance(v, float) else str(int(v))


class ArduPilotSitl(SitlProcess):
    """One ArduCopter SITL process (a context manager, or :meth:`start` / :meth:`stop`).

    ``model``: ``'quad'`` (ArduPilot's built-in physics) or ``'JSON'`` (an external physics
    program on UDP :attr:`ports` ``['physics_udp']``, :mod:`deck_simulator.ardupilot_json`).
    ``params``: set at boot, after ``copter.parm`` (ArduPilot's SITL defaults) — they win;
    :data:`MISSION_PARAMS` are included unless ``mission_params=False``. ``nice``: the
    process's niceness (the machine is shared). ``keep_log_dir``: the dataflash logs
    (``logs/*.BIN``) and the console output are copied there at :meth:`stop`.
    """

    NAME = 'ArduCopter'
    LOG_NAME = 'arducopter.log'
    PREFIX = 'deckland-ardupilot-'
    START_ERROR = ArduPilotStartError

    def __init__(self, model: str = 'quad', params: dict[str, float] | None = None, *,
                 binary: pathlib.Path | None = None, defaults: pathlib.Path | None = None,
                 home: tuple[float, float, float, float] = CMAC_HOME, speedup: float = 1.0,
                 instance: int | None = None, nice: int = 0, mission_params: bool = True,
                 keep_log_dir: pathlib.Path | None = None) -> None:
        super().__init__(instance=instance, nice=nice, keep_log_dir=keep_log_dir)
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
        self._lock_fd: int | None = None

    def _ports_of(self, instance: int) -> dict[str, int]:
        return ports(instance)

    @property
    def connection(self) -> str:
        """pymavlink device string of SERIAL0 (``tcp:127.0.0.1:5760`` for instance 0)."""
        return f"tcp:127.0.0.1:{self.ports['mavlink_tcp']}"

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
        self._popen([str(self.binary), '--model', self.model, '--speedup', f'{self.speedup:g}',
                     '--defaults', ','.join(defaults), '-I', str(self.instance),
                     '--home', f'{lat:.7f},{lon:.7f},{alt:g},{hdg:g}', '-w'], cwd=self.workdir)

    def wait_listening(self, timeout_s: float = 10.0) -> float:
        """Seconds from the spawn until SERIAL0 accepts connections ("Waiting for
        connection")."""
        return self.wait_for_log(r'Serial port 0 on TCP port|Waiting for connection', timeout_s)

    def _release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def _keep_logs(self, dest: pathlib.Path) -> None:
        assert self.workdir is not None
        for log in (self.workdir / 'logs').glob('*.BIN'):
            shutil.copy2(log, dest / log.name)
        super()._keep_logs(dest)


# --- deckland up --autopilot ardupilot-sitl -------------------------------------------------

#: the JSON physics rate = the world's physics rate (one servo frame per sub-step): 400 Hz,
#: ArduCopter's main-loop rate (measured: 2.5-9.9x real time unpaced, vs 2.0-4.3x at 1200 Hz)
JSON_RATE_HZ = 400
#: the bridge on a shared 2-core machine: ArduCopter answers TIMESYNC in its own (simulated)
#: time, so a lockstep slowed to 0.35x real time by the load made 343-393 ms of wall-clock
#: "latency" (measured; 0.25 s stopped the first missions, the latency stop's LAND); the
#: graph's setpoints arrive late too. The 60 ms / 0.3 s of the deck set-up are for the real
#: link, where time is not stretched; ArduCopter's 1 Hz heartbeat is in its time too (a
#: 3 s link timeout was crossed at 0.3x real time)
BRIDGE_SITL_PARAMS = {'max_link_latency_s': 1.0, 'stop_after_s': 1.0, 'link_timeout_s': 8.0}
def require_ardupilot() -> pathlib.Path:
    """:func:`find_ardupilot`, or ArduPilotNotFoundError saying how to get ArduCopter SITL
    (the registry's ``find``)."""
    found = find_ardupilot()
    if found is None:
        raise ArduPilotNotFoundError(
            'ArduCopter SITL not found: set DECKLAND_ARDUPILOT_SITL to an arducopter SITL '
            'binary (ArduCopter 4.5.6), or provide ../shared/ardupilot-sitl')
    return found


MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_SET_MESSAGE_INTERVAL = 511
GUIDED = 4


def mission_params(scenario) -> dict[str, float]:
    """ArduCopter's parameters for a mission of ``scenario`` (besides :data:`MISSION_PARAMS`):
    the vehicle and lidar as the JSON physics flies them
    (:func:`deck_simulator.ardupilot_json.ardupilot_params`) at :data:`JSON_RATE_HZ`."""
    from deck_simulator.ardupilot_json import ardupilot_params
    lp = scenario.sensors.lidar
    p = ardupilot_params(scenario.vehicle, lp.min_range_m, lp.max_range_m)
    p['SIM_RATE_HZ'] = JSON_RATE_HZ
    return p


def all_mission_params(scenario) -> dict[str, float]:
    """Everything ArduCopter is told for a mission of ``scenario``: :data:`MISSION_PARAMS`
    and :func:`mission_params` (the registry's ``params``; :attr:`ArduPilotMission.params`)."""
    return {**MISSION_PARAMS, **mission_params(scenario)}


def failsafe_check(report: dict, params: dict) -> dict:
    """For a link-fault mission (the registry's ``failsafe_check``): ArduCopter flew LAND
    after GUIDED_NOGPS (the bridge's stop action, or ArduCopter's GCS failsafe, FS_GCS_ENABLE
    5, when the bridge itself is gone), ended disarmed and not on the deck edge."""
    from deckland.sitl.campaign import safe_action_check
    return safe_action_check(report, 'ardupilot', ArduPilotMission.OFFBOARD_MODE, 'LAND')


class ArduPilotOperator(GcsOperator):
    """A ground station on ArduCopter's SERIAL1 (TCP 5762 + 10 × instance), as the PX4
    mission's :class:`~deckland.sitl.mission.Operator`, over TCP (reconnected when
    ArduCopter comes back). Its system id (255) is not ``SYSID_MYGCS``: the GCS failsafe
    watches the bridge, not this link."""

    THREAD_NAME = 'ardupilot_operator'

    def __init__(self, port: int, system_id: int = 1) -> None:
        super().__init__(system_id)
        self.port = port
        self.sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._start()

    def write(self, data: bytes) -> None:      # pymavlink's file
        with self._lock:
            if self.sock is not None:
                with contextlib.suppress(OSError):
                    self.sock.sendall(data)

    def _connect(self) -> bool:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.settimeout(0.5)
        try:
            s.connect(('127.0.0.1', self.port))
        except OSError:
            s.close()
            return False
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.settimeout(0.05)
        with self._lock:
            self.sock = s
        return True

    def _recv(self) -> bytes | None:
        if self.sock is None and not self._connect():
            self._stop.wait(0.5)
            return None
        assert self.sock is not None
        try:
            data = self.sock.recv(65536)
        except (TimeoutError, BlockingIOError):
            return None
        except OSError:
            data = b''
        if not data:          # ArduCopter gone: try again later
            with self._lock:
                with contextlib.suppress(OSError):
                    self.sock.close()
                self.sock = None
        return data

    def _mode_of(self, m) -> str | None:
        from mavlink_bridge.conversions import ardupilot_mode_name
        if m.autopilot != self._mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
            return None
        return ardupilot_mode_name(m.custom_mode)

    def _on_heartbeat(self) -> None:
        mavlink = self._mavlink
        self.stream(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5.0)
        self.stream(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10.0)

    def stream(self, msg_id: int, rate_hz: float) -> None:
        self.command(MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz)

    def set_mode(self, custom_mode: int) -> None:
        self.command(MAV_CMD_DO_SET_MODE, 1, custom_mode)

    def _close_transport(self) -> None:
        with self._lock:
            if self.sock is not None:
                self.sock.close()
                self.sock = None


class ArduPilotMission(_Px4MissionBase):
    """ArduCopter SITL for one mission of ``scenario``: the :class:`~deckland.sitl.mission.
    Px4Mission` interface (``deckland up`` drives both), ArduCopter's way.

    ArduCopter ``--model JSON`` on deckland's physics (the simulator node, ``autopilot:
    ardupilot-sitl``, lockstep at :data:`JSON_RATE_HZ`), the bridge on SERIAL0 (its TCP
    connection boots ArduCopter), the operator on SERIAL1: the EKF origin at the world's
    origin, GUIDED, arm, ArduCopter's own take-off to the scenario's start height; the
    bridge then measures the hover and enters GUIDED_NOGPS (:attr:`OFFBOARD_MODE`). Its
    stop action (LAND) ends the mission; ArduCopter's LAND disarms."""

    NAME = 'ArduCopter'
    OFFBOARD_MODE = 'GUIDED_NOGPS'
    #: silent on the ground: the thrust, and the position until EKF3 has its GPS origin
    #: (the bridge's map anchor; 60-80 s after the start on a loaded machine, measured)
    GROUND_SILENT = ('control/thrust', 'control/attitude', 'vehicle/odom', 'apron/state')
    ORIGIN_MSG_ID = 49     # GPS_GLOBAL_ORIGIN

    def __init__(self, scenario, *, keep_ulog: str | None = None, nice: int = 0) -> None:
        from deck_simulator.ardupilot_json import SEA_LEVEL_HOME
        self.scenario = scenario
        self.home = SEA_LEVEL_HOME
        self.params = all_mission_params(scenario)
        self.wire = False
        self.keep_ulog = pathlib.Path(keep_ulog) if keep_ulog else None
        self.sitl = ArduPilotSitl('JSON', self.params, home=SEA_LEVEL_HOME, nice=nice,
                                  keep_log_dir=self.keep_ulog)
        self.operator: ArduPilotOperator | None = None
        self.times: dict[str, float] = {}
        self.param_fixes: dict[str, float | None] = {}
        self.hover: float | None = None
        self._subs: list = []               # rclpy subscriptions on the monitor's node
        self._t0 = float('nan')

    def start(self) -> None:
        self._t0 = time.monotonic()
        self.sitl.start()
        self.sitl.wait_listening()
        self.operator = ArduPilotOperator(self.ports['serial1_tcp'])

    def stop(self) -> None:
        if self.operator is not None:
            self.operator.close()
        self.sitl.stop()

    @property
    def ports(self) -> dict[str, int]:
        return self.sitl.ports

    def describe(self) -> str:
        s = self.sitl
        return (f'ArduCopter SITL {s.binary} instance {s.instance} in {s.workdir} (SERIAL0 TCP '
                f"{self.ports['mavlink_tcp']}, JSON physics UDP {self.ports['physics_udp']}, "
                f"operator TCP {self.ports['serial1_tcp']})")

    def configure_graph(self, nodes: list) -> None:
        """The simulator is ArduCopter's JSON physics (UDP 9002 + 10 i, physics at
        :data:`JSON_RATE_HZ`); the bridge talks ArduPilot on SERIAL0 (TCP 5760 + 10 i), its
        map anchored at the world's origin (:attr:`home`: the JSON positions are relative to
        it)."""
        for spec in nodes:
            if spec.name == 'deck_simulator':
                spec.parameters.update(autopilot='ardupilot-sitl',
                                       ardupilot_physics_port=self.ports['physics_udp'],
                                       physics_rate_hz=float(JSON_RATE_HZ))
            elif spec.name == 'mavlink_bridge':
                lat, lon, alt, _ = self.home
                spec.parameters.update(connection=self.sitl.connection, autopilot='ardupilot',
                                       map_origin_llh=f'{lat:.7f},{lon:.7f},{alt:g}',
                                       **BRIDGE_SITL_PARAMS)

    def _log_tail(self) -> str:
        return self.sitl.log_text()[-1500:]

    def cpu_s(self) -> float:
        """ArduCopter's CPU time so far (user + system, seconds)."""
        return self.sitl.cpu_s()

    def _proc_gone(self) -> bool:
        return self.sitl.proc is None or self.sitl.proc.poll() is not None

    def wait_up(self, timeout_s: float, abort=None) -> tuple[bool, str]:
        """ArduCopter's heartbeat on the operator's link (it boots once the bridge connected
        and the simulator answers its servo frames), then its parameters checked."""
        op = self.operator
        assert op is not None
        _wait(lambda: op.heartbeats > 0 or self._proc_gone(), timeout_s, abort)
        if self._proc_gone():
            return False, f'ArduCopter exited while starting; its output ends:\n{self._log_tail()}'
        if op.heartbeats == 0:
            return False, (f'ArduCopter sent no heartbeat within {timeout_s:g} s; its output '
                           f'ends:\n{self._log_tail()}')
        self.times['up_s'] = time.monotonic() - self._t0
        return self.check_params()

    def check_params(self) -> tuple[bool, str]:
        """Every parameter of the mission read back (float32 on the wire)."""
        op = self.operator
        assert op is not None
        vals = op.read_params(self.params)
        bad = {k: vals.get(k) for k, v in self.params.items()
               if k not in vals or abs(vals[k] - float(v)) > 1e-5 + 1e-6 * abs(float(v))}
        self.param_fixes = dict(bad)
        if bad:
            return False, f'ArduCopter did not take the parameters {bad}'
        return True, 'ArduCopter up, parameters checked'

    def take_off(self, timeout_s: float = 150.0, abort=None) -> tuple[bool, str]:
        """As an operator would: wait for ArduCopter's EKF origin (its first GPS fix: the
        bridge anchors map at :attr:`home` through it), GUIDED and arm (repeated until
        ArduCopter has a position estimate), ArduCopter's own take-off (NAV_TAKEOFF) to the
        scenario's start height, until it hovers there (within 0.3 m)."""
        from mavlink_bridge.conversions import origin_offset_enu
        op = self.operator
        assert op is not None
        end = time.monotonic() + timeout_s

        def left() -> float:
            return max(0.0, end - time.monotonic())

        def origin_known() -> bool:
            if op.origin is None and time.monotonic() - origin_known.last > 2.0:
                origin_known.last = time.monotonic()
                op.command(512, self.ORIGIN_MSG_ID)          # REQUEST_MESSAGE
            return op.origin is not None

        origin_known.last = 0.0
        if not _wait(origin_known, min(90.0, left()), abort, 0.1):
            return False, 'ArduCopter set no EKF origin within 90 s (no GPS fix used)'
        lat, lon, alt, _ = self.home
        origin = origin_offset_enu(op.origin, (lat, lon, alt))
        self.times['origin_s'] = time.monotonic() - self._t0
        t_arm = time.monotonic()

        def armed_in_guided() -> bool:
            if time.monotonic() - armed_in_guided.last > 1.0:
                armed_in_guided.last = time.monotonic()
                if op.mode != 'GUIDED':
                    op.set_mode(GUIDED)
                elif not op.armed:
                    op.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
            return op.armed and op.mode == 'GUIDED'

        armed_in_guided.last = 0.0
        if not _wait(armed_in_guided, min(90.0, left()), abort, 0.1):
            texts = '; '.join(t for _, t in op.texts[-5:])
            return False, f'ArduCopter did not arm in GUIDED within 90 s ({texts})'
        self.times['armed_s'] = time.monotonic() - self._t0
        self.times['arm_wait_s'] = time.monotonic() - t_arm
        # above the resting point, where it armed (its home; the local origin's height)
        height = float(self.scenario.start_position_m[2]) - origin[2]
        op.command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, height)

        def up_there() -> bool:
            lp = op.local_ned
            return lp is not None and abs(-lp[2] - height) < 0.3 and op.mode == 'GUIDED'

        if not _wait(up_there, left(), abort):
            return False, (f'ArduCopter not at {height:.2f} m after its take-off (mode '
                           f'{op.mode}, local position {op.local_ned})')
        self.times['loiter_s'] = time.monotonic() - self._t0
        return True, (f'ArduCopter hovers at {-op.local_ned[2] + origin[2]:.2f} m (GUIDED); '
                      f'its local origin at ({origin[0]:.2f}, {origin[1]:.2f}, '
                      f'{origin[2]:.2f}) m in map')

    def report(self, t_ref_s: float | None = None) -> dict:
        """What ArduCopter did, for ``report.json`` (the PX4 mission's keys)."""
        op = self.operator
        t_ref = self._t0 if t_ref_s is None else t_ref_s
        return {
            'binary': str(self.sitl.binary), 'instance': self.sitl.instance,
            'params': dict(self.params), 'params_wrong_after_boot': dict(self.param_fixes),
            'hover_thrust_measured': self.hover,
            'times_s': {k: round(v, 2) for k, v in self.times.items()},
            'armed_at_end': op.armed if op is not None else None,
            'landed_state_at_end': op.landed_state if op is not None else None,
            'mode_at_end': op.mode if op is not None else '',
            'modes': self.modes_since(t_ref) if op is not None else [],
            'statustext': [t for _, t in op.texts[-12:]] if op is not None else [],
            'ardupilot_cpu_s': round(self.sitl.cpu_s(), 1),
            'log_dir': str(self.keep_ulog) if self.keep_ulog else None,
        }
