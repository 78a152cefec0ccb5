"""deck_simulator.px4_hil, deckland's world as PX4's simulator (the Simulator MAVLink API).

Without PX4: the sensors it sends are the world's physics in PX4's frames and units, the motor
outputs drive the motors through the thrust curve, the lockstep waits for PX4's answer, and
px4_params' geometry gives PX4 the torques of the paper's mixer (1). With PX4 (``sitl``,
skipped when PX4 is not found): PX4 (airframe 10016 none_iris) boots on the world's clock,
arms, takes off with its own take-off, and the mavlink_bridge node hands over to OFFBOARD and
holds the hover on SET_ATTITUDE_TARGET."""

import itertools
import math
import threading
import time

from deck_simulator.px4_hil import HilParams, Px4Hil, px4_params
from deck_simulator.scenario import load_scenario
from deck_simulator.vehicle import unmix
from deck_simulator.world import World
from deckland.sitl.px4 import NONE_IRIS, Px4NotFoundError, Px4Sitl, find_px4
from mavlink_bridge.conversions import distance_sensor_to_rep117
from pymavlink.dialects.v20 import common as mavlink
import pytest
from test_sitl_px4_bridge import Operator, call, fit_accel, wait_for

try:
    PX4_ROOT = find_px4()
    NO_PX4 = 'PX4 SITL not found (set DECKLAND_PX4_SITL or provide ../shared/px4-sitl)'
except Px4NotFoundError as exc:
    PX4_ROOT, NO_PX4 = None, str(exc)

SITL = [pytest.mark.sitl, pytest.mark.skipif(PX4_ROOT is None, reason=NO_PX4)]


class FakePx4:
    """The autopilot side of the TCP link, in memory: what the simulator sends is parsed; the
    test queues HIL_ACTUATOR_CONTROLS (answered to the latest HIL_SENSOR when ``auto``)."""

    def __init__(self, auto_controls=None):
        self.rx = mavlink.MAVLink(None)
        self.enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.sent = []
        self.inbox = b''
        self.auto = auto_controls          # (u0..u3, armed) answered to each HIL_SENSOR

    def accept(self, timeout_s):
        return True

    def write(self, data):
        for m in self.rx.parse_buffer(data) or []:
            self.sent.append(m)
            if m.get_type() == 'HIL_SENSOR' and self.auto is not None:
                self.controls(m.time_usec, *self.auto)

    def controls(self, t_us, u, armed=True):
        c = list(u) + [0.0] * (16 - len(u))
        self.inbox += self.enc.hil_actuator_controls_encode(
            t_us, c, 1 | (128 if armed else 0), 1).pack(self.enc)

    def receive(self, timeout_s):
        data, self.inbox = self.inbox, b''
        return data

    def close(self):
        pass

    def last(self, kind):
        return [m for m in self.sent if m.get_type() == kind]


def hil_world(**kw):
    sc = load_scenario('paper')
    world = World(sc, 1, physics_dt_s=1.0 / 500.0)
    fake = FakePx4(**kw)
    return world, Px4Hil(world, HilParams(lockstep_timeout_s=0.05), link=fake), fake


def test_sensors_at_rest_are_gravity_earth_field_and_isa_pressure():
    world, hil, fake = hil_world()
    world.step(2.0)                                 # 500 periods on the ground, no PX4 yet
    assert world.resting_on == 'ground' and world.contact is None
    imu = fake.last('HIL_SENSOR')
    assert len(imu) == 500 and imu[0].time_usec == 1_000_000
    assert {b.time_usec - a.time_usec for a, b in itertools.pairwise(imu)} == {4000}
    # the IMU model's noise and vibration (~0.55 m/s², 0.024 rad/s per sample) average out:
    # FRD specific force at rest is −g on z, the rates are zero (bias ≤ 0.03 m/s², 0.002 rad/s)
    acc = [(m.xacc, m.yacc, m.zacc) for m in imu]
    mean = [sum(a[i] for a in acc) / len(acc) for i in range(3)]
    g = world.params.gravity_mps2
    assert mean == pytest.approx([0.0, 0.0, -g], abs=0.1)
    gyro = [sum(getattr(m, k) for m in imu) / len(imu) for k in ('xgyro', 'ygyro', 'zgyro')]
    assert gyro == pytest.approx([0.0, 0.0, 0.0], abs=0.01)
    # the Earth field in the body: level, so its vertical part is F sin(I) down
    m = [x for x in imu if x.fields_updated & 0x1C0][-1]
    p = hil.params
    f, inc = p.mag_strength_gauss, math.radians(p.mag_inclination_deg)
    assert m.zmag == pytest.approx(f * math.sin(inc), abs=0.01)
    assert math.hypot(m.xmag, m.ymag) == pytest.approx(f * math.cos(inc), abs=0.01)
    # heading: the horizontal field points to magnetic north (heading = the declination), so
    # seen from the nose (FRD, clockwise) it lies at declination − heading
    yaw_ned = math.pi / 2 - world.vehicle.yaw
    field_dir = math.atan2(m.ymag, m.xmag)
    assert math.remainder(field_dir - (math.radians(p.mag_declination_deg) - yaw_ned),
                          2 * math.pi) == pytest.approx(0.0, abs=0.05)
    b = [x for x in imu if x.fields_updated & 0x1A00][-1]
    h = p.home_alt_m + world.vehicle.z
    assert b.abs_pressure == pytest.approx(1013.25 * (1 - 2.25577e-5 * h) ** 5.25588, abs=0.05)
    assert b.pressure_alt == pytest.approx(h, abs=1e-3)
    gps = fake.last('HIL_GPS')[-1]
    assert gps.fix_type == 3 and abs(gps.lat - round(p.home_lat_deg * 1e7)) < 600   # < 7 m
    ds = fake.last('DISTANCE_SENSOR')[-1]
    assert ds.orientation == 25
    r = distance_sensor_to_rep117(ds.current_distance, ds.min_distance, ds.max_distance)
    assert r == pytest.approx(world.params.gear_height_m, abs=0.08)   # lidar at the gear
    assert fake.last('HIL_STATE_QUATERNION')


def test_motor_outputs_drive_the_motors_through_the_thrust_curve():
    world, hil, fake = hil_world(auto_controls=([0.647, 0.647, 0.647, 0.647], True))
    vp = world.params
    world.step(0.004)                  # first period: PX4's answer arrives during the read
    world.step(1.0)
    e = hil.params.thrust_expo
    f = vp.motor_max_n * (e * 0.647 ** 2 + (1 - e) * 0.647)
    assert world.vehicle.motor_cmd == pytest.approx((f,) * 4)
    assert world.vehicle.thrust_n == pytest.approx(4 * f, rel=1e-3)      # after the lag
    # u = 0.647 with THR_MDL_FAC = e: 0.4986 of the maximum, i.e. hover at T/W = 2
    assert 4 * f / (vp.mass_kg * vp.gravity_mps2) == pytest.approx(0.4986 * 2, abs=1e-3)
    assert hil.counters['lockstep_timeouts'] == 0 and hil.counters['controls_rx'] >= 250
    fake.auto = ([0.9, 0.9, 0.9, 0.9], False)                  # disarmed: motors off
    world.step(0.1)
    assert world.vehicle.motor_cmd == (0.0, 0.0, 0.0, 0.0) and not hil.armed


def test_lockstep_waits_for_px4_and_counts_a_silent_period():
    world, hil, fake = hil_world(auto_controls=([0.0] * 4, True))
    world.step(0.008)
    assert hil.got_first_controls
    fake.auto = None                                           # PX4 stops answering
    t0 = time.monotonic()
    world.step(0.004)
    assert time.monotonic() - t0 >= 0.05                       # waited lockstep_timeout_s
    assert hil.counters['lockstep_timeouts'] == 1


def test_px4_geometry_gives_the_torques_of_the_papers_mixer():
    """PX4's allocation sees rotor i at (PX, PY) with moment KM: roll −PY F, pitch PX F, yaw
    KM F (FRD). With px4_params these equal (1) — u_φ = L(F2−F4), u_θ = L(F3−F1),
    u_ψ = c_d(−F1+F2−F3+F4) in FLU — for any motor forces."""
    vp = load_scenario('paper').vehicle
    p = px4_params(vp)
    for forces in ((1.0, 2.0, 3.0, 4.0), (5.0, 0.5, 2.0, 7.0)):
        roll = sum(-p[f'CA_ROTOR{i}_PY'] * f for i, f in enumerate(forces))
        pitch = sum(p[f'CA_ROTOR{i}_PX'] * f for i, f in enumerate(forces))
        yaw = sum(p[f'CA_ROTOR{i}_KM'] * f for i, f in enumerate(forces))
        _, u_phi, u_theta, u_psi = unmix(*forces, vp.arm_length_m, vp.yaw_moment_coeff_m)
        # FRD ↔ FLU: roll the same, pitch and yaw negated
        assert (roll, pitch, yaw) == pytest.approx((u_phi, -u_theta, -u_psi))
    assert p['MPC_THR_HOVER'] == pytest.approx(1.0 / vp.thrust_to_weight)
    assert p['COM_OBL_RC_ACT'] == 4 and p['COM_RC_IN_MODE'] == 4


class Lockstep:
    """The world thread of this test: lockstep periods paced to the wall clock (x1)."""

    def __init__(self, hil: Px4Hil):
        self.hil = hil
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        w = self.hil.world
        start, t0 = time.monotonic(), w.t_s
        try:
            while not self.stop.is_set():
                w.step(self.hil.period_s)
                ahead = (w.t_s - t0) - (time.monotonic() - start)
                if ahead > 0.0:
                    time.sleep(ahead)
        except BaseException as exc:      # reported by the test
            self.error = exc

    def close(self):
        self.stop.set()
        self.thread.join(timeout=3.0)


@SITL[0]
@SITL[1]
@pytest.mark.ros
def test_px4_flies_deckland_physics_and_the_bridge_holds_the_hover(ros_context):
    from deckland_common.frames import euler_to_quaternion
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger

    sc = load_scenario('paper')
    world = World(sc, 1, physics_dt_s=1.0 / 500.0)
    v = world.vehicle
    vp = sc.vehicle
    context, executor = ros_context
    with Px4Sitl(NONE_IRIS, px4_params(vp, takeoff_alt_m=2.0), nice=10) as px4:
        hil = Px4Hil(world, HilParams(port=px4.ports['simulator_tcp']))
        assert v.z == pytest.approx(vp.gear_height_m, abs=1e-3) and world.resting_on == 'ground'
        lock = None
        op = None
        try:
            assert hil.accept(30.0), 'PX4 did not connect to the simulator port'
            lock = Lockstep(hil)
            t_ready = px4.wait_for_log('Ready for takeoff', 60.0)
            assert hil.got_first_controls and hil.counters['lockstep_timeouts'] == 0
            bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
                Parameter('connection',
                          value=f"udpin:127.0.0.1:{px4.ports['onboard_remote']}"),
                Parameter('system_id', value=px4.system_id),
                Parameter('mass_kg', value=vp.mass_kg)])
            helper = Node('hil_helper', context=context)
            executor.add_node(bridge)
            executor.add_node(helper)
            core = bridge.core
            op = Operator(px4)
            assert wait_for(lambda: core.link_up(time.monotonic()), 10.0)
            # the bridge reads PX4's parameters one by one: wait for the ones checked here
            assert wait_for(lambda: {'COM_OBL_RC_ACT', 'MPC_THR_HOVER'} <= set(
                core.autopilot_params), 10.0)
            assert core.autopilot_params['COM_OBL_RC_ACT'] == 4.0      # set by px4_params
            assert core.autopilot_params['MPC_THR_HOVER'] == pytest.approx(0.5)
            # the operator arms and takes off with PX4's own take-off to MIS_TAKEOFF_ALT
            assert wait_for(lambda: (op.command(400, 1) or True) and core.armed, 30.0, 0.5)
            op.command(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
            assert wait_for(lambda: core.mode == 'AUTO.TAKEOFF', 5.0)
            assert wait_for(lambda: core.mode == 'AUTO.LOITER', 30.0)
            # PX4 ends the take-off within its altitude acceptance radius (NAV_MC_ALT_RAD)
            # of MIS_TAKEOFF_ALT and climbs the rest in LOITER (seen: 1.34 m at the switch)
            assert wait_for(lambda: 1.5 < v.z < 2.6, 15.0), v.z
            assert world.resting_on is None
            # PX4 hovers the simulated vehicle at its linearised hover thrust 1 / (T/W):
            # THR_MDL_FAC inverts the simulated thrust curve (u_z = m g / γ, γ ≈ 1 at 2 m)
            assert wait_for(lambda: core.hover.valid, 25.0)
            hover = core.hover.estimate
            assert hover == pytest.approx(1.0 / vp.thrust_to_weight, abs=0.02), hover
            # the stack's stream: level, the current heading, u_z = m g
            stream = {'go': True}
            pub_att = helper.create_publisher(QuaternionStamped, 'control/attitude', 10)
            pub_thr = helper.create_publisher(WrenchStamped, 'control/thrust', 10)
            yaw0 = v.yaw

            def publish():
                w, x, y, z = euler_to_quaternion(0.0, 0.0, yaw0)
                while stream['go']:
                    now = helper.get_clock().now().to_msg()
                    a = QuaternionStamped()
                    a.header.stamp = now
                    a.quaternion.w, a.quaternion.x, a.quaternion.y, a.quaternion.z = w, x, y, z
                    pub_att.publish(a)
                    f = WrenchStamped()
                    f.header.stamp = now
                    f.wrench.force.z = vp.mass_kg * vp.gravity_mps2
                    pub_thr.publish(f)
                    time.sleep(0.01)

            th = threading.Thread(target=publish, daemon=True)
            th.start()
            try:
                res = call(helper, Trigger, 'bridge/offboard', Trigger.Request())
                assert res.success and 'measured' in res.message, res.message
                assert wait_for(core.in_offboard, 5.0), core.last_result
                # the hover on SET_ATTITUDE_TARGET alone (open loop: PX4 flies attitude and
                # the bridge's thrust): level, and no vertical acceleration to speak of
                t_off = time.monotonic()
                samples, tilts = [], []
                while time.monotonic() - t_off < 5.0:
                    samples.append((world.t_s, v.z))
                    tilts.append(max(abs(v.roll), abs(v.pitch)))
                    time.sleep(0.1)
                accel = fit_accel(samples)
                print(f'HIL: ready {t_ready:.1f} s, hover {hover:.4f}, open-loop vertical '
                      f'acceleration {accel:+.3f} m/s^2, max tilt {max(tilts):.3f} rad, '
                      f'lockstep {hil.counters}')
                assert abs(accel) < 0.1, (accel, samples)
                assert max(tilts) < 0.1
                assert core.in_offboard() and world.contact is None
            finally:
                stream['go'] = False
                th.join(timeout=1.0)
            assert lock.error is None, lock.error
        finally:
            if op is not None:
                op.close()
            if lock is not None:
                lock.close()
            hil.close()
