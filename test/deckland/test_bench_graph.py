"""deckland bench: the bridge's time_boot_ms hook over UDP, and a short run of the whole bench."""

import json
import math
import os
import socket
import subprocess
import sys
import threading
import time

from deckland.graph.bench import set_attitude_target_boot_ms, stamp_ms
import pytest
from rostest import isolated_env, wait_for

pytestmark = pytest.mark.ros


def test_bridge_puts_the_thrust_stamp_into_time_boot_ms(ros_context):
    """A fake autopilot (raw UDP + pymavlink encoder) receives SET_ATTITUDE_TARGET whose
    time_boot_ms is the control/thrust header stamp in ms mod 2^32."""
    os.environ['MAVLINK20'] = '1'
    from deckland_common.ros_node import s_to_stamp
    from geometry_msgs.msg import QuaternionStamped, WrenchStamped
    from mavlink_bridge.node import MavlinkBridgeNode
    from pymavlink.dialects.v20 import common as mav
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    context, executor = ros_context
    ap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ap.bind(('127.0.0.1', 0))
    ap.settimeout(0.05)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
    s.close()
    bridge = MavlinkBridgeNode(context=context, parameter_overrides=[
        Parameter('connection', value=f'udpin:127.0.0.1:{port}')])
    helper = Node('bench_hook_helper', context=context)
    executor.add_node(bridge)
    executor.add_node(helper)
    pub_att = helper.create_publisher(QuaternionStamped, 'control/attitude', 10)
    pub_thr = helper.create_publisher(WrenchStamped, 'control/thrust', 10)
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = enc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0,
                                     mav.MAV_STATE_STANDBY).pack(enc)
    got: list[int] = []
    sent: list[float] = []
    stop = threading.Event()

    def autopilot():
        while not stop.is_set():
            ap.sendto(heartbeat, ('127.0.0.1', port))
            try:
                data, _ = ap.recvfrom(65535)
                got.extend(set_attitude_target_boot_ms(data))
            except (TimeoutError, OSError):
                pass

    thread = threading.Thread(target=autopilot, daemon=True)
    thread.start()
    try:
        assert wait_for(lambda: bridge.core.link_up(time.monotonic()), 5.0)
        # stamps 1.5 ms past a ms boundary and 0.4 ms before one (rounding), one every 20 ms
        base = math.floor(helper.get_clock().now().nanoseconds * 1e-9) - 0.5
        for k in range(10):
            t_s = base + 0.02 * k + (0.0015 if k % 2 else 0.0196)
            a, f = QuaternionStamped(), WrenchStamped()
            s_to_stamp(t_s, a.header.stamp)
            s_to_stamp(t_s, f.header.stamp)
            a.quaternion.w = 1.0
            f.wrench.force.z = 20.0
            pub_att.publish(a)
            pub_thr.publish(f)
            sent.append(t_s)
            time.sleep(0.02)
        assert wait_for(lambda: len(got) >= 5, 3.0)
    finally:
        stop.set()
        thread.join(timeout=2.0)
        ap.close()
    expected = {stamp_ms(t) for t in sent}
    assert got and set(got) <= expected, (got, sorted(expected))
    assert got == sorted(got)  # stamps increase; the send time (old field value) is not used


def test_short_bench_run_writes_finite_positive_figures(tmp_path):
    out = tmp_path / 'bench.json'
    proc = subprocess.run(
        [sys.executable, '-m', 'deckland.graph.bench', 'latency', '--duration', '5', '--out',
         str(out), '--log', str(tmp_path / 'graph.log'), '--startup-timeout', '12'],
        capture_output=True, text=True, timeout=40, env=isolated_env())
    assert out.exists(), proc.stdout + proc.stderr
    r = json.loads(out.read_text())
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for key in ('e2e_latency_ms', 'loop_jitter_ms', 'stack_latency_ms'):
        for q in ('p50', 'p99'):
            v = r[key][q]
            # jitter is lateness against the 10 ms schedule: 0.0 is a real (good) figure
            floor_ok = v >= 0.0 if key == 'loop_jitter_ms' else v > 0.0
            assert isinstance(v, float) and math.isfinite(v) and floor_ok, (key, q, v)
        assert r[key]['p99'] >= r[key]['p50']
    # the total contains the camera's own 20 ms exposure-to-delivery latency
    # the Pixy's exposure-to-publish latency the driver is configured with (the scenario's)
    from deck_simulator.scenario import load_scenario
    cam_ms = load_scenario('paper').sensors.true_camera.timing.assumed_latency_s * 1e3
    assert r['e2e_latency_ms']['p50'] > r['camera_latency_ms'] == pytest.approx(cam_ms)
    nodes = {'deck_simulator', 'pixy_driver', 'mavlink_bridge', 'apron_estimator',
             'landing_planner', 'dob_altitude'}
    assert set(r['cpu_percent']) == nodes | {'total_without_sim'}
    for name, v in r['cpu_percent'].items():
        assert math.isfinite(v) and v > 0.0, (name, v)
    total = sum(v for k, v in r['cpu_percent'].items() if k not in ('deck_simulator',
                                                                     'total_without_sim'))
    assert r['cpu_percent']['total_without_sim'] == pytest.approx(total)
    assert 0.0 < r['duration_s'] <= 5.5
    assert r['samples'] > 10 and r['counts']['matched'] > 10
    assert 'total_without_sim' in proc.stdout    # the table was printed
