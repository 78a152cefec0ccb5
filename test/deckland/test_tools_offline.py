"""deckland topic/bag helpers without a ROS graph: QoS rules, message rendering, rate
statistics, the MCAP bag writer, and crash recovery of a bag cut at arbitrary bytes."""

import math
from pathlib import Path
import random
import shutil

from deckland.ros import bag, rosio, topic
from geometry_msgs.msg import Point32, PoseStamped
from mcap.reader import make_reader
from nav_msgs.msg import Odometry
import pytest
from rclpy.qos import (
    DurabilityPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2.metadata import parse_qos
from sensor_msgs.msg import ChannelFloat32, PointCloud, Range
from std_msgs.msg import String
import yaml


def qos(rel, dur, depth=10):
    return QoSProfile(depth=depth, reliability=rel, durability=dur)


REL, BE = ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT
VOL, TL = DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL


# ---------------------------------------------------------------------------------- QoS rules

@pytest.mark.parametrize(('pubs', 'expected'), [
    ([], (REL, VOL)),
    ([(REL, VOL)], (REL, VOL)),
    ([(BE, VOL)], (BE, VOL)),
    ([(REL, VOL), (BE, VOL)], (BE, VOL)),        # one best-effort publisher -> best effort
    ([(REL, TL)], (REL, TL)),                    # latched topic stays latched
    ([(REL, TL), (REL, VOL)], (REL, VOL)),       # TL would not match the volatile one
    ([(BE, TL), (REL, TL)], (BE, TL)),
])
def test_subscription_qos_matches_every_publisher(pubs, expected):
    profile = rosio.subscription_qos([qos(r, d) for r, d in pubs], 'auto')
    assert (profile.reliability, profile.durability) == expected
    # Compatibility rule (RMW): a subscription requests no more than each publisher offers.
    for r, d in pubs:
        assert not (profile.reliability == REL and r == BE)
        assert not (profile.durability == TL and d == VOL)


def test_subscription_qos_modes():
    pubs = [qos(REL, TL)]
    assert rosio.subscription_qos(pubs, 'sensor').reliability == BE
    forced = rosio.subscription_qos([qos(BE, VOL)], 'reliable')
    assert (forced.reliability, forced.durability) == (REL, VOL)
    with pytest.raises(ValueError, match='qos mode'):
        rosio.subscription_qos(pubs, 'fast')


def test_offered_qos_roundtrip_through_rosbag2_yaml():
    offered = [rosio.qos_to_rosbags(qos_profile_sensor_data),
               rosio.qos_to_rosbags(qos(REL, TL, depth=1))]
    parsed = parse_qos(rosio.offered_qos_yaml(offered))
    assert [q.reliability.name for q in parsed] == ['BEST_EFFORT', 'RELIABLE']
    assert [q.durability.name for q in parsed] == ['VOLATILE', 'TRANSIENT_LOCAL']
    assert parsed[0].depth == qos_profile_sensor_data.depth
    # Republish: best effort because one recorded publisher was; volatile because not all TL.
    pub = rosio.publisher_qos_from_offered(parsed)
    assert (pub.reliability, pub.durability) == (BE, VOL)
    latched = rosio.publisher_qos_from_offered([parsed[1]])
    assert (latched.reliability, latched.durability) == (REL, TL)


def test_message_type_import():
    assert rosio.import_message_type('std_msgs/msg/String') is String
    assert rosio.import_message_type('sensor_msgs/Range') is Range
    assert rosio.message_type_name(PoseStamped) == 'geometry_msgs/msg/PoseStamped'
    for bad in ('nope_msgs/msg/Thing', 'std_msgs/msg/NoSuch', 'not a type'):
        with pytest.raises(ValueError):
            rosio.import_message_type(bad)


# ---------------------------------------------------------------------------------- rendering

def test_message_to_dict_and_yaml_roundtrip():
    odom = Odometry()
    odom.header.frame_id = 'map'
    odom.pose.pose.position.x = 1.25
    odom.pose.covariance[7] = 0.5
    d = rosio.message_to_dict(odom)
    assert list(d) == ['header', 'child_frame_id', 'pose', 'twist']
    assert len(d['pose']['covariance']) == 36 and d['pose']['covariance'][7] == 0.5
    text = topic.to_yaml(d)
    assert 'frame_id: map' in text and "child_frame_id: ''" in text
    assert yaml.safe_load(text) == d


def test_flatten_and_csv_columns():
    cloud = PointCloud()
    cloud.points = [Point32(x=10.0, y=20.0), Point32(x=30.0, y=40.0)]
    cloud.channels = [ChannelFloat32(name='signature', values=[1.0, 2.0])]
    pairs = topic.flatten(rosio.message_to_dict(cloud))
    paths = [p for p, _ in pairs]
    assert paths[:3] == ['header.stamp.sec', 'header.stamp.nanosec', 'header.frame_id']
    assert 'points[1].y' in paths and 'channels[0].values[1]' in paths
    assert dict(pairs)['points[1].x'] == 30.0
    line = topic.csv_line(['a,b', 0.1, 3])
    assert line == '"a,b",0.1,3'


def test_rate_meter_against_known_periods():
    rng = random.Random(7)
    meter = topic.RateMeter(window=500)
    t = 0.0
    periods = []
    for _ in range(1000):
        meter.add(t)
        p = 0.02 + rng.uniform(-0.002, 0.002)
        periods.append(p)
        t += p
    kept = periods[-501:-1]   # the window holds the last 500 periods
    stats = meter.stats()
    mean = sum(kept) / len(kept)
    assert stats.window == 500
    assert stats.rate_hz == pytest.approx(1.0 / mean, rel=1e-12)
    assert stats.min_s == pytest.approx(min(kept)) and stats.max_s == pytest.approx(max(kept))
    std = math.sqrt(sum((x - mean) ** 2 for x in kept) / len(kept))
    assert stats.std_s == pytest.approx(std, rel=1e-9)
    assert 49.0 < stats.rate_hz < 51.0


def test_rate_meter_rejects_bad_stamps_and_keeps_state():
    meter = topic.RateMeter()
    assert meter.stats() is None
    for t in (0.0, 0.1, float('nan'), 0.05, float('inf'), 0.2):
        meter.add(t)
    assert meter.rejected == {'nan': 2, 'out_of_order': 1}
    assert meter.stats().rate_hz == pytest.approx(10.0)
    with pytest.raises(ValueError, match='window'):
        topic.RateMeter(0)


# ------------------------------------------------------------------------------------- writer

def make_msgs(n, seed=3):
    """(topic, type, msg) triples, interleaved, with sequence numbers in the payload."""
    rng = random.Random(seed)
    out = []
    for i in range(n):
        kind = rng.choice(('s', 'r', 'p'))
        if kind == 's':
            out.append(('/chatter', 'std_msgs/msg/String', String(data=f'msg {i}')))
        elif kind == 'r':
            m = Range(range=float(i), min_range=0.25, max_range=40.0)
            m.header.frame_id = 'lidar_link'
            out.append(('/vehicle/range', 'sensor_msgs/msg/Range', m))
        else:
            m = PoseStamped()
            m.pose.position.x = float(i)
            m.pose.orientation.w = 1.0
            out.append(('/pose', 'geometry_msgs/msg/PoseStamped', m))
    return out


def write_bag(path, msgs, flush_every=None, close=True):
    writer = bag.BagWriter(path)
    offered = {'/chatter': [rosio.qos_to_rosbags(qos(REL, TL, 1))],
               '/vehicle/range': [rosio.qos_to_rosbags(qos_profile_sensor_data)],
               '/pose': [rosio.qos_to_rosbags(qos(REL, VOL))]}
    flushed_at = []
    for i, (name, msgtype, msg) in enumerate(msgs):
        writer.add_topic(name, msgtype, offered[name])
        writer.write(name, 1_000_000_000 + i * 10_000_000, serialize_message(msg))
        if flush_every and (i + 1) % flush_every == 0:
            writer.flush()
            flushed_at.append((i + 1, writer.mcap_path.stat().st_size))
    if close:
        writer.close()
    return writer, flushed_at


def read_anyreader(path):
    with AnyReader([Path(path)]) as reader:
        conns = {c.topic: c for c in reader.connections}
        msgs = [(c.topic, c.msgtype, t, bytes(d)) for c, t, d in reader.messages()]
    return conns, msgs


def test_bag_writer_reads_back_with_rosbags_and_mcap(tmp_path):
    msgs = make_msgs(60)
    write_bag(tmp_path / 'b', msgs)
    conns, read = read_anyreader(tmp_path / 'b')
    assert [(t, ty) for t, ty, _, _ in read] == [(t, ty) for t, ty, _ in msgs]
    for (_, ty, _, data), (_, _, msg) in zip(read, msgs, strict=True):
        # (not compared as bytes: rclpy leaves CDR alignment padding uninitialised)
        assert deserialize_message(data, rosio.import_message_type(ty)) == msg
    # Explicit offered QoS survives in metadata.yaml (rosbags reads it from there).
    assert conns['/chatter'].ext.offered_qos_profiles[0].durability.name == 'TRANSIENT_LOCAL'
    assert conns['/vehicle/range'].ext.offered_qos_profiles[0].reliability.name == 'BEST_EFFORT'
    # The mcap library: indexed reader, ros2msg schemas with full definitions, QoS metadata.
    with open(tmp_path / 'b' / 'b_0.mcap', 'rb') as f:
        reader = make_reader(f)
        assert reader.get_header().profile == 'ros2'
        seen = list(reader.iter_messages())
        summary = reader.get_summary()
    assert len(seen) == 60
    schema, channel, _ = seen[0]
    assert schema.encoding == 'ros2msg' and channel.message_encoding == 'cdr'
    assert 'offered_qos_profiles' in channel.metadata
    assert summary.statistics.message_count == 60
    rng_schema = next(s for s in summary.schemas.values() if s.name == 'sensor_msgs/msg/Range')
    assert b'MSG: std_msgs/Header' in rng_schema.data
    # And our own info agrees.
    info = bag.bag_info(tmp_path / 'b')
    assert info.message_count == 60 and not info.recording
    assert {t.name: t.msgtype for t in info.topics}['/pose'] == 'geometry_msgs/msg/PoseStamped'
    assert info.duration_s == pytest.approx(0.59)
    assert 'Topic information' in bag.format_info(info)


def test_writer_refuses_a_non_empty_directory(tmp_path):
    (tmp_path / 'x').mkdir()
    (tmp_path / 'x' / 'keep').write_text('data')
    with pytest.raises(FileExistsError):
        bag.BagWriter(tmp_path / 'x')


def test_truncated_bag_is_recovered_up_to_the_last_flushed_chunk(tmp_path):
    """A recorder killed mid-write leaves an MCAP without footer: rosbags refuses it,
    reindex keeps every message of every chunk that was completely on disk."""
    msgs = make_msgs(200, seed=11)
    writer, flushed = write_bag(tmp_path / 'live', msgs, flush_every=25, close=False)
    live = writer.mcap_path.read_bytes()
    writer.update_metadata()
    writer.close()
    # Where each chunk record ends (from the finished file's index; the prefix is identical).
    with open(writer.mcap_path, 'rb') as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)
    assert len(chunks) == len(flushed) == 8
    ends = [(25 * (i + 1), c.chunk_start_offset + c.chunk_length) for i, c in enumerate(chunks)]
    rng = random.Random(5)
    cuts = [len(live), ends[2][1], ends[2][1] - 1] + [rng.randrange(100, len(live))
                                                      for _ in range(6)]
    for k, cut in enumerate(cuts):
        d = tmp_path / f'cut{k}'
        d.mkdir()
        shutil.copy(tmp_path / 'live' / 'metadata.yaml', d / 'metadata.yaml')
        (d / 'live_0.mcap').write_bytes(live[:cut])
        assert bag.needs_reindex(d)
        with pytest.raises(Exception, match='magic'):
            read_anyreader(d)
        counts = bag.reindex(d)
        expected = max([n for n, end in ends if end <= cut], default=0)
        assert sum(counts.values()) == expected, (cut, ends)
        _, read = read_anyreader(d)
        assert [(t, ty) for t, ty, _, _ in read] == [(t, ty) for t, ty, _ in msgs[:expected]]
        assert not bag.needs_reindex(d)


def test_reindex_refuses_a_bag_held_by_a_live_recorder(tmp_path):
    import fcntl

    write_bag(tmp_path / 'b', make_msgs(5), close=True)
    with open(tmp_path / 'b' / bag.LOCK_NAME, 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert bag.is_recording(tmp_path / 'b')
        with pytest.raises(RuntimeError, match='being recorded'):
            bag.reindex(tmp_path / 'b')
    assert not bag.is_recording(tmp_path / 'b')


def test_cli_parsers_register_their_verbs():
    import argparse

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest='command')
    topic.register(sub)
    bag.register(sub)
    a = parser.parse_args(['topic', 'hz', 'vehicle/range', '--window', '50', '--count', '10'])
    assert a.func is topic.cmd_hz and a.window == 50 and a.count == 10
    a = parser.parse_args(['bag', 'record', '-o', 'x', '--all', '--duration', '2'])
    assert a.all and a.duration == 2.0
    a = parser.parse_args(['bag', 'play', 'x', '--rate', '2', '--loop', '--start-offset', '1'])
    assert a.rate == 2.0 and a.loop and a.start_offset == 1.0
    a = parser.parse_args(['topic', 'echo', 't', '--csv', '--qos', 'sensor'])
    assert a.csv and a.qos == 'sensor' and a.func is topic.cmd_echo
