"""Readiness lines: how a node process tells its orchestrator it is built (no rclpy).

The orchestrator passes the write end of one pipe to every child and names it in
``$DECKLAND_READY_FD``; a child writes one JSON line per node once the node is constructed
(parameters validated, sockets and devices opened, publishers created), ``problem`` saying
which device it could not open. A line is one ``write`` shorter than ``PIPE_BUF``, so lines
of several children never interleave.
"""

from __future__ import annotations

import contextlib
import json
import os
from typing import Any

READY_FD_ENV = 'DECKLAND_READY_FD'


def ready_line(node: str, pid: int, problem: str = '') -> bytes:
    """The line for ``node`` (``problem`` cut to 300 characters so the write stays atomic)."""
    return (json.dumps({'node': node, 'pid': pid, 'problem': problem[:300]}) + '\n').encode()


def parse_ready_line(line: str) -> dict[str, Any] | None:
    """``{'node', 'pid', 'problem'}`` of a readiness line, or None if it is not one."""
    try:
        msg = json.loads(line)
        return {'node': str(msg['node']), 'pid': int(msg['pid']),
                'problem': str(msg.get('problem', ''))}
    except (ValueError, KeyError, TypeError):
        return None


def write_ready(node: str, problem: str = '', environ: dict | None = None) -> bool:
    """Write the line to ``$DECKLAND_READY_FD`` if it is set; True when written."""
    fd = (os.environ if environ is None else environ).get(READY_FD_ENV, '')
    if not fd.isdigit():
        return False
    with contextlib.suppress(OSError):
        os.write(int(fd), ready_line(node, os.getpid(), problem))
        return True
    return False
