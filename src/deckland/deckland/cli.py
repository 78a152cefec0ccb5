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
    'deckland.campaign',
    'deckland.up',
    'deckland.topic',
    'deckland.bag',
    'deckland.plot',
    'deckland.bench',
    'deckland.tune',
)


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
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
