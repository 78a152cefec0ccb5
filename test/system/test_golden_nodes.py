"""Golden bag, node replay: the estimator, planner and altitude nodes (own processes, this
session's ROS domain) get the recorded inputs through `deckland bag play` at rate 1.0 and
their outputs are compared with the recording within NODE_TOLERANCES."""

from pathlib import Path

import golden
import pytest

pytestmark = pytest.mark.timing   # a graph on the wall clock: reruns on a miss

BAG = Path(__file__).parents[1] / 'fixtures' / 'golden_paper'


def test_nodes_reproduce_the_recording(ros_context):
    context, executor = ros_context
    replayed, offset_s = golden.replay_nodes(BAG, context, executor)
    gold = golden.load(BAG)
    report = golden.compare(golden.recorded_outputs(gold), replayed, golden.NODE_TOLERANCES,
                            time_offset_s=offset_s)
    assert report.ok, '\n' + str(report)
    # the nodes flew the same mission: the recorded mode sequence, in order
    assert golden.mode_sequence(replayed.modes) == golden.mode_sequence(
        golden.recorded_outputs(gold).modes)
