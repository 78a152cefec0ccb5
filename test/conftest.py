"""Session-wide isolation for tests that start ROS nodes.

A random ROS_DOMAIN_ID per test session and localhost-only discovery are set before anything
imports rclpy, so parallel CI jobs and developers' machines never see each other's topics.
"""

import contextlib
import os
import random
import sys
import threading

# (under pytest-xdist each worker draws from its own half of 1-100: no two share a domain)
os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 50) + 50 * (
    int(os.environ.get('PYTEST_XDIST_WORKER', 'gw0')[2:] or 0) % 2))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RCUTILS_LOGGING_BUFFERED_STREAM', '1')
# Fast DDS without intra-process delivery, for this process and every graph it starts
# (isolated_env copies os.environ): see the comment in the profile.
os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = os.path.join(
    os.path.dirname(os.path.abspath(__file__)), 'fastdds_profile.xml')
# The tests patch and inspect the Python sources of the cores: never load the compiled build
# in this process (deckland/test_accel.py runs it in subprocesses of its own).
os.environ['DECKLAND_CORES'] = 'python'

from hypothesis import settings
import pytest

# Reproducible property tests: no example database carried between runs or machines.
settings.register_profile('deckland', database=None)
settings.load_profile('deckland')

sys.dont_write_bytecode = True



#: markers of tests whose pass depends on wall-clock scheduling: only these are retried
TIMING_MARKERS = ('ros', 'timing')


#: markers of tests that start graphs, nodes or firmware: under ``make test`` (pytest-xdist,
#: ``-n 2 --dist loadgroup``) they run one after another on one worker (group ``graph``)
#: while the pure tests (group ``cores``) run beside them, niced, on the other
#: (tests marked ``solo``, whole missions against the wall clock, run after, alone: beside the
#: parallel suite a slow 2-core machine starved their graph, 2026-12-07)
GRAPH_MARKERS = (*TIMING_MARKERS, 'sitl')


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Retry a timing-sensitive test twice before its failure counts (pytest-rerunfailures);
    put every test in the ``graph`` or the ``cores`` group (pytest-xdist).

    ``tryfirst``: xdist's worker turns the ``xdist_group`` marker into the ``@group`` suffix of
    the node id in its own hook of this name, which must see the marker."""
    for item in items:
        timing = any(item.get_closest_marker(m) for m in TIMING_MARKERS)
        if timing and not item.get_closest_marker('flaky'):
            item.add_marker(pytest.mark.flaky(reruns=2, reruns_delay=1))
        graph = any(item.get_closest_marker(m) for m in GRAPH_MARKERS)
        item.add_marker(pytest.mark.xdist_group('graph' if graph else 'cores'))


def pytest_xdist_node_collection_finished(node, ids):
    """Under ``--dist loadgroup`` every node id must carry its group, else xdist schedules the
    graph tests on both workers at once, silently: pytest 9.2 drops the suffix (pytest-xdist
    #1386; the CI of 2026-12-07 hung so, past its 90 min). Stops the run with the reason."""
    if node.config.getoption('dist', None) == 'loadgroup':
        lost = [i for i in ids if '@' not in i]
        if lost:
            pytest.exit(f'pytest-xdist lost the test groups ({len(lost)} node ids without '
                        f'"@group", e.g. {lost[0]}): pytest {pytest.__version__} with this '
                        'pytest-xdist cannot run `make test`; install the pinned versions '
                        '(requirements.txt)',
                        returncode=3)


def pytest_runtest_setup(item):
    """On an xdist worker, the first pure test lowers the worker's priority (niceness 10, its
    subprocesses too): the graphs' wall-clock deadlines on the other worker come first."""
    if int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1')) >= 2 and not _NICED:
        group = item.get_closest_marker('xdist_group')
        if group is not None and group.args and group.args[0] == 'cores':
            os.nice(10)
            _NICED.append(True)


_NICED: list[bool] = []


@pytest.fixture
def ros_context():
    """A private rclpy context with a single-threaded executor spinning in a thread.

    Yields ``(context, executor)``; add nodes with ``executor.add_node(node)``. Teardown
    shuts the executor and the context down and joins the thread.

    Single-threaded on purpose. rclpy 7.1's MultiThreadedExecutor, with a node under test and a
    helper publishing at 100 Hz in one process, spent ~93 % of a core on dispatch and fired the
    helper's 10 ms timer 19-68 times in 3 s (300 expected); the SingleThreadedExecutor fired it
    300 times at ~34 % of a core (measured 2026-11-22, same machine, same nodes). The starvation
    depended on machine load, which is why these tests passed on some runs and not others.
    Test code blocks only in the test thread (``wait_for`` on futures), never in a callback, so
    one executor thread is enough.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    added = []                  # every node ever added, even if a test removed it again
    add_node = executor.add_node

    def add_and_remember(node):
        added.append(node)
        return add_node(node)

    executor.add_node = add_and_remember
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield context, executor
    finally:
        # shutdown() forgets the executor's nodes, so they are destroyed from ``added``: a node
        # never destroyed keeps its own threads (the estimator's loop, the bridge's reader)
        # running for the rest of the worker's session (2026-12-08: 12 loops and 7 readers by
        # the bridge tests, 30-60 % of a core between tests)
        executor.shutdown(timeout_sec=2.0)
        for node in reversed(added):
            with contextlib.suppress(Exception):     # already destroyed by the test
                node.destroy_node()
        context.try_shutdown()
        thread.join(timeout=5.0)
