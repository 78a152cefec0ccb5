"""Cost of the contact cores per 400 Hz physics tick (µs), Python or mypyc-compiled.

    .venv/bin/python docs/world/bench_contact.py                 # the Python sources
    .venv/bin/python docs/world/bench_contact.py --compiled      # compile first (mypyc, -O3)
    .venv/bin/python docs/world/bench_contact.py --substep-study # accuracy against ω_max h

Phases, as the world will step them: ``air`` far from and near the pad (rigid body + the
contact broad phase + the per-rotor ground effect, one step per tick); ``contact`` on the
pad with the impact sub-step count and with the resting one (each sub-step: wrench +
touchdown monitor + rigid body; the ground effect once per tick).
CPU time of this process (robust to other load), best of the repeats. Prints one JSON
line; docs/world/contact.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]
MODULES = ('deckland_common/frames.py', 'deck_simulator/rigid_body.py',
           'deck_simulator/contact.py', 'deck_simulator/rotor_ground_effect.py',
           'deck_simulator/touchdown.py')


def compile_into(stage: pathlib.Path) -> None:
    for pkg in ('deckland_common', 'deck_simulator', 'dob_altitude'):
        shutil.copytree(ROOT / 'src' / pkg / pkg, stage / pkg)
    (stage / 'mypy.ini').write_text('[mypy]\nignore_missing_imports = True\n'
                                    'follow_imports = silent\n')
    (stage / 'setup.py').write_text(
        'from setuptools import setup\nfrom mypyc.build import mypycify\n'
        f'setup(name="bench", ext_modules=mypycify({list(MODULES)!r}, opt_level="3", '
        'multi_file=True, group_name="bench_contact"))\n')
    env = dict(os.environ, CFLAGS='-ffp-contract=off')
    subprocess.run([sys.executable, 'setup.py', 'build_ext', '--inplace'], cwd=stage, env=env,
                   check=True, capture_output=True)


def measure(ticks: int) -> dict:
    import deck_simulator.contact as contact_mod
    from deck_simulator.contact import (
        ContactModel,
        ContactParams,
        GearGeometry,
        Surface,
        ground_surface,
        prop_tip_points,
    )
    from deck_simulator.rigid_body import RigidBody, RigidBodyParams
    from deck_simulator.rotor_ground_effect import RotorGroundEffect, RotorGroundEffectParams
    from deck_simulator.touchdown import OutcomeRules, Pad, TouchdownMonitor

    dt = 1.0 / 400.0
    bp = RigidBodyParams()
    gear = GearGeometry()
    deck = Surface('deck', 0.525, 0.425, 0.6, 0.6)
    deck.set_pose((0.0, 0.0, 0.6), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    surfaces = [deck, ground_surface(0.6)]
    cm = ContactModel(ContactParams(), bp.mass_kg, bp.inertia_kgm2, gear.points(),
                      prop_tip_points(0.225, 0.127, 0.05), surfaces)
    rotors = ((0.225, 0.0, 0.05), (0.0, 0.225, 0.05), (-0.225, 0.0, 0.05), (0.0, -0.225, 0.05))
    ge = RotorGroundEffect(RotorGroundEffectParams(), rotors, (0.0, 0.0, 0.05))
    mon = TouchdownMonitor(OutcomeRules(), cm, Pad(), gear.static_tip_angle_rad())
    hover = bp.mass_kg * bp.gravity_mps2
    out: dict = {'compiled': not contact_mod.__file__.endswith('.py')}

    def air(z: float) -> float:
        body = RigidBody(bp, (0.0, 0.0, z))
        t = 0.0
        t0 = time.process_time()
        for _ in range(ticks):
            near = cm.near(body, dt)
            ge.update(body, surfaces)
            if not near:
                mon.update(t, body, True)
                body.step(dt, 0.0, 0.0, hover, 0.0, 0.0, 0.0)
            t += dt
        return (time.process_time() - t0) / ticks * 1e6

    def resting(full: bool) -> float:
        body = RigidBody(bp, (0.0, 0.0, 0.75 - 0.00066))
        t = 0.0
        t0 = time.process_time()
        for _ in range(ticks):
            cm.near(body, dt)
            ge.update(body, surfaces)
            n = cm.substeps(dt)
            if full:
                n = n_full
            h = dt / n
            for _ in range(n):
                fx, fy, fz, tx, ty, tz = cm.wrench(body)
                mon.update(t, body, False)
                body.step(h, fx, fy, fz, tx, ty, tz)
                t += h
        out['substeps_resting'] = n
        return (time.process_time() - t0) / ticks * 1e6

    n_full = cm.substeps(dt)
    out['substeps_impact'] = n_full
    out['air_far_us_per_tick'] = air(2.1)        # rotors 1.5 m above the pad
    out['air_near_us_per_tick'] = air(0.95)      # rotors 0.4 m above: GE at full rate
    out['contact_impact_us_per_tick'] = resting(True)
    out['contact_resting_us_per_tick'] = resting(False)
    out['settled'] = mon.settled
    return out


def substep_study() -> list[dict]:
    """Accuracy against the sub-step: a flat drop's restitution (1 m/s, no gravity, 40
    random contact phases) and a tilted, spinning drop against a 128-sub-step reference."""
    import math
    import random

    from deck_simulator.contact import (
        ContactModel,
        ContactParams,
        GearGeometry,
        ground_surface,
        prop_tip_points,
    )
    from deck_simulator.rigid_body import RigidBody, RigidBodyParams

    dt = 1.0 / 400.0
    gear = GearGeometry()
    hull = prop_tip_points(0.225, 0.127, 0.05)

    def model(g: float) -> tuple[RigidBodyParams, ContactModel]:
        bp = RigidBodyParams(gravity_mps2=g)
        return bp, ContactModel(ContactParams(), bp.mass_kg, bp.inertia_kgm2, gear.points(),
                                hull, [ground_surface(0.6)])

    def fly(n: int, body: RigidBody, cm: ContactModel, seconds: float) -> RigidBody:
        h = dt / n
        for _ in range(round(seconds / h)):
            w = cm.wrench(body)
            body.step(h, *w)
        return body

    def tilted(n: int) -> tuple[float, ...]:
        bp, cm = model(9.81)
        b = RigidBody(bp, (0.0, 0.0, 0.0), (0.25, 0.15, 0.3), (0.3, 0.0, -1.0), (1.0, -2.0, 0.5))
        b.z -= min(b.point_world(*p)[2] for p in gear.points()) - 1e-3
        fly(n, b, cm, 0.4)
        return (b.x, b.y, b.z, *b.euler(), b.p, b.q, b.r)

    ref = tilted(128)
    omega = model(9.81)[1].omega_max
    rng = random.Random('contact:substep-study')
    rows = []
    for n in (1, 2, 3, 4, 6, 8, 16):
        errs = []
        for _ in range(40):
            bp, cm = model(0.0)
            b = RigidBody(bp, (0.0, 0.0, 0.15 + rng.uniform(0.0, dt / n)), velocity_mps=(0, 0, -1))
            errs.append(fly(n, b, cm, 0.1).vz / cm.params.restitution - 1.0)
        s = tilted(n)
        rows.append({'substeps': n, 'omega_h': round(omega * dt / n, 3),
                     'restitution_err_min_pct': round(100 * min(errs), 2),
                     'restitution_err_max_pct': round(100 * max(errs), 2),
                     'tilted_drop_pos_err_mm': round(1000 * math.dist(s[:3], ref[:3]), 2),
                     'tilted_drop_angle_err_deg':
                         round(math.degrees(math.dist(s[3:6], ref[3:6])), 3),
                     'tilted_drop_rate_err_radps': round(math.dist(s[6:], ref[6:]), 4)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--compiled', action='store_true')
    ap.add_argument('--ticks', type=int, default=20000)
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--substep-study', action='store_true')
    args = ap.parse_args()
    if args.substep_study:
        for pkg in ('deckland_common', 'deck_simulator', 'dob_altitude'):
            sys.path.insert(0, str(ROOT / 'src' / pkg))
        for row in substep_study():
            print(json.dumps(row))
        return
    with tempfile.TemporaryDirectory(prefix='bench-contact-') as tmp:
        if args.compiled:
            compile_into(pathlib.Path(tmp))
            sys.path.insert(0, tmp)
        else:
            for pkg in ('deckland_common', 'deck_simulator', 'dob_altitude'):
                sys.path.insert(0, str(ROOT / 'src' / pkg))
        runs = [measure(args.ticks) for _ in range(args.repeats)]
    best = {k: min(r[k] for r in runs) for k in runs[0] if k.endswith('_us_per_tick')}
    print(json.dumps({**runs[0], **{k: round(v, 2) for k, v in best.items()},
                      'ticks': args.ticks, 'repeats': args.repeats,
                      'python': platform.python_version(), 'machine': platform.machine()}))


if __name__ == '__main__':
    main()
