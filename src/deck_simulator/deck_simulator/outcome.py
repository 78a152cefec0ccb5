"""The outcome record of one landing run and its safety class (pure).

:class:`RunOutcome` is the one definition of a run's outcome fields: the in-process runner's
``RunResult`` extends it, and the simulator node publishes it as JSON on ``sim/outcome``.
:func:`landing_outcome` fills it from a :class:`~deck_simulator.world.World`; :func:`classify`
names the safety class (docs/failsafe.md): ``deck``, ``fallback``, ``hold``, ``crash`` or
``unstable``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
import json
import math
from typing import Any

from deck_simulator.world import World

HOLD_MAX_SPEED_MPS = 0.5     # 'hold': airborne at the end and slower than this ...
HOLD_MIN_HEIGHT_M = 0.3      # ... at least this high above the surface below ...
HOLD_MAX_TILT_RAD = 0.35     # ... and not tilted more than this


@dataclass
class RunOutcome:
    """Outcome of one run: the contact, the landing figures and the autopilot's failsafes."""

    seed: int
    scenario: str
    landed_on_deck: bool = False
    success: bool = False           # on the pad and no crash
    crash: bool = False
    fallback: bool = False          # a landing on the ground
    contact_kind: str = 'none'      # 'pad' | 'edge' | 'ground' | 'none'
    horizontal_error_m: float = math.nan
    touchdown_speed_mps: float = math.nan
    time_to_land_s: float = math.nan   # contact time from the landing trigger
    searches: int = 0
    max_thrust_n: float = 0.0
    final_mode: str = ''            # the planner's mode when the record was made
    reason: str = ''
    sim_time_s: float = 0.0
    outcome: str = ''               # safety class, see classify()
    failsafes: int = 0              # times the autopilot's offboard-loss failsafe engaged
    failsafe_mode: str = ''         # its phase at the end ('' = none)
    final_height_m: float = math.nan   # true height above the surface below at the end
    final_speed_mps: float = math.nan  # true speed at the end (3-D)


def classify(crash: bool, contact_kind: str, final_speed_mps: float, final_height_m: float,
             roll_rad: float = 0.0, pitch_rad: float = 0.0) -> str:
    """Safety class of a finished run: ``deck`` (landed on the pad), ``fallback`` (a
    deliberate landing on the ground, not a crash), ``hold`` (no touchdown, airborne and
    stable at the end), ``crash`` (edge strike, too fast or too tilted) or ``unstable`` (no
    touchdown but not a stable hover: counted as unsafe)."""
    if crash:
        return 'crash'
    if contact_kind == 'pad':
        return 'deck'
    if contact_kind == 'ground':
        return 'fallback'
    tilt = math.acos(max(-1.0, min(1.0, math.cos(roll_rad) * math.cos(pitch_rad))))
    if (final_speed_mps <= HOLD_MAX_SPEED_MPS and tilt <= HOLD_MAX_TILT_RAD
            and final_height_m >= HOLD_MIN_HEIGHT_M):
        return 'hold'
    return 'unstable'


def landing_outcome(world: World, seed: int, trigger_t_s: float | None, searches: int,
                    final_mode: str, no_contact_reason: str) -> RunOutcome:
    """The record of ``world`` now: its first contact (``time_to_land_s`` from
    ``trigger_t_s``, NaN without a trigger), or ``no_contact_reason``; the autopilot's
    failsafes; the final state and the safety class."""
    o = world.outcome()
    rec = RunOutcome(seed=seed, scenario=world.scenario.name, searches=searches,
                     max_thrust_n=o.max_thrust_n, final_mode=final_mode,
                     sim_time_s=world.t_s)
    if o.contact_kind == 'none':
        rec.reason = no_contact_reason
    else:
        rec.contact_kind = o.contact_kind
        rec.touchdown_speed_mps = o.touchdown_speed_mps
        rec.horizontal_error_m = o.horizontal_error_m
        rec.time_to_land_s = math.nan if trigger_t_s is None else o.t_s - trigger_t_s
        rec.landed_on_deck = o.landed_on_deck
        rec.crash = o.crash
        rec.fallback = o.fallback
        rec.success = o.landed_on_deck and not o.crash
        rec.reason = o.reason
    truth = world.truth()
    ap = world.autopilot
    rec.failsafes = ap.failsafes if ap is not None else 0
    rec.failsafe_mode = world.failsafe or ''
    rec.final_height_m = truth.height_above_surface_m
    rec.final_speed_mps = math.hypot(*truth.velocity_mps)
    rec.outcome = classify(rec.crash, rec.contact_kind, rec.final_speed_mps,
                           rec.final_height_m, truth.roll_rad, truth.pitch_rad)
    return rec


def outcome_dict(record: RunOutcome, **extra: Any) -> dict[str, Any]:
    """``record`` (plus ``extra`` keys) as a JSON-ready dict: non-finite numbers are None."""
    data = asdict(record)
    data.update(extra)
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v
            for k, v in data.items()}


def outcome_json(record: RunOutcome | dict[str, Any], **extra: Any) -> str:
    """The ``sim/outcome`` payload: strict JSON (non-finite numbers are null), sorted keys."""
    data = outcome_dict(record, **extra) if isinstance(record, RunOutcome) else {
        k: None if isinstance(v, float) and not math.isfinite(v) else v
        for k, v in {**record, **extra}.items()}
    return json.dumps(data, allow_nan=False, sort_keys=True)


__all__ = ['HOLD_MAX_SPEED_MPS', 'HOLD_MAX_TILT_RAD', 'HOLD_MIN_HEIGHT_M', 'RunOutcome',
           'classify', 'landing_outcome', 'outcome_dict', 'outcome_json']
