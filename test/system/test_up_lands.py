"""End to end in CI: ``deckland up --scenario paper --record DIR --timeout 90`` as a subprocess
flies the whole node graph in real time and lands on the heaving deck within its timeout:
exit status 0, ``report.json`` says success, and the bag is readable and holds the landing.
"""

import json
import math
import pathlib
import subprocess
import sys
import time

import pytest
from rostest import isolated_env

pytestmark = pytest.mark.ros

DECKLAND = str(pathlib.Path(sys.executable).with_name('deckland'))


@pytest.mark.solo
def test_deckland_up_paper_lands_in_real_time(tmp_path):
    from rosbags.highlevel import AnyReader

    run = tmp_path / 'run'
    t0 = time.monotonic()
    res = subprocess.run([DECKLAND, 'up', '--scenario', 'paper', '--record', str(run),
                          '--timeout', '90'], capture_output=True, text=True, timeout=120,
                         env=isolated_env())
    wall_s = time.monotonic() - t0
    log = res.stdout[-4000:] + res.stderr[-4000:]
    assert res.returncode == 0, log
    report = json.loads((run / 'report.json').read_text())
    assert report['success'] is True and report['landed_on_deck'] is True, report
    assert report['crash'] is False and report['contact_kind'] == 'pad', report
    assert report['exit_status'] == 0 and report['scenario'] == 'paper'
    # a landing, not a crash: below the scenario's crash speed (1 m/s); the graph is not
    # reproducible run to run (real-time scheduling), the same seed touched down at 0.12 and
    # at 0.59 m/s in two runs, so no tighter bound here (README-up.md, Graph vs in-process)
    assert 0.0 <= report['touchdown_speed_mps'] < 1.0, report
    assert report['horizontal_error_m'] < 0.2, report
    # real time: the mission's sim time fits in the wall time the whole run took
    assert report['time_to_land_s'] < report['sim_time_s'] < wall_s, (report, wall_s)
    assert 'OFFBOARD' in [m['mode'] for m in report['autopilot_modes']]
    assert '==== deckland up: summary' in res.stdout

    # the bag: readable, and it shows the vehicle coming down onto the deck
    with AnyReader([run]) as reader:
        topics = {c.topic for c in reader.connections}
        assert {'sim/truth/vehicle', 'sim/truth/apron', 'control/thrust',
                'planner/mode'} <= {t.lstrip('/') for t in topics}, topics
        conns = [c for c in reader.connections if c.topic.lstrip('/') == 'sim/truth/vehicle']
        z = []
        for conn, t_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            z.append((t_ns * 1e-9, msg.pose.pose.position.z))
        modes = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages(
            connections=[c for c in reader.connections
                         if c.topic.lstrip('/') == 'planner/mode'])]
    assert len(z) > 100 and all(math.isfinite(v) for _, v in z)
    # recorded at ~50 Hz (truth_rate_hz) over the mission
    span = z[-1][0] - z[0][0]
    assert 40.0 < len(z) / span < 55.0, (len(z), span)
    # from the start hover (~2 m) down to the deck top (0.6 m ± 0.15 m heave)
    assert max(v for _, v in z[:50]) > 1.5
    assert 0.3 < z[-1][1] < 0.9, z[-5:]
    assert 'APPROACH' in modes or 'ALIGN' in modes, modes
