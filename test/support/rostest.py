"""Helpers for tests that start ROS nodes or whole graphs (the session's isolation itself is
set up by test/conftest.py before anything imports rclpy)."""

import os
import random
import socket
import time


def wait_for(pred, timeout_s=5.0):
    """Poll ``pred()`` every 10 ms until it is true (True) or ``timeout_s`` passes (False)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def free_udp_port() -> int:
    """A loopback UDP port free now (racy: for tests whose binder takes no socket)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def isolated_env(**extra: str) -> dict:
    """Environment for a subprocess graph: its own ROS domain, apart from this session's.

    A whole graph started by a test (``deckland up``, a bench) must not hear another test's
    nodes (e.g. a latched ``sim/outcome`` of a simulator another test has not yet torn down).
    """
    domain = random.SystemRandom().choice(
        [d for d in range(101, 201) if d != int(os.environ['ROS_DOMAIN_ID'])])
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1', **extra)
