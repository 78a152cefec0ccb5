"""ROS 2 adapter of the MAVLink bridge (thin: transport + message conversion only).

Decisions live in :mod:`mavlink_bridge.core` and frame/unit conversions in
:mod:`mavlink_bridge.conversions`; this module owns the pymavlink connection (TCP through
:class:`~mavlink_bridge.tcp.ReconnectingTcp`), a background reader thread, a 50 Hz
housekeeping timer and the ROS publishers, subscribers and services.
The core runs on ``time.monotonic()`` (link and input freshness are about the real transport);
published headers carry the node clock (ROS time, sim time when ``use_sim_time``).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time

os.environ.setdefault('MAVLINK20', '1')  # before pymavlink.mavutil picks its dialect

from deckland_common.contract import VehicleDescription
from deckland_common.frames import euler_to_quaternion, rot_body_to_world
from deckland_common.params import (
    ParameterError,
    ParamSpec,
    in_range,
    one_of,
    positive,
)
from deckland_common.ros_node import (
    LATCHED_QOS,
    RELIABLE_QOS,
    SENSOR_QOS,
    declare_and_validate,
    run_node,
    stamp_to_s,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import QuaternionStamped, TwistStamped, WrenchStamped
from nav_msgs.msg import Odometry
from pymavlink import mavutil
from rclpy.node import Node
from sensor_msgs.msg import Imu, Range
from std_msgs.msg import Bool, String
from std_srvs.srv import SetBool, Trigger

from deckland_interfaces.msg import LinkStatus
from mavlink_bridge.conversions import (
    MAV_SENSOR_ROTATION_PITCH_270,
    PX4_OFFBOARD_LOSS_ACTIONS,
    ThrustCalibration,
    attitude_to_enu,
    distance_sensor_to_rep117,
    imu_frd_to_flu,
    landing_target_ardupilot,
    landing_target_px4,
    local_position_ned_to_enu,
    origin_offset_enu,
    parse_llh,
    scaled_imu_to_flu,
)
from mavlink_bridge.core import ARDUPILOT_STOP_MODES, BridgeCore, BridgeParams, LinkMonitorParams
from mavlink_bridge.signing import load_signing_key, verify_signature_first
from mavlink_bridge.tcp import ReconnectingTcp

_load_signing_key = load_signing_key   # the earlier private name

_VEHICLE = VehicleDescription()


def _actions(value: str) -> tuple[str, ...]:
    return tuple(a.strip().lower() for a in str(value).split(',') if a.strip())


def _valid_llh(value: str) -> bool:
    try:
        parse_llh(value)
    except ValueError:
        return False
    return True


PARAMS = [
    ParamSpec('connection', 'udpin:127.0.0.1:14540',
              "pymavlink device: 'udpin:HOST:PORT' listens (PX4 SITL/emulator send here), "
              "'udpout:HOST:PORT' or 'tcp:HOST:PORT' connects, '/dev/ttyACM0' is serial",
              lambda v: bool(v.strip()), 'must not be empty'),
    positive('baud', 921600, 'serial baud rate (serial devices only)'),
    one_of('autopilot', 'px4', ('px4', 'ardupilot'), 'autopilot flavour'),
    in_range('system_id', 1, 1, 255, "our MAVLink system id (normally the vehicle's)"),
    in_range('component_id', 191, 1, 255, 'our component id (191 = onboard computer)'),
    in_range('target_component', 1, 0, 255, 'autopilot component id'),
    positive('mass_kg', _VEHICLE.mass_kg,
             'vehicle mass for the thrust calibration (paper Table 2; deckland up passes the '
             'vehicle description)'),
    positive('gravity_mps2', _VEHICLE.gravity_mps2, 'gravity for the thrust calibration'),
    ParamSpec('hover_thrust_norm', _VEHICLE.hover_thrust_norm,
              'normalised thrust that hovers (PX4 MPC_THR_HOVER, ArduPilot MOT_THST_HOVER)',
              lambda v: 0.0 < v < 1.0, 'must be in (0, 1)'),
    in_range('thrust_expo', _VEHICLE.thrust_expo, 0.0, 1.0,
             'residual thrust curve expo e in F = Fmax(e n^2 + (1-e) n); 0 = linear'),
    positive('input_timeout_s', 0.2, 'max age of control/thrust and control/attitude'),
    positive('link_timeout_s', 3.0, 'autopilot heartbeat age that means link lost'),
    positive('max_stream_rate_hz', 250.0,
             'long-term cap of the SET_ATTITUDE_TARGET rate; each new control/thrust is sent '
             'at once while the cap leaves room (token bucket refill rate)'),
    in_range('stream_burst', 3, 1, 100,
             'setpoints allowed back to back under the cap (token bucket depth; 1 = a plain '
             'minimum interval of 1/max_stream_rate_hz)'),
    positive('fresh_period_s', 0.02,
             'a command whose stamp is this much newer than the last one sent is never '
             'rate-limited (one camera period, 50 Hz); must be <= 0.5 s'),
    ParamSpec('offboard_warmup_s', 0.2, 'setpoint streaming before the OFFBOARD request (PX4 '
              'v1.16 needs one setpoint younger than COM_OF_LOSS_T)',
              lambda v: 0.0 <= v < 5.0, 'must be in [0, 5)'),
    ParamSpec('offboard_loss_actions', 'land,hold',
              "PX4 COM_OBL_RC_ACT values OFFBOARD may be entered with, comma-separated names "
              "of 'position, altitude, manual, return, land, hold, terminate, disarm'; any "
              'other (or unknown) action refuses bridge/offboard',
              lambda v: bool(_actions(v)) and all(a in PX4_OFFBOARD_LOSS_ACTIONS.values()
                                                  for a in _actions(v)),
              'must be a comma-separated list of PX4 offboard-loss action names'),
    positive('max_offboard_loss_timeout_s', 2.0,
             'PX4 COM_OF_LOSS_T above this refuses bridge/offboard (PX4 flies the last '
             'setpoint that long)'),
    one_of('hover_thrust_source', 'autopilot', ('autopilot', 'parameter'),
           "PX4: 'autopilot' = the thrust PX4 commands in its own hover (ATTITUDE_TARGET), "
           "else MPC_THR_HOVER; 'parameter' = hover_thrust_norm"),
    ParamSpec('trim_telemetry', True, 'ask the autopilot to stop every stream the bridge does '
              'not read (SET_MESSAGE_INTERVAL -1)'),
    ParamSpec('use_highres_imu', True, 'vehicle/imu from HIGHRES_IMU (PX4); False = SCALED_IMU. '
              'An autopilot that refuses HIGHRES_IMU (ArduPilot: DENIED) gets SCALED_IMU '
              'anyway'),
    one_of('ardupilot_stop_action', 'land', tuple(ARDUPILOT_STOP_MODES),
           'ArduPilot: what the bridge commands when its setpoints stop while ArduPilot flies '
           "them ('land' = LAND; 'loiter' = LOITER, needs a position estimate, else LAND; "
           "'none' = GUIDED_NOGPS's own timeout: level, hold altitude, indefinitely)"),
    positive('stop_after_s', 0.3, 'ArduPilot: setpoint gap after which the stop action is '
             'commanded'),
    positive('disarm_timeout_s', 15.0, 'ArduPilot: a disarm refused while its land detector '
             'catches up (FAILED) is retried this long'),
    ParamSpec('signing_key_file', '', 'MAVLink 2 signing key file (32 raw bytes or 64 hex '
              'characters); empty = unsigned'),
    ParamSpec('landing_target_output', False,
              'send LANDING_TARGET from apron/odom (PX4: LOCAL_NED position, ArduPilot: body)'),
    ParamSpec('map_frame', 'map', 'world frame id (ENU)'),
    ParamSpec('map_origin_llh', '', "'lat_deg,lon_deg,alt_m' of map's origin: positions are "
              "shifted by where the autopilot's local origin (GPS_GLOBAL_ORIGIN, requested) lies "
              "in map, and vehicle/odom waits for it (ArduCopter puts its origin at its first "
              "GPS fix and refuses SET_GPS_GLOBAL_ORIGIN while it uses GPS); empty = map is the "
              "autopilot's local frame", _valid_llh, "must be empty or 'lat,lon,alt'"),
    ParamSpec('base_frame', 'base_link', 'body frame id (FLU)'),
    ParamSpec('lidar_frame', 'lidar_link', 'frame id of vehicle/range'),
    positive('range_field_of_view_rad', 0.008, 'Range.field_of_view (LidarLite v3 beam)'),
    positive('timesync_period_s', 0.1, 'TIMESYNC request period (link round-trip probe)'),
    positive('max_link_latency_s', 0.06,
             'one-way link latency (TIMESYNC rtt / 2) above which setpoints stop streaming so '
             "that the autopilot's offboard-loss failsafe takes over"),
    in_range('latency_window', 4, 1, 100,
             'latency estimate = minimum of this many last one-way samples'),
    ParamSpec('latency_confirm_s', 0.2, 'the estimate must stay above max_link_latency_s this '
              'long before streaming stops', lambda v: v >= 0.0, 'must be >= 0'),
]


class MavlinkBridgeNode(Node):
    """The ``mavlink_bridge`` node; see the package README for its interface."""

    def __init__(self, **kwargs) -> None:
        super().__init__('mavlink_bridge', **kwargs)
        cfg = declare_and_validate(self, PARAMS)
        self.cfg = cfg
        try:
            calib = ThrustCalibration(mass_kg=cfg['mass_kg'], gravity_mps2=cfg['gravity_mps2'],
                                      hover_thrust_norm=cfg['hover_thrust_norm'],
                                      expo=cfg['thrust_expo'])
            self.core = BridgeCore(BridgeParams(
                autopilot=cfg['autopilot'], input_timeout_s=cfg['input_timeout_s'],
                link_timeout_s=cfg['link_timeout_s'],
                max_stream_rate_hz=cfg['max_stream_rate_hz'], stream_burst=cfg['stream_burst'],
                fresh_period_s=cfg['fresh_period_s'],
                offboard_warmup_s=cfg['offboard_warmup_s'],
                offboard_loss_actions=_actions(cfg['offboard_loss_actions']),
                max_offboard_loss_timeout_s=cfg['max_offboard_loss_timeout_s'],
                hover_thrust_source=cfg['hover_thrust_source'],
                trim_telemetry=cfg['trim_telemetry'],
                use_highres_imu=bool(cfg['use_highres_imu']),
                ardupilot_stop_action=cfg['ardupilot_stop_action'],
                stop_after_s=cfg['stop_after_s'], disarm_timeout_s=cfg['disarm_timeout_s'],
                system_id=cfg['system_id'],
                target_component=cfg['target_component'], thrust=calib,
                link_monitor=LinkMonitorParams(
                    period_s=cfg['timesync_period_s'], max_latency_s=cfg['max_link_latency_s'],
                    window=cfg['latency_window'], confirm_s=cfg['latency_confirm_s'])))
        except ValueError as exc:
            raise ParameterError(str(exc)) from exc
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        mavutil.set_dialect('common')  # MAVLink 2 common (MAVLINK20 set above)
        dev = cfg['connection'].strip()
        if dev.startswith('tcp:'):
            # survives the peer going away: no busy loop, reconnects (issue 17, finding 7)
            self.conn = ReconnectingTcp(dev[4:], source_system=cfg['system_id'],
                                        source_component=cfg['component_id'])
        else:
            self.conn = mavutil.mavlink_connection(
                dev, baud=cfg['baud'], source_system=cfg['system_id'],
                source_component=cfg['component_id'], dialect='common')
        self.signed = bool(cfg['signing_key_file'])
        if self.signed:
            try:
                key = load_signing_key(cfg['signing_key_file'])
            except ParameterError:
                with contextlib.suppress(Exception):
                    self.conn.close()
                raise
            # outgoing: signed (link id 0, timestamp from the wall clock, as pymavlink does);
            # incoming: only correctly signed messages (no unsigned callback)
            self.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=None,
                                    link_id=0)
            verify_signature_first(self.conn.mav)
        self.errors = {'recv_exceptions': 0, 'send_exceptions': 0}
        # latest telemetry (ENU/FLU)
        self._att = None          # ((roll, pitch, yaw), rates)
        self._pos = None          # (position, velocity)
        self._anchor = parse_llh(cfg['map_origin_llh'])
        #: the autopilot's local origin in map (ENU), from GPS_GLOBAL_ORIGIN; None = unknown
        self._origin_enu: tuple[float, float, float] | None = (
            None if self._anchor is not None else (0.0, 0.0, 0.0))
        self._origin_asked_s = -math.inf
        self._published_state: dict[str, object] = {}

        self.pub_odom = self.create_publisher(Odometry, 'vehicle/odom', RELIABLE_QOS)
        self.pub_vel = self.create_publisher(TwistStamped, 'vehicle/velocity', RELIABLE_QOS)
        self.pub_imu = self.create_publisher(Imu, 'vehicle/imu', RELIABLE_QOS)
        self.pub_range = self.create_publisher(Range, 'vehicle/range', RELIABLE_QOS)
        self.pub_armed = self.create_publisher(Bool, 'vehicle/armed', LATCHED_QOS)
        self.pub_mode = self.create_publisher(String, 'vehicle/mode', LATCHED_QOS)
        self.pub_landed = self.create_publisher(Bool, 'vehicle/landed', LATCHED_QOS)
        self.create_subscription(QuaternionStamped, 'control/attitude', self._on_attitude,
                                 SENSOR_QOS)
        self.create_subscription(WrenchStamped, 'control/thrust', self._on_thrust, SENSOR_QOS)
        self.create_subscription(Bool, 'control/enabled', self._on_enabled, LATCHED_QOS)
        if cfg['landing_target_output']:
            self.create_subscription(Odometry, 'apron/odom', self._on_apron, SENSOR_QOS)
        self.create_service(SetBool, 'bridge/arm', self._srv_arm)
        self.create_service(Trigger, 'bridge/offboard', self._srv_offboard)
        self.pub_diag = self.create_publisher(DiagnosticArray, 'diagnostics', RELIABLE_QOS)
        self.pub_status = self.create_publisher(LinkStatus, 'bridge/status', RELIABLE_QOS)
        self.create_timer(0.02, self._on_timer)
        self.create_timer(1.0, self._publish_diagnostics)
        self._build_messages()
        self._degraded_logged = False
        self._last_result_logged = ''
        self._running = True
        self._reader = threading.Thread(target=self._read_loop, name='mavlink_reader',
                                        daemon=True)
        self._reader.start()

    # --- helpers -------------------------------------------------------------------------

    def _now(self) -> float:
        return time.monotonic()

    def _boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000.0) & 0xFFFFFFFF

    def _build_messages(self) -> None:
        """The 100 Hz telemetry messages, built once and refilled by the reader thread (the
        only thread that publishes them; publish() serialises, so reuse is safe)."""
        od = Odometry()
        od.header.frame_id = self.cfg['map_frame']
        od.child_frame_id = self.cfg['base_frame']
        self._msg_odom = od
        ts = TwistStamped()
        ts.header.frame_id = self.cfg['map_frame']
        self._msg_vel = ts
        imu = Imu()
        imu.header.frame_id = self.cfg['base_frame']
        self._msg_imu = imu
        rng = Range()
        rng.header.frame_id = self.cfg['lidar_frame']
        rng.radiation_type = Range.INFRARED
        rng.field_of_view = float(self.cfg['range_field_of_view_rad'])
        self._msg_range = rng

    def _send(self, fn, *args, **kwargs) -> None:
        try:
            fn(*args, **kwargs)
        except Exception:  # a serial write error must not kill a callback
            self.errors['send_exceptions'] += 1

    def _target(self) -> tuple[int, int]:
        return self.core.target_system or 1, self.core.target_component

    # --- MAVLink in ----------------------------------------------------------------------

    def _read_loop(self) -> None:
        while self._running:
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.05)
            except Exception:
                self.errors['recv_exceptions'] += 1
                with self._lock:
                    self.core.count_bad_data()
                time.sleep(0.001)
                continue
            if msg is None:
                continue
            try:
                self._handle(msg)
            except Exception as exc:  # never let one odd message stop the reader
                if not self.context.ok():
                    break           # shutting down: the publishers are gone, not an error
                self.errors['recv_exceptions'] += 1
                self.get_logger().warning(f'MAVLink {msg.get_type()} handling failed: {exc}',
                                          throttle_duration_sec=5.0)

    def _handle(self, msg) -> None:
        kind = msg.get_type()
        now = self._now()
        if kind not in ('BAD_DATA', 'HEARTBEAT') and self.core.target_system is not None \
                and msg.get_srcSystem() != self.core.target_system:
            self._count_rejected('other_system')  # another vehicle's data is not ours
            return
        if kind != 'BAD_DATA' and msg.get_srcComponent() == self.core.target_component:
            self.core.on_message(msg.get_msgId())   # (a set insertion: no lock needed)
        if kind == 'BAD_DATA':
            with self._lock:
                self.core.count_bad_data()
            if getattr(msg, 'reason', '') == 'Invalid signature':
                self._count_rejected('bad_signature')   # unsigned or another key
        elif kind == 'HEARTBEAT':
            with self._lock:
                ok = self.core.on_heartbeat(now, msg.get_srcSystem(), msg.get_srcComponent(),
                                            msg.type, msg.autopilot, msg.base_mode,
                                            msg.custom_mode)
                armed, mode = self.core.armed, self.core.mode
            if ok:
                self._publish_latched('armed', self.pub_armed, Bool(data=armed))
                self._publish_latched('mode', self.pub_mode, String(data=mode))
        elif kind == 'COMMAND_ACK':
            with self._lock:
                self.core.on_command_ack(now, msg.command, msg.result)
        elif kind == 'TIMESYNC':
            with self._lock:
                self.core.on_timesync(now, int(msg.tc1), int(msg.ts1))
        elif kind == 'PARAM_VALUE':
            with self._lock:
                self.core.on_param_value(msg.param_id, msg.param_value, msg.param_type)
        elif kind == 'EXTENDED_SYS_STATE':
            with self._lock:
                self.core.on_extended_sys_state(msg.landed_state)
                landed = self.core.landed
            if landed is not None:
                self._publish_latched('landed', self.pub_landed, Bool(data=landed))
        elif kind == 'ATTITUDE_TARGET':
            # PX4's own commanded thrust: a hover-thrust sample while PX4 flies by itself
            if self._att is not None and self._pos is not None and math.isfinite(msg.thrust):
                (roll, pitch, _), _ = self._att
                with self._lock:
                    self.core.on_attitude_target(now, msg.thrust,
                                                 math.cos(roll) * math.cos(pitch),
                                                 self._pos[1][2])
        elif kind == 'ATTITUDE':
            vals = (msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
            if all(map(math.isfinite, vals)):
                self._att = attitude_to_enu(*vals)
            else:
                self._count_rejected('nan')
        elif kind == 'LOCAL_POSITION_NED':
            vals = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
            if all(map(math.isfinite, vals)):
                (x, y, z), vel = local_position_ned_to_enu(*vals)
                o = self._origin_enu
                if o is None:
                    self._count_rejected('no_origin')    # map anchored, origin not known yet
                    return
                self._pos = ((x + o[0], y + o[1], z + o[2]), vel)
                self._publish_odom()
            else:
                self._count_rejected('nan')
        elif kind == 'GPS_GLOBAL_ORIGIN':
            if self._anchor is not None:
                o = origin_offset_enu((msg.latitude, msg.longitude, msg.altitude), self._anchor)
                if o != self._origin_enu:
                    self.get_logger().info(
                        f"autopilot's local origin at ({o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}) m "
                        'in map')
                self._origin_enu = o
        elif kind == 'HIGHRES_IMU':
            if self.core.imu_msg != kind:
                return            # (only one IMU stream is published)
            vals = (msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro)
            if all(map(math.isfinite, vals)):
                self._publish_imu(*imu_frd_to_flu(*vals))
            else:
                self._count_rejected('nan')
        elif kind == 'SCALED_IMU':
            if self.core.imu_msg != kind:
                return
            self._publish_imu(*scaled_imu_to_flu(msg.xacc, msg.yacc, msg.zacc, msg.xgyro,
                                                 msg.ygyro, msg.zgyro))
        elif kind == 'STATUSTEXT':
            with self._lock:
                text = self.core.on_statustext(now, msg.severity, msg.text,
                                               getattr(msg, 'id', 0), getattr(msg, 'chunk_seq', 0))
            if text is not None:
                self._log_statustext(msg.severity, text)
        elif kind == 'DISTANCE_SENSOR':
            if msg.orientation != MAV_SENSOR_ROTATION_PITCH_270:
                return  # not the downward LidarLite
            out = self._msg_range
            out.header.stamp = self.get_clock().now().to_msg()
            out.min_range = msg.min_distance * 0.01
            out.max_range = msg.max_distance * 0.01
            # REP-117: -inf too close (<= min_distance, e.g. PX4 SIH's 0 cm on the ground),
            # +inf no return (beyond max_distance, UINT16_MAX unknown)
            out.range = distance_sensor_to_rep117(msg.current_distance, msg.min_distance,
                                                  msg.max_distance)
            self.pub_range.publish(out)

    def _log_statustext(self, severity: int, text: str) -> None:
        """The autopilot's text at the matching log level (MAV_SEVERITY 0-3 error, 4 warning,
        5-6 info, 7 debug)."""
        # one call site per severity: rclpy refuses a call site whose severity changes
        log, line = self.get_logger(), f'autopilot: {text}'
        if severity <= 3:
            log.error(line)
        elif severity == 4:
            log.warning(line)
        elif severity <= 6:
            log.info(line)
        else:
            log.debug(line)

    def _count_rejected(self, reason: str) -> None:
        with self._lock:
            self.core.rejected[reason] = self.core.rejected.get(reason, 0) + 1

    def _publish_latched(self, key: str, pub, msg) -> None:
        if self._published_state.get(key) != msg.data:
            self._published_state[key] = msg.data
            pub.publish(msg)

    def _publish_odom(self) -> None:
        (x, y, z), (vx, vy, vz) = self._pos
        euler, rates = self._att if self._att is not None else ((0.0, 0.0, 0.0), (0.0,) * 3)
        w, qx, qy, qz = euler_to_quaternion(*euler)
        od = self._msg_odom
        od.header.stamp = self.get_clock().now().to_msg()
        od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = x, y, z
        q = od.pose.pose.orientation
        q.w, q.x, q.y, q.z = w, qx, qy, qz
        m = rot_body_to_world(*euler)  # twist in base_link (REP-105): v_body = Rᵀ v_world
        tw = od.twist.twist
        tw.linear.x = m[0][0] * vx + m[1][0] * vy + m[2][0] * vz
        tw.linear.y = m[0][1] * vx + m[1][1] * vy + m[2][1] * vz
        tw.linear.z = m[0][2] * vx + m[1][2] * vy + m[2][2] * vz
        tw.angular.x, tw.angular.y, tw.angular.z = rates
        self.pub_odom.publish(od)
        ts = self._msg_vel
        ts.header.stamp = od.header.stamp
        ts.twist.linear.x, ts.twist.linear.y, ts.twist.linear.z = vx, vy, vz
        self.pub_vel.publish(ts)

    def _publish_imu(self, accel_flu, gyro_flu) -> None:
        imu = self._msg_imu
        imu.header.stamp = self.get_clock().now().to_msg()
        if self._att is not None:
            w, qx, qy, qz = euler_to_quaternion(*self._att[0])
            imu.orientation_covariance[0] = 0.0
        else:
            w, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
            imu.orientation_covariance[0] = -1.0  # REP-145: orientation unknown
        imu.orientation.w, imu.orientation.x = w, qx
        imu.orientation.y, imu.orientation.z = qy, qz
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = gyro_flu
        acc = imu.linear_acceleration
        acc.x, acc.y, acc.z = accel_flu
        self.pub_imu.publish(imu)

    # --- ROS in --------------------------------------------------------------------------

    def _future(self, stamp_s: float) -> bool:
        """A command stamped ahead of the node clock by more than ``input_timeout_s`` is
        refused: accepted, it would make every later command "out of order" until then."""
        if stamp_s - self.get_clock().now().nanoseconds * 1e-9 > self.cfg['input_timeout_s']:
            self._count_rejected('future_stamp')
            return True
        return False

    def _on_attitude(self, msg: QuaternionStamped) -> None:
        q = msg.quaternion
        if self._future(stamp_to_s(msg.header.stamp)):
            return
        with self._lock:
            self.core.on_attitude_command(self._now(), stamp_to_s(msg.header.stamp),
                                          (q.w, q.x, q.y, q.z))

    def _on_thrust(self, msg: WrenchStamped) -> None:
        stamp_s = stamp_to_s(msg.header.stamp)
        if self._future(stamp_s):
            return
        with self._lock:
            sp = self.core.on_thrust_command(self._now(), stamp_s, msg.wrench.force.z)
            if sp is not None:
                ts, tc = self._target()
                # [bench hook] time_boot_ms = the command's source stamp (control/thrust
                # header = the apron state's t_s) in ms mod 2^32, so a MAVLink tap maps each
                # setpoint back to its camera frame (deckland bench latency, README-bench.md).
                # The autopilots (PX4, ArduPilot, the simulator) ignore this field here.
                boot_ms = round(stamp_s * 1000.0) & 0xFFFFFFFF
                self._send(self.conn.mav.set_attitude_target_send, boot_ms, ts, tc,
                           sp.type_mask, list(sp.q_ned_frd), 0.0, 0.0, 0.0, sp.thrust_norm)

    def _on_enabled(self, msg: Bool) -> None:
        with self._lock:
            self.core.on_enabled(self._now(), bool(msg.data))

    def _on_apron(self, msg: Odometry) -> None:
        p = msg.pose.pose.position
        if not all(map(math.isfinite, (p.x, p.y, p.z))):
            return
        if self.cfg['autopilot'] == 'px4':
            fields = landing_target_px4(int(self._boot_ms() * 1000), (p.x, p.y, p.z))
        else:
            if self._pos is None or self._att is None:
                return
            (vx, vy, vz), euler = self._pos[0], self._att[0]
            m = rot_body_to_world(*euler)
            d = (p.x - vx, p.y - vy, p.z - vz)
            rel = tuple(m[0][i] * d[0] + m[1][i] * d[1] + m[2][i] * d[2] for i in range(3))
            fields = landing_target_ardupilot(int(self._boot_ms() * 1000), rel)
        with self._lock:
            self._send(self.conn.mav.landing_target_send, **fields)

    def _srv_arm(self, request, response):
        with self._lock:
            response.success, response.message = self.core.request_arm(self._now(),
                                                                        bool(request.data))
        return response

    def _srv_offboard(self, request, response):
        with self._lock:
            response.success, response.message = self.core.request_offboard(self._now())
        log = self.get_logger()
        # (two call sites: rclpy raises when one call site's severity changes)
        if response.success:
            log.info(f'bridge/offboard: {response.message}')
        else:
            log.warning(f'bridge/offboard: {response.message}')
        return response

    # --- periodic ------------------------------------------------------------------------

    def _on_timer(self) -> None:
        with self._lock:
            out = self.core.step(self._now())
            ts, tc = self._target()
            for o in out:
                if o.kind == 'heartbeat':
                    self._send(self.conn.mav.heartbeat_send,
                               mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                               mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                               mavutil.mavlink.MAV_STATE_ACTIVE)
                elif o.kind == 'command':
                    self._send(self.conn.mav.command_long_send, ts, tc, o.command, 0,
                               *o.params)
                elif o.kind == 'param_request':
                    self._send(self.conn.mav.param_request_read_send, ts, tc,
                               o.param_id.encode('ascii'), -1)
                elif o.kind == 'timesync':
                    self._send(self.conn.mav.timesync_send, 0, round(o.params[0] * 1e9))
            now = self._now()
            if self._anchor is not None and self._origin_enu is None and \
                    now - self._origin_asked_s > 2.0 and self.core.link_up(now):
                self._origin_asked_s = now       # MAV_CMD_REQUEST_MESSAGE GPS_GLOBAL_ORIGIN
                self._send(self.conn.mav.command_long_send, ts, tc, 512, 0, 49, 0, 0, 0, 0,
                           0, 0)
            mon = self.core.link_monitor
            degraded, reason = mon.degraded, mon.reason
            result = self.core.last_result
        if degraded and not self._degraded_logged:
            self.get_logger().error(reason)
        self._degraded_logged = degraded
        if result != self._last_result_logged:
            self._last_result_logged = result
            if result.startswith(('stop:', 'HIGHRES_IMU refused', 'disarm refused',
                                  'disarm request timed out')):
                self.get_logger().warning(result)
        events = getattr(self.conn, 'events', None)
        if events:
            for e in events[:]:
                self.get_logger().warning(f'MAVLink {e}')
            del events[:]

    def _publish_diagnostics(self) -> None:
        """1 Hz: the link monitor (latency, degraded and why), our own setpoint stream (rate
        and largest gap of the last second; WARN when a gap nears COM_OF_LOSS_T) and the
        counters."""
        now = self._now()
        with self._lock:
            core = self.core
            mon = core.link_monitor
            lat, rtt, degraded, reason = mon.latency_s, mon.rtt_s, mon.degraded, mon.reason
            counters = dict(core.counters)
            counters.update({f'timesync_{k}': v for k, v in mon.counters.items()})
            counters.update({f'timesync_rejected_{k}': v for k, v in mon.rejected.items()})
            mode, last = core.mode, core.last_result
            rate, gap, gap_warn = core.stream_diagnostics(now)
            max_gap_total = core.setpoint_stats.max_gap_total_s
            hover, hover_src = core.thrust.hover_thrust_norm, core.hover_source
            measured = core.hover.estimate
            problem = core.px4_config_problem() or core.ardupilot_config_problem()
            params = dict(core.autopilot_params)
            imu_msg = core.imu_msg
            texts = list(core.statustexts)
            stop = core.pending()['stop']
            link_loss = (core.ardupilot_link_loss() if core.params.autopilot == 'ardupilot'
                         else '')
            link = LinkStatus(
                autopilot=(LinkStatus.AUTOPILOT_PX4 if core.params.autopilot == 'px4'
                           else LinkStatus.AUTOPILOT_ARDUPILOT),
                autopilot_mode=mode, offboard=core.in_offboard(), link_up=core.link_up(now),
                armed=bool(core.armed), streaming=core.streaming(now),
                stream_age_s=core.stream_age_s(now), window_s=1.0,
                latency_valid=not math.isnan(lat), degraded=degraded,
                reason=reason if degraded else '', last_result=last,
                setpoints_sent=counters['setpoints_sent'],
                rejected=sum(core.rejected.values()) + sum(mon.rejected.values()))
        # the timer runs at 1 Hz: rate and largest gap are over the last second
        link.setpoint_rate_hz = 0.0 if math.isnan(rate) else rate
        link.largest_gap_s = 1.0 if math.isnan(gap) else gap
        if link.latency_valid:
            link.latency_s, link.rtt_s = lat, rtt
        link.header.stamp = self.get_clock().now().to_msg()
        self.pub_status.publish(link)
        st = DiagnosticStatus(name='mavlink_bridge: link', hardware_id='mavlink')
        if degraded:
            st.level, st.message = DiagnosticStatus.ERROR, reason
        elif math.isnan(lat):
            st.level, st.message = DiagnosticStatus.WARN, 'no TIMESYNC reply yet'
        else:
            st.level, st.message = DiagnosticStatus.OK, f'latency {lat * 1e3:.0f} ms'
        vals = {'latency_ms': f'{lat * 1e3:.1f}', 'rtt_ms': f'{rtt * 1e3:.1f}',
                'degraded': str(degraded), 'mode': mode, 'last_result': last,
                'offboard_refused_because': problem,
                'hover_thrust_norm': f'{hover:.4f}', 'hover_thrust_source': hover_src,
                'hover_thrust_measured': f'{measured:.4f}', 'imu_message': imu_msg,
                'stop_pending': '' if stop is None else str(stop),
                'statustext_last': (f'[{texts[-1][1]}] {texts[-1][2]}' if texts else ''),
                'statustext_recent': ' | '.join(t for _, _, t in texts[-4:])}
        if link_loss:
            vals['ardupilot_link_loss'] = link_loss
        tcp = getattr(self.conn, 'stats', None)
        if tcp is not None:
            vals.update({f'tcp_{k}': str(v) for k, v in tcp.items()})
        vals.update({f'param_{k}': f'{v:g}' for k, v in params.items()})
        vals.update({k: str(v) for k, v in counters.items()})
        st.values = [KeyValue(key=k, value=v) for k, v in vals.items()]
        sp = DiagnosticStatus(name='mavlink_bridge: setpoints', hardware_id='mavlink')
        if gap_warn:
            sp.level, sp.message = DiagnosticStatus.WARN, gap_warn
        else:
            sp.level = DiagnosticStatus.OK
            sp.message = ('not streaming' if math.isnan(rate) or rate == 0.0 else
                          f'{rate:.0f} Hz, largest gap {gap * 1e3:.0f} ms')
        sp.values = [KeyValue(key='rate_hz', value=f'{rate:.1f}'),
                     KeyValue(key='max_gap_ms', value=f'{gap * 1e3:.1f}'),
                     KeyValue(key='max_gap_since_start_ms', value=f'{max_gap_total * 1e3:.1f}'),
                     KeyValue(key='sent', value=str(counters['setpoints_sent']))]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st, sp]
        self.pub_diag.publish(arr)
        if gap_warn:
            self.get_logger().warning(gap_warn, throttle_duration_sec=5.0)

    def destroy_node(self) -> None:
        self._running = False
        if self._reader.is_alive() and self._reader is not threading.current_thread():
            self._reader.join(timeout=1.0)
        with contextlib.suppress(Exception):
            self.conn.close()
        return super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(MavlinkBridgeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
