"""A real ``deckland up`` subprocess stopped with SIGINT or SIGTERM once the topics flow: every
child pid is gone within 5 s, no node prints a traceback or FATAL, the exit status is 128 + the
signal (README-up.md), and the bag being recorded is finished and readable, with report.json
saying why the run ended."""

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

pytestmark = pytest.mark.timing   # a graph on the wall clock: reruns on a miss

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))


def alive(pid: int) -> bool:
    try:
        with open(f'/proc/{pid}/stat') as fh:
            return fh.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except (FileNotFoundError, ProcessLookupError):
        return False


def wait_in_log(proc: subprocess.Popen, log: pathlib.Path, marker: str) -> str:
    """The log once ``marker`` is in it (60 s at most); fails if ``deckland up`` exits first."""
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and marker not in log.read_text():
        assert proc.poll() is None, log.read_text()
        time.sleep(0.1)
    return log.read_text()


def node_pids(text: str) -> list[int]:
    return [int(p) for p in re.findall(r'started \w+ \(pid (\d+)\)', text)]


@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_every_child_within_5_s_cleanly_and_finishes_the_bag(tmp_path, sig):
    run = tmp_path / 'run'
    log = tmp_path / 'up.log'
    with open(log, 'w') as out:
        proc = subprocess.Popen([DECKLAND, 'up', '--scenario', 'paper', '--record', str(run),
                                 '--timeout', '60'], stdout=out, stderr=subprocess.STDOUT,
                                env=isolated_env())
    try:
        text = wait_in_log(proc, log, 'start_landing:')
        assert 'all topics flowing' in text and 'recording' in text, text
        pids = node_pids(text)
        assert len(pids) == 6
        time.sleep(1.0)                       # well into the mission
        t0 = time.monotonic()
        proc.send_signal(sig)
        while any(alive(p) for p in pids) and time.monotonic() - t0 < 10.0:
            time.sleep(0.02)
        children_gone_s = time.monotonic() - t0
        # the children are the 5 s requirement; deckland up then finishes the bag and reads
        # it back (bag_info: 17 s at loadavg 50, most of its own exit time there)
        code = proc.wait(timeout=60.0)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert children_gone_s <= 5.0, text
    name = signal.Signals(sig).name
    assert code == 128 + sig, text
    assert f'interrupted by {name}' in text and f'exit status       {128 + sig}' in text
    assert 'Traceback' not in text and 'FATAL' not in text, text
    # the bag is finished (footer, index, metadata) and holds the mission since the trigger
    assert not is_recording(run) and not needs_reindex(run)
    info = bag_info(run, recover=False)
    topics = {t.name.lstrip('/'): t.count for t in info.topics}
    assert topics.get('control/thrust', 0) > 50 and topics.get('planner/mode', 0) >= 1
    assert info.duration_s > 1.0
    report = json.loads((run / 'report.json').read_text())
    assert report['interrupted'] == name and report['exit_status'] == 128 + sig
    assert report['success'] is False and report['bag']['messages'] == info.message_count
    assert 'crashed_nodes' not in report          # the stop is not a crash


def test_a_killed_deckland_up_takes_its_nodes_with_it(tmp_path):
    """SIGKILL (no handler runs) to ``deckland up``: every node still gets SIGTERM from the
    kernel (PR_SET_PDEATHSIG) and is gone within 5 s, instead of flying on unsupervised."""
    log = tmp_path / 'up.log'
    with open(log, 'w') as out:
        proc = subprocess.Popen([DECKLAND, 'up', '--scenario', 'paper', '--timeout', '60'],
                                stdout=out, stderr=subprocess.STDOUT, env=isolated_env())
    pids: list[int] = []
    try:
        text = wait_in_log(proc, log, 'all topics flowing')
        pids = node_pids(text)
        assert len(pids) == 6 and all(alive(p) for p in pids), text
        proc.kill()
        proc.wait(timeout=10.0)
        t0 = time.monotonic()
        while any(alive(p) for p in pids) and time.monotonic() - t0 < 10.0:
            time.sleep(0.02)
        gone_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
        for p in pids:                      # never leave them behind, even when failing
            if alive(p):
                os.kill(p, signal.SIGKILL)
    assert gone_s <= 5.0, [p for p in pids if alive(p)]
