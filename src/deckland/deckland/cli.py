"""The ``deckland`` command: one console script, one subcommand per tool.

Each tool module exposes ``register(subparsers)`` which adds its subcommand(s) and sets
``func`` (``func(args) -> int``, the exit status) as the parser default.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Tool modules, in the order their subcommands are listed in ``deckland --help``.
TOOL_MODULES = (
    'deckland.batch.campaign',
    'deckland.graph.up',
    'deckland.ros.topic',
    'deckland.ros.bag',
    'deckland.plot',
    'deckland.graph.bench',
    'deckland.graph.viz',
    'deckland.batch.tune',
    'deckland.batch.accel',
)

#: Subcommands that fly the in-process simulator: ``--cores`` picks Python or compiled cores.
BATCH_COMMANDS = ('campaign', 'sim', 'tune')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='deckland',
        description='deckland: precision landing on a heaving deck (ROS 2 Jazzy).')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for name in TOOL_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # before build_parser: the tool modules import the cores, and a core module can only be
    # loaded compiled if nothing imported it yet (deckland.batch.accel)
    from deckland.batch.accel import select_from_argv
    select_from_argv(argv, BATCH_COMMANDS)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
