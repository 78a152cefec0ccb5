"""What ``deckland up`` reports at the end of a run, from plain values (no rclpy).

:func:`summary_lines` is the short summary it prints; :func:`failsafe_fields` names the
autopilot's offboard-loss action from the modes the bridge saw, or from the emulated
autopilot's own record when the bridge died with the node killed; :data:`EXIT_CODES` are the
command's exit statuses (``src/deckland/README-up.md``).
"""

from __future__ import annotations

import itertools
import json
import math
import pathlib
from typing import Any

EXIT_CODES = {
    0: 'landed (simulation: on the deck, no crash; hardware: the planner reached LANDED)',
    1: 'mission failed: no successful landing (missed/crashed/failsafe landing, timeout)',
    2: 'usage or configuration error (bad scenario, graph, record directory, arguments)',
    3: 'start-up failed (topics not flowing, a node died while starting)',
    4: 'the landing could not be triggered (planner/start_landing refused or absent)',
    130: 'interrupted by SIGINT (128 + 2)',
    143: 'interrupted by SIGTERM (128 + 15)',
}


def failsafe_fields(modes: list[dict[str, Any]], report: dict[str, Any]) -> dict[str, str]:
    """``failsafe`` (and ``failsafe_source``) of a run's report: the first mode the autopilot
    switched to out of OFFBOARD. When no mode was seen leaving OFFBOARD — the bridge that
    reports them can be gone with the node killed (composed mode) — the emulated autopilot's
    record (``failsafe_mode`` of the simulator's outcome), in PX4's name as the bridge would
    have reported it. Nothing for a firmware in the loop (``autopilot`` set) or no failsafe."""
    seq = [m['mode'] for m in modes]
    left = [b for a, b in itertools.pairwise(seq) if a == 'OFFBOARD' and b != 'OFFBOARD']
    if left:
        return {'failsafe': left[0]}
    if report.get('failsafe_mode') and 'autopilot' not in report:
        from deck_simulator.px4_emulator import px4_name
        return {'failsafe': px4_name(report['failsafe_mode']), 'failsafe_source': 'simulator'}
    return {}


def finish_report(report: dict[str, Any], *, scenario: str | None, seed: int | None,
                  composed: bool, modes: list[dict[str, Any]], injected: list,
                  device_problems: list, crashed: list[dict[str, Any]], code: int,
                  bag: dict[str, Any] | None) -> dict[str, Any]:
    """The run's report: the simulator's outcome ``report`` plus what ``deckland up`` saw
    (``scenario``/``seed`` None on hardware); a new dict."""
    report = dict(report)
    if scenario is not None:
        report.setdefault('scenario', scenario)
        report.setdefault('seed', seed)
    report['hardware'] = scenario is None
    report['composed'] = composed
    if 'crash' in report:
        report['safe'] = not report['crash']
    report.update(failsafe_fields(modes, report))
    report['autopilot_modes'] = modes
    report['injected_faults'] = injected
    if device_problems:
        report['device_problems'] = device_problems
    if crashed:
        report['crashed_nodes'] = crashed
    report['exit_status'] = code
    if bag is not None:
        report['bag'] = bag
    return report


def bridge_modes(seen: list[tuple[float, str]],
                 t_trigger: float | None) -> list[dict[str, Any]]:
    """The autopilot modes ``vehicle/mode`` showed, ``(monotonic s, mode)``, as report rows
    timed from the landing trigger (from 0.5 s before it; all, untimed, without one)."""
    return [{'t_s': round(t - (t_trigger or t), 3), 'mode': m} for t, m in seen
            if t_trigger is None or t >= t_trigger - 0.5]


def firmware_modes(modes: list[dict[str, Any]], t_trigger: float | None,
                   t_outcome: float | None) -> list[dict[str, Any]]:
    """A firmware's own mode rows (``t_s`` from the trigger; the operator's view: the bridge
    may be the node killed) up to the touchdown; after it the land detector or the offboard
    loss may switch, which is not the mission's doing."""
    return [{'t_s': r['t_s'], 'mode': r['mode']} for r in modes
            if t_outcome is None or t_trigger is None or r['t_s'] <= t_outcome - t_trigger]


def parse_outcome(text: str, expect: dict[str, Any]) -> tuple[dict[str, Any] | None, str]:
    """A ``sim/outcome`` message: ``(outcome, '')``, ``(None, 'foreign')`` for another
    simulation's (a key of ``expect`` differs: another graph on the ROS domain), or an
    ``{'reason': 'unparsable ...'}`` outcome for text that is no JSON object."""
    try:
        outcome = json.loads(text)
    except ValueError:
        outcome = None
    if not isinstance(outcome, dict):
        return {'reason': f'unparsable outcome: {text[:80]}'}, ''
    if any(outcome.get(k) != v for k, v in expect.items()):
        return None, 'foreign'
    return outcome, ''


class KillSchedule:
    """When the scenario's ``node_kill`` faults act, in seconds since the landing trigger:
    :meth:`due` returns the faults to kill now and the nodes to release (a fault with a
    finite ``end_s``), each once."""

    def __init__(self, faults: list[Any]) -> None:
        self._pending = sorted(faults, key=lambda f: f.start_s)
        self._releases: list[tuple[float, str]] = []

    def due(self, t_s: float) -> tuple[list[Any], list[str]]:
        kills = []
        while self._pending and t_s >= self._pending[0].start_s:
            f = self._pending.pop(0)
            kills.append(f)
            if math.isfinite(f.end_s):
                self._releases.append((f.end_s, f.node))
        released = [node for end, node in self._releases if t_s >= end]
        self._releases = [r for r in self._releases if t_s < r[0]]
        return kills, released


def _fmt(value: Any, unit: str, digits: int = 2) -> str:
    if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
        return f'{value:.{digits}f} {unit}'
    return 'n/a'


def summary_lines(report: dict[str, Any], code: int, record: str | None) -> list[str]:
    """The short end-of-run summary ``deckland up`` prints (also shown by ``make run``)."""
    if report.get('interrupted'):
        outcome = f'interrupted ({report["interrupted"]})'
    elif report.get('success'):
        outcome = f'landed ({report.get("reason", "success")})'
    else:
        outcome = f'no successful landing ({report.get("reason", "unknown")})'
    if report.get('crash'):
        outcome += ', CRASH'
    elif report.get('safe') and not report.get('success'):
        outcome += ', safe (no crash)'
    if report.get('failsafe'):
        outcome += f'; autopilot failsafe {report["failsafe"]}'
    lines = [
        '==== deckland up: summary ====',
        f'outcome           {outcome}',
        f'touchdown speed   {_fmt(report.get("touchdown_speed_mps"), "m/s")}',
        f'horizontal error  {_fmt(report.get("horizontal_error_m"), "m", 3)}',
        f'time to land      {_fmt(report.get("time_to_land_s"), "s", 1)}',
    ]
    if report.get('outcome'):     # the landing record (deck_simulator.outcome, campaigns')
        lines.insert(2, f'class             {report["outcome"]}'
                     + (' (settled)' if report.get('settled') else ''))
    if report.get('contact_kind') not in (None, 'none'):
        tilt = report.get('tilt_rad')
        tilt_deg = math.degrees(tilt) if isinstance(tilt, int | float) else None
        lines += [f'lateral speed     {_fmt(report.get("lateral_speed_mps"), "m/s")}',
                  f'relative tilt     {_fmt(tilt_deg, "deg", 1)}',
                  f'impacts, bounces  {report.get("impacts", 0)}, {report.get("bounces", 0)} '
                  f'(fastest {_fmt(report.get("max_impact_speed_mps"), "m/s")}, highest hop '
                  f'{_fmt(report.get("max_bounce_height_m"), "m", 3)})']
    if report.get('autopilot_modes'):
        lines.append('autopilot modes   ' + ' -> '.join(m['mode'] for m in
                                                        report['autopilot_modes']))
    for k in report.get('injected_faults', []):
        lines.append(f'fault injected    node_kill {k["node"]} at {_fmt(k["at_s"], "s", 1)} '
                     f'after the trigger')
    for node, problem in report.get('device_problems', {}).items():
        lines.append(f'device problem    {node}: {problem}')
    for c in report.get('crashed_nodes', []):
        lines.append(f'node exited       {c["node"]}: {c["description"]} ({c["action"]})')
    bag = report.get('bag') or {}
    if record and bag.get('not_started'):
        lines.append(f'bag               not started: {bag["not_started"]}')
        lines.append(f'report            {pathlib.Path(record) / "report.json"}')
    elif record:
        lines.append(f'bag               {record} ({bag.get("messages", "?")} messages, '
                     f'{bag.get("topics", "?")} topics)')
        lines.append(f'report            {pathlib.Path(record) / "report.json"}')
    else:
        lines.append('bag, report       not recorded (use --record DIR)')
    lines.append(f'exit status       {code}: {EXIT_CODES.get(code, "")}')
    return lines
