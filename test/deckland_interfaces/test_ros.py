"""deckland_interfaces over a live graph: `deckland topic echo` prints the fields by name
(nested messages, arrays, sequences), and `deckland bag` records a custom type, plays it back
through a real publisher and records it again unchanged."""

import argparse
import io
from pathlib import Path
import random
import threading
import time

from deckland.ros import bag, topic
import pytest
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
import yaml

from deckland_interfaces.msg import ApronState, Rival

pytestmark = [pytest.mark.ros]


class ApronTalker:
    """50 Hz ApronState publisher (best effort, like a sensor stream): tick i in the
    vertical filter's surface_epoch, i % 3 rivals."""

    def __init__(self, context, executor, name):
        import rclpy

        self.node = rclpy.create_node(name.strip('/').replace('/', '_'), context=context)
        self.pub = self.node.create_publisher(ApronState, name, qos_profile_sensor_data)
        self.i = 0
        self.lock = threading.Lock()
        self.executor = executor
        self.timer = self.node.create_timer(0.02, self._tick)
        executor.add_node(self.node)

    def _tick(self):
        with self.lock:
            self.i += 1
            i = self.i
        m = ApronState(source=ApronState.SOURCE_BEACON, tracked=True, time_since_seen_s=0.25)
        m.header.frame_id = 'map'
        m.rel_position_m = [0.5, -0.25]
        m.vertical.valid = True
        m.vertical.surface_epoch = i
        m.rivals = [Rival(offset_m=[0.6, 0.0], hits=i % 7, confirmed=False)] * (i % 3)
        self.pub.publish(m)

    def stop(self):
        self.timer.cancel()
        self.executor.remove_node(self.node)
        self.node.destroy_node()


def _ns():
    return f'/ifc{random.SystemRandom().randrange(10**6)}'


def test_topic_echo_prints_a_custom_type_by_field_name(ros_context):
    context, executor = ros_context
    name = _ns() + '/apron/state'
    talker = ApronTalker(context, executor, name)
    try:
        args = argparse.Namespace(topic=name, timeout=5.0, count=3, duration=20.0, qos='auto',
                                  csv=False, out=io.StringIO(), err=io.StringIO())
        assert topic.cmd_echo(args) == 0, args.err.getvalue()
    finally:
        talker.stop()
    docs = [d for d in yaml.safe_load_all(args.out.getvalue()) if d is not None]
    assert len(docs) == 3
    d = docs[0]
    assert d['header']['frame_id'] == 'map'
    assert d['source'] == ApronState.SOURCE_BEACON and d['tracked'] is True
    assert d['rel_position_m'] == [0.5, -0.25]
    assert d['vertical']['valid'] is True and d['vertical']['height_m'] == 0.0
    assert d['deck_orientation'] == {'x': 0.0, 'y': 0.0, 'z': 0.0, 'w': 1.0}
    epochs = [doc['vertical']['surface_epoch'] for doc in docs]
    assert epochs == list(range(epochs[0], epochs[0] + 3))
    for doc in docs:
        assert len(doc['rivals']) == doc['vertical']['surface_epoch'] % 3
        for rv in doc['rivals']:
            assert set(rv) == {'offset_m', 'hits', 'confirmed', 'sampled', 'surface_level_m',
                               'rejected', 'time_since_seen_s'}


def _epochs(bag_dir):
    with AnyReader([Path(bag_dir)]) as reader:
        assert [c.msgtype for c in reader.connections] == ['deckland_interfaces/msg/ApronState']
        return [deserialize_message(bytes(raw), ApronState).vertical.surface_epoch
                for _, _, raw in reader.messages()]


def test_bag_records_and_plays_a_custom_type(ros_context, tmp_path):
    context, executor = ros_context
    name = _ns() + '/apron/state'
    talker = ApronTalker(context, executor, name)
    rec = bag.Recorder(tmp_path / 'one', topics=[name], context=context,
                       discovery_period_s=0.2)
    rec.start()
    try:
        assert rec.wait_for_subscriptions(1, timeout_s=5.0)
        time.sleep(1.0)
    finally:
        rec.stop()
        talker.stop()
    one = _epochs(tmp_path / 'one')
    assert len(one) >= 20 and one == list(range(one[0], one[0] + len(one)))
    info = bag.bag_info(tmp_path / 'one')
    assert [t.msgtype for t in info.topics] == ['deckland_interfaces/msg/ApronState']

    rec2 = bag.Recorder(tmp_path / 'two', topics=[name], context=context,
                        discovery_period_s=0.1)
    rec2.start()
    try:
        n = bag.play(tmp_path / 'one', rate=4.0, context=context, wait_for_subscribers_s=5.0)
        # until the recorder has taken the last one (a fixed 0.3 s lost it under CI load)
        end = time.monotonic() + 5.0
        while sum(rec2.counts.values()) < n and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        rec2.stop()
    assert n == len(one)
    assert _epochs(tmp_path / 'two') == one
