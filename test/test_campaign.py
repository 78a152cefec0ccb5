"""The in-process closed loop and the campaign tool: the paper scenario lands, reproducibly."""

import json
import math
import os

from deck_simulator.scenario import load_scenario
from deckland.backends import CampaignError, LocalPool, run_chunk
from deckland.campaign import format_table, run_campaign, run_seed, summarize
from deckland.cli import main as cli_main
from deckland.runner import RunConfig, RunResult, run_landing
import pytest


def test_paper_campaign_lands_every_run():
    """A small campaign in CI: the paper mission lands on the pad, softly and accurately."""
    report, results = run_campaign('paper', 6, 11, RunConfig(), workers=2, progress=False)
    assert report['runs'] == 6
    assert report['success_rate'] == 1.0, report['failures']
    assert report['crash_rate'] == 0.0
    # the crash limit is 1.0 m/s; a final approach of 0.08 m/s relative lands far below it
    assert report['touchdown_speed_mps']['max'] < 0.5
    # the pad is 1.05 x 0.85 m; precision landing puts the vehicle within centimetres
    assert report['horizontal_error_m']['max'] < 0.15
    assert all(r.final_mode == 'LANDED' for r in results)


def test_same_seed_same_report_different_seed_different_flight():
    config = RunConfig()
    a, _ = run_campaign('paper', 3, 5, config, workers=1, progress=False)
    b, _ = run_campaign('paper', 3, 5, config, workers=2, progress=False)
    for report in (a, b):   # how it was run, not what was flown
        for key in ('wall_time_s', 'realtime_factor', 'realtime_factor_per_worker', 'workers'):
            report.pop(key)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    scenario = load_scenario('paper')
    r1 = run_landing(scenario, run_seed(5, 0), config)
    r2 = run_landing(scenario, run_seed(5, 1), config)
    assert (r1.touchdown_speed_mps, r1.horizontal_error_m) != (
        r2.touchdown_speed_mps, r2.horizontal_error_m)


def test_a_failure_is_reproduced_alone_from_its_seed():
    """The seed printed for a run flies the identical run through `deckland sim`."""
    scenario = load_scenario('paper')
    seed = run_seed(3, 2)
    _, results = run_campaign('paper', 3, 3, RunConfig(), workers=1, progress=False)
    alone = run_landing(scenario, seed, RunConfig())
    assert results[2].seed == seed
    assert results[2].summary() == alone.summary()


def _dies_in_chunk_1(chunk):
    if chunk.index == 1:
        os._exit(1)     # a worker killed mid-campaign (OOM killer, kill -9)
    return run_chunk(chunk)


def test_a_local_worker_that_dies_fails_the_campaign_naming_its_seeds():
    """The pool breaks instead of hanging; the report never silently lacks the runs."""
    pool = LocalPool(2, chunk_fn=_dies_in_chunk_1)
    with pytest.raises(CampaignError, match=r'worker died') as info:
        run_campaign('paper', 4, 2, RunConfig(), progress=False, backend=pool, chunk=2)
    assert 'seeds 200002..200003 (chunk 1)' in str(info.value)


def test_deck_blind_baseline_lands_harder_than_the_deck_relative_descent():
    """constant-rate descends at 0.5 m/s in the world frame, blind to the deck."""
    config = RunConfig(controller='constant-rate')
    report, _ = run_campaign('paper', 3, 2, config, workers=1, progress=False)
    assert report['touchdown_speed_mps']['p50'] > 0.35


def test_summary_statistics_and_json_shape():
    results = [
        RunResult(seed=i, scenario='s', controller='dob', landed_on_deck=True, success=True,
                  contact_kind='pad', horizontal_error_m=0.01 * i, touchdown_speed_mps=0.1 * i,
                  time_to_land_s=10.0 + i, sim_time_s=11.0 + i, outcome='deck')
        for i in range(1, 5)
    ] + [RunResult(seed=9, scenario='s', controller='dob', contact_kind='ground',
                   fallback=True, time_to_land_s=50.0, sim_time_s=50.0, reason='fallback',
                   outcome='fallback')]
    report = summarize(results, 's', 'dob', 1, wall_time_s=2.0)
    assert report['success_rate'] == pytest.approx(0.8)
    assert report['fallback_rate'] == pytest.approx(0.2)
    # percentiles over the pad landings only (numpy's linear interpolation)
    assert report['horizontal_error_m']['p50'] == pytest.approx(0.025)
    assert report['touchdown_speed_mps']['max'] == pytest.approx(0.4)
    assert report['realtime_factor'] == pytest.approx((12 + 13 + 14 + 15 + 50) / 2.0)
    assert report['failures'] == [{'seed': 9, 'reason': 'fallback', 'outcome': 'fallback'}]
    assert report['outcomes'] == {'deck': 4, 'fallback': 1, 'hold': 0, 'crash': 0,
                                  'unstable': 0}
    for key in ('scenario', 'controller', 'runs', 'seed', 'success_rate', 'fallback_rate',
                'crash_rate', 'horizontal_error_m', 'touchdown_speed_mps', 'time_to_land_s',
                'wall_time_s', 'realtime_factor', 'failures', 'outcomes'):
        assert key in report
    json.dumps(report, allow_nan=False)
    assert 'success' in format_table([report])


def test_cli_campaign_writes_the_report(tmp_path):
    out = tmp_path / 'report.json'
    status = cli_main(['campaign', '--scenario', 'paper', '--runs', '2', '--seed', '4',
                       '--workers', '1', '--quiet', '--out', str(out),
                       '--plots', str(tmp_path / 'plots')])
    assert status == 0
    report = json.loads(out.read_text())
    assert report['runs'] == 2 and report['scenario'] == 'paper'
    assert math.isfinite(report['realtime_factor'])
    assert (tmp_path / 'plots' / 'paper_touchdown_speed_mps.png').stat().st_size > 1000
