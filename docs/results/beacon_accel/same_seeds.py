"""Before/after of this stop's only in-process behaviour change (deck acceleration D6), same
seeds: 'before' = beacon_accel True (the tree at c2e1d78), 'after' = the default. Python
cores, one worker (the patch must reach the runs)."""
import dataclasses
import json
import os
import sys

os.environ['DECKLAND_CORES'] = 'python'

import apron_estimator.deck as deck
from deckland.batch.campaign import run_campaign
from deckland.batch.runner import RunConfig

variant, scen, runs = sys.argv[1], sys.argv[2], int(sys.argv[3])
if variant == 'before':
    @dataclasses.dataclass(frozen=True)
    class Before(deck.DeckFusionParams):
        beacon_accel: bool = True
    deck.DeckFusionParams = Before
rep, _ = run_campaign(scen, runs, 1, RunConfig(controller='dob'), workers=1, progress=False)
keep = ('scenario', 'runs', 'success_rate', 'success_ci95', 'outcomes', 'first_contact',
        'horizontal_error_m', 'time_to_land_s')
print(json.dumps({'variant': variant, **{k: rep.get(k) for k in keep}}))
