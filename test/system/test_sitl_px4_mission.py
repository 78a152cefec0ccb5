"""``deckland up`` / ``deckland campaign`` with ``--autopilot px4-sitl`` (deckland.sitl).

Without PX4: the parameters a mission gives PX4 (the vehicle, the take-off height, the
scenario's offboard-loss failsafe), PX4's zero-parameter rule, the firmware loop (faults held
until the landing trigger, the onboard relay through the wire faults, the outcome record), the
campaign's bookkeeping, and the clear errors when PX4 is missing or does not come up. With
PX4 (``sitl``): a paper mission lands on the deck and cleans up after itself; a link loss ends
in PX4's configured Return, landed and disarmed, off the deck.
"""

import json
import math
import pathlib
import subprocess
import sys

from deck_simulator.faults import FaultSet
from deck_simulator.link import ImpairedLink
from deck_simulator.loop import SimulationLoop
from deck_simulator.px4_hil import HilParams, Px4Hil
from deck_simulator.scenario import load_scenario, scenario_from_dict
from deck_simulator.transport import MemoryLink
from deckland.sitl.campaign import compare, failsafe_check, outcome_from_report, spoiled
from deckland.sitl.mission import OBL_LAND, OBL_RETURN, mission_params, wire_faults
from deckland.sitl.px4 import ZERO_FLOAT, Px4NotFoundError, find_px4, px4_param_text
import pytest
from rostest import isolated_env
from test_sitl_px4_hil import FakePx4

try:
    PX4_ROOT = find_px4()
    NO_PX4 = 'PX4 SITL not found (set DECKLAND_PX4_SITL or provide ../shared/px4-sitl)'
except Px4NotFoundError as exc:
    PX4_ROOT, NO_PX4 = None, str(exc)

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))
REPO = pathlib.Path(__file__).resolve().parents[2]
BRIDGE_KILL = REPO / 'docs' / 'results' / 'scenarios' / 'fault_bridge_kill.yaml'


# --- what PX4 is told ------------------------------------------------------------------------

def test_mission_params_carry_the_scenarios_failsafe_to_px4():
    paper = mission_params(load_scenario('paper'))
    # no fault: PX4's Land after the default 1 s, take-off to the scenario's start height
    assert paper['COM_OBL_RC_ACT'] == OBL_LAND and paper['COM_OF_LOSS_T'] == 1.0
    assert paper['MIS_TAKEOFF_ALT'] == load_scenario('paper').start_position_m[2]
    assert 'RTL_RETURN_ALT' not in paper
    sc = load_scenario('fault_mavlink_link_loss')
    (f,) = sc.faults
    p = mission_params(sc)
    # action: return -> PX4 Return (3) at min_alt_m, landing at land_speed_mps, after
    # loss_timeout_s: the emulated PX4's failsafe, now PX4's own
    assert p['COM_OBL_RC_ACT'] == OBL_RETURN == 3
    assert p['COM_OF_LOSS_T'] == f.loss_timeout_s == 0.3
    assert p['RTL_RETURN_ALT'] == p['RTL_DESCEND_ALT'] == f.min_alt_m == 2.0
    assert p['MPC_LAND_SPEED'] == f.land_speed_mps == 0.5 and p['RTL_LAND_DELAY'] == 0.0
    # home (1.7 m from the deck) is not "reached" at once, and PX4 climbs before it returns
    assert p['NAV_ACC_RAD'] < 0.5 and p['RTL_MIN_DIST'] == 0.0 and p['RTL_CONE_ANG'] == 0
    assert 'NAV_ACC_RAD' not in paper
    assert wire_faults(sc) and not wire_faults(load_scenario('fault_node_kill'))
    kill = mission_params(load_scenario(str(BRIDGE_KILL)))
    assert kill['COM_OBL_RC_ACT'] == OBL_RETURN and kill['COM_OF_LOSS_T'] == 0.3


def test_a_zero_parameter_is_sent_as_a_value_px4_keeps():
    # PX4 stores only values that differ from the compiled default; 0.0 would be dropped
    # and the airframe's set-default (Iris geometry) would win
    assert px4_param_text(0.0) == repr(ZERO_FLOAT) and float(px4_param_text(0.0)) != 0.0
    assert px4_param_text(-0.225) == '-0.225' and px4_param_text(4) == '4'
    p = mission_params(load_scenario('paper'))
    zeros = [k for k, v in p.items() if isinstance(v, float) and v == 0.0]
    assert {'CA_ROTOR0_PY', 'CA_ROTOR1_PX', 'CA_ROTOR2_PY', 'CA_ROTOR3_PX'} <= set(zeros)


# --- the firmware loop -----------------------------------------------------------------------

def _fault_scenario():
    return scenario_from_dict({
        'name': 'px4_loop', 'timeout_s': 30.0, 'apron': {'heave': {'model': 'none'}},
        'randomize': {'start_offset_m': 0.0, 'gps_bias': False},
        'faults': [{'type': 'mavlink_link_loss', 'trigger_height_m': 1.0, 'duration_s': 1.0},
                   {'type': 'gps_jump', 'start_s': 0.5, 'magnitude_m': 1.0}]},
        'test')


def test_the_firmware_loop_holds_faults_until_the_trigger_and_relays_through_them():
    sc = _fault_scenario()
    fake = FakePx4(auto_controls=([0.0] * 4, True))
    companion, px4_side = MemoryLink(), MemoryLink()
    frames = []
    loop = SimulationLoop(
        sc, 3, None, frames.append, 500.0,
        firmware=lambda w: Px4Hil(w, HilParams(lockstep_timeout_s=0.05), link=fake),
        relay=(companion.a, px4_side.a))
    world = loop.world
    assert world.autopilot is loop.autopilot and isinstance(loop.autopilot, Px4Hil)
    assert isinstance(loop.relay[0], ImpairedLink)
    # on the ground (0.15 m < the 1 m trigger) and past the gps_jump's 0.5 s: nothing fires
    loop.advance(2.0)
    assert world.resting_on == 'ground' and world.faults.active(world.t_s) == ()
    assert world.faults.pending and all(math.isinf(a.on) for a in world.faults.all)
    # 250 Hz HIL_SENSOR; 50 Hz Pixy frames plus the one exposed before t = 0, which the world
    # delivers first (the last sample before the start reaches the stack: commit 6376288)
    assert len(fake.last('HIL_SENSOR')) == 500 and len(frames) == 100 + 1
    # the relay carries both ways while no fault is on
    companion.b.send(b'up')
    px4_side.b.send(b'down')
    loop.advance(0.002)
    assert px4_side.b.receive() == [(b'up', None)] and companion.b.receive() == [
        (b'down', None)]
    # taken off (PX4 hovers it at 2 m: u = 0.647 is the hover of T/W = 2), the landing
    # trigger starts the scenario's clock: gps_jump 0.5 s later, the height trigger armed
    fake.auto = ([0.647] * 4, True)
    v = world.vehicle
    v.z, v.vz, world.resting_on = 2.0, 0.0, None
    v.f1 = v.f2 = v.f3 = v.f4 = world.params.mass_kg * world.params.gravity_mps2 / 4.0
    loop.on_planner_mode('APPROACH')
    t0 = world.t_s
    loop.advance(0.6)
    gps = next(a for a in world.faults.all if a.name == 'gps_jump')
    assert gps.on == pytest.approx(t0 + 0.5, abs=0.003)
    cut = next(a for a in world.faults.all if a.name == 'mavlink_link_loss')
    assert math.isinf(cut.on) and v.z > 1.5
    v.z = 0.9                               # below the 1 m trigger: the cut opens
    loop.advance(0.01)
    assert cut.on < world.t_s < cut.off
    companion.b.send(b'lost')
    loop.advance(0.01)
    assert px4_side.b.receive() == [] and loop.link.counters['rx_cut'] == 1


def test_the_firmware_loop_records_the_touchdown_as_the_outcome():
    sc = _fault_scenario()
    fake = FakePx4(auto_controls=([0.0] * 4, True))
    loop = SimulationLoop(sc, 3, None, lambda _b: None, 500.0,
                          firmware=lambda w: Px4Hil(w, HilParams(), link=fake,
                                                    start_on_ground=False))
    loop.on_planner_mode('FINAL')
    out = None
    for _ in range(400):                    # motors off at 2 m: a free fall onto the ground
        _, out = loop.advance(0.01)
        if out is not None:
            break
    assert out is not None and out['contact_kind'] == 'ground' and out['crash'] is True
    # a free fall of 1.85 m (start 2 m, gear 0.15 m), less the motors' 40 ms spin-down
    assert out['touchdown_speed_mps'] == pytest.approx(math.sqrt(2 * 9.81 * 1.85), rel=0.1)
    assert loop.rejection_counts()['world.nan'] == 0


def test_the_loop_takes_one_backend():
    with pytest.raises(ValueError, match='either an emulator or a firmware'):
        SimulationLoop(load_scenario('paper'), 1, None, lambda _b: None)


def test_faults_start_at_rebases_windows_and_rearms_height_triggers():
    sc = _fault_scenario()
    fs = FaultSet(sc.faults, 1)
    fs.update_height(0.0, 0.1)
    assert not fs.pending                      # fired at t = 0 on the ground
    fs.start_at(None)
    assert fs.active(0.6) == () and fs.pending
    fs.start_at(10.0)
    assert fs.active(10.6) == ('gps_jump',) and fs.active(10.4) == ()
    fs.update_height(9.0, 0.5)
    assert fs.pending                          # before the new start: not yet
    fs.update_height(10.1, 0.5)
    assert fs.active(10.2) == ('mavlink_link_loss',)
    assert fs.active(10.6) == ('mavlink_link_loss', 'gps_jump')


# --- the campaign's bookkeeping --------------------------------------------------------------

def test_a_mission_report_becomes_the_campaigns_record():
    rep = {'success': True, 'landed_on_deck': True, 'contact_kind': 'pad',
           'horizontal_error_m': 0.02, 'touchdown_speed_mps': 0.1, 'time_to_land_s': None,
           'outcome': 'deck', 'reason': 'landed on deck', 'sim_time_s': 40.0,
           'lockstep': {'stalls': 1}, 'px4': {}, 'exit_status': 0}
    rec = outcome_from_report(7, 'paper', rep)
    assert (rec.seed, rec.success, rec.horizontal_error_m) == (7, True, 0.02)
    assert math.isnan(rec.time_to_land_s)
    assert spoiled(rep, 5) == '' and 'stalled 9' in spoiled({**rep, 'lockstep': {
        'stalls': 9}}, 5)
    none = outcome_from_report(8, 'paper', {'success': False, 'reason': 'start-up failed: x',
                                            'exit_status': 3})
    assert none.outcome == 'no_run' and 'start-up' in none.reason
    assert spoiled({'exit_status': 3, 'reason': 'start-up failed'}, 5).startswith('did not')


def test_failsafe_check_wants_the_configured_action_landed_and_disarmed():
    params = {'COM_OBL_RC_ACT': OBL_RETURN}
    good = {'contact_kind': 'ground', 'crash': False, 'px4': {
        'armed_at_end': False, 'landed_state_at_end': 1, 'modes': [
            {'mode': 'OFFBOARD'}, {'mode': 'AUTO.RTL'}, {'mode': 'OFFBOARD'}]}}
    assert failsafe_check(good, params)['ok']
    assert not failsafe_check({**good, 'contact_kind': 'edge'}, params)['ok']
    armed = {**good, 'px4': {**good['px4'], 'armed_at_end': True}}
    assert not failsafe_check(armed, params)['ok']
    land = {**good, 'px4': {**good['px4'], 'modes': [{'mode': 'OFFBOARD'},
                                                     {'mode': 'AUTO.LAND'}]}}
    chk = failsafe_check(land, params)
    assert not chk['ok'] and chk['action_seen'] == 'AUTO.LAND'


def test_compare_is_the_ratio_of_the_percentiles():
    a = {'horizontal_error_m': {'p50': 0.02, 'p95': 0.04},
         'touchdown_speed_mps': {'p50': 0.2, 'p95': 0.5}}
    b = {'horizontal_error_m': {'p50': 0.01, 'p95': 0.04},
         'touchdown_speed_mps': {'p50': 0.1, 'p95': 0.2}}
    c = compare(a, b)
    assert c['horizontal_error_m_p50_ratio'] == 2.0 and c['touchdown_speed_mps_p95_ratio'] == 2.5
    assert c['within_factor_2'] is False
    assert compare(b, b)['within_factor_2'] is True


class _Monitor:
    """MissionMonitor's trigger and planner/mode, scripted."""

    def __init__(self, answers, mode_after=None):
        self.answers, self.calls, self.mode, self.node = list(answers), 0, 'IDLE', None
        self.mode_after = mode_after

    def trigger(self, service, timeout_s=5.0):
        self.calls += 1
        if self.mode_after is not None and self.calls >= self.mode_after:
            self.mode = 'TAKEOFF'
        return self.answers.pop(0)


class _Px4:
    NAME = 'PX4'

    def take_off(self, abort=None):
        return True, 'PX4 loiters at 2.00 m'

    def wait_hover_measured(self, node, timeout_s, abort=None):
        return math.nan


def test_the_operator_asks_the_planner_again_when_a_reply_is_lost():
    from deckland.sitl.mission import TAKEOFF_TRIGGER_ATTEMPTS, operator_take_off
    lost = (False, 'service planner/takeoff timed out')
    # no reply and planner/mode unchanged: asked again, the second call answers
    mon = _Monitor([lost, (True, 'taking off')])
    assert operator_take_off(_Px4(), mon, lambda _t: None) == (True, 'taking off')
    assert mon.calls == 2
    # no reply but planner/mode shows the take-off: not asked again
    mon = _Monitor([lost], mode_after=1)
    ok, msg = operator_take_off(_Px4(), mon, lambda _t: None)
    assert ok and 'reply lost' in msg and mon.calls == 1
    # a refusal is final; so is silence every time
    mon = _Monitor([(False, 'not in IDLE')])
    assert operator_take_off(_Px4(), mon, lambda _t: None)[0] is False and mon.calls == 1
    mon = _Monitor([lost] * TAKEOFF_TRIGGER_ATTEMPTS)
    ok, msg = operator_take_off(_Px4(), mon, lambda _t: None)
    assert not ok and 'timed out' in msg and mon.calls == TAKEOFF_TRIGGER_ATTEMPTS


# --- the registry of firmwares ---------------------------------------------------------------

def test_the_registry_names_px4_and_every_entry_loads():
    from deckland.sitl import SITL_AUTOPILOTS, SitlAutopilot, SitlNotFoundError, register
    from deckland.sitl.mission import Px4Mission
    from deckland.sitl.px4 import Px4StartError
    px4 = SITL_AUTOPILOTS['px4-sitl']
    assert px4.load('mission') is Px4Mission and px4.load('params') is mission_params
    assert px4.load('failsafe_check') is failsafe_check and px4.report_key == 'px4'
    # up/campaign/bench catch the generic errors: PX4's are those
    assert issubclass(Px4NotFoundError, SitlNotFoundError)
    assert issubclass(Px4StartError, RuntimeError) and not issubclass(
        Px4StartError, SitlNotFoundError)
    for name in ('px4-sitl', 'emulator', 'in-process'):
        with pytest.raises(ValueError, match='already registered'):
            register(SitlAutopilot(name, '', *('m:a',) * 4, 'k'))


# --- clear errors ----------------------------------------------------------------------------

def test_up_says_when_px4_is_missing(tmp_path):
    res = subprocess.run([DECKLAND, 'up', '--autopilot', 'px4-sitl'], capture_output=True,
                         text=True, timeout=60,
                         env=isolated_env(DECKLAND_PX4_SITL=str(tmp_path / 'nothing')))
    assert res.returncode == 2
    assert 'DECKLAND_PX4_SITL=' in res.stderr and 'make px4_sitl_default' in res.stderr
    res = subprocess.run([DECKLAND, 'campaign', '--autopilot', 'px4-sitl', '--runs', '1'],
                         capture_output=True, text=True, timeout=60,
                         env=isolated_env(DECKLAND_PX4_SITL=str(tmp_path / 'nothing')))
    assert res.returncode == 2 and 'DECKLAND_PX4_SITL=' in res.stderr


@pytest.mark.ros
@pytest.mark.slow
def test_up_says_when_px4_does_not_come_up(tmp_path):
    fake = tmp_path / 'px4'
    (fake / 'bin').mkdir(parents=True)
    (fake / 'etc' / 'init.d-posix').mkdir(parents=True)
    (fake / 'etc' / 'init.d-posix' / 'rcS').write_text('')
    (fake / 'bin' / 'px4').write_text('#!/bin/sh\necho "ERROR [px4] no ROMFS"\nexit 3\n')
    (fake / 'bin' / 'px4').chmod(0o755)
    out = tmp_path / 'report.json'
    res = subprocess.run([DECKLAND, 'up', '--autopilot', 'px4-sitl', '--report', str(out),
                          '--startup-timeout', '20'], capture_output=True, text=True,
                         timeout=90, env=isolated_env(DECKLAND_PX4_SITL=str(fake)))
    report = json.loads(out.read_text())
    assert res.returncode == 3, res.stdout[-2000:]
    assert 'PX4 exited while starting' in report['reason'] and 'no ROMFS' in report['reason']
    assert not pathlib.Path(report['px4']['workdir']).exists()      # its directory removed


# --- with PX4 --------------------------------------------------------------------------------

SITL = [pytest.mark.sitl, pytest.mark.ros, pytest.mark.slow,
        pytest.mark.skipif(PX4_ROOT is None, reason=NO_PX4), pytest.mark.sitl_mission]


def _fly(tmp_path, scenario, seed, *extra):
    out = tmp_path / 'report.json'
    res = subprocess.run([DECKLAND, 'up', '--autopilot', 'px4-sitl', '--scenario', scenario,
                          '--seed', str(seed), '--timeout', '60', '--report', str(out), *extra],
                         capture_output=True, text=True, timeout=220, env=isolated_env())
    log = res.stdout + res.stderr
    assert out.exists(), log[-3000:]
    return res, json.loads(out.read_text()), log


@SITL[0]
@SITL[1]
@SITL[2]
@SITL[3]
@SITL[4]
def test_up_px4_sitl_lands_on_the_deck_and_cleans_up(tmp_path):
    ulog = tmp_path / 'ulog'
    res, report, log = _fly(tmp_path, 'paper', 100001, '--keep-ulog', str(ulog))
    px4 = report['px4']
    # PX4 took every parameter at boot (none had to be set again), flew its own take-off,
    # was handed over to OFFBOARD before the trigger and disarmed after the touchdown
    assert px4['params_fixed_after_boot'] == {}, px4
    assert report['autopilot_modes'][0]['mode'] == 'OFFBOARD', log[-3000:]
    assert report['success'] and report['contact_kind'] == 'pad', log[-3000:]
    assert report['touchdown_speed_mps'] < 0.5 and report['horizontal_error_m'] < 0.2
    assert px4['armed_at_end'] is False and px4['landed_state_at_end'] == 1
    assert res.returncode == 0
    # clean shutdown: PX4 gone, its working directory removed, the ULog kept on request
    assert not pathlib.Path(px4['workdir']).exists()
    assert list(ulog.glob('*.ulg')) and (ulog / 'px4.log').exists()
    assert 'PX4 stopped, its working directory removed' in log
    print(f"PX4 mission: {report['reason']}, error {report['horizontal_error_m']:.3f} m, "
          f"touchdown {report['touchdown_speed_mps']:.2f} m/s, lockstep {report['lockstep']}")


@SITL[0]
@SITL[1]
@SITL[2]
@SITL[3]
@SITL[4]
def test_up_px4_sitl_link_loss_ends_in_pxs_return_landed_and_disarmed(tmp_path):
    res, report, log = _fly(tmp_path, 'fault_mavlink_link_loss', 100000)
    chk = failsafe_check(report, mission_params(load_scenario('fault_mavlink_link_loss')))
    # the link cut 1 m above the deck (through the simulator's relay): PX4's own Return
    # after COM_OF_LOSS_T, home where it took off (clear of the deck), landed and disarmed
    assert 'link.rx_cut' in log and 'link.tx_cut' in log, log[-3000:]
    assert chk['ok'], (chk, log[-3000:])
    assert report['failsafe'] == 'AUTO.RTL' and report['contact_kind'] == 'ground'
    assert report['crash'] is False and report['touchdown_speed_mps'] < 1.0
    assert res.returncode == 1        # a safe landing, not a successful one
