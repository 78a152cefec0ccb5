"""The outcome record of one landing run and its class (pure).

:class:`RunOutcome` is the one definition of a run's outcome fields: the in-process runner's
``RunResult`` extends it, and the simulator node publishes it as JSON on ``sim/outcome``.
:func:`landing_outcome` fills it from a :class:`~deck_simulator.world.World` (its touchdown
record over the whole landing); :func:`classify` names the class (docs/failsafe.md):
``deck``, ``failed``, ``fallback``, ``hold``, ``crash`` or ``unstable``.
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
    landed_on_deck: bool = False    # every landing rule kept (the class is 'deck')
    success: bool = False           # the same: a landing a pilot would accept
    crash: bool = False
    fallback: bool = False          # first contact on the ground (a landing elsewhere)
    contact_kind: str = 'none'      # first contact: pad | deck | edge | ground | water | hull
    horizontal_error_m: float = math.nan   # first contact, centre of mass to the pad centre
    touchdown_speed_mps: float = math.nan  # first contact, relative, along the deck normal
    time_to_land_s: float = math.nan   # contact time from the landing trigger
    searches: int = 0
    max_thrust_n: float = 0.0
    final_mode: str = ''            # the planner's mode when the record was made
    reason: str = ''
    sim_time_s: float = 0.0
    outcome: str = ''               # safety class, see classify()
    failsafes: int = 0              # times the autopilot's offboard-loss failsafe engaged
    failsafe_mode: str = ''         # its mode at the end (World.failsafe_mode), or the last
    final_height_m: float = math.nan   # true height above the surface below at the end
    final_speed_mps: float = math.nan  # true speed at the end (3-D)
    # the touchdown record (deck_simulator.touchdown): first contact, later impacts, bounces
    lateral_speed_mps: float = math.nan   # first contact, relative, along the surface
    tilt_rad: float = math.nan            # first contact, body z vs the surface normal
    impacts: int = 0                      # the first contact and every later impact
    max_impact_speed_mps: float = math.nan   # largest relative normal speed of any impact
    bounces: int = 0
    max_bounce_height_m: float = math.nan
    settled: bool = False                 # disarmed and still on a surface for 1 s


def classify(crash: bool, contact_kind: str, final_speed_mps: float, final_height_m: float,
             roll_rad: float = 0.0, pitch_rad: float = 0.0, failed: bool = False) -> str:
    """Class of a finished run: ``crash`` (a crash rule of the landing broken: docs/world/
    contact.md), ``fallback`` (first contact on the ground, not a crash: a deliberate landing
    elsewhere), ``failed`` (touched the deck but broke a pilot's rule: ``failed``), ``deck``
    (landed on the pad, every rule kept), ``hold`` (no touchdown, airborne and stable at the
    end) or ``unstable`` (no touchdown but not a stable hover: counted as unsafe)."""
    if crash:
        return 'crash'
    if contact_kind == 'ground':
        return 'fallback'
    if failed or contact_kind not in ('pad', 'none'):
        return 'failed'
    if contact_kind == 'pad':
        return 'deck'
    tilt = math.acos(max(-1.0, min(1.0, math.cos(roll_rad) * math.cos(pitch_rad))))
    if (final_speed_mps <= HOLD_MAX_SPEED_MPS and tilt <= HOLD_MAX_TILT_RAD
            and final_height_m >= HOLD_MIN_HEIGHT_M):
        return 'hold'
    return 'unstable'


def landing_outcome(world: World, seed: int, trigger_t_s: float | None, searches: int,
                    final_mode: str, no_contact_reason: str) -> RunOutcome:
    """The record of ``world`` now: its landing (first contact, ``time_to_land_s`` from
    ``trigger_t_s``, NaN without a trigger; later impacts, bounces, the rules broken), or
    ``no_contact_reason``; the autopilot's failsafes; the final state and the class."""
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
        rec.success = o.landed_on_deck
        rec.reason = o.reason
        rec.lateral_speed_mps = o.lateral_speed_mps
        rec.tilt_rad = o.tilt_rad
        rec.impacts = o.impacts
        rec.max_impact_speed_mps = o.max_impact_speed_mps
        rec.bounces = o.bounces
        rec.max_bounce_height_m = o.max_bounce_height_m
        rec.settled = o.settled
    truth = world.truth()
    ap = world.autopilot
    rec.failsafes = ap.failsafes if ap is not None else 0
    rec.failsafe_mode = world.failsafe_mode or world.last_failsafe
    rec.final_height_m = truth.height_above_surface_m
    rec.final_speed_mps = math.hypot(*truth.velocity_mps)
    rec.outcome = classify(rec.crash, rec.contact_kind, rec.final_speed_mps,
                           rec.final_height_m, truth.roll_rad, truth.pitch_rad,
                           failed=o.landing == 'failed')
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
