"""Re-fly the README results: every built-in scenario, dob / pid / constant-rate, same seeds.

``python docs/results/refly.py [--runs N] [--seed 1] [--out JSON] [--only a,b] [--cores C]``
flies each campaign through `deckland.batch.campaign.run_campaign` with the deckland of the
interpreter that runs it (so the same script flies an older tree from that tree's venv),
writes one JSON and, when the other column exists, the old | new Markdown table
(`docs/results/world_refly_table.md`) and the README's results table between its markers.
``--only`` re-flies some campaigns and merges them into an existing JSON; ``table`` only
rewrites the tables from the two JSONs. The issue-12 record is docs/results/world_refly.md.
"""

from __future__ import annotations

import argparse
from collections import Counter
import json
import math
import os
import pathlib
import re
import subprocess
import sys
import time
from typing import Any

HERE = pathlib.Path(__file__).resolve().parent
NEW_JSON = HERE / 'world_refly.json'
OLD_JSON = HERE / 'world_refly_old.json'
TABLE_MD = HERE / 'world_refly_table.md'
README = HERE.parent.parent / 'README.md'
BEGIN, END = '<!-- refly:begin -->', '<!-- refly:end -->'
CONTROLLERS = ('dob', 'pid', 'constant-rate')
#: runs per campaign by default: 19 scenarios x 3 controllers x 60 runs = 3420 landings,
#: about 10 min on the 2-core machine with the compiled cores (docs/results/world_refly.md)
DEFAULT_RUNS = 60


def scenario_names() -> list[str]:
    """Every built-in scenario, the nominal ones first, then the ``fault_*``."""
    from deck_simulator.scenario import builtin_names
    return sorted(builtin_names(), key=lambda n: (n.startswith('fault_'), n))


def _stats(xs: list[float]) -> dict[str, float | None]:
    from deckland_common.stats import percentile
    xs = [x for x in xs if math.isfinite(x)]
    if not xs:
        return {'p50': None, 'p95': None, 'max': None}
    return {'p50': round(percentile(xs, 50.0), 4), 'p95': round(percentile(xs, 95.0), 4),
            'max': round(max(xs), 4)}


def reason_class(item: str) -> str:
    """One broken rule with its figures taken out ('impact 1.20 m/s > 1.00 at 3.1 s' ->
    'impact > crash speed'), so that runs can be counted by why they failed."""
    item = item.strip()
    for prefix, name in (('impact', 'impact > crash speed'), ('lateral', 'lateral > limit'),
                         ('tilt', 'tilt > limit'), ('touchdown speed', 'impact > crash speed'),
                         ('bounce ', 'bounce > limit')):
        if item.startswith(prefix):
            return name
    return re.sub(r'[-+]?\d+(\.\d+)?', '#', item)


def derived(results: list[Any]) -> dict[str, Any]:
    """What either tree's per-run results give, computed the same way for both: the
    first-contact normal speed over every run that touched (the old report censors it), the
    contact kinds, and the broken rules of the runs that did not succeed."""
    touched = [r for r in results if r.contact_kind != 'none']
    reasons: Counter[str] = Counter()
    for r in results:
        if not r.success:
            for item in {reason_class(x) for x in (r.reason or 'no reason').split(';')}:
                reasons[item] += 1
    return {
        'first_contact_runs': len(touched),
        'first_contact_normal_speed_mps': _stats([r.touchdown_speed_mps for r in touched]),
        'contact_kinds': dict(sorted(Counter(r.contact_kind for r in results).items())),
        'failure_reasons': dict(reasons.most_common()),
        'successes': sum(bool(r.success) for r in results),
    }


def tree() -> dict[str, str]:
    """The commit of the deckland being flown (the interpreter's, not this file's)."""
    import deckland
    src = pathlib.Path(deckland.__file__).resolve().parent
    try:
        head = subprocess.run(['git', '-C', str(src), 'rev-parse', '--short', 'HEAD'],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(['git', '-C', str(src), 'status', '--porcelain',
                                '--untracked-files=no'],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        head, dirty = 'unknown', ''
    return {'commit': head + ('+dirty' if dirty else ''), 'path': str(src.parent.parent.parent)}


def fly(args: argparse.Namespace) -> dict[str, Any]:
    from deckland.batch import accel
    cores = accel.enable(args.cores)   # before anything imports a core module
    from deckland.batch.backends import LocalPool
    from deckland.batch.campaign import run_campaign
    from deckland.batch.runner import RunConfig

    names = scenario_names()
    only = set(args.only.split(',')) if args.only else None
    out = pathlib.Path(args.out)
    doc: dict[str, Any] = {'campaigns': {}}
    if only and out.exists():
        doc = json.loads(out.read_text('utf-8'))
    pool = LocalPool(args.workers)
    start = time.perf_counter()
    load0 = os.getloadavg()[0]
    for name in names:
        for controller in CONTROLLERS:
            key = f'{name}/{controller}'
            if only and not (name in only or key in only):
                continue
            t0 = time.perf_counter()
            report, results = run_campaign(name, args.runs, args.seed,
                                           RunConfig(controller=controller), progress=False,
                                           backend=pool)
            report['derived'] = derived(results)
            doc['campaigns'][key] = report
            _write(out, doc, args, names, pool.workers, cores, start, load0, only, False)
            ok = report['derived']['successes']
            sys.stderr.write(f'{key:<36} {ok:>4}/{report["runs"]} success  '
                             f'{time.perf_counter() - t0:6.1f} s\n')
    pool.close()
    _write(out, doc, args, names, pool.workers, cores, start, load0, only, True)
    sys.stderr.write(f'wrote {out} ({doc["meta"]["wall_time_s"]} s)\n')
    return doc


def _write(out: pathlib.Path, doc: dict[str, Any], args: argparse.Namespace, names: list[str],
           workers: int, cores: str, start: float, load0: float, only: set[str] | None,
           complete: bool) -> None:
    """Write ``doc`` after every campaign (``complete`` false until the last): an
    interrupted re-fly keeps what it flew."""
    doc['meta'] = {
        'seed': args.seed, 'runs': args.runs, 'tree': tree(), 'cores': cores,
        'workers': workers, 'wall_time_s': round(time.perf_counter() - start, 1),
        'load_before': round(load0, 2), 'scenarios': names, 'complete': complete,
        'command': 'python docs/results/refly.py ' + ' '.join(sys.argv[1:]),
    }
    if only:
        doc['meta']['merged'] = sorted(only)
    doc['campaigns'] = dict(sorted(doc['campaigns'].items(), key=lambda kv: (
        names.index(kv[0].split('/')[0]) if kv[0].split('/')[0] in names else len(names),
        CONTROLLERS.index(kv[0].split('/')[1]))))
    tmp = out.with_suffix('.tmp')
    tmp.write_text(json.dumps(doc, indent=1) + '\n', encoding='utf-8')
    tmp.replace(out)


# --- tables -------------------------------------------------------------------------------

def _pct(x: float | None) -> str:
    return '—' if x is None else f'{100 * x:.1f}'


def _num(x: float | None, digits: int = 2) -> str:
    return '—' if x is None else f'{x:.{digits}f}'


def _get(report: dict[str, Any] | None, *path: str) -> Any:
    cur: Any = report
    for p in path:
        if not isinstance(cur, dict) or p not in cur:
            return None
        cur = cur[p]
    return cur


def success_cell(r: dict[str, Any] | None) -> str:
    if r is None:
        return '—'
    ci = r.get('success_ci95')
    if ci is None:   # the old report has no interval: Wilson of its own count
        from deckland_common.stats import wilson_interval
        ci = wilson_interval(r['derived']['successes'], r['runs'])
    return f'{_pct(r["success_rate"])} ({_pct(ci[0])}–{_pct(ci[1])})'


def classes_cell(r: dict[str, Any] | None) -> str:
    if r is None:
        return '—'
    short = {'deck': 'd', 'failed': 'f', 'fallback': 'g', 'hold': 'h', 'crash': 'c',
             'unstable': 'u'}
    return ' '.join(f'{short[k]}{v}' for k, v in r['outcomes'].items() if v and k in short)


def triple(stats: dict[str, Any] | None, digits: int = 2, scale: float = 1.0) -> str:
    if not stats or stats.get('p50') is None:
        return '—'
    return ' / '.join(_num(None if stats.get(k) is None else stats[k] * scale, digits)
                      for k in ('p50', 'p95', 'max'))


def first_normal(r: dict[str, Any] | None) -> dict[str, Any] | None:
    """Uncensored first-contact normal speed: the report's, else the derived one (old)."""
    return _get(r, 'first_contact', 'normal_speed_mps') or _get(
        r, 'derived', 'first_contact_normal_speed_mps')


def rows(old: dict[str, Any], new: dict[str, Any]) -> list[tuple[str, str, Any, Any]]:
    names = list(new['meta']['scenarios']) + [
        n for n in old['meta']['scenarios'] if n not in new['meta']['scenarios']]
    keys = sorted(set(new['campaigns']) | set(old['campaigns']), key=lambda k: (
        names.index(k.split('/')[0]), CONTROLLERS.index(k.split('/')[1])))
    out = []
    for key in keys:
        name, controller = key.split('/')
        out.append((name, controller, old['campaigns'].get(key), new['campaigns'].get(key)))
    return out


def full_table(old: dict[str, Any], new: dict[str, Any]) -> str:
    deg = 180.0 / math.pi
    head = ('| scenario | ctrl | success % (95 % CI) old → new | classes old → new | '
            '1st-contact normal p50/p95/max [m/s] old → new | lateral p50/p95/max [m/s] | '
            'tilt p50/p95/max [°] | bounce runs | later impacts (runs) | '
            'error p50/p95 [m] old → new | time p50/p95 [s] old → new |')
    lines = [head, '|' + ' --- |' * 11]
    for name, ctrl, o, n in rows(old, new):
        def err(r):
            s = _get(r, 'horizontal_error_m')
            return '—' if not s or s.get('p50') is None else (
                f'{_num(s["p50"], 3)} / {_num(s["p95"], 3)}')

        def tl(r):
            s = _get(r, 'time_to_land_s')
            return '—' if not s or s.get('p50') is None else (
                f'{_num(s["p50"], 1)} / {_num(s["p95"], 1)}')
        lines.append(
            f'| {name} | {ctrl} | {success_cell(o)} → {success_cell(n)} | '
            f'{classes_cell(o)} → {classes_cell(n)} | '
            f'{triple(first_normal(o))} → {triple(first_normal(n))} | '
            f'{triple(_get(n, "first_contact", "lateral_speed_mps"))} | '
            f'{triple(_get(n, "first_contact", "tilt_rad"), 1, deg)} | '
            f'{_get(n, "bounces", "runs") if n else "—"} | '
            f'{_get(n, "impacts", "runs_with_later_impacts") if n else "—"} | '
            f'{err(o)} → {err(n)} | {tl(o)} → {tl(n)} |')
    return '\n'.join(lines)


def reasons_table(new: dict[str, Any]) -> str:
    lines = ['| campaign | runs not successful | broken rules (runs) |', '| --- | --- | --- |']
    for key, r in new['campaigns'].items():
        fails = r['runs'] - r['derived']['successes']
        if fails:
            why = ', '.join(f'{k} {v}' for k, v in r['derived']['failure_reasons'].items())
            lines.append(f'| {key} | {fails} | {why} |')
    return '\n'.join(lines)


def readme_table(old: dict[str, Any], new: dict[str, Any]) -> str:
    head = ('| scenario | controller | success % (95 % CI) old → new | classes old → new | '
            '1st-contact normal p95 / max [m/s] old → new | lateral p95 [m/s] | tilt p95 [°] | '
            'error p95 [m] old → new | time p50 [s] old → new |')
    lines = [head, '|' + ' --- |' * 9]
    for name, ctrl, o, n in rows(old, new):
        def p95max(r):
            s = first_normal(r)
            return '—' if not s or s.get('p95') is None else (
                f'{_num(s["p95"])} / {_num(s["max"])}')
        tilt = _get(n, 'first_contact', 'tilt_rad', 'p95')
        lines.append(
            f'| {name} | {ctrl} | {success_cell(o)} → {success_cell(n)} | '
            f'{classes_cell(o)} → {classes_cell(n)} | {p95max(o)} → {p95max(n)} | '
            f'{_num(_get(n, "first_contact", "lateral_speed_mps", "p95"))} | '
            f'{_num(None if tilt is None else math.degrees(tilt), 1)} | '
            f'{_num(_get(o, "horizontal_error_m", "p95"), 3)} → '
            f'{_num(_get(n, "horizontal_error_m", "p95"), 3)} | '
            f'{_num(_get(o, "time_to_land_s", "p50"), 1)} → '
            f'{_num(_get(n, "time_to_land_s", "p50"), 1)} |')
    return '\n'.join(lines)


def _meta_line(doc: dict[str, Any], label: str) -> str:
    m = doc['meta']
    return (f'{label}: tree `{m["tree"]["commit"]}`, {m["runs"]} runs per campaign, seed '
            f'{m["seed"]}, {m["cores"]} cores, {m["workers"]} workers, {m["wall_time_s"]} s')


def write_tables(old_path: pathlib.Path, new_path: pathlib.Path,
                 readme: pathlib.Path | None) -> None:
    old = json.loads(old_path.read_text('utf-8'))
    new = json.loads(new_path.read_text('utf-8'))
    legend = ('classes: d deck (success), f failed (landed, a rule broken), g fallback '
              '(ground), h hold, c crash, u unstable. Old first-contact speeds are derived from '
              "the old runs' per-run records (the old report had them over pad landings only); "
              'lateral, tilt, bounces and impacts exist in the new world only; error is over '
              'the successes; — = not in that report (or no such scenario).')
    text = '\n\n'.join([
        '# World re-fly: old | new (generated by docs/results/refly.py; do not edit)',
        _meta_line(old, 'old') + '  \n' + _meta_line(new, 'new'), legend,
        full_table(old, new), '## Why the runs that did not succeed failed (new world)',
        reasons_table(new)]) + '\n'
    TABLE_MD.write_text(text, encoding='utf-8')
    sys.stderr.write(f'wrote {TABLE_MD}\n')
    if readme is None or not readme.exists():
        return
    body = readme.read_text('utf-8')
    if BEGIN not in body or END not in body:
        sys.stderr.write(f'{readme}: no {BEGIN} / {END} markers, README table not written\n')
        return
    pre, rest = body.split(BEGIN, 1)
    _, post = rest.split(END, 1)
    table = (f'{BEGIN}\n{_meta_line(old, "old")}; {_meta_line(new, "new")}.\n\n'
             f'{readme_table(old, new)}\n{END}')
    readme.write_text(pre + table + post, encoding='utf-8')
    sys.stderr.write(f'wrote the results table into {readme}\n')


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('mode', nargs='?', choices=('fly', 'table'), default='fly')
    ap.add_argument('--runs', type=int, default=DEFAULT_RUNS)
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--out', default=str(NEW_JSON), help='the JSON this run writes')
    ap.add_argument('--old', default=str(OLD_JSON), help='the old column (for the tables)')
    ap.add_argument('--only', help='comma-separated scenarios or scenario/controller keys to '
                    're-fly and merge into --out')
    ap.add_argument('--workers', type=int, default=0, help='processes (default: all cores)')
    ap.add_argument('--cores', default='compiled', choices=('auto', 'compiled', 'python'))
    ap.add_argument('--no-table', action='store_true', help='write the JSON only')
    args = ap.parse_args(argv)
    if args.mode == 'fly':
        if args.runs < 1:
            ap.error(f'--runs must be >= 1, got {args.runs}')
        fly(args)
    old, new = pathlib.Path(args.old), pathlib.Path(args.out)
    if not args.no_table and old.exists() and new.exists() and old != new:
        write_tables(old, new, README if new.resolve() == NEW_JSON else None)
    return 0


if __name__ == '__main__':
    sys.exit(main())
