"""The issue-13 planner table from docs/results/planner_<scenario>_<ctrl>.json (markdown).

`.venv/bin/python docs/results/planner_table.py` prints it; the JSONs come from
`deckland campaign --scenario S --runs 20 --seed 1 --controller C --out ...`.
"""

import json
import pathlib

HERE = pathlib.Path(__file__).parent


def row(path: pathlib.Path) -> str:
    r = json.loads(path.read_text())
    lo, hi = r['success_ci95']
    o = r['outcomes']
    classes = ', '.join(f'{k} {v}' for k, v in o.items() if v)
    fc = r['first_contact']['normal_speed_mps']
    t = r['time_to_land_s']['p50']
    return (f"| {r['scenario']} | {r['controller']} | {r['runs']} | "
            f"{100 * r['success_rate']:.1f} ({100 * lo:.1f}–{100 * hi:.1f}) | {classes} | "
            f"{o.get('crash', 0)} | {fc['p95']:.3f} / {fc['max']:.3f} | {t:.1f} |")


def main() -> None:
    print('| scenario | ctrl | runs | success % (95 % Wilson) | classes | crashes | '
          '1st-contact normal p95 / max [m/s] | time to land p50 [s] |')
    print('| --- | --- | --- | --- | --- | --- | --- | --- |')
    for sc in ('paper', 'paper_translating', 'ship_ss3'):
        for c in ('dob', 'pid'):
            p = HERE / f'planner_{sc}_{c}.json'
            if p.exists():
                print(row(p))


if __name__ == '__main__':
    main()
