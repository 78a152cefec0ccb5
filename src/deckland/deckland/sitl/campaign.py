"""``deckland campaign --autopilot NAME``: seeded missions through a registered firmware.

More in the package README, "Module notes" (`deckland.sitl.campaign`).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time
from typing import Any

from deck_simulator.outcome import RunOutcome

#: PX4 mode names of the offboard-loss actions (COM_OBL_RC_ACT)
SAFE_ACTION_MODES = {3: 'AUTO.RTL', 4: 'AUTO.LAND', 5: 'AUTO.LOITER'}
def add_arguments(p: argparse.ArgumentParser) -> None:
    """The SITL options of ``deckland campaign`` (used with ``--autopilot px4-sitl``)."""
    from deckland.sitl import SITL_AUTOPILOTS
    p.add_argument('--autopilot', choices=('in-process', *SITL_AUTOPILOTS),
                   default='in-process',
                   help="a firmware (e.g. px4-sitl): every run a 'deckland up --autopilot "
                   "NAME' mission, one after another in real time (deckland.sitl.campaign)")
    p.add_argument('--mission-timeout', type=float, default=120.0,
                   help='px4-sitl: mission timeout after the landing trigger [s]')
    p.add_argument('--retries', type=int, default=2,
                   help='px4-sitl: fly a seed again when PX4 did not come up or the world '
                   'stalled (the machine, not the stack)')
    p.add_argument('--max-stalls', type=int, default=5,
                   help='px4-sitl: world stalls (> 0.1 s behind the wall clock) in a mission '
                   'above which it counts as spoiled by the machine')
    p.add_argument('--keep-runs', help="px4-sitl: keep each mission's report and log here")


def outcome_from_report(seed: int, scenario: str, report: dict[str, Any]) -> RunOutcome:
    """A mission's ``report.json`` as the campaign's per-run record (missing numbers NaN; a
    mission that never flew has outcome ``'no_run'``)."""
    fields = {f.name for f in dataclasses.fields(RunOutcome)}
    data = {k: (math.nan if v is None else v) for k, v in report.items()
            if k in fields and k not in ('seed', 'scenario')}
    rec = RunOutcome(seed=seed, scenario=scenario, **data)
    if not rec.outcome:
        rec.outcome = 'no_run'
    if not rec.reason:
        rec.reason = str(report.get('reason', 'no report'))
    return rec


def spoiled(report: dict[str, Any], max_stalls: int) -> str:
    """Why a mission says nothing about the stack ('' = it counts): PX4 or the graph did not
    come up, or the world stalled more than ``max_stalls`` times over the mission."""
    if report.get('exit_status') in (3, 4) or 'contact_kind' not in report:
        return f"did not fly: {str(report.get('reason', 'no report'))[:200]}"
    health = report.get('lockstep') or {}
    if int(health.get('stalls') or 0) > max_stalls:
        return (f"world stalled {health['stalls']} times (x{health.get('realtime_factor')} "
                'real time)')
    return ''


def failsafe_check(report: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    """For a link-fault mission: PX4 flew its configured offboard-loss action
    (``COM_OBL_RC_ACT``) after OFFBOARD, ended landed and disarmed, and not on the deck
    edge."""
    want = SAFE_ACTION_MODES.get(int(params.get('COM_OBL_RC_ACT', -1)), '?')
    return safe_action_check(report, 'px4', 'OFFBOARD', want)


def safe_action_check(report: dict[str, Any], key: str, offboard_mode: str,
                      want: str) -> dict[str, Any]:
    """The firmware (``report[key]``) flew ``want`` first after leaving ``offboard_mode``,
    ended disarmed, not on the deck edge and without a crash (a backend's
    ``failsafe_check``)."""
    fw = report.get(key) or {}
    modes = [m['mode'] for m in fw.get('modes', [])]
    after = [b for a, b in itertools.pairwise(modes) if a == offboard_mode
             and b != offboard_mode]
    seen = after[0] if after else ''
    disarmed = fw.get('armed_at_end') is False
    edge = report.get('contact_kind') == 'edge'
    return {'action_expected': want, 'action_seen': seen, 'disarmed': disarmed,
            'landed_state_at_end': fw.get('landed_state_at_end'), 'edge': edge,
            'crash': bool(report.get('crash')),
            'ok': seen == want and disarmed and not edge and not report.get('crash')}


def _mission(scenario: str, seed: int, args, workdir: pathlib.Path) -> dict[str, Any]:
    out = workdir / f'{seed}.json'
    log = workdir / f'{seed}.log'
    cmd = [sys.executable, '-m', 'deckland.cli', 'up', '--autopilot', args.autopilot,
           '--scenario', scenario, '--seed', str(seed), '--timeout',
           str(args.mission_timeout), '--report', str(out)]
    t0 = time.monotonic()
    with open(log, 'w') as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL, check=False,
                              timeout=args.mission_timeout + 240.0)
    try:
        report = json.loads(out.read_text())
    except (OSError, ValueError):
        report = {'success': False, 'reason': f'no report (exit {proc.returncode}; log {log})'}
    report['wall_s'] = round(time.monotonic() - t0, 1)
    return report


def _figures(r: RunOutcome) -> dict[str, Any]:
    def num(x: float, d: int = 4) -> float | None:
        return round(x, d) if isinstance(x, float) and math.isfinite(x) else None
    return {'outcome': r.outcome, 'contact': r.contact_kind,
            'horizontal_error_m': num(r.horizontal_error_m),
            'touchdown_speed_mps': num(r.touchdown_speed_mps),
            'time_to_land_s': num(r.time_to_land_s, 2), 'searches': r.searches,
            'reason': r.reason}


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not b:
        return None
    return round(a / b, 2)


def compare(px4: dict[str, Any], ref: dict[str, Any]) -> dict[str, Any]:
    """PX4 / in-process ratios of the error and touchdown-speed percentiles (target: within
    a factor of 2 either way)."""
    out: dict[str, Any] = {}
    for key in ('horizontal_error_m', 'touchdown_speed_mps'):
        for q in ('p50', 'p95'):
            r = _ratio(px4[key][q], ref[key][q])
            out[f'{key}_{q}_ratio'] = r
    rs = [v for v in out.values() if v is not None]
    out['within_factor_2'] = bool(rs) and all(0.5 <= v <= 2.0 for v in rs)
    return out


def run_sitl_campaign(args) -> dict[str, Any]:
    """The campaign (see the module docstring); progress lines on stderr."""
    from deck_simulator.scenario import load_scenario

    from deckland.batch.campaign import run_seed, summarize
    from deckland.batch.runner import RunConfig, run_landing
    from deckland.sitl import SITL_AUTOPILOTS

    backend = SITL_AUTOPILOTS[args.autopilot]
    key = backend.report_key
    check = backend.load('failsafe_check')
    scen = load_scenario(args.scenario)
    params = backend.load('params')(scen)
    link_fault = any(getattr(f, 'loss_timeout_s', None) is not None for f in scen.faults)
    keep = pathlib.Path(args.keep_runs) if args.keep_runs else None
    workdir = keep or pathlib.Path(tempfile.mkdtemp(prefix='deckland-sitl-campaign-'))
    workdir.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    start = time.perf_counter()
    results, per_run, attempts, checks = [], [], [], []
    ref_results = []
    for i in range(args.runs):
        seed = run_seed(args.seed, i)
        for attempt in range(args.retries + 1):
            report = _mission(args.scenario, seed, args, workdir)
            why = spoiled(report, args.max_stalls)
            attempts.append({'seed': seed, 'attempt': attempt, 'spoiled': why,
                             'exit_status': report.get('exit_status'),
                             'lockstep': report.get('lockstep'),
                             'wall_s': report.get('wall_s'),
                             'load_1min': round(os.getloadavg()[0], 2)})
            if not why:
                break
            sys.stderr.write(f'  seed {seed} attempt {attempt}: {why}\n')
        rec = outcome_from_report(seed, scen.name, report)
        results.append(rec)
        ref = run_landing(scen, seed, RunConfig(controller='dob'))
        ref_results.append(ref)
        row = {'seed': seed, key: _figures(rec), 'in_process': _figures(ref),
               'lockstep': report.get('lockstep'), 'spoiled': why,
               'hover_thrust_source': _hover_source(report.get(key)),
               f'{key}_modes': [m['mode'] for m in (report.get(key) or {}).get('modes', [])]}
        if link_fault:
            row['failsafe_check'] = chk = check(report, params)
            checks.append(chk)
        per_run.append(row)
        sys.stderr.write(f'{scen.name} {key} {i + 1}/{args.runs} seed {seed}: {rec.outcome} '
                         f'{rec.reason} (in-process {ref.outcome}); '
                         f'{time.perf_counter() - start:.0f} s\n')
        sys.stderr.flush()
    wall = time.perf_counter() - start
    report = summarize(results, scen.name, 'dob', args.seed, wall, 1)
    ref_summary = summarize(ref_results, scen.name, 'dob', args.seed, 0.0, 1)
    ref_summary.pop('wall_time_s')
    for k in ('realtime_factor', 'realtime_factor_per_worker', 'workers'):
        ref_summary.pop(k)
    report.update({
        'autopilot': backend.name,
        f'{key}_params': params,
        'in_process': ref_summary,
        'comparison': compare(report, ref_summary),
        'per_run': per_run,
        'attempts': attempts,
        'machine': {'cpus': os.cpu_count(), 'load_1min_before': round(load0, 2),
                    'load_1min_after': round(os.getloadavg()[0], 2),
                    'niceness': os.nice(0)},
        'command': f'deckland campaign --autopilot {backend.name} ' + ' '.join(
            f'--{k.replace("_", "-")} {v}' for k, v in (
                ('scenario', args.scenario), ('runs', args.runs), ('seed', args.seed))),
    })
    if link_fault:
        report['failsafe_check'] = {'runs': len(checks), 'ok': sum(c['ok'] for c in checks),
                                    'expected_action': checks[0]['action_expected']
                                    if checks else None}
    if keep is None:
        for f in workdir.iterdir():
            f.unlink()
        workdir.rmdir()
    return report


def _hover_source(firmware: dict[str, Any] | None) -> str:
    """Where the bridge's hover thrust came from: measured in the firmware's own hover, or
    its parameter (PX4 MPC_THR_HOVER, ArduCopter MOT_THST_HOVER) when that hover was not
    steady enough (``firmware``: the mission report's firmware record)."""
    h = (firmware or {}).get('hover_thrust_measured')
    return f'measured {h:.4f}' if isinstance(h, float) else 'the hover parameter'


def cmd_sitl_campaign(args) -> int:
    """``deckland campaign --autopilot NAME`` (a registered firmware): run, print, write
    ``--out``."""
    from deckland.batch.campaign import format_table
    from deckland.sitl import SITL_AUTOPILOTS, SitlNotFoundError

    backend = SITL_AUTOPILOTS[args.autopilot]
    try:
        backend.load('find')()
    except SitlNotFoundError as exc:
        print(f'deckland campaign: {exc}', file=sys.stderr)
        return 2
    if args.compare or args.controller != 'dob':
        print(f'deckland campaign: --autopilot {backend.name} flies the graph (controller dob)',
              file=sys.stderr)
        return 2
    report = run_sitl_campaign(args)
    print(format_table([{**report, 'controller': backend.name},
                        {**report['in_process'], 'controller': 'in-process',
                                 'wall_time_s': 0.0, 'realtime_factor': 0.0}]))
    print(f"comparison ({backend.name} / in-process): {json.dumps(report['comparison'])}")
    if 'failsafe_check' in report:
        print(f"failsafe check: {json.dumps(report['failsafe_check'])}")
    for f in report['failures'][:10]:
        print(f"  {backend.name} failed seed {f['seed']}: {f['reason']}")
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=2) + '\n')
        print(f'wrote {out}')
    return 0
