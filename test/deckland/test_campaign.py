"""The in-process closed loop and the campaign tool: the paper scenario lands, reproducibly."""

import json
import math
import os

from deck_simulator.scenario import load_scenario
from deckland.batch.backends import CampaignError, LocalPool, run_chunk
from deckland.batch.campaign import format_table, run_campaign, run_seed, summarize
from deckland.batch.runner import RunConfig, RunResult, run_landing
from deckland.cli import main as cli_main
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


def landed(i, **kw):
    base = {'seed': i, 'scenario': 's', 'controller': 'dob', 'landed_on_deck': True,
            'success': True, 'contact_kind': 'pad', 'horizontal_error_m': 0.01 * i,
            'touchdown_speed_mps': 0.1 * i, 'lateral_speed_mps': 0.02 * i,
            'tilt_rad': 0.01 * i, 'impacts': 1, 'max_impact_speed_mps': 0.1 * i,
            'bounces': 0, 'settled': True, 'time_to_land_s': 10.0 + i,
            'sim_time_s': 11.0 + i, 'outcome': 'deck'}
    base.update(kw)
    return RunResult(**base)


def test_summary_statistics_and_json_shape():
    results = [landed(i) for i in range(1, 5)] + [
        RunResult(seed=9, scenario='s', controller='dob', contact_kind='ground',
                  fallback=True, touchdown_speed_mps=0.5, lateral_speed_mps=0.0, tilt_rad=0.0,
                  impacts=1, max_impact_speed_mps=0.5, settled=True, time_to_land_s=50.0,
                  sim_time_s=50.0, reason='fallback', outcome='fallback')]
    report = summarize(results, 's', 'dob', 1, wall_time_s=2.0)
    assert report['success_rate'] == pytest.approx(0.8)
    assert report['fallback_rate'] == pytest.approx(0.2)
    # percentiles over the pad landings only (numpy's linear interpolation)
    assert report['horizontal_error_m']['p50'] == pytest.approx(0.025)
    assert report['touchdown_speed_mps']['max'] == pytest.approx(0.4)
    assert report['realtime_factor'] == pytest.approx((12 + 13 + 14 + 15 + 50) / 2.0)
    assert report['failures'] == [{'seed': 9, 'reason': 'fallback', 'outcome': 'fallback'}]
    assert report['outcomes'] == {'deck': 4, 'failed': 0, 'fallback': 1, 'hold': 0,
                                  'crash': 0, 'unstable': 0}
    # the first contact over every run that touched: the fallback's 0.5 m/s is the max
    assert report['first_contact']['runs'] == 5
    assert report['first_contact']['normal_speed_mps']['max'] == pytest.approx(0.5)
    assert report['first_contact']['normal_speed_mps']['p50'] == pytest.approx(0.3)
    assert report['first_contact']['lateral_speed_mps']['max'] == pytest.approx(0.08)
    for key in ('scenario', 'controller', 'runs', 'seed', 'success_rate', 'fallback_rate',
                'crash_rate', 'horizontal_error_m', 'touchdown_speed_mps', 'time_to_land_s',
                'wall_time_s', 'realtime_factor', 'failures', 'outcomes', 'success_ci95',
                'first_contact', 'impacts', 'bounces', 'settled_rate'):
        assert key in report
    json.dumps(report, allow_nan=False)
    table = format_table([report])
    assert 'success' in table and '95 % interval' in table and '1st normal max' in table


def test_report_is_uncensored_and_the_success_rate_has_its_wilson_interval():
    """A hard bounce that a first-contact-only score would call a landing counts as what it
    is; the interval is Wilson's (4 of 5: 37.6-96.4 %, 100 of 100: 96.3-100 %)."""
    results = [landed(i) for i in range(1, 5)] + [
        landed(7, success=False, landed_on_deck=False, crash=True, touchdown_speed_mps=0.3,
               impacts=3, max_impact_speed_mps=1.4, bounces=2, max_bounce_height_m=0.12,
               settled=False, outcome='crash', reason='impact 1.40 m/s > 1.00 at 12.30 s')]
    report = summarize(results, 's', 'dob', 1, wall_time_s=1.0)
    assert report['crash_rate'] == pytest.approx(0.2) and report['outcomes']['crash'] == 1
    assert report['impacts'] == {'runs_with_later_impacts': 1, 'later_impacts': 2,
                                 'max_speed_mps': report['impacts']['max_speed_mps']}
    assert report['impacts']['max_speed_mps']['max'] == pytest.approx(1.4)
    assert report['bounces']['runs'] == 1 and report['bounces']['total'] == 2
    assert report['bounces']['max_height_m']['max'] == pytest.approx(0.12)
    assert report['settled_rate'] == pytest.approx(0.8)
    assert report['touchdown_speed_mps']['max'] == pytest.approx(0.4)   # successes only
    assert report['success_ci95'] == pytest.approx([0.3755, 0.9638], abs=1e-4)
    many = summarize([landed(1)] * 100, 's', 'dob', 1, wall_time_s=1.0)
    assert many['success_ci95'] == pytest.approx([0.963, 1.0], abs=1e-3)


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
