"""``deckland up`` safety without starting anything: every socket of the graph's defaults is on
loopback, parameters are never evaluated (no eval/exec/shell anywhere in src/), the record
directory never overwrites foreign data, and the summary says what happened."""

import argparse
import importlib
import ipaddress
import math
import pathlib
import tokenize

from deckland.graph.mission_report import EXIT_CODES, failsafe_fields, summary_lines
from deckland.graph.orchestrator import load_graph
from deckland.graph.up import (
    UdpReservations,
    default_graph_path,
    graph_substitutions,
    prepare_record_dir,
)
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
SOCKET_WORDS = ('address', 'url', 'connection', 'host')


def sim_args(**kw):
    base = {'scenario': 'paper', 'seed': 1, 'hardware': False, 'mavlink': None,
            'pixy_port': None, 'area': (0.0, 0.0)}
    base.update(kw)
    return argparse.Namespace(**base)


def effective_parameters(spec) -> dict:
    """The node's declared defaults (its module's PARAMS) overridden by the graph entry."""
    module = importlib.import_module(f'{spec.package}.{spec.module}')
    values = {p.name: p.default for p in module.PARAMS}
    values.update(spec.parameters)
    return values


def host_of(value: str) -> str:
    """'udpin:H:P' / 'udpout:H:P' / 'tcp:H:P' / 'H' -> H."""
    parts = value.split(':')
    if parts[0] in ('udp', 'udpin', 'udpout', 'udpbcast', 'tcp', 'tcpin') and len(parts) == 3:
        return parts[1]
    return value


def is_loopback(host: str) -> bool:
    if host == 'localhost':
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def socket_parameters(hardware: bool, **kw):
    udp = UdpReservations()
    try:
        subs = graph_substitutions(sim_args(hardware=hardware, **kw), udp)
    finally:
        udp.close()
    graph = load_graph(default_graph_path(), subs, hardware)
    out = []
    for spec in graph['nodes']:
        for name, value in effective_parameters(spec).items():
            # an empty one opens no socket (deck_simulator's px4_onboard_url: no relay)
            if isinstance(value, str) and value and any(w in name for w in SOCKET_WORDS):
                out.append((spec.name, name, value))
    return graph, out


def test_every_socket_of_the_simulated_graph_is_on_loopback():
    _, found = socket_parameters(hardware=False)
    names = {(n, p) for n, p, _ in found}
    # the scan really sees the sockets this test is about
    assert {('pixy_driver', 'udp_bind_address'), ('mavlink_bridge', 'connection'),
            ('deck_simulator', 'mavlink_url'), ('deck_simulator', 'pixy_udp_address')} <= names
    bad = [(n, p, v) for n, p, v in found if not is_loopback(host_of(v))]
    assert not bad, f'non-loopback socket defaults: {bad}'


def test_hardware_graph_is_loopback_unless_configured_otherwise():
    # serial devices for the autopilot and the Pixy: the only UDP left is pixy's (unused) bind
    _, found = socket_parameters(hardware=True, mavlink='/dev/ttyACM0', pixy_port='/dev/ttyUSB0')
    for node, name, value in found:
        assert value.startswith('/dev/') or is_loopback(host_of(value)), (node, name, value)
    # an explicit non-loopback URL is passed through unchanged (configured otherwise)
    _, found = socket_parameters(hardware=True, mavlink='udpin:0.0.0.0:14540',
                                 pixy_port='/dev/ttyUSB0')
    assert ('mavlink_bridge', 'connection', 'udpin:0.0.0.0:14540') in found


def test_loopback_check_itself_rejects_wildcards():
    assert not is_loopback(host_of('udpin:0.0.0.0:14540'))
    assert not is_loopback('192.168.1.5') and is_loopback('127.0.0.1') and is_loopback('::1')


# ----------------------------------------------------------------------- no code evaluation

FORBIDDEN_CALLS = {'eval', 'exec', 'compile', '__import__', 'execfile'}
FORBIDDEN_ATTRS = {('os', 'system'), ('os', 'popen'), ('yaml', 'load'), ('yaml', 'unsafe_load'),
                   ('pickle', 'load'), ('pickle', 'loads'), ('marshal', 'loads')}


def offending_tokens(path: pathlib.Path) -> list[str]:
    """Calls of eval/exec/compile/__import__ (not attributes like re.compile), os.system & co,
    and shell=True, found with the tokenizer (strings and comments do not count)."""
    out = []
    with open(path, 'rb') as fh:
        toks = [t for t in tokenize.tokenize(fh.readline)
                if t.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE,
                                  tokenize.INDENT, tokenize.DEDENT)]
    for i, t in enumerate(toks[:-1]):
        prev = toks[i - 1].string if i else ''
        nxt = toks[i + 1].string
        if t.type == tokenize.NAME and nxt == '(' and prev != '.' and \
                t.string in FORBIDDEN_CALLS and prev != 'def':
            out.append(f'{path}:{t.start[0]}: {t.string}(')
        if t.type == tokenize.NAME and prev == '.' and i >= 2 and \
                (toks[i - 2].string, t.string) in FORBIDDEN_ATTRS:
            out.append(f'{path}:{t.start[0]}: {toks[i - 2].string}.{t.string}')
        if t.string == 'shell' and nxt == '=' and i + 2 < len(toks) and \
                toks[i + 2].string == 'True':
            out.append(f'{path}:{t.start[0]}: shell=True')
    return out


def test_no_eval_exec_or_shell_anywhere_in_src():
    files = [p for p in (ROOT / 'src').rglob('*.py') if '.egg-info' not in p.as_posix()]
    assert len(files) > 30
    bad = [hit for p in files for hit in offending_tokens(p)]
    assert not bad, bad


def test_the_scanner_finds_what_it_looks_for(tmp_path):
    f = tmp_path / 'x.py'
    f.write_text("import os, re, subprocess, yaml\n"
                 "eval('1')\nexec ('x=1')\nos.system('ls')\nyaml.load(s)\n"
                 "subprocess.run('ls', shell=True)\n__import__('os')\n"
                 "re.compile('a')  # eval( in a comment\ns = 'exec(1)'\nyaml.safe_load(s)\n")
    hits = offending_tokens(f)
    assert [h.split(': ', 1)[1] for h in hits] == [
        'eval(', 'exec(', 'os.system', 'yaml.load', 'shell=True', '__import__(']


# ------------------------------------------------------------------------- record directory

def test_record_dir_rotates_a_previous_run_and_refuses_foreign_data(tmp_path):
    new = tmp_path / 'new'
    assert prepare_record_dir(str(new)) == new and not new.exists()
    run = tmp_path / 'run'
    run.mkdir()
    (run / 'report.json').write_text('{"old": 1}')
    prepare_record_dir(str(run))
    assert not run.exists() and (tmp_path / 'run.prev' / 'report.json').exists()
    run.mkdir()
    (run / 'metadata.yaml').write_text('x')
    prepare_record_dir(str(run))         # the older .prev (a run too) is replaced
    assert (tmp_path / 'run.prev' / 'metadata.yaml').exists()
    assert not (tmp_path / 'run.prev' / 'report.json').exists()
    mine = tmp_path / 'thesis'
    mine.mkdir()
    (mine / 'chapter1.tex').write_text('precious')
    with pytest.raises(ValueError, match='not empty and not a previous run'):
        prepare_record_dir(str(mine))
    assert (mine / 'chapter1.tex').read_text() == 'precious'


# -------------------------------------------------------------------------------- summary

def test_summary_lists_outcome_numbers_and_where_things_are():
    report = {'success': True, 'reason': 'landed on deck', 'crash': False, 'safe': True,
              'touchdown_speed_mps': 0.4506, 'horizontal_error_m': 0.0589,
              'time_to_land_s': 11.71, 'autopilot_modes': [{'t_s': 0.1, 'mode': 'OFFBOARD'}],
              'bag': {'messages': 100, 'topics': 20}}
    text = '\n'.join(summary_lines(report, 0, '/tmp/r'))
    for want in ('landed (landed on deck)', '0.45 m/s', '0.059 m', '11.7 s',
                 '/tmp/r (100 messages, 20 topics)', '/tmp/r/report.json', 'exit status       0'):
        assert want in text, text
    fs = {'success': False, 'reason': 'landed on the ground', 'crash': False, 'safe': True,
          'failsafe': 'AUTO.LAND', 'touchdown_speed_mps': None,
          'injected_faults': [{'node': 'dob_altitude', 'at_s': 5.01}]}
    text = '\n'.join(summary_lines(fs, 1, None))
    assert 'safe (no crash); autopilot failsafe AUTO.LAND' in text
    assert 'touchdown speed   n/a' in text and 'node_kill dob_altitude at 5.0 s' in text
    assert 'not recorded' in text and EXIT_CODES[1] in text


def test_summary_shows_the_landing_record_of_the_shared_scoring():
    """The simulator's outcome record (the campaigns' RunOutcome): class, relative figures,
    impacts and bounces."""
    report = {'success': False, 'reason': 'not settled', 'crash': False, 'safe': True,
              'outcome': 'failed', 'settled': False, 'contact_kind': 'pad',
              'touchdown_speed_mps': 0.31, 'lateral_speed_mps': 0.12, 'tilt_rad': 0.05,
              'impacts': 3, 'bounces': 2, 'max_impact_speed_mps': 0.52,
              'max_bounce_height_m': 0.043}
    text = '\n'.join(summary_lines(report, 1, None))
    for want in ('class             failed', 'lateral speed     0.12 m/s',
                 'relative tilt     2.9 deg', 'impacts, bounces  3, 2 (fastest 0.52 m/s, '
                 'highest hop 0.043 m)', 'no successful landing (not settled)'):
        assert want in text, text
    assert '(settled)' in '\n'.join(summary_lines({**report, 'settled': True}, 0, None))


def test_exit_codes_are_documented():
    readme = (ROOT / 'src' / 'deckland' / 'README-up.md').read_text()
    for code in EXIT_CODES:
        assert f'| {code} |' in readme


def test_the_failsafe_is_the_first_mode_out_of_offboard_else_the_emulators_record():
    modes = [{'t_s': 0.0, 'mode': 'POSCTL'}, {'t_s': 1.0, 'mode': 'OFFBOARD'},
             {'t_s': 9.0, 'mode': 'AUTO.LAND'}, {'t_s': 12.0, 'mode': 'AUTO.RTL'}]
    assert failsafe_fields(modes, {'failsafe_mode': 'return'}) == {'failsafe': 'AUTO.LAND'}
    # the bridge died with the stack (composed node kill): the emulated PX4's record
    seen = modes[:2]
    assert failsafe_fields(seen, {'failsafe_mode': 'return'}) == {
        'failsafe': 'AUTO.RTL', 'failsafe_source': 'simulator'}
    assert failsafe_fields(seen, {'failsafe_mode': 'land'})['failsafe'] == 'AUTO.LAND'
    # no failsafe flown, or a real firmware in the loop: nothing is made up
    assert failsafe_fields(seen, {'failsafe_mode': ''}) == {}
    assert failsafe_fields(seen, {'failsafe_mode': 'return', 'autopilot': 'px4-sitl'}) == {}


def test_kill_schedule_kills_each_fault_once_and_releases_at_its_end():
    from types import SimpleNamespace as F

    from deckland.graph.mission_report import KillSchedule

    sched = KillSchedule([F(node='b', start_s=3.0, end_s=math.inf),
                          F(node='a', start_s=1.0, end_s=2.5)])
    assert sched.due(0.5) == ([], [])
    kills, released = sched.due(1.0)
    assert [f.node for f in kills] == ['a'] and released == []
    assert sched.due(2.0) == ([], [])
    kills, released = sched.due(3.2)              # a's end passed, b's start too
    assert [f.node for f in kills] == ['b'] and released == ['a']
    assert sched.due(100.0) == ([], [])           # b is never released


def test_an_outcome_of_another_simulation_is_not_ours():
    from deckland.graph.mission_report import parse_outcome

    mine = {'scenario': 'paper', 'seed': 3}
    assert parse_outcome('{"scenario": "paper", "seed": 3, "success": true}', mine) == (
        {'scenario': 'paper', 'seed': 3, 'success': True}, '')
    assert parse_outcome('{"scenario": "paper", "seed": 4}', mine) == (None, 'foreign')
    out, why = parse_outcome('[1, 2]', mine)
    assert why == '' and out['reason'].startswith('unparsable outcome')
    assert parse_outcome('not json', {})[0]['reason'] == 'unparsable outcome: not json'


def test_report_modes_are_timed_from_the_trigger_and_end_at_the_touchdown():
    """vehicle/mode rows from 0.5 s before the trigger, timed from it; a firmware's own rows
    up to the touchdown only (its land detector switches after it)."""
    from deckland.graph.mission_report import bridge_modes, firmware_modes

    seen = [(9.0, 'POSCTL'), (9.7, 'OFFBOARD'), (30.0, 'AUTO.LAND')]
    assert bridge_modes(seen, 10.0) == [{'t_s': -0.3, 'mode': 'OFFBOARD'},
                                        {'t_s': 20.0, 'mode': 'AUTO.LAND'}]
    assert [r['t_s'] for r in bridge_modes(seen, None)] == [0.0, 0.0, 0.0]
    fw = [{'t_s': 1.0, 'mode': 'OFFBOARD', 'x': 1}, {'t_s': 25.0, 'mode': 'AUTO.LAND'}]
    assert firmware_modes(fw, 10.0, 30.0) == [{'t_s': 1.0, 'mode': 'OFFBOARD'}]
    assert len(firmware_modes(fw, 10.0, None)) == 2


def test_finish_report_adds_what_deckland_up_saw_and_keeps_the_outcome():
    from deckland.graph.mission_report import finish_report
    outcome = {'outcome': 'deck', 'crash': False, 'seed': 7}
    modes = [{'t_s': 0.0, 'mode': 'OFFBOARD'}, {'t_s': 9.0, 'mode': 'AUTO.LAND'}]
    r = finish_report(outcome, scenario='paper', seed=3, composed=True, modes=modes,
                      injected=[], device_problems=[], crashed=[], code=0,
                      bag={'path': 'b', 'messages': 5})
    assert r is not outcome and 'hardware' not in outcome
    assert r['scenario'] == 'paper' and r['seed'] == 7          # the simulator's seed wins
    assert r['hardware'] is False and r['composed'] is True and r['safe'] is True
    assert r['failsafe'] == 'AUTO.LAND' and r['exit_status'] == 0
    assert r['bag'] == {'path': 'b', 'messages': 5}
    assert 'device_problems' not in r and 'crashed_nodes' not in r
    hw = finish_report({}, scenario=None, seed=None, composed=False, modes=[], injected=[],
                       device_problems=['pixy: cannot open'], crashed=[{'name': 'x'}], code=3,
                       bag=None)
    assert hw['hardware'] is True and 'scenario' not in hw and 'bag' not in hw
    assert hw['device_problems'] == ['pixy: cannot open']
    assert hw['crashed_nodes'] == [{'name': 'x'}]
