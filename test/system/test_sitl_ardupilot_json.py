"""deck_simulator.ardupilot_json, deckland's world as ArduPilot's physics (SITL ``--model JSON``).

Without ArduCopter: the servo packets drive the motors through the curve ArduCopter inverts
(its normalised thrust becomes linear in newtons), the PLUSREV motor order gives ArduCopter's
torques the signs of the paper's mixer (1), the answer is the world's state in ArduPilot's
frames and format, and the lockstep answers repeats, resets and silence as SITL expects. With
ArduCopter (``sitl``, skipped when the binary is not found): ArduCopter boots on deckland's
physics, the mavlink_bridge node enters GUIDED_NOGPS, arms, takes off and holds the hover on
SET_ATTITUDE_TARGET, and when the thrust stops it commands LAND: ArduCopter lands and disarms."""

import itertools
import json
import math
import struct
import threading
import time

from deck_simulator.ardupilot_json import (
    PLUSREV_CHANNEL,
    SEA_LEVEL_HOME,
    ArduPilotJson,
    JsonParams,
    ardupilot_params,
)
from deck_simulator.scenario import load_scenario
from deck_simulator.vehicle import unmix
from deck_simulator.world import World
from deckland.sitl.ardupilot import ArduPilotNotFoundError, ArduPilotSitl, find_ardupilot
from mavlink_bridge.conversions import euler_enu_to_quat_ned
import pytest
from test_sitl_ardupilot_bridge import LATENCY_S, STOP_AFTER_S
from test_sitl_px4_bridge import call, fit_accel, wait_for

LINK_TIMEOUT_S = 8.0

try:
    AP_BIN = find_ardupilot()
    NO_AP = ('ArduCopter SITL not found (set DECKLAND_ARDUPILOT_SITL or provide '
             '../shared/ardupilot-sitl)')
except ArduPilotNotFoundError as exc:
    AP_BIN, NO_AP = None, str(exc)


class FakeSitl:
    """ArduCopter's side of the UDP link, in memory: queued servo frames, answers kept."""

    def __init__(self, rate=1200):
        self.rate = rate
        self.count = 0
        self.queue = []
        self.answers = []
        self.pwm = [1000] * 16
        self.auto = True                  # a new frame for every receive()

    def frame(self, count=None, pwm=None):
        if count is None:
            self.count += 1
            count = self.count
        return struct.pack('<HHI16H', 18458, self.rate, count, *(pwm or self.pwm))

    def receive(self, timeout_s):
        if self.queue:
            return self.queue.pop(0)
        if self.auto:
            return self.frame()
        time.sleep(timeout_s)
        return None

    def send(self, data):
        self.answers.append(data)

    def close(self):
        pass


def backend(**kw):
    sc = load_scenario('paper')
    world = World(sc, 1)
    fake = FakeSitl()
    return world, ArduPilotJson(world, JsonParams(lockstep_timeout_s=0.05, **kw), link=fake), \
        fake


def wait_sim(world, cond, sim_s, wall_s=120.0):
    """``cond()`` within ``sim_s`` of the world's (ArduCopter's) clock: the lockstep runs
    slower than the wall clock on a loaded machine (0.3x seen), and ArduCopter's own delays
    (MOT_SAFE_TIME 1 s, spool-up 0.5 s, its land detector) are in its simulated time."""
    t0, w0 = world.t_s, time.monotonic()
    while world.t_s - t0 < sim_s and time.monotonic() - w0 < wall_s:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def arducopter_pwm(thrust_norm, p=None):
    """ArduCopter's output for a normalised thrust (AP_MotorsMulticopter thrust_to_actuator,
    battery and air-density compensation 1): the inverse of its thrust curve, then spin
    range and PWM range."""
    p = p or JsonParams()
    e = p.thrust_expo
    t = ((e - 1.0) + math.sqrt((1.0 - e) ** 2 + 4.0 * e * thrust_norm)) / (2.0 * e)
    a = p.spin_min + (p.spin_max - p.spin_min) * t
    return round(p.pwm_min_us + (p.pwm_max_us - p.pwm_min_us) * a)


def test_servo_packets_drive_the_motors_linearly_in_arducopters_thrust():
    world, ap, fake = backend()
    fmax = world.params.motor_max_n
    for u in (0.2, 0.5, 0.9):
        fake.pwm = [arducopter_pwm(u)] * 4 + [0] * 12
        ap.step(0.1)
        # ArduCopter's normalised thrust is newtons / F_max: hover at 1 / (T/W) = 0.5
        assert world.vehicle.motor_cmd == pytest.approx((u * fmax,) * 4, rel=2e-3)
        assert ap.armed
    fake.pwm = [1100] * 4 + [0] * 12                 # MOT_SPIN_ARM 0.1: armed, idling
    ap.step(0.01)
    assert ap.armed and world.vehicle.motor_cmd == (0.0, 0.0, 0.0, 0.0)
    fake.pwm = [1000] * 16                           # disarmed: MOT_PWM_MIN
    ap.step(0.01)
    assert not ap.armed
    p = ardupilot_params(world.params, 0.05, 40.0)
    assert p['MOT_THST_HOVER'] == pytest.approx(1.0 / world.params.thrust_to_weight)
    assert (p['FRAME_CLASS'], p['FRAME_TYPE'], p['MOT_BAT_VOLT_MAX']) == (1, 6, 0.0)
    assert (p['RNGFND1_MIN_CM'], p['RNGFND1_MAX_CM']) == (5, 4000)


def torques_frd(channel_thrust, vp):
    """Torques (roll, pitch, yaw; FRD) of ArduCopter channel thrusts through
    PLUSREV_CHANNEL on deckland's mixer (1)."""
    f = [channel_thrust[ch] for ch in PLUSREV_CHANNEL]
    _, u_phi, u_theta, u_psi = unmix(*f, vp.arm_length_m, vp.yaw_moment_coeff_m)
    return u_phi, -u_theta, -u_psi                   # FLU → FRD: pitch and yaw negated


@pytest.mark.parametrize('frame_type, yaw_ok', [(6, True), (0, False)])
def test_plusrev_motor_order_gives_arducopters_torques_on_the_papers_mixer(frame_type, yaw_ok):
    """ArduCopter's matrix (AP_MotorsMatrix): motor i adds cos(angle + 90°) per unit roll,
    cos(angle) per unit pitch and its yaw factor (CW −1, CCW +1) per unit yaw (FRD demands).
    PLUS (0): 1 right CCW, 2 left CCW, 3 front CW, 4 back CW; PLUSREV (6): the same motors with
    the spin directions reversed — deckland's."""
    vp = load_scenario('paper').vehicle
    spins = {0: (1, 1, -1, -1), 6: (-1, -1, 1, 1)}[frame_type]
    angles = (90.0, -90.0, 0.0, 180.0)
    for axis in range(3):
        inc = [(math.cos(math.radians(a + 90.0)), math.cos(math.radians(a)), s)[axis]
               for a, s in zip(angles, spins, strict=True)]
        tq = torques_frd(inc, vp)
        others = [tq[k] for k in range(3) if k != axis]
        assert others == pytest.approx([0.0, 0.0], abs=1e-12)
        if axis < 2 or yaw_ok:
            assert tq[axis] > 0.0                    # the demanded axis, the demanded sign
        else:
            assert tq[axis] < 0.0                    # PLUS on this vehicle: yaw diverges


def test_the_answer_is_the_world_in_arducopters_frames_and_format():
    world, ap, fake = backend()
    assert ap.accept(1.0) and ap.frame_rate_hz == 1200.0
    ap.step(0.5)
    raw = fake.answers[-1]
    assert raw.startswith(b'\n') and raw.endswith(b'\n') and b': ' not in raw and b' ' not in raw
    msgs = [json.loads(a) for a in fake.answers]
    stamps = [m['timestamp'] for m in msgs]
    assert stamps[0] == pytest.approx(1.0 / 1200.0)
    assert all(b - a == pytest.approx(1.0 / 1200.0) for a, b in itertools.pairwise(stamps))
    v = world.vehicle
    m = msgs[-1]
    assert m['position'] == pytest.approx([v.y, v.x, -v.z], abs=1e-4)        # NED from home
    assert m['velocity'] == pytest.approx([0.0, 0.0, 0.0], abs=1e-4)
    q = euler_enu_to_quat_ned(v.roll, v.pitch, v.yaw)
    assert m['quaternion'] == pytest.approx(list(q), abs=1e-6)
    # at rest: FRD specific force −g on z (the IMU model's noise and vibration average out)
    n = len(msgs)
    acc = [sum(x['imu']['accel_body'][i] for x in msgs) / n for i in range(3)]
    gyro = [sum(x['imu']['gyro'][i] for x in msgs) / n for i in range(3)]
    assert acc == pytest.approx([0.0, 0.0, -world.params.gravity_mps2], abs=0.1)
    assert gyro == pytest.approx([0.0, 0.0, 0.0], abs=0.01)
    assert m['rng_1'] == pytest.approx(world.params.gear_height_m, abs=0.08)  # lidar at rest


def test_lockstep_repeats_resets_and_silence():
    world, ap, fake = backend()
    fake.auto = False
    fake.queue = [fake.frame(1), fake.frame(2)]
    assert ap.step(2.0 / 1200.0) == 2
    t = world.t_s
    fake.queue = [fake.frame(2), fake.frame(3)]
    assert ap.step(1.0 / 1200.0) == 1        # the same frame again: the same answer, then 3
    assert world.t_s == pytest.approx(t + 1.0 / 1200.0) and ap.counters['repeats'] == 1
    assert fake.answers[-2] == fake.answers[-3] != fake.answers[-1]
    fake.queue = [fake.frame(1)]             # ArduCopter restarted
    ap.step(1.0 / 1200.0)
    assert ap.counters['resets'] == 1
    t0 = time.monotonic()
    assert ap.step(0.01) == 0                # silence: waited lockstep_timeout_s, counted
    assert time.monotonic() - t0 >= 0.05 and ap.counters['lockstep_timeouts'] == 1
    fake.queue = [b'garbage']
    ap.step(1.0 / 1200.0)
    assert ap.rejected['bad_data'] == 1


def test_tick_mode_answers_each_frame_with_the_state_the_world_reached():
    """As the simulator loop drives it (the world steps, the backend ticks every sub-step):
    one frame per period, the answer to frame n carries the world's time after the sub-step
    frame n's PWM flew, PWM drives the motors; silence ends in ConnectionError."""
    sc = load_scenario('paper')
    world = World(sc, 1, physics_dt_s=1.0 / 400.0)
    fake = FakeSitl(rate=400)
    ap = ArduPilotJson(world, JsonParams(lockstep_timeout_s=0.02, max_silent_frames=3),
                       link=fake)
    world.attach_autopilot(ap)
    hover = arducopter_pwm(1.0 / sc.vehicle.thrust_to_weight)
    fake.pwm = [hover] * 4 + [1000] * 12
    assert ap.accept(1.0) and fake.answers == []
    for _ in range(400):                     # 1 s: the motors' lag settles
        world.step(1.0 / 400.0)
    stamps = [json.loads(a)['timestamp'] for a in fake.answers]
    assert len(stamps) == 400 and ap.counters['frames'] == 400
    assert stamps == pytest.approx([k / 400.0 for k in range(400)], abs=1e-9)
    v = world.vehicle
    assert v.f1 + v.f2 + v.f3 + v.f4 == pytest.approx(
        sc.vehicle.mass_kg * sc.vehicle.gravity_mps2, rel=0.02)
    fake.auto = False
    with pytest.raises(ConnectionError):
        for _ in range(3):
            world.step(1.0 / 400.0)
    assert ap.counters['lockstep_timeouts'] == 3


class Lockstep:
    """The world thread: answers ArduCopter's frames as they come (ArduCopter paces them to
    the wall clock at --speedup 1)."""

    def __init__(self, ap: ArduPilotJson):
        self.ap = ap
        self.stop = threading.Event()
        self.error = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            while not self.stop.is_set():
                self.ap.step(0.01)
        except BaseException as exc:        # reported by the test
            self.error = exc

    def close(self):
        self.stop.set()
        self.thread.join(timeout=3.0)


@pytest.mark.sitl
@pytest.mark.sitl_mission
@pytest.mark.ros
@pytest.mark.skipif(AP_BIN is None, reason=NO_AP)
def test_arducopter_flies_deckland_physics_and_the_bridge_holds_the_hover(ros_context):
    from deckland_common.frames import euler_to_quaternion
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    from mavlink_bridge.node import MavlinkBridgeNode
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from std_srvs.srv import SetBool, Trigger

    sc = load_scenario('paper')
    world = World(sc, 1)
    v, vp, lp = world.vehicle, sc.vehicle, sc.sensors.lidar
    context, executor = ros_context
    params = ardupilot_params(vp, lp.min_range_m, lp.max_range_m)
    with ArduPilotSitl('JSON', params, home=SEA_LEVEL_HOME, nice=10) as sitl:
        phys = ArduPilotJson(world, JsonParams(port=sitl.ports['physics_udp']))
        lock = None
        try:
            sitl.wait_listening()
            bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
                Parameter('connection', value=sitl.connection),
                Parameter('autopilot', value='ardupilot'),
                Parameter('mass_kg', value=vp.mass_kg),
                Parameter('max_link_latency_s', value=LATENCY_S),
                Parameter('stop_after_s', value=STOP_AFTER_S),
                # ArduCopter's 1 Hz heartbeat is in its (the world's) time: a lockstep slowed
                # to 0.3x real time by the machine's load stretches it past 3 s of wall time
                Parameter('link_timeout_s', value=LINK_TIMEOUT_S)])
            t_conn = time.monotonic()
            assert phys.accept(20.0), 'ArduCopter sent no servo frame'
            lock = Lockstep(phys)
            helper = Node('json_helper', context=context)
            executor.add_node(bridge)
            executor.add_node(helper)
            core = bridge.core
            assert wait_for(lambda: core.link_up(time.monotonic()), 40.0)   # (boot under load)
            # ready: its parameters read, its EKF3 aligned on deckland's IMU (tilt + yaw)
            assert wait_for(lambda: not core.ardupilot_config_problem(), 15.0), \
                core.ardupilot_config_problem()
            assert core.autopilot_params['MOT_THST_HOVER'] == pytest.approx(0.5)
            assert wait_for(lambda: any('yaw alignment complete' in t for _, _, t in
                                        core.statustexts), 20.0)
            t_ready = time.monotonic() - t_conn
            assert core.imu_msg == 'SCALED_IMU'
            # resting on the gear's contact spring: its height less the static sag m g / k
            wp = world.params
            sag = wp.mass_kg * wp.gravity_mps2 / wp.contact.stiffness_n_per_m
            assert world.resting_on == 'ground'
            assert v.z == pytest.approx(wp.gear.height_m - sag, abs=2e-4)
            stream = {'go': True, 'thrust': 0.0, 'on': True, 'pd': False}
            pub_att = helper.create_publisher(QuaternionStamped, 'control/attitude', 10)
            pub_thr = helper.create_publisher(WrenchStamped, 'control/thrust', 10)
            yaw0 = v.yaw
            weight = vp.mass_kg * vp.gravity_mps2

            def publish():
                w, x, y, z = euler_to_quaternion(0.0, 0.0, yaw0)
                while stream['go']:
                    now = helper.get_clock().now().to_msg()
                    a = QuaternionStamped()
                    a.header.stamp = now
                    a.quaternion.w, a.quaternion.x, a.quaternion.y, a.quaternion.z = w, x, y, z
                    pub_att.publish(a)
                    if stream['on']:
                        f = WrenchStamped()
                        f.header.stamp = now
                        f.wrench.force.z = (weight * (1.0 + 0.3 * (1.5 - v.z) - 0.5 * v.vz)
                                            if stream['pd'] else stream['thrust'])
                        pub_thr.publish(f)
                    time.sleep(0.01)

            th = threading.Thread(target=publish, daemon=True)
            th.start()
            try:
                res = call(helper, Trigger, 'bridge/offboard', Trigger.Request())
                assert res.success and 'MOT_THST_HOVER' in res.message, res.message
                assert wait_for(lambda: core.mode == 'GUIDED_NOGPS', 5.0), core.last_result
                assert call(helper, SetBool, 'bridge/arm', SetBool.Request(data=True)).success
                assert wait_for(core.in_offboard, 5.0), core.last_result
                assert wait_sim(world, lambda: phys.armed, 3.0), (phys.pwm[:4], world.t_s)
                # take off to 1.5 m (a PD loop on the truth), then the hover on open-loop m g
                stream['pd'] = True
                assert wait_sim(world, lambda: v.z > 1.3 and abs(v.vz) < 0.1, 15.0), (v.z, v.vz)
                time.sleep(1.0)
                stream['pd'] = False
                stream['thrust'] = weight
                time.sleep(0.3)
                t_off = time.monotonic()
                samples, tilts = [], []
                while time.monotonic() - t_off < 5.0:
                    samples.append((world.t_s, v.z))
                    tilts.append(max(abs(v.roll), abs(v.pitch)))
                    time.sleep(0.05)
                accel = fit_accel(samples)
                assert abs(accel) < 0.1, (accel, samples[::10])
                assert max(tilts) < 0.1 and world.contact is None and core.in_offboard()
                rate = phys.counters['frames'] / max(world.t_s, 1e-9)
                # the thrust stops: the bridge commands LAND after stop_after_s, ArduCopter
                # lands on deckland's ground and disarms by itself
                stream['on'] = False
                assert wait_sim(world, lambda: core.mode == 'LAND', 3.0), core.last_result
                assert wait_sim(world, lambda: not phys.armed and not core.armed, 20.0)
                assert world.contact is not None and world.contact.kind == 'ground'
                assert world.contact.touchdown_speed_mps < 0.8
            finally:
                stream['go'] = False
                th.join(timeout=1.0)
            assert lock.error is None, lock.error
            assert phys.counters['lockstep_timeouts'] == 0
            print(f'JSON: ready {t_ready:.1f} s after connecting; open-loop vertical '
                  f'acceleration {accel:+.3f} m/s^2, max tilt {max(tilts):.3f} rad; '
                  f'{rate:.0f} frames per simulated second; touchdown '
                  f'{world.contact.touchdown_speed_mps:.2f} m/s; ArduCopter CPU '
                  f'{sitl.cpu_s():.1f} s; counters {phys.counters}')
        finally:
            if lock is not None:
                lock.close()
            phys.close()
