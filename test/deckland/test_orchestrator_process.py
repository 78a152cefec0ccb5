"""deckland.graph.orchestrator with real child processes: crash reports, respawn limit and
back-off, fault-injected kills, shutdown escalation, and parameters that stay data.

The children are tiny throw-away packages written to ``tmp_path`` (on the children's
PYTHONPATH), so every behaviour is checked on real processes and real signals.
"""

import io
import json
import os
import signal
import sys
import textwrap
import time

from deckland.graph.orchestrator import (
    NodeSpec,
    Orchestrator,
    _ros_value,
    describe_status,
    load_graph,
)
import pytest

pytestmark = pytest.mark.timing   # a graph on the wall clock: reruns on a miss

CHILDREN = {
    # prints its lines and exits with status 3
    'crasher': """
        import sys
        def main():
            for i in range(30):
                print(f'line {i}', flush=True)
            print('Traceback: boom', flush=True)
            return 3
    """,
    # exits 1 immediately, appending its start time to a file (respawn test)
    'flaky': """
        import os, sys, time
        def main():
            with open(os.environ['FLAKY_LOG'], 'a') as fh:
                fh.write(f'{time.monotonic()}\\n')
            return 1
    """,
    # sleeps until killed; ignores SIGINT/SIGTERM and starts a grandchild in its group
    'stubborn': """
        import os, signal, subprocess, sys, time
        def main():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
            with open(os.environ['GRANDCHILD_PIDS'], 'a') as fh:
                fh.write(f'{child.pid}\\n')
            print('ready', flush=True)
            time.sleep(60)
    """,
    # sleeps until killed (polite: exits on SIGINT)
    'sleeper': """
        import time
        def main():
            print('ready', flush=True)
            try:
                time.sleep(60)
            except KeyboardInterrupt:
                return 0
    """,
    # a heavy import (rclpy and the cores take seconds on a loaded machine): stopped there
    'slow_import': """
        import time
        print('importing', flush=True)
        time.sleep(60)
        def main():
            return 0
    """,
    # prints its ROS parameters as JSON (parsed by rcl from the command line)
    'params': """
        import json, sys
        import rclpy
        from rclpy.node import Node
        def main():
            rclpy.init(args=sys.argv)
            node = Node('x', automatically_declare_parameters_from_overrides=True)
            out = {n: p.value for n, p in node._parameters.items()
                   if n not in ('use_sim_time', 'start_type_description_service')}
            print('PARAMS ' + json.dumps(out), flush=True)
            node.destroy_node()
            rclpy.shutdown()
            return 0
    """,
}


@pytest.fixture
def pkg_env(tmp_path):
    """A package ``orch_children`` with one module per child, importable by the children."""
    pkg = tmp_path / 'orch_children'
    pkg.mkdir()
    (pkg / '__init__.py').write_text('')
    for name, code in CHILDREN.items():
        (pkg / f'{name}.py').write_text(textwrap.dedent(code))
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(tmp_path), env.get('PYTHONPATH', '')])
    env['FLAKY_LOG'] = str(tmp_path / 'flaky.log')
    env['GRANDCHILD_PIDS'] = str(tmp_path / 'grandchildren')
    return env


def spec(name, module, **kw):
    return NodeSpec(name=name, package='orch_children', module=module, **kw)


def wait_for(cond, timeout_s=10.0, orch=None):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if orch is not None:
            orch.check()
        if cond():
            return True
        time.sleep(0.02)
    return False


def pid_gone(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # a zombie still answers kill(0); it is gone for our purpose when its state is Z
    try:
        with open(f'/proc/{pid}/stat') as fh:
            return fh.read().split(')')[1].split()[0] == 'Z'
    except FileNotFoundError:
        return True


# --------------------------------------------------------------------------------- crashes

def test_crash_is_reported_with_status_and_log_tail(pkg_env):
    out = io.StringIO()
    orch = Orchestrator([spec('crasher', 'crasher')], out=out, env=pkg_env)
    orch.start()
    try:
        assert wait_for(lambda: orch.exits, orch=orch)
    finally:
        orch.stop()
    (event,) = orch.exits
    assert (event.node, event.status, event.injected, event.action) == (
        'crasher', 3, False, 'not respawned')
    assert event.log_tail[-1] == 'Traceback: boom' and len(event.log_tail) == 15
    assert event.log_tail[0] == 'line 16'           # the last 15 lines, in order
    text = out.getvalue()
    assert 'crasher (pid' in text and 'died: exit status 3' in text
    assert '  crasher | Traceback: boom' in text
    assert orch.crashed == [('crasher', 3)]


def test_respawn_limit_and_exponential_backoff(pkg_env, tmp_path):
    orch = Orchestrator([spec('flaky', 'flaky', respawn=True, respawn_limit=2,
                              respawn_delay_s=0.3)], out=io.StringIO(), env=pkg_env)
    orch.start()
    try:
        assert wait_for(lambda: len(orch.exits) == 3, timeout_s=15.0, orch=orch)
        time.sleep(1.5)     # no fourth start after the limit
        orch.check()
    finally:
        orch.stop()
    starts = [float(x) for x in (tmp_path / 'flaky.log').read_text().split()]
    assert len(starts) == 3 and len(orch.pids()) == 3
    assert [e.action for e in orch.exits] == ['respawn', 'respawn', 'gave up']
    assert all(e.status == 1 for e in orch.exits)
    gap1, gap2 = starts[1] - starts[0], starts[2] - starts[1]
    assert gap1 >= 0.3 and gap2 >= 0.6          # delay · 2^k
    assert gap2 > gap1


def test_killed_node_is_held_down_then_released(pkg_env):
    orch = Orchestrator([spec('sleeper', 'sleeper', respawn=True, respawn_delay_s=0.0)],
                        out=io.StringIO(), env=pkg_env)
    orch.start()
    try:
        first = orch.by_name['sleeper'].proc.pid
        assert wait_for(lambda: 'ready' in orch.by_name['sleeper'].tail)
        assert orch.kill('sleeper') is True
        assert wait_for(lambda: orch.exits, orch=orch)
        time.sleep(0.3)
        orch.check()
        (event,) = orch.exits
        assert event.injected and event.action == 'held'
        assert event.status == -signal.SIGKILL and describe_status(event.status) == \
            'killed by SIGKILL'
        assert orch.alive() == [] and orch.crashed == []     # respawn: true did not apply
        orch.release('sleeper')
        assert orch.alive() == ['sleeper'] and orch.by_name['sleeper'].proc.pid != first
    finally:
        orch.stop()
    with pytest.raises(KeyError, match='no node'):
        orch.kill('nobody')


def test_stop_escalates_and_kills_the_process_groups_within_the_timeout(pkg_env, tmp_path):
    nodes = [spec('stubborn', 'stubborn'), spec('sleeper', 'sleeper')]
    orch = Orchestrator(nodes, out=io.StringIO(), env=pkg_env, stop_timeout_s=2.0)
    orch.start()
    assert wait_for(lambda: all('ready' in p.tail for p in orch.procs))
    grandchild = int((tmp_path / 'grandchildren').read_text().split()[0])
    pids = [*orch.pids(), grandchild]
    took = orch.stop()
    assert took <= 2.0 + 0.5
    assert all(pid_gone(pid) for pid in pids if pid != grandchild)
    assert wait_for(lambda: pid_gone(grandchild), timeout_s=1.0)
    assert orch.by_name['sleeper'].proc.returncode == 0          # SIGINT was enough for it
    assert orch.by_name['stubborn'].proc.returncode == -signal.SIGKILL
    orch.check()
    assert orch.exits == [] or all(e.action == 'not respawned' for e in orch.exits)


def test_a_stop_during_the_import_exits_quietly_with_128_plus_sigint(pkg_env):
    # a failed start stops every node, some still importing: no KeyboardInterrupt traceback
    out = io.StringIO()
    orch = Orchestrator([spec('slow', 'slow_import')], out=out, env=pkg_env,
                        stop_timeout_s=5.0)
    orch.start()
    assert wait_for(lambda: 'importing' in orch.by_name['slow'].tail)
    orch.stop()
    assert orch.by_name['slow'].proc.returncode == 130
    assert 'Traceback' not in out.getvalue() and 'KeyboardInterrupt' not in out.getvalue()


# ------------------------------------------------------------------- parameters are data

NASTY = {
    'code': "__import__('os').system('touch PWNED')",
    'shell': '$(touch PWNED); `touch PWNED` | touch PWNED',
    'looks_bool': 'true',
    'looks_int': '1',
    'comment': 'x # not a comment',
    'quote': "it's",
    'yaml': 'a: b',
    'empty': '',
}


def test_parameter_values_reach_the_node_verbatim_and_are_never_run(pkg_env, tmp_path):
    params = dict(NASTY, flag=True, count=7, gain=0.25, far=float('inf'), names=['a', "b'c"])
    out = io.StringIO()
    orch = Orchestrator([spec('params', 'params', parameters=params)], out=out, env=pkg_env)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        orch.start()
        assert wait_for(lambda: orch.exits, timeout_s=20.0, orch=orch), out.getvalue()
    finally:
        orch.stop()
        os.chdir(cwd)
    line = next(x for x in orch.exits[0].log_tail if x.startswith('PARAMS '))
    got = json.loads(line[len('PARAMS '):].replace('Infinity', '1e999'))
    assert {k: got[k] for k in NASTY} == NASTY
    assert got['flag'] is True and got['count'] == 7 and got['gain'] == 0.25
    assert got['far'] == float('inf') and got['names'] == ['a', "b'c"]
    assert not (tmp_path / 'PWNED').exists()


def test_command_is_an_argv_with_quoted_values_and_no_shell():
    s = NodeSpec('n', 'pkg', parameters={'p': NASTY['code'], 'q': 'true'})
    argv = s.command(python='/py')
    assert argv[:2] == ['/py', '-c'] and 'from pkg.node import main' in argv[2]
    assert "p:='__import__(''os'').system(''touch PWNED'')'" in argv
    assert "q:='true'" in argv
    assert _ros_value(float('nan')) == '.nan' and _ros_value(-float('inf')) == '-.inf'


@pytest.mark.parametrize('field,value,match', [
    ('package', 'os; import shutil', 'package must be a dotted Python identifier'),
    ('module', 'node\nimport os', 'module must be a dotted Python identifier'),
    ('name', 'bad name', 'name must be a ROS node name'),
    ('parameters', {'a b': 1}, 'parameter name must be a ROS parameter name'),
    ('parameters', {'p': {'nested': 1}}, 'parameters.p must be a bool, number'),
    ('parameters', {'p': 'line\nbreak'}, 'must not contain control characters'),
    ('parameters', {'p': [1, 'a']}, 'must be a list of one scalar type'),
    ('remappings', {'a:=b': 'c'}, 'remapping must be a ROS topic'),
    ('respawn_limit', -1, 'respawn_limit must be an integer >= 0'),
    ('respawn_delay_s', float('nan'), 'respawn_delay_s must be a finite number'),
    ('log_level', 'loud', 'log_level must be one of'),
])
def test_node_spec_rejects_bad_fields_naming_them(field, value, match):
    kw = {'name': 'n', 'package': 'pkg', field: value}
    with pytest.raises(ValueError, match=match):
        NodeSpec(**kw)


# ------------------------------------------------------------------------------ graph YAML

def test_load_graph_validates_and_substitutes(tmp_path):
    g = tmp_path / 'g.yaml'
    g.write_text(textwrap.dedent("""
        nodes:
          - {name: a, package: pkg, parameters: {port: '{port}', s: '{literal'}}
          - {name: b, package: pkg, sim_only: true}
          - {name: c, package: pkg, hardware_only: true, respawn: true}
        wait_for_topics: [x/y]
    """))
    sim = load_graph(str(g), {'port': 5}, hardware=False)
    assert [n.name for n in sim['nodes']] == ['a', 'b']
    assert sim['nodes'][0].parameters == {'port': 5, 's': '{literal'}
    assert [n.name for n in load_graph(str(g), {'port': 5}, hardware=True)['nodes']] == \
        ['a', 'c']
    with pytest.raises(ValueError, match=r'placeholder \{port\} has no value'):
        load_graph(str(g), {}, hardware=False)
    bad = {
        'nodes: [{name: a, package: pkg, respwan: true}]': "unknown keys \\['respwan'\\]",
        'nodes: [{name: a, package: pkg}, {name: a, package: pkg}]': 'used twice',
        'nodes: [{name: a}]': 'nodes\\[0\\]',
        'nodes: [{name: a, package: "x;y"}]': 'package must be',
        'nodes: []\nextra: 1': 'unknown top-level keys',
        'nodes: []\nwait_for_topics: ["a b"]': 'wait_for_topics',
        'nodes: {}': 'list under "nodes"',
    }
    for text, match in bad.items():
        g.write_text(text)
        with pytest.raises(ValueError, match=match):
            load_graph(str(g), {'port': 5}, hardware=False)


def test_orchestrator_rejects_duplicate_names_and_bad_timeout():
    with pytest.raises(ValueError, match='unique'):
        Orchestrator([NodeSpec('a', 'p'), NodeSpec('a', 'q')], out=io.StringIO())
    with pytest.raises(ValueError, match='stop_timeout_s'):
        Orchestrator([], out=io.StringIO(), stop_timeout_s=0)


def test_python_is_this_interpreter():
    assert NodeSpec('n', 'pkg').command()[0] == sys.executable
