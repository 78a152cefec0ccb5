"""Figures of ArduCopter SITL in the loop: boot-to-ready, lockstep rate, CPU (ArduCopter, bridge).

``python -m deckland.sitl.measure_ardupilot [boot] [bridge_cpu] [json] [--out FILE]
[--seconds S]``: ``boot`` the built-in quad on EKF3 (connect → HEARTBEAT, ready, EKF3 aligned,
first LOCAL_POSITION_NED); ``bridge_cpu`` the ``mavlink_bridge_node`` process and ArduCopter on
the ground, and the link's traffic at the bridge's rates; ``json`` ArduCopter on deckland's
physics paced (x1) and unpaced (x20), on the ground and in a GUIDED_NOGPS hover: simulated
seconds per wall second, servo frames per second, CPU of ArduCopter and of the physics
process. Each ArduCopter runs niced (10) in a fresh directory.
"""

from __future__ import annotations

import math
import os
import pathlib
import random
import subprocess
import sys
import threading
import time

os.environ.setdefault('MAVLINK20', '1')

from deckland.sitl.ardupilot import ArduPilotSitl
from deckland.sitl.process import measure_main, proc_cpu_s


def _connect(sitl: ArduPilotSitl):
    from pymavlink import mavutil
    return mavutil.mavlink_connection(sitl.connection, source_system=1, source_component=191,
                                      dialect='common')


def boot(seconds: float) -> dict:
    """Boot-to-ready of the built-in quad with ArduCopter's own EKF3."""
    out: dict = {}
    with ArduPilotSitl('quad', nice=10) as sitl:
        out['listening_s'] = round(sitl.wait_listening(), 2)
        t0 = time.monotonic()
        conn = _connect(sitl)
        marks = {'heartbeat': None, 'ArduPilot Ready': None, 'tilt alignment complete': None,
                 'initial yaw alignment complete': None, 'origin set': None,
                 'is using GPS': None, 'local_position': None}
        asked = -math.inf
        while time.monotonic() - t0 < 120.0 and marks['local_position'] is None:
            if marks['heartbeat'] is not None and time.monotonic() - asked > 5.0:
                asked = time.monotonic()       # (asked again: the first may precede the boot)
                conn.mav.command_long_send(1, 1, 511, 0, 32, 1e5, 0, 0, 0, 0, 0)
            m = conn.recv_match(blocking=True, timeout=0.2)
            if m is None:
                continue
            now = round(time.monotonic() - t0, 2)
            kind = m.get_type()
            if kind == 'HEARTBEAT' and marks['heartbeat'] is None:
                marks['heartbeat'] = now
            elif kind == 'STATUSTEXT':
                for k in marks:
                    if k in m.text and marks[k] is None:
                        marks[k] = now
            elif kind == 'LOCAL_POSITION_NED':
                marks['local_position'] = now
        conn.close()
        out['after_connect_s'] = marks
    return out


def bridge_cpu(seconds: float) -> dict:
    """CPU of the bridge node process and of ArduCopter, on the ground."""
    from pymavlink import mavutil

    out: dict = {}
    exe = pathlib.Path(sys.executable).with_name('mavlink_bridge_node')
    with ArduPilotSitl('quad', {'AHRS_EKF_TYPE': 10, 'RNGFND1_TYPE': 100,
                                'RNGFND1_ORIENT': 25}, nice=10) as sitl:
        sitl.wait_listening()
        env = dict(os.environ, ROS_DOMAIN_ID=str(random.SystemRandom().randint(150, 230)),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        node = subprocess.Popen([str(exe), '--ros-args', '-p', f'connection:={sitl.connection}',
                                 '-p', 'autopilot:=ardupilot'], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(8.0)
            c0, t0, a0 = proc_cpu_s(node.pid), time.monotonic(), sitl.cpu_s()
            time.sleep(seconds)
            c1, t1, a1 = proc_cpu_s(node.pid), time.monotonic(), sitl.cpu_s()
        finally:
            node.terminate()
            node.wait(timeout=10)
        out['bridge_cpu_pct'] = round(100.0 * (c1 - c0) / (t1 - t0), 1)
        out['arducopter_cpu_pct'] = round(100.0 * (a1 - a0) / (t1 - t0), 1)
    # the link's traffic at the bridge's rates (a plain client asking for the same streams:
    # ATTITUDE, SCALED_IMU 100 Hz, LOCAL_POSITION_NED, DISTANCE_SENSOR 50 Hz,
    # EXTENDED_SYS_STATE 5 Hz, ATTITUDE_TARGET 10 Hz)
    with ArduPilotSitl('quad', {'AHRS_EKF_TYPE': 10, 'RNGFND1_TYPE': 100,
                                'RNGFND1_ORIENT': 25}, nice=10) as sitl:
        sitl.wait_listening()
        conn = mavutil.mavlink_connection(sitl.connection, source_system=1,
                                          source_component=191, dialect='common')
        conn.wait_heartbeat(timeout=20)
        for mid, us in ((30, 1e4), (32, 2e4), (132, 2e4), (26, 1e4), (245, 2e5), (83, 1e5)):
            conn.mav.command_long_send(1, 1, 511, 0, mid, us, 0, 0, 0, 0, 0)
        time.sleep(2.0)
        counts: dict[str, int] = {}
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            m = conn.recv_match(blocking=True, timeout=0.1)
            if m is not None:
                counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
        dur = time.monotonic() - t0
        conn.close()
        out['link_msgs_per_s'] = round(sum(counts.values()) / dur, 1)
        out['link_rates'] = {k: round(v / dur, 1) for k, v in sorted(counts.items())}
    return out


def _json_run(speedup: float, seconds: float, sim_rate_hz: int | None = None) -> dict:
    from deck_simulator.ardupilot_json import (
        SEA_LEVEL_HOME,
        ArduPilotJson,
        JsonParams,
        ardupilot_params,
    )
    from deck_simulator.scenario import load_scenario
    from deck_simulator.world import World
    from mavlink_bridge.conversions import euler_enu_to_quat_ned

    sc = load_scenario('paper')
    world = World(sc, 1)
    lp = sc.sensors.lidar
    out: dict = {'speedup': speedup, 'sim_rate_hz': sim_rate_hz or 1200}
    params = ardupilot_params(sc.vehicle, lp.min_range_m, lp.max_range_m)
    if sim_rate_hz:
        params['SIM_RATE_HZ'] = sim_rate_hz
    th: threading.Thread | None = None
    with ArduPilotSitl('JSON', params, home=SEA_LEVEL_HOME, speedup=speedup, nice=10) as sitl:
        phys = ArduPilotJson(world, JsonParams(port=sitl.ports['physics_udp']))
        stop = threading.Event()
        try:
            sitl.wait_listening()
            conn = _connect(sitl)
            w0 = time.monotonic()
            if not phys.accept(20.0):
                raise RuntimeError('ArduCopter sent no servo frame')

            def lockstep() -> None:
                while not stop.is_set():
                    phys.step(0.01)

            th = threading.Thread(target=lockstep, daemon=True)
            th.start()
            # (ArduCopter sends STATUSTEXT only on links it has heard from)
            conn.mav.heartbeat_send(18, 8, 0, 0, 4)
            marks: dict = {}
            while time.monotonic() - w0 < 60.0 and 'yaw' not in marks:
                m = conn.recv_match(type=['STATUSTEXT', 'HEARTBEAT'], blocking=True, timeout=0.2)
                now = (round(time.monotonic() - w0, 2), round(world.t_s, 2))
                if m is None:
                    continue
                if m.get_type() == 'HEARTBEAT':
                    marks.setdefault('heartbeat', now)
                elif 'ArduPilot Ready' in m.text:
                    marks.setdefault('ready', now)
                elif 'tilt alignment complete' in m.text:
                    marks.setdefault('tilt', now)
                elif 'initial yaw alignment complete' in m.text:
                    marks['yaw'] = now
            # (wall s, simulated s) after the connection
            out['after_connect_wall_sim_s'] = marks

            def window(label: str, setpoint=None) -> None:
                c0, a0, w_0, s0 = time.process_time(), sitl.cpu_s(), time.monotonic(), world.t_s
                n0 = phys.counters['frames']
                nxt = 0.0
                while time.monotonic() - w_0 < seconds:
                    if setpoint is not None and time.monotonic() >= nxt:
                        nxt = time.monotonic() + 0.01
                        conn.mav.set_attitude_target_send(0, 1, 1, 7, *setpoint())
                    conn.recv_match(blocking=True, timeout=0.005)
                c1, a1, w1, s1 = time.process_time(), sitl.cpu_s(), time.monotonic(), world.t_s
                wall = w1 - w_0
                out[f'{label}_sim_per_wall'] = round((s1 - s0) / wall, 2)
                out[f'{label}_frames_per_wall_s'] = round(
                    (phys.counters['frames'] - n0) / wall, 1)
                out[f'{label}_arducopter_cpu_pct'] = round(100.0 * (a1 - a0) / wall, 1)
                out[f'{label}_physics_process_cpu_pct'] = round(100.0 * (c1 - c0) / wall, 1)
                out[f'{label}_physics_cpu_per_sim_s'] = round((c1 - c0) / max(s1 - s0, 1e-9), 3)

            window('ground')
            v, weight = world.vehicle, sc.vehicle.mass_kg * sc.vehicle.gravity_mps2
            yaw = v.yaw

            def hover():
                # a PD loop on the truth around 1.5 m (thrust normalised at the 0.5 hover)
                thrust = 0.5 * (1.0 + 0.3 * (1.5 - v.z) - 0.4 * v.vz)
                return list(euler_enu_to_quat_ned(0.0, 0.0, yaw)), 0.0, 0.0, 0.0, max(
                    0.0, min(1.0, thrust))

            conn.mav.command_long_send(1, 1, 176, 0, 1, 20, 0, 0, 0, 0, 0)
            time.sleep(0.3)
            for _ in range(20):
                conn.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
                time.sleep(0.3)
                if phys.armed:
                    break
            end = time.monotonic() + 10.0
            while time.monotonic() < end and not (v.z > 1.3 and abs(v.vz) < 0.2):
                conn.mav.set_attitude_target_send(0, 1, 1, 7, *hover())
                conn.recv_match(blocking=True, timeout=0.01)
            out['hover_z_m'] = round(v.z, 2)
            window('hover', hover)
            out['weight_n'] = round(weight, 2)
            out['lockstep_timeouts'] = phys.counters['lockstep_timeouts']
            out['repeats'] = phys.counters['repeats']
            conn.close()
        finally:
            stop.set()
            if th is not None:
                th.join(timeout=3.0)
            phys.close()
    return out


def json_physics(seconds: float) -> dict:
    """ArduCopter on deckland's physics, paced (x1) and unpaced (x20, at SIM_RATE_HZ 1200 and
    400)."""
    return {'paced': _json_run(1.0, seconds), 'unpaced': _json_run(20.0, seconds),
            'unpaced_400hz': _json_run(20.0, seconds, 400)}


def main(argv: list[str] | None = None) -> int:
    runs = {'boot': boot, 'bridge_cpu': bridge_cpu, 'json': json_physics}
    return measure_main('python -m deckland.sitl.measure_ardupilot', __doc__, runs, argv)


if __name__ == '__main__':
    raise SystemExit(main())
