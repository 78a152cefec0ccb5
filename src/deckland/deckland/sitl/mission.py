"""PX4 SITL as the autopilot of a ``deckland up`` mission: PX4, its parameters, the operator.

:class:`Px4Mission` starts PX4 v1.16 (airframe 10016 ``none_iris``, :mod:`deckland.sitl.px4`)
with :func:`mission_params` (the scenario's vehicle, take-off height and offboard-loss
failsafe), points the graph's simulator and bridge at it (:meth:`Px4Mission.configure_graph`),
and plays the operator on PX4's GCS link (:class:`Operator`): the EKF origin at the world's
origin, arm, PX4's own take-off, then PX4's modes, arming and landed state as PX4 reports them
(the bridge may be the node a fault kills). Pure MAVLink and processes; no rclpy here except
the bridge diagnostics read in :meth:`Px4Mission.wait_hover_measured`.
"""

from __future__ import annotations

import contextlib
import math
import os
import pathlib
import socket
import time
from typing import Any

os.environ.setdefault('MAVLINK20', '1')

from deck_simulator.faults import FaultSet
from deck_simulator.px4_hil import HilParams, px4_params
from deck_simulator.scenario import Scenario
from mavlink_bridge.conversions import (
    param_value_from_wire,
    param_value_to_wire,
    px4_mode_name,
)
from pymavlink.dialects.v20 import common as mavlink

from deckland.sitl.process import GcsOperator, UdpWriter
from deckland.sitl.px4 import NONE_IRIS, ZERO_FLOAT, Px4Sitl

#: the physics rate of the simulator with PX4: two sub-steps per 250 Hz lockstep period
PHYSICS_RATE_HZ = 500.0
#: how long the bridge may measure the hover thrust in PX4's loiter (its estimator needs 4 s
#: of steady hover; gusts can keep it from converging, then MPC_THR_HOVER is used)
HOVER_WAIT_S = 20.0
#: PX4 COM_OBL_RC_ACT values (v1.16 parameter metadata): Return, Land
OBL_RETURN, OBL_LAND = 3, 4
#: meant to make PX4's Return fly home (where it armed, clear of the deck) at RTL_RETURN_ALT
#: before it descends, as the emulated one does. With PX4's defaults and home 1.7 m from the
#: deck, PX4 v1.16's Return came down from 1 m above the deck onto its edge (link loss, seed
#: 100001: "RTL: land at destination" 2 s after the failsafe, 0.56 m/s, 0.63 m off centre). A
#: 2 m NAV_ACC_RAD counts the loiter point above home as reached from there; RTL_MIN_DIST and
#: the RTL_CONE_ANG cone can skip the climb. Not yet shown to be enough (one re-run: safe, on
#: the ground 0.77 m off centre, so still short of home)
RETURN_HOME: dict[str, float | int] = {'NAV_ACC_RAD': 0.25, 'RTL_MIN_DIST': 0.0,
                                       'RTL_CONE_ANG': 0}
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_LANDED_STATE_ON_GROUND = 1
#: planner modes that show it took planner/takeoff (landing_planner's Mode names)
TAKEOFF_TAKEN = ('TAKEOFF', 'HOLD')
#: planner/takeoff's wait for the planner, and how often a call that got no reply (and left
#: planner/mode unchanged) is made again with a fresh client: at load 40 on 2 cores single
#: 5 s and 15 s calls got no reply; PX4 loiters meanwhile, so trying again costs nothing
TAKEOFF_TRIGGER_TIMEOUT_S = 6.0
TAKEOFF_TRIGGER_ATTEMPTS = 3


def mission_params(scenario: Scenario, hil: HilParams | None = None) -> dict[str, float | int]:
    """PX4's parameters for a mission of ``scenario``: :func:`px4_params` (the vehicle, no
    RC, Land on offboard loss), take-off to the scenario's start height, and with a link
    fault its failsafe as the emulated PX4 flies it (docs/failsafe.md): ``COM_OF_LOSS_T`` =
    ``loss_timeout_s``; ``action: return`` → Return (``COM_OBL_RC_ACT`` 3) at ``min_alt_m``
    (``RTL_RETURN_ALT`` / ``RTL_DESCEND_ALT``, no loiter before landing), else Land;
    ``MPC_LAND_SPEED`` = ``land_speed_mps``; and :data:`RETURN_HOME`."""
    p = px4_params(scenario.vehicle, hil, takeoff_alt_m=float(scenario.start_position_m[2]))
    faults = FaultSet(scenario.faults, 0, (0.0, 0.0), 0.0) if scenario.faults else None
    if faults is not None and faults.has_link:
        spec = faults.link_spec
        p['COM_OF_LOSS_T'] = float(spec.loss_timeout_s)
        p['MPC_LAND_SPEED'] = float(spec.land_speed_mps)
        if spec.action == 'return':
            alt = max(float(spec.min_alt_m), 1.0)
            p.update({'COM_OBL_RC_ACT': OBL_RETURN, 'RTL_RETURN_ALT': alt,
                      'RTL_DESCEND_ALT': alt, 'RTL_LAND_DELAY': 0.0, **RETURN_HOME})
        else:
            p['COM_OBL_RC_ACT'] = OBL_LAND
    return p


def wire_faults(scenario: Scenario) -> bool:
    """The scenario has faults that act on the MAVLink wire (link loss, loss, latency): the
    simulator then carries PX4's onboard link to the bridge (``px4_onboard_url``)."""
    from deck_simulator.link import WIRE_FAULT_TYPES
    return any(f.type in WIRE_FAULT_TYPES for f in scenario.faults)


class Operator(GcsOperator):
    """A ground station on PX4's GCS link (UDP 18570 + instance): what an operator does and
    sees. PX4 answers whoever sent to it last, so a GCS heartbeat (1 Hz) brings its GCS
    telemetry here (:class:`~deckland.sitl.process.GcsOperator`)."""

    THREAD_NAME = 'px4_operator'

    def __init__(self, port: int, system_id: int) -> None:
        super().__init__(system_id)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.sock.settimeout(0.05)
        self._writer = UdpWriter(self.sock, ('127.0.0.1', port))
        self._start()

    def write(self, data: bytes) -> None:      # pymavlink's file
        self._writer.write(data)

    def _recv(self) -> bytes | None:
        try:
            return self.sock.recv(65535)
        except (TimeoutError, OSError):
            return None

    def _mode_of(self, m: Any) -> str | None:
        if m.get_srcComponent() != 1 or m.autopilot != mavlink.MAV_AUTOPILOT_PX4:
            return None
        return px4_mode_name(m.custom_mode)

    def _param_of(self, m: Any) -> float:
        # PX4 sends integers bytewise in the float field (MAV_PROTOCOL_CAPABILITY_PARAM_
        # ENCODE_BYTEWISE)
        return param_value_from_wire(m.param_value, m.param_type, True)

    def _close_transport(self) -> None:
        self.sock.close()

    #: the 50 Hz streams of PX4's GCS link an operator does not read here (SET_MESSAGE_INTERVAL
    #: -1; v1.16 sends ~370 messages/s on this link, ~300 of them these), and
    #: LOCAL_POSITION_NED at 10 Hz
    TRIM = (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET,
            mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED,
            mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)

    def trim(self) -> None:
        """Ask PX4 to stop the GCS streams in :data:`TRIM` (PX4's CPU, and ours)."""
        for msg_id in self.TRIM:
            self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, -1)
        self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                     mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100_000)

    def set_param(self, name: str, value: float) -> None:
        """PARAM_SET with PX4's type for ``name`` (read first)."""
        ptype = self.params[name][1]
        self.mav.param_set_send(self.target, 1, name.encode('ascii'),
                                param_value_to_wire(value, ptype, True), ptype)

    def set_origin(self, hil: HilParams) -> None:
        """PX4's EKF origin at the world's origin (PX4's local frame = the world's map)."""
        self.mav.set_gps_global_origin_send(self.target, round(hil.home_lat_deg * 1e7),
                                            round(hil.home_lon_deg * 1e7),
                                            round(hil.home_alt_m * 1000.0), 0)
        self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)


def _wait(pred, timeout_s: float, abort=None, step_s: float = 0.05) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        if abort is not None and abort():
            return False
        time.sleep(step_s)
    return bool(pred())


class Px4Mission:
    """PX4 SITL for one mission of ``scenario`` (see the module docstring).

    :meth:`start` (PX4 in a fresh directory, the operator link; Px4NotFoundError /
    Px4StartError), :meth:`configure_graph`, :meth:`wait_up`, :meth:`take_off`,
    :meth:`wait_hover_measured`, :meth:`wait_disarmed`, :meth:`report`, :meth:`stop` (PX4
    killed, its directory removed; the ULog and PX4's log copied to ``keep_ulog`` first).
    """

    #: topics that flow only in the air (on the ground the planner disables the thrust)
    GROUND_SILENT = ('control/thrust', 'control/attitude')
    #: the firmware's name and the mode it flies the companion's setpoints in
    #: (:class:`deckland.sitl.ardupilot.ArduPilotMission` is the other backend)
    NAME = 'PX4'
    OFFBOARD_MODE = 'OFFBOARD'

    def __init__(self, scenario: Scenario, *, keep_ulog: str | None = None, nice: int = 0,
                 hil: HilParams | None = None) -> None:
        self.scenario = scenario
        self.hil = hil or HilParams()
        self.params = mission_params(scenario, self.hil)
        self.wire = wire_faults(scenario)
        self.keep_ulog = pathlib.Path(keep_ulog) if keep_ulog else None
        self.px4 = Px4Sitl(NONE_IRIS, self.params, nice=nice, keep_log_dir=self.keep_ulog)
        self.operator: Operator | None = None
        self.times: dict[str, float] = {}
        self.param_fixes: dict[str, float | None] = {}
        self.hover: float | None = None     # the bridge's hover thrust measured in PX4's loiter
        self._subs: list[Any] = []          # rclpy subscriptions on the monitor's node
        self._t0 = math.nan

    # --- lifecycle ---------------------------------------------------------------------

    def start(self) -> None:
        self._t0 = time.monotonic()
        self.px4.start()
        self.operator = Operator(self.px4.ports['gcs_local'], self.px4.system_id)

    def stop(self) -> None:
        if self.operator is not None:
            self.operator.close()
        self.px4.stop()

    @property
    def ports(self) -> dict[str, int]:
        return self.px4.ports

    def configure_graph(self, nodes: list) -> None:
        """Point the graph at PX4: the simulator flies in lockstep with it (TCP 4560 + i,
        physics at :data:`PHYSICS_RATE_HZ`); the bridge talks to PX4's onboard link (UDP
        14540 + i, PX4's system id), through the simulator's relay when the scenario has
        MAVLink wire faults."""
        p = self.ports
        onboard = f"udpin:127.0.0.1:{p['onboard_remote']}"
        for spec in nodes:
            if spec.name == 'deck_simulator':
                spec.parameters.update(autopilot='px4-sitl', px4_sim_port=p['simulator_tcp'],
                                       physics_rate_hz=PHYSICS_RATE_HZ)
                if self.wire:
                    spec.parameters['px4_onboard_url'] = onboard
            elif spec.name == 'mavlink_bridge':
                spec.parameters['system_id'] = self.px4.system_id
                if not self.wire:
                    spec.parameters['connection'] = onboard

    # --- the operator's part -------------------------------------------------------------

    def _log_tail(self) -> str:
        return self.px4.log_text()[-1500:]

    def wait_up(self, timeout_s: float, abort=None) -> tuple[bool, str]:
        """PX4 is running and its heartbeat reaches the operator (it boots once the
        simulator accepted its connection)."""
        op = self.operator
        assert op is not None
        ok = _wait(lambda: op.heartbeats > 0 or self.px4.proc is None
                   or self.px4.proc.poll() is not None, timeout_s, abort)
        if self.px4.proc is None or self.px4.proc.poll() is not None:
            return False, f'PX4 exited while starting; its log ends:\n{self._log_tail()}'
        if not ok or op.heartbeats == 0:
            return False, (f'PX4 sent no heartbeat within {timeout_s:g} s; its log ends:\n'
                           f'{self._log_tail()}')
        self.times['up_s'] = time.monotonic() - self._t0
        op.trim()
        return self.check_params()

    def check_params(self) -> tuple[bool, str]:
        """Read back every parameter of :func:`mission_params`; set the ones PX4 did not
        take (PARAM_SET) and check again. Floats within 1e-5 (PX4 stores float32; 0.0 is
        sent as :data:`~deckland.sitl.px4.ZERO_FLOAT`)."""
        op = self.operator
        assert op is not None

        def wrong(vals: dict[str, float]) -> dict[str, float | None]:
            return {k: vals.get(k) for k, v in self.params.items()
                    if k not in vals or abs(vals[k] - float(v)) > 1e-5 + 1e-6 * abs(v)}

        bad = wrong(op.read_params(self.params))
        self.param_fixes = dict(bad)
        for name in bad:
            if name in op.params:
                op.set_param(name, float(self.params[name]) or ZERO_FLOAT)
        if bad:
            time.sleep(0.5)
            bad = wrong(op.read_params(bad))
        if bad:
            return False, f'PX4 did not take the parameters {bad} (asked {self.params})'
        return True, 'PX4 up, parameters checked'


    def take_off(self, timeout_s: float = 90.0, abort=None) -> tuple[bool, str]:
        """As an operator would: EKF origin at the world's origin, arm (repeated until PX4's
        pre-flight checks pass), PX4's own take-off (NAV_TAKEOFF to MIS_TAKEOFF_ALT), until PX4
        loiters at the take-off height (AUTO.LOITER, within 0.3 m)."""
        op = self.operator
        assert op is not None
        end = time.monotonic() + timeout_s

        def left() -> float:
            return max(0.0, end - time.monotonic())

        op.set_origin(self.hil)
        if not _wait(lambda: op.origin is not None, min(10.0, left()), abort):
            return False, 'PX4 did not report its EKF origin (GPS_GLOBAL_ORIGIN)'
        want = (round(self.hil.home_lat_deg * 1e7), round(self.hil.home_lon_deg * 1e7))
        if op.origin[:2] != want:
            op.set_origin(self.hil)
            if not _wait(lambda: op.origin is not None and op.origin[:2] == want,
                         min(5.0, left()), abort):
                return False, f'PX4 kept its EKF origin {op.origin} (asked {want})'
        t_arm = time.monotonic()

        def arm() -> bool:
            if not op.armed and time.monotonic() - arm.last > 0.5:
                arm.last = time.monotonic()
                op.command(MAV_CMD_COMPONENT_ARM_DISARM, 1)
            return op.armed

        arm.last = 0.0
        if not _wait(arm, min(40.0, left()), abort):
            texts = '; '.join(t for _, t in op.texts[-5:])
            return False, f'PX4 refused to arm within 40 s ({texts})'
        self.times['armed_s'] = time.monotonic() - self._t0
        self.times['arm_wait_s'] = time.monotonic() - t_arm
        home_z = op.local_ned[2] if op.local_ned is not None else 0.0
        op.command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        alt = self.params['MIS_TAKEOFF_ALT']    # above home, where PX4 armed

        def up_there() -> bool:
            lp = op.local_ned
            return (op.mode == 'AUTO.LOITER' and lp is not None
                    and abs(home_z - lp[2] - alt) < 0.3)

        if not _wait(lambda: op.mode == 'AUTO.TAKEOFF' or up_there(), min(5.0, left()), abort):
            return False, f'PX4 did not start its take-off (mode {op.mode})'
        if not _wait(up_there, left(), abort):
            return False, (f'PX4 not loitering at {alt:g} m after its take-off (mode '
                           f'{op.mode}, local position {op.local_ned})')
        self.times['loiter_s'] = time.monotonic() - self._t0
        op.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION)
        return True, f'PX4 loiters at {-op.local_ned[2]:.2f} m'

    def wait_hover_measured(self, node, timeout_s: float = 30.0, abort=None) -> float:
        """The bridge's hover thrust measured in PX4's hover (its diagnostics key
        ``hover_thrust_measured``; NaN if not within ``timeout_s``). ``node``: an rclpy node
        being spun (the mission monitor's)."""
        from deckland_common.ros_node import RELIABLE_QOS
        from diagnostic_msgs.msg import DiagnosticArray

        seen = {'h': math.nan}

        def on_diag(msg) -> None:
            for st in msg.status:
                for kv in st.values:
                    if kv.key == 'hover_thrust_measured':
                        with contextlib.suppress(ValueError):
                            seen['h'] = float(kv.value)

        # kept until the node goes (not destroyed here): destroying a subscription from this
        # thread while the monitor's executor spins it can end that executor's thread, and
        # then no service reply and no planner/mode reaches the monitor any more (suspected
        # in the planner/takeoff time-outs at load 10-50)
        self._subs.append(node.create_subscription(DiagnosticArray, 'diagnostics', on_diag,
                                                   RELIABLE_QOS))
        _wait(lambda: math.isfinite(seen['h']), timeout_s, abort, 0.1)
        if math.isfinite(seen['h']):
            self.times['hover_measured_s'] = time.monotonic() - self._t0
            self.hover = seen['h']
        return seen['h']

    def operator_take_off(self, monitor, log, abort=None) -> tuple[bool, str]:
        """:func:`operator_take_off` with this PX4 (the registry's mission interface)."""
        return operator_take_off(self, monitor, log, abort)

    @property
    def mode(self) -> str:
        """PX4's mode as the operator sees it ('' before its first heartbeat)."""
        return self.operator.mode if self.operator is not None else ''

    def cpu_s(self) -> float:
        """PX4's CPU time so far (user + system, seconds)."""
        return self.px4.cpu_s()

    def describe(self) -> str:
        """One log line: which PX4, where, on which ports."""
        p = self.ports
        return (f'PX4 SITL {self.px4.root} instance {self.px4.instance} in {self.px4.workdir} '
                f"(simulator TCP {p['simulator_tcp']}, onboard UDP {p['onboard_remote']}, "
                f"GCS UDP {p['gcs_local']})")

    def wait_mode(self, mode: str, timeout_s: float, abort=None) -> bool:
        """PX4 reports ``mode`` (e.g. ``'OFFBOARD'``) within ``timeout_s``."""
        op = self.operator
        assert op is not None
        return _wait(lambda: op.mode == mode, timeout_s, abort)

    def wait_disarmed(self, timeout_s: float, abort=None) -> bool:
        """PX4 disarmed (after its land detector, or a failsafe landing)."""
        op = self.operator
        assert op is not None
        ok = _wait(lambda: not op.armed and op.heartbeats > 0, timeout_s, abort, 0.1)
        if ok:
            self.times['disarmed_s'] = time.monotonic() - self._t0
        return ok

    def modes_since(self, t_s: float) -> list[dict[str, Any]]:
        """PX4's modes (operator's view) from monotonic ``t_s`` on (t relative to it)."""
        op = self.operator
        if op is None:
            return []
        modes = op.modes
        first = max([i for i, (t, _, _) in enumerate(modes) if t <= t_s] or [0])
        return [{'t_s': round(t - t_s, 3), 'mode': m, 'armed': a}
                for t, m, a in modes[first:]]

    def report(self, t_ref_s: float | None = None) -> dict[str, Any]:
        """What PX4 did, for ``report.json`` (``t_ref_s``: the landing trigger, monotonic)."""
        op = self.operator
        t_ref = self._t0 if t_ref_s is None else t_ref_s
        return {
            'px4_root': str(self.px4.root), 'instance': self.px4.instance,
            'workdir': str(self.px4.workdir),
            'params': dict(self.params), 'params_fixed_after_boot': dict(self.param_fixes),
            'hover_thrust_measured': self.hover,
            'times_s': {k: round(v, 2) for k, v in self.times.items()},
            'armed_at_end': op.armed if op is not None else None,
            'landed_state_at_end': op.landed_state if op is not None else None,
            'mode_at_end': op.mode if op is not None else '',
            # PX4's home (where a Return lands) in the world's ENU map frame (PX4's local
            # frame is the world's, origin shared: x east = NED y)
            'home_map_m': None if op is None or op.home_ned is None else [
                round(op.home_ned[1], 3), round(op.home_ned[0], 3), round(-op.home_ned[2], 3)],
            'modes': self.modes_since(t_ref) if op is not None else [],
            'statustext': [t for _, t in op.texts[-12:]] if op is not None else [],
            'px4_cpu_s': round(self.px4.cpu_s(), 1),
            'ulog_dir': str(self.keep_ulog) if self.keep_ulog else None,
        }


def operator_take_off(px4: Px4Mission, monitor, log, abort=None) -> tuple[bool, str]:
    """The operator's take-off with PX4 (:meth:`Px4Mission.take_off`), the bridge's hover
    thrust in PX4's loiter, and the planner's take-off (its IDLE holds the height it latched
    on the ground; TAKEOFF resets the reference to the height flown now and holds the
    approach height). ``monitor``: :class:`deckland.graph.up.MissionMonitor`; ``log(text)``."""
    name = px4.NAME
    log(f"{name}: EKF origin, arm, take off ({name}'s own take-off)")
    ok, msg = px4.take_off(abort=abort)
    log(f'{name} take-off: {msg}')
    if not ok:
        return False, f'{name} take-off failed: {msg}'
    hover = px4.wait_hover_measured(monitor.node, HOVER_WAIT_S, abort=abort)
    log(f"bridge: hover thrust measured in {name}'s hover {hover:.4f}" if math.isfinite(hover)
        else f"bridge: no steady hover thrust in {name}'s hover within {HOVER_WAIT_S:g} s "
        "(the autopilot's hover parameter is used)")
    for attempt in range(TAKEOFF_TRIGGER_ATTEMPTS):
        ok, msg = monitor.trigger('planner/takeoff', timeout_s=TAKEOFF_TRIGGER_TIMEOUT_S)
        if ok or 'timed out' not in msg:
            break
        if _wait(lambda: monitor.mode in TAKEOFF_TAKEN, 2.0, abort, 0.1):
            # the planner took it (planner/mode says so) but its reply was lost: a DDS
            # reply to a fresh client can go out before the client's reader is matched
            # (seen at load 10); the mode, not the reply, is what counts
            ok, msg = True, f'reply lost, planner/mode {monitor.mode}'
            break
        log(f'planner/takeoff: {msg} (attempt {attempt + 1}; planner/mode '
            f'{monitor.mode or "none"}), again')
    log(f'planner/takeoff: {ok} {msg}')
    if not ok:
        return False, f'planner/takeoff refused: {msg}'
    return True, msg
