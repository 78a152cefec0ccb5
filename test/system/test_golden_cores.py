"""Golden bag, pure replay: the recorded `paper` landing through the cores (no ROS).

The replay must reproduce the recorded outputs within CORE_TOLERANCES, and deliberately
changed cores (a gain, a sign) must fail the same comparison: the tolerances catch a change.
"""

from dataclasses import replace
import math
from pathlib import Path

from apron_estimator.estimator import EstimatorParams
from apron_estimator.vertical import VerticalParams
from dob_altitude.dob import DobParams
import golden
from landing_planner.horizontal import HorizontalController, HorizontalParams
import pytest

from dob_altitude import adapter

BAG = Path(__file__).parents[1] / 'fixtures' / 'golden_paper'


@pytest.fixture(scope='module')
def gold():
    return golden.load(BAG)


@pytest.fixture(scope='module')
def recorded(gold):
    return golden.recorded_outputs(gold)


def _report(gold, recorded, make=None, meta=None):
    g = gold if meta is None else golden.Golden(gold.path, meta, gold.events)
    return golden.compare(recorded, golden.replay_cores(g, make), golden.CORE_TOLERANCES)


def test_fixture_is_small_complete_and_has_explicit_qos(gold):
    from deckland.ros.bag import bag_info

    size = sum(p.stat().st_size for p in BAG.iterdir())
    assert size <= golden.MAX_BAG_BYTES
    info = bag_info(BAG, recover=False)
    topics = {t.name: t for t in info.topics}
    assert set(topics) - set(golden.INPUT_TOPICS) in (set(golden.OUTPUT_TOPICS),
                                                      set(golden.LEGACY_OUTPUT_TOPICS))
    for t in topics.values():
        assert t.offered_qos, f'{t.name}: no offered QoS stored'
    assert topics['/planner/mode'].offered_qos[0].durability.name == 'TRANSIENT_LOCAL'
    # a whole landing, first input to touchdown, and ~100 Hz commands
    assert 8.0 < info.duration_s < 40.0
    assert topics['/control/thrust'].count > 60 * info.duration_s
    assert gold.meta['scenario'] == 'paper' and gold.meta['outcome']['success']
    modes = [e.data[0] for e in gold.events if e.kind == 'mode']
    assert golden.mode_sequence([(0.0, m) for m in modes])[:2] == ['IDLE', 'APPROACH']


def test_pure_replay_reproduces_the_recording(gold, recorded):
    report = _report(gold, recorded)
    assert report.ok, '\n' + str(report)
    # the landing's mode sequence is the recorded one, each change within two ticks
    rec = [(t, m) for t, m in recorded.modes if m != 'IDLE']
    rep = golden.replay_cores(gold).modes
    assert [m for _, m in rep] == [m for _, m in rec]
    for (ta, _), (tb, _) in zip(rec, rep, strict=True):
        assert abs(ta - tb) <= 0.025


def test_dob_gain_change_is_caught(gold, recorded):
    meta = dict(gold.meta)
    meta['parameters'] = {**gold.meta['parameters'],
                          'dob_altitude': {'k': DobParams.profile('default').k * 1.2}}
    report = _report(gold, recorded, meta=meta)
    assert any(f.startswith('FAIL thrust') for f in report.failures), str(report)


def test_dob_sign_error_is_caught(gold, recorded, monkeypatch):
    real = adapter.altitude_input

    def flipped(vertical, *args, **kwargs):
        inp = real(vertical, *args, **kwargs)
        return replace(inp, z_dot_mps=-inp.z_dot_mps)   # closing speed with the wrong sign

    monkeypatch.setattr(adapter, 'altitude_input', flipped)
    report = _report(gold, recorded)
    assert any(f.startswith('FAIL thrust') for f in report.failures), str(report)


def test_horizontal_gain_change_is_caught(gold, recorded):
    def make(meta):
        est, planner, _, ctrl = golden.make_cores(meta)
        hp = HorizontalParams()
        return est, planner, HorizontalController(replace(hp, kp=hp.kp * 1.2)), ctrl

    report = _report(gold, recorded, make)
    assert any(f.startswith('FAIL attitude roll/pitch') for f in report.failures), str(report)


def test_estimator_change_is_caught(gold, recorded):
    def make(meta):
        from apron_estimator.estimator import ApronEstimator

        _, planner, horizontal, ctrl = golden.make_cores(meta)
        vp = VerticalParams()
        params = EstimatorParams(vertical=replace(vp, sigma_lidar_m=vp.sigma_lidar_m * 2.0))
        return ApronEstimator(params), planner, horizontal, ctrl

    out = golden.replay_estimator(gold, make=make)
    replayed = golden.Replay(apron=out.apron)
    report = golden.compare(recorded, replayed, golden.CORE_TOLERANCES)
    assert any(f.startswith('FAIL apron') for f in report.failures), str(report)


def test_node_defaults_mirrored():
    """The replay's copy of the nodes' parameters equals the nodes' declared defaults."""
    from apron_estimator.node import PARAMS as EST
    from dob_altitude.node import PARAMS as DOB
    from landing_planner.node import PARAMS as PLAN

    for node, specs in (('apron_estimator', EST), ('landing_planner', PLAN),
                        ('dob_altitude', DOB)):
        declared = {s.name: s.default for s in specs}
        for name, value in golden.NODE_DEFAULTS[node].items():
            assert declared[name] == value, f'{node}.{name}'


def test_shifted_copy_moves_stamps_only(tmp_path, gold):
    n = golden.shifted_copy(BAG, tmp_path / 'play', 5_000_000_000, gate=True)
    shifted = golden.load_events(tmp_path / 'play')
    imu = [e for e in gold.events if e.kind == 'imu']
    imu2 = [e for e in shifted if e.kind == 'imu']
    assert n == sum(1 for e in gold.events if e.kind in
                    ('imu', 'odom', 'velocity', 'range', 'blocks', 'landed'))
    assert len(imu) == len(imu2)
    for a, b in zip(imu, imu2, strict=True):
        assert b.t_ns - a.t_ns == 5_000_000_000
        assert math.isclose(b.data[0] - a.data[0], 5.0, abs_tol=1e-6)
        assert a.data[1:] == b.data[1:]


def test_load_rejects_a_plain_bag(tmp_path):
    with pytest.raises(FileNotFoundError, match='golden'):
        golden.load(tmp_path)
