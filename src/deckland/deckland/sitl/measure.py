"""Figures of PX4 SITL in the loop: boot-to-ready, lockstep rate, CPU of PX4 and of the bridge.

More in the package README, "Module notes" (`deckland.sitl.measure`).
"""

from __future__ import annotations

import math
import os
import pathlib
import random
import socket
import subprocess
import sys
import threading
import time

os.environ.setdefault('MAVLINK20', '1')

from deckland.sitl.process import UdpWriter, measure_main, proc_cpu_s
from deckland.sitl.px4 import NONE_IRIS, SIH_QUADX, Px4Sitl


def link_rates(seconds: float) -> dict:
    """PX4's onboard-link traffic before and after the bridge core's trim requests."""
    from mavlink_bridge.core import MAV_CMD_SET_MESSAGE_INTERVAL, BridgeCore, BridgeParams
    from pymavlink.dialects.v20 import common as mavlink

    out: dict = {}
    with Px4Sitl(SIH_QUADX, {'COM_OBL_RC_ACT': 4}, nice=10) as px4:
        out['sih_ready_s'] = round(px4.wait_for_log('Ready for takeoff', 60.0), 2)
        p = px4.ports
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(('127.0.0.1', p['onboard_remote']))
        sock.settimeout(0.02)
        mav = mavlink.MAVLink(UdpWriter(sock, ('127.0.0.1', p['onboard_local'])),
                              srcSystem=px4.system_id, srcComponent=191)
        rx = mavlink.MAVLink(None)
        core = BridgeCore(BridgeParams(trim_telemetry=False))

        def run(dur: float, trim: bool) -> tuple[float, int]:
            counts: dict[str, int] = {}
            end = time.monotonic() + dur
            while time.monotonic() < end:
                now = time.monotonic()
                for o in core.step(now):
                    if o.kind == 'command' and (trim or o.command != MAV_CMD_SET_MESSAGE_INTERVAL
                                                or o.params[1] >= 0):
                        mav.command_long_send(px4.system_id, 1, o.command, 0, *o.params)
                try:
                    data = sock.recv(65535)
                except TimeoutError:
                    continue
                for m in rx.parse_buffer(data) or []:
                    counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
                    if m.get_type() == 'HEARTBEAT':
                        core.on_heartbeat(now, m.get_srcSystem(), m.get_srcComponent(), m.type,
                                          m.autopilot, m.base_mode, m.custom_mode)
                    if m.get_srcComponent() == 1:
                        core.on_message(m.get_msgId())
            run.last = {k: round(v / dur, 1) for k, v in sorted(counts.items())}
            return sum(counts.values()) / dur, len(counts)

        run(3.0, False)
        rate, types = run(seconds, False)
        out['px4_default_msgs_per_s'], out['px4_default_types'] = round(rate, 1), types
        out['px4_default_rates'] = run.last
        core = BridgeCore(BridgeParams(trim_telemetry=True))
        run(6.0, True)                              # link-up, intervals, three trim rounds
        rate, types = run(seconds, True)
        out['trimmed_msgs_per_s'], out['trimmed_types'] = round(rate, 1), types
        out['trimmed_rates'] = run.last
        sock.close()
    return out


def bridge_cpu(seconds: float) -> dict:
    """CPU of the bridge node process against PX4 SIH on the ground, trim off and on."""
    out: dict = {}
    exe = pathlib.Path(sys.executable).with_name('mavlink_bridge_node')
    for trim in (False, True):
        with Px4Sitl(SIH_QUADX, {'COM_OBL_RC_ACT': 4}, nice=10) as px4:
            px4.wait_for_log('Ready for takeoff', 60.0)
            env = dict(os.environ, ROS_DOMAIN_ID=str(random.SystemRandom().randint(150, 230)),
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
            cmd = [str(exe), '--ros-args', '-p',
                   f"connection:=udpin:127.0.0.1:{px4.ports['onboard_remote']}", '-p',
                   f'system_id:={px4.system_id}', '-p', f'trim_telemetry:={str(trim).lower()}']
            node = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
            try:
                time.sleep(6.0)
                c0, t0, p0 = proc_cpu_s(node.pid), time.monotonic(), px4.cpu_s()
                time.sleep(seconds)
                c1, t1, p1 = proc_cpu_s(node.pid), time.monotonic(), px4.cpu_s()
            finally:
                node.terminate()
                node.wait(timeout=10)
            key = 'trim' if trim else 'no_trim'
            out[f'bridge_cpu_pct_{key}'] = round(100.0 * (c1 - c0) / (t1 - t0), 1)
            out[f'px4_sih_cpu_pct_{key}'] = round(100.0 * (p1 - p0) / (t1 - t0), 1)
    return out


def hil(seconds: float) -> dict:
    """PX4 on deckland's physics, unpaced lockstep: boot, take-off, hover; rates and CPU."""
    from deck_simulator.px4_hil import HilParams, Px4Hil, px4_params
    from deck_simulator.scenario import load_scenario
    from deck_simulator.world import World
    from pymavlink.dialects.v20 import common as mavlink

    sc = load_scenario('paper')
    world = World(sc, 1, physics_dt_s=1.0 / 500.0)
    out: dict = {}
    with Px4Sitl(NONE_IRIS, px4_params(sc.vehicle), nice=10) as px4:
        sim = Px4Hil(world, HilParams(port=px4.ports['simulator_tcp']))
        try:
            if not sim.accept(30.0):
                raise RuntimeError('PX4 did not connect to the simulator port')
            stop = threading.Event()

            def lockstep() -> None:
                while not stop.is_set():
                    world.step(sim.period_s)    # the world ticks PX4 (its autopilot)

            th = threading.Thread(target=lockstep, daemon=True)
            w0, s0 = time.monotonic(), world.t_s
            th.start()
            out['hil_ready_wall_s'] = round(px4.wait_for_log('Ready for takeoff', 120.0), 2)
            out['hil_ready_sim_s'] = round(world.t_s - s0, 2)
            out['ground_sim_per_wall'] = round((world.t_s - s0) / (time.monotonic() - w0), 2)
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(('127.0.0.1', 0))
            mav = mavlink.MAVLink(UdpWriter(sock, ('127.0.0.1', px4.ports['gcs_local'])),
                                  srcSystem=255, srcComponent=190)

            def cmd(c: int, *p: float) -> None:
                q = [float(v) for v in p] + [0.0] * (7 - len(p))
                mav.command_long_send(px4.system_id, 1, c, 0, *q)

            for _ in range(40):
                cmd(400, 1)
                time.sleep(0.3)
                if sim.armed:
                    break
            cmd(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
            t_to = world.t_s
            while world.t_s - t_to < 15.0 and th.is_alive():
                time.sleep(0.05)
            out['hover_z_m'] = round(world.vehicle.z, 2)
            c0, p0, w0, s0 = time.process_time(), px4.cpu_s(), time.monotonic(), world.t_s
            n0 = sim.counters['periods']
            while world.t_s - s0 < seconds and th.is_alive():
                time.sleep(0.05)
            c1, p1, w1, s1 = time.process_time(), px4.cpu_s(), time.monotonic(), world.t_s
            stop.set()
            th.join(timeout=5.0)
            sock.close()
            wall = w1 - w0
            out['hover_sim_per_wall'] = round((s1 - s0) / wall, 2)
            out['hover_lockstep_hz'] = round((sim.counters['periods'] - n0) / wall, 1)
            out['hover_px4_cpu_pct'] = round(100.0 * (p1 - p0) / wall, 1)
            out['hover_sim_process_cpu_pct'] = round(100.0 * (c1 - c0) / wall, 1)
            out['lockstep_timeouts'] = sim.counters['lockstep_timeouts']
            out['px4_cpu_per_sim_s'] = round((p1 - p0) / (s1 - s0), 3)
        finally:
            sim.close()
    return out


def main(argv: list[str] | None = None) -> int:
    runs = {'link': link_rates, 'bridge_cpu': bridge_cpu, 'hil': hil}
    return measure_main('python -m deckland.sitl.measure', __doc__, runs, argv)


if __name__ == '__main__':
    raise SystemExit(main())
