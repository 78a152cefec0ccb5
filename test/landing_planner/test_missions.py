"""Whole missions in the in-process runner on the moving-deck built-ins (issue 13), a few seeds.

The full simulator and stack (estimator, planner, DOB altitude loop): the planner must land on
the translating paper apron when it sees it, and never put the vehicle into the sea beside a
ship it has tracked (the Step 14 refusal), whatever else happens.
"""

from __future__ import annotations

from deck_simulator.scenario import load_scenario
from deckland.batch.runner import RunConfig, run_landing
import pytest


def test_the_translating_apron_seen_at_the_start_is_intercepted_and_landed_on():
    # seed 100001: the beacon comes into view 1.9 s after the start, 1.5 m from the area; the
    # deck then moves 0.5 m/s east for another 20 s while the planner tracks and lands on it
    r = run_landing(load_scenario('paper_translating'), 100001, RunConfig(controller='dob'))
    assert r.outcome == 'deck' and r.landed_on_deck
    assert r.touchdown_speed_mps <= 0.2
    assert r.lateral_speed_mps <= 0.15         # velocity matched (0.5 m/s deck)
    assert r.horizontal_error_m <= 0.1


@pytest.mark.parametrize('seed', [100000, 100002, 100003])
def test_a_ship_underway_never_ends_in_the_sea(seed):
    # before the Step 14 refusal seed 100002 (track lost at 2 s, searches used up, the track
    # timed out) landed in the water 230 m astern of the ship
    r = run_landing(load_scenario('ship_ss3'), seed, RunConfig(controller='dob'))
    assert not r.crash and r.contact_kind != 'water', (r.outcome, r.reason)
    assert r.outcome in ('deck', 'failed', 'hold')


def test_a_beacon_first_seen_beside_a_raised_heaving_deck_is_not_chased_off():
    # sea_state_4 seed 100036 (stop 24): acquired 1.7 m off a deck at rest, 1 m above the
    # ground, the young track read 0.8 m/s of deck motion (the estimator's start "moving with
    # the vehicle" and the camera's scale error beside the deck); ALIGN chased it, lost the
    # beacon and searched along the phantom's track for 150 s. Now it lands.
    r = run_landing(load_scenario('sea_state_4'), 100036, RunConfig(controller='dob'))
    assert r.outcome == 'deck' and r.landed_on_deck, r.reason
    assert r.time_to_land_s < 60.0
