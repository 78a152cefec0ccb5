"""A bag written with deckland_interfaces types carries their definitions: the mcap library
finds ros2msg schemas with every nested type, the channel's RIHS01 hash is rosidl's, and a
reader that knows nothing of deckland (a plain Jazzy typestore, as Foxglove or ros2 bag on
another machine) decodes the messages from the bag's own text."""

import json
from pathlib import Path
import sys

from deckland.ros import bag, rosio
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from deckland_interfaces.msg import ApronState, PlannerStatus, Rival

SHARE = Path(sys.prefix) / 'share' / 'deckland_interfaces' / 'msg'


def apron(i):
    m = ApronState(source=ApronState.SOURCE_BEACON, tracked=True, visible=i % 2 == 0,
                   time_since_seen_s=0.02 * i, ambiguous=i % 3 == 0)
    m.header.frame_id = 'map'
    m.header.stamp.sec, m.header.stamp.nanosec = 100 + i, 5
    m.rel_position_m = [0.1 * i, -0.2]
    m.rel_position_cov_m2 = [0.01, 0.0, 0.0, 0.02]
    m.vertical.valid = True
    m.vertical.height_m = 1.5 - 0.01 * i
    m.vertical.surface_epoch = i
    m.rivals = [Rival(offset_m=[0.6, 0.0], hits=5, confirmed=True)] * (i % 3)
    return m


def status(i):
    m = PlannerStatus(mode=PlannerStatus.MODE_DESCEND, previous_mode=PlannerStatus.MODE_ALIGN,
                      reason='horizontally close for 1.0 s (Step 5 → Step 6)', paper_step=6)
    m.reference.vertical_frame = m.reference.VERTICAL_RELATIVE
    m.reference.z_d_m = 1.0 - 0.01 * i
    return m


def write(tmp_path, n=20):
    w = bag.BagWriter(tmp_path / 'b')
    w.add_topic('/apron/state', 'deckland_interfaces/msg/ApronState',
                [rosio.default_offered_qos()])
    w.add_topic('/planner/status', 'deckland_interfaces/msg/PlannerStatus',
                [rosio.default_offered_qos(transient_local=True)])
    for i in range(n):
        w.write('/apron/state', 10**9 + i * 10**7, serialize_message(apron(i)))
        w.write('/planner/status', 10**9 + i * 10**7 + 1, serialize_message(status(i)))
    w.close()
    return tmp_path / 'b'


def rosidl_hash(name):
    desc = json.loads((SHARE / f'{name}.json').read_text())
    return desc['type_hashes'][0]['hash_string']


def test_the_bag_carries_full_definitions_and_rosidl_hashes(tmp_path):
    path = write(tmp_path)
    with open(path / 'b_0.mcap', 'rb') as f:
        summary = make_reader(f).get_summary()
    schemas = {s.name: s for s in summary.schemas.values()}
    apron_schema = schemas['deckland_interfaces/msg/ApronState']
    assert apron_schema.encoding == 'ros2msg'
    text = apron_schema.data.decode()
    for nested in ('deckland_interfaces/VerticalState', 'deckland_interfaces/Rival',
                   'geometry_msgs/Quaternion', 'std_msgs/Header', 'builtin_interfaces/Time'):
        assert f'MSG: {nested}\n' in text, nested
    assert 'uint8 SOURCE_BEACON=1' in text and 'float64[4] rel_position_cov_m2' in text
    assert 'uint8 MODE_FINAL=5' in schemas['deckland_interfaces/msg/PlannerStatus'].data.decode()
    hashes = {c.topic: c.metadata['topic_type_hash'] for c in summary.channels.values()}
    assert hashes == {'/apron/state': rosidl_hash('ApronState'),
                      '/planner/status': rosidl_hash('PlannerStatus')}
    # metadata.yaml (what ros2 bag info reads) names the types and the same hashes
    info = bag.bag_info(path)
    assert {t.name: t.msgtype for t in info.topics} == {
        '/apron/state': 'deckland_interfaces/msg/ApronState',
        '/planner/status': 'deckland_interfaces/msg/PlannerStatus'}
    assert rosidl_hash('ApronState') in (path / 'metadata.yaml').read_text()


def _split_definition(name, text):
    """rosbag2's concatenated definition -> {type name: .msg text}."""
    parts = text.split('=' * 80 + '\n')
    out = {name: parts[0]}
    for part in parts[1:]:
        head, _, body = part.partition('\n')
        out[head.removeprefix('MSG: ')] = body
    return out


def test_a_reader_without_deckland_decodes_from_the_bag_alone(tmp_path):
    path = write(tmp_path)
    plain = get_typestore(Stores.ROS2_JAZZY)
    assert 'deckland_interfaces/msg/ApronState' not in plain.types
    with open(path / 'b_0.mcap', 'rb') as f:
        reader = make_reader(f)
        decoded = []
        for schema, _, message in reader.iter_messages(topics=['/apron/state']):
            if schema.name not in plain.types:
                for name, body in _split_definition(schema.name,
                                                    schema.data.decode()).items():
                    if name.startswith('deckland_interfaces'):
                        plain.register(get_types_from_msg(body, name))
            decoded.append(plain.deserialize_cdr(message.data, schema.name))
    assert [d.vertical.surface_epoch for d in decoded] == list(range(20))
    assert [len(d.rivals) for d in decoded] == [i % 3 for i in range(20)]
    assert decoded[7].rel_position_m[0] == 0.1 * 7
    assert decoded[4].vertical.height_m == 1.5 - 0.04
    # rosbags' AnyReader builds its types from the bag's definitions too
    with AnyReader([path]) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert [m.reason for m in msgs if hasattr(m, 'reason')] == [status(0).reason] * 20
    assert all(m.paper_step == 6 for m in msgs if hasattr(m, 'paper_step'))
