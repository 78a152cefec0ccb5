"""Real autopilots as processes for tests, demos and campaigns, and their registry.

:data:`SITL_AUTOPILOTS` maps an ``--autopilot`` value of ``deckland up``, ``deckland
campaign`` and ``deckland bench latency`` to a :class:`SitlAutopilot`: where its build is
found, the mission object that starts it and plays the operator, the parameters a scenario
gives it and the check of its offboard-loss failsafe. PX4 v1.16 SITL (:mod:`.px4`,
:mod:`.mission`) and ArduCopter 4.5.6 SITL (:mod:`.ardupilot`) are the entries; another
firmware registers one more with :func:`register`.
"""

from __future__ import annotations

import dataclasses
from importlib import import_module
from typing import Any


class SitlNotFoundError(RuntimeError):
    """No build of the firmware where its :class:`SitlAutopilot` looks (the message says
    where, and how to get one)."""


class SitlStartError(RuntimeError):
    """The firmware could not be started (the message says why)."""


@dataclasses.dataclass(frozen=True)
class SitlAutopilot:
    """One firmware in the loop. Each field but ``name``, ``help`` and ``report_key`` is a
    ``'module:attribute'`` imported on use (no firmware code is loaded to list them):

    - ``mission``: a class ``(scenario, *, keep_ulog=None)`` with ``NAME`` (for logs),
      ``OFFBOARD_MODE`` (the mode it flies the companion's setpoints in), ``start()``,
      ``configure_graph(nodes)``, ``wait_up(timeout_s, abort)``, ``times`` (``up_s``),
      ``GROUND_SILENT``, ``operator_take_off(monitor, log, abort)``, ``mode``,
      ``wait_mode(mode, timeout_s, abort)``, ``wait_disarmed(timeout_s, abort)``,
      ``describe()``, ``ports`` (PX4's names: ``simulator_tcp``, ``onboard_remote`` where
      the companion listens, ``onboard_local``, ``gcs_local``), ``cpu_s()``,
      ``report(t_ref_s)``, ``stop()`` (:class:`.mission.Px4Mission`);
    - ``params``: ``(scenario) -> dict``, what the firmware is told for a mission;
    - ``find``: ``() -> path``, its build (raises :class:`SitlNotFoundError`);
    - ``failsafe_check``: ``(report, params) -> dict`` with ``ok``, for link-fault missions.

    ``report_key``: the key of the mission's firmware record in ``report.json``.
    """

    name: str
    help: str
    mission: str
    params: str
    find: str
    failsafe_check: str
    report_key: str

    def load(self, field: str) -> Any:
        """The object a ``'module:attribute'`` field names."""
        module, _, attr = getattr(self, field).partition(':')
        return getattr(import_module(module), attr)


SITL_AUTOPILOTS: dict[str, SitlAutopilot] = {}


def register(autopilot: SitlAutopilot) -> None:
    """Add a firmware (its ``name`` becomes an ``--autopilot`` choice)."""
    if autopilot.name in SITL_AUTOPILOTS or autopilot.name in ('emulator', 'in-process'):
        raise ValueError(f'SITL autopilot {autopilot.name!r} already registered')
    SITL_AUTOPILOTS[autopilot.name] = autopilot


def sitl_autopilot(name: str) -> SitlAutopilot | None:
    """The registered firmware called ``name``; None for the emulator / in-process."""
    return SITL_AUTOPILOTS.get(name)


register(SitlAutopilot(
    name='px4-sitl',
    help='PX4 v1.16 SITL from $DECKLAND_PX4_SITL / ../shared/px4-sitl (airframe 10016, '
    "deckland's world as its simulator in lockstep)",
    mission='deckland.sitl.mission:Px4Mission',
    params='deckland.sitl.mission:mission_params',
    find='deckland.sitl.px4:require_px4',
    failsafe_check='deckland.sitl.campaign:failsafe_check',
    report_key='px4'))
register(SitlAutopilot(
    name='ardupilot-sitl',
    help='ArduCopter 4.5.6 SITL from $DECKLAND_ARDUPILOT_SITL / ../shared/ardupilot-sitl '
    "(--model JSON: deckland's world as its physics in lockstep)",
    mission='deckland.sitl.ardupilot:ArduPilotMission',
    params='deckland.sitl.ardupilot:all_mission_params',
    find='deckland.sitl.ardupilot:require_ardupilot',
    failsafe_check='deckland.sitl.ardupilot:failsafe_check',
    report_key='ardupilot'))
