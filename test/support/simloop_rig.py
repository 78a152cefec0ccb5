"""The simulator loop rig: SimulationLoop with the PX4 emulator on a MemoryLink, the test
playing the companion; and a calm scenario builder. Used by the deck_simulator tests."""

import json

from deck_simulator.loop import SimulationLoop
from deck_simulator.px4_emulator import EmulatorParams, Px4Emulator
from deck_simulator.scenario import scenario_from_dict
from deck_simulator.transport import MemoryLink
from deck_simulator.vehicle import VehicleParams
from mavlink_bridge.conversions import set_attitude_target_fields
from pymavlink.dialects.v20 import common as mavlink

G = VehicleParams().gravity_mps2
M = VehicleParams().mass_kg
CALM = {
    'name': 'calm_test',
    'timeout_s': 60.0,
    'start_position_m': [3.0, 3.0, 2.0],
    'apron': {'position_m': [-3.2, -2.0], 'heave': {'model': 'none'}},
    'wind': {'mean_mps': [0.0, 0.0], 'gust_std_mps': 0.0},
    'randomize': {'heave_phase': False, 'gps_bias': False},
}


def calm(**overrides):
    data = json.loads(json.dumps(CALM))
    data.update(overrides)
    return scenario_from_dict(data, 'test')


class Rig:
    """SimulationLoop with the emulator on a MemoryLink; the test plays the companion."""

    def __init__(self, scenario=None, seed=1, params=None):
        self.link = MemoryLink()
        self.emu = Px4Emulator(params or EmulatorParams(), transport=self.link.a)
        self.frames = []
        self.sim = SimulationLoop(scenario or calm(), seed, self.emu, self.frames.append)
        self.mav = mavlink.MAVLink(self.link.b, srcSystem=1, srcComponent=191)
        self.rx = mavlink.MAVLink(None)
        self.outcomes = []

    def received(self):
        out = []
        for data, _ in self.link.b.receive():
            out += self.rx.parse_buffer(data) or []
        return out

    def run(self, seconds, setpoint=None, chunk_s=0.02):
        """Advance in 20 ms chunks; stream ``setpoint`` (roll, pitch, yaw, thrust) meanwhile."""
        n = round(seconds / chunk_s)
        for _ in range(n):
            if setpoint is not None:
                self.mav.set_attitude_target_send(**set_attitude_target_fields(
                    *setpoint, self.emu.params.thrust))
            _, out = self.sim.advance(chunk_s)
            if out is not None:
                self.outcomes.append(out)

    def set_mode(self, main, sub=0):
        self.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, main, sub,
                                   0, 0, 0, 0)

    def truth(self):
        return self.sim.world.truth()
