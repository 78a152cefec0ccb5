"""``deckland up`` ends cleanly when a start fails and when a node crashes mid-mission: every
child gone, no traceback, report.json and the summary say what happened, and the bag is either
finished (the crash) or reported as never started (the failed start)."""

import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

from deckland.ros.bag import bag_info, is_recording, needs_reindex
import pytest
from rostest import isolated_env

pytestmark = pytest.mark.ros

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))


def alive(pid: int) -> bool:
    try:
        with open(f'/proc/{pid}/stat') as fh:
            return fh.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except (FileNotFoundError, ProcessLookupError):
        return False


def child_pids(text: str) -> dict[str, int]:
    return {n: int(p) for n, p in re.findall(r'started (\w+) \(pid (\d+)\)', text)}


def test_a_failed_start_stops_everything_and_says_why(tmp_path):
    params = tmp_path / 'bad.yaml'
    # a value the planner refuses at construction: it exits 2 with a clear message
    params.write_text('/**:\n  ros__parameters:\n    rate_hz: -5.0\n')
    run = tmp_path / 'run'
    res = subprocess.run([DECKLAND, 'up', '--params', str(params), '--record', str(run),
                          '--startup-timeout', '60'], capture_output=True, text=True,
                         timeout=120, env=isolated_env())
    text = res.stdout + res.stderr
    assert res.returncode == 3, text
    assert 'Traceback' not in text, text
    assert 'start-up failed' in text and 'rate_hz' in text, text
    assert not any(alive(p) for p in child_pids(text).values()), text
    report = json.loads((run / 'report.json').read_text())
    assert report['reason'] == 'start-up failed' and report['exit_status'] == 3
    assert report['bag']['not_started'] and report['crashed_nodes'], report
    assert 'bag               not started' in res.stdout


def test_a_node_crash_mid_mission_is_reported_and_the_run_ends_cleanly(tmp_path):
    run = tmp_path / 'run'
    log = tmp_path / 'up.log'
    with open(log, 'w') as out:
        proc = subprocess.Popen([DECKLAND, 'up', '--scenario', 'paper', '--record', str(run),
                                 '--timeout', '40'], stdout=out, stderr=subprocess.STDOUT,
                                env=isolated_env())
    try:
        deadline = time.monotonic() + 90.0
        while time.monotonic() < deadline and 'start_landing:' not in log.read_text():
            assert proc.poll() is None, log.read_text()
            time.sleep(0.1)
        pids = child_pids(log.read_text())
        time.sleep(1.0)
        os.kill(pids['dob_altitude'], signal.SIGSEGV)      # not a fault of the scenario
        code = proc.wait(timeout=120.0)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert code in (0, 1), text
    assert 'dob_altitude (pid' in text and 'died: killed by SIGSEGV' in text, text
    assert not any(alive(p) for p in pids.values()), text
    report = json.loads((run / 'report.json').read_text())
    (crash,) = report['crashed_nodes']
    assert crash['node'] == 'dob_altitude' and crash['action'] == 'not respawned'
    assert not is_recording(run) and not needs_reindex(run)
    assert bag_info(run, recover=False).message_count == report['bag']['messages'] > 0
