"""PX4 v1.16 SITL flying deckland's physics (deck_simulator.px4_hil, the Simulator MAVLink API):
PX4 (airframe 10016 none_iris, parameters from px4_params) boots on the world's clock, arms,
takes off with its own take-off, and the mavlink_bridge node hands over to OFFBOARD and holds
the hover on SET_ATTITUDE_TARGET. Marked ``sitl``; skipped when PX4 is not found."""

import math
import threading
import time

from deck_simulator.px4_hil import HilParams, Px4Hil, px4_params
from deck_simulator.scenario import load_scenario
from deck_simulator.world import World
from deckland.sitl.px4 import NONE_IRIS, Px4NotFoundError, Px4Sitl, find_px4
import pytest
from test_sitl_px4_bridge import Operator, call, fit_accel, wait_for

try:
    PX4_ROOT = find_px4()
    NO_PX4 = 'PX4 SITL not found (set DECKLAND_PX4_SITL or provide ../shared/px4-sitl)'
except Px4NotFoundError as exc:
    PX4_ROOT, NO_PX4 = None, str(exc)

pytestmark = [pytest.mark.sitl, pytest.mark.skipif(PX4_ROOT is None, reason=NO_PX4)]


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
                self.hil.step(self.hil.period_s)
                ahead = (w.t_s - t0) - (time.monotonic() - start)
                if ahead > 0.0:
                    time.sleep(ahead)
        except BaseException as exc:      # reported by the test
            self.error = exc

    def close(self):
        self.stop.set()
        self.thread.join(timeout=3.0)


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
        assert v.z == pytest.approx(vp.gear_height_m) and world.resting_on == 'ground'
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
            assert wait_for(lambda: 'COM_OBL_RC_ACT' in core.autopilot_params, 10.0)
            assert core.autopilot_params['COM_OBL_RC_ACT'] == 4.0      # set by px4_params
            assert core.autopilot_params['MPC_THR_HOVER'] == pytest.approx(0.5)
            # the operator arms and takes off with PX4's own take-off to MIS_TAKEOFF_ALT
            assert wait_for(lambda: (op.command(400, 1) or True) and core.armed, 30.0, 0.5)
            op.command(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
            assert wait_for(lambda: core.mode == 'AUTO.TAKEOFF', 5.0)
            assert wait_for(lambda: core.mode == 'AUTO.LOITER', 30.0)
            assert world.resting_on is None and 1.5 < v.z < 2.6, v.z
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
