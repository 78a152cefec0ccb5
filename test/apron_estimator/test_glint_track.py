"""Persistent glint beside the deck: once the lidar has rejected it, the track never returns
to it (docs/failsafe.md "False blobs"), and the end-to-end landings that used to strike the
deck edge land on the deck."""

from __future__ import annotations

import math
import random

from apron_estimator.horizontal import HorizontalParams, HorizontalTracker
import pytest

DT = 0.02                 # 50 Hz frames
BEACON = (0.0, 0.0)       # world ENU, on the deck
GLINT = (0.6, 0.08)       # world ENU, beside the deck (the scenario's 0.6 m)
HEIGHT_M = 2.2            # height used for the measurement noise (over the ground)


def _surface(x: float, y: float) -> float:
    """Lidar surface under the vehicle: the 1.05 x 0.85 m pad is 0.6 m above the ground."""
    return 0.6 if abs(x) <= 0.525 and abs(y) <= 0.425 else 0.0


class _Run:
    """Static world, vehicle moved by the test, noisy detections of the beacon and glint."""

    def __init__(self, seed: int, params: HorizontalParams | None = None) -> None:
        self.rng = random.Random(seed)
        self.tr = HorizontalTracker(params or HorizontalParams(use_accel_input=False))
        self.t = 0.0
        self.v = (0.0, 0.0)

    def frame(self, beacon: bool = True, glint: bool = True) -> None:
        self.t += DT
        g = self.rng.gauss
        vx, vy = self.v
        cands = []
        if beacon:
            cands.append((BEACON[0] - vx + g(0, 0.01), BEACON[1] - vy + g(0, 0.01)))
        if glint:
            cands.append((GLINT[0] - vx + g(0, 0.01), GLINT[1] - vy + g(0, 0.01)))
        self.tr.update(self.t, cands, HEIGHT_M, _surface(vx, vy))

    def hover(self, seconds: float, **kw) -> None:
        for _ in range(round(seconds / DT)):
            self.frame(**kw)

    def follow(self, seconds: float, speed: float = 0.4) -> None:
        """Fly toward the track like the planner's ALIGN slew (speed-limited)."""
        for _ in range(round(seconds / DT)):
            x, y, *_ = self.tr.state(self.t)
            n = math.hypot(x, y)
            step = min(n, speed * DT)
            if n > 1e-9:
                self.v = (self.v[0] + x / n * step, self.v[1] + y / n * step)
            self.frame()

    def rel(self, world: tuple[float, float]) -> tuple[float, float]:
        return world[0] - self.v[0], world[1] - self.v[1]

    def track_error(self, world: tuple[float, float]) -> float:
        x, y, *_ = self.tr.state(self.t)
        rx, ry = self.rel(world)
        return math.hypot(x - rx, y - ry)


def _resolved(seed: int) -> _Run:
    """Acquire the beacon, probe the glint, reject it with the lidar, come back."""
    run = _Run(seed)
    run.hover(0.2, glint=False)
    run.hover(1.0)                     # over the beacon: deck surface; glint confirmed
    assert run.tr.events['probes'] == 1
    run.follow(4.0)                    # the planner flies to the probed glint ...
    assert run.tr.events['switches'] == 1 and run.tr.events['rivals_rejected'] >= 1
    return run


def test_after_a_switch_the_target_is_not_ambiguous_in_the_same_frame():
    """The switch back to the beacon rejects the glint; the ambiguity must drop with it (a
    stale rival list kept the switched-to rival 'open': σ² stayed 0.36 m² and the planner
    held over the glint, seed 100031)."""
    run = _Run(5)
    run.hover(0.2, glint=False)
    run.hover(1.0)
    for _ in range(round(4.0 / DT)):
        x, y, *_ = run.tr.state(run.t)
        n = math.hypot(x, y)
        if n > 1e-9:
            s = min(n, 0.4 * DT)
            run.v = (run.v[0] + x / n * s, run.v[1] + y / n * s)
        switches = run.tr.events['switches']
        run.frame()
        if run.tr.events['switches'] > switches:
            break
    assert run.tr.events['switches'] == 1
    assert not run.tr.ambiguous
    _, _, _, _, var_x, var_y, tracked, _ = run.tr.state(run.t)
    assert tracked and var_x + var_y < 0.2 ** 2      # the planner may descend again
    assert run.track_error(BEACON) < 0.1


def test_a_track_never_slides_onto_a_rejected_glint_while_the_beacon_is_out_of_view():
    run = _resolved(6)
    run.hover(1.0)                         # hovering over the glint, both in view
    assert run.track_error(BEACON) < 0.05
    gated = run.tr.rejected['gated']
    # the beacon leaves the image; the glint below the vehicle stays (0.9 s < lost timeout)
    run.hover(0.9, beacon=False)
    assert run.tr.tracked
    assert run.track_error(BEACON) < 0.1
    assert run.track_error(GLINT) > 0.5
    assert run.tr.rejected['gated'] - gated >= 40      # ~45 glint-only frames refused
    assert not run.tr.ambiguous


def test_without_the_rejected_rival_check_the_track_would_slide(monkeypatch):
    """Control experiment for the test above: the scenario really provokes the slide."""
    monkeypatch.setattr(HorizontalTracker, '_explained', lambda *a: False)
    # a looser gate stands for the grown velocity variance of a longer blind spell
    run = _Run(6, HorizontalParams(use_accel_input=False, accel_psd_m2ps3=2.0))
    run.hover(0.2, glint=False)
    run.hover(1.0)
    run.follow(4.0)
    run.hover(1.0)
    run.hover(0.9, beacon=False)
    assert run.track_error(GLINT) < 0.1


def test_the_check_also_holds_with_a_loose_gate():
    run = _Run(6, HorizontalParams(use_accel_input=False, accel_psd_m2ps3=2.0))
    run.hover(0.2, glint=False)
    run.hover(1.0)
    run.follow(4.0)
    assert run.tr.events['switches'] == 1
    run.hover(1.0)
    run.hover(0.9, beacon=False)
    assert run.track_error(BEACON) < 0.15 and run.track_error(GLINT) > 0.5


def test_a_single_beacon_is_not_affected():
    """No rivals → no rejected rivals → the association is the plain nearest-NIS one."""
    a = _Run(7)
    b = _Run(7)

    def _never(*args):
        raise AssertionError('the rejected-rival check ran without rivals')

    b.tr._explained = _never
    a.hover(2.0, glint=False)
    b.hover(2.0, glint=False)
    assert a.tr.state(a.t) == b.tr.state(b.t)


@pytest.mark.parametrize('seed', [100031, 100035, 100037])
def test_the_former_edge_strikes_land_on_the_deck(seed):
    """The three runs of ``campaign --scenario fault_false_blobs --runs 40 --seed 1`` that
    struck the deck edge before the fix (simulated physics decides the outcome)."""
    from deck_simulator.scenario import load_scenario
    from deckland.batch.runner import RunConfig, run_landing
    res = run_landing(load_scenario('fault_false_blobs'), seed, RunConfig())
    assert res.outcome in ('deck', 'fallback', 'hold'), res.reason
    assert not res.crash
