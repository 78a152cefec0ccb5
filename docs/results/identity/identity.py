"""The renovation's identity check (issue 11): fly `paper`, `gusty`, `sea_state_4` and every
`fault_*` built-in, 40 runs, seed 1, all three controllers, and write each report (minus the
keys that say how it was run) with a digest of its per-run summaries; `--compare A B` lists the
cells whose report or runs differ. Flown in this process on the Python cores (the same on both
sides)."""
import argparse
import hashlib
import json
from pathlib import Path
import sys

from deck_simulator.scenario import builtin_names
from deckland.batch.campaign import HOW_RUN_KEYS, run_campaign
from deckland.batch.runner import CONTROLLERS, RunConfig


def scenarios() -> list[str]:
    return ['paper', 'gusty', 'sea_state_4', *sorted(
        s for s in builtin_names() if s.startswith('fault_'))]


def fly(out: Path, runs: int) -> None:
    cells = {}
    for scen in scenarios():
        for ctl in CONTROLLERS:
            rep, results = run_campaign(scen, runs, 1, RunConfig(controller=ctl), progress=False)
            runs_json = json.dumps([r.summary() for r in results], sort_keys=True)
            cells[f'{scen}/{ctl}'] = {
                'report': {k: v for k, v in rep.items() if k not in HOW_RUN_KEYS},
                'runs_sha256': hashlib.sha256(runs_json.encode()).hexdigest()}
            print(scen, ctl, rep['success_rate'], flush=True)
    out.write_text(json.dumps(cells, indent=1, sort_keys=True) + '\n')


def compare(a: Path, b: Path) -> int:
    ca, cb = json.loads(a.read_text()), json.loads(b.read_text())
    diff = sorted(k for k in set(ca) | set(cb) if ca.get(k) != cb.get(k))
    print(f'{len(ca)} vs {len(cb)} cells; {len(diff)} differ' + ''.join(f'\n  {k}' for k in diff))
    return 1 if diff else 0


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('--out', type=Path)
    ap.add_argument('--runs', type=int, default=40)
    ap.add_argument('--compare', nargs=2, type=Path)
    args = ap.parse_args()
    sys.exit(compare(*args.compare) if args.compare else fly(args.out, args.runs))
