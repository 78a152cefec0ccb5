"""``deckland bag``: record, play, inspect and repair rosbag2 MCAP bags (rclpy + rosbags + mcap).

A bag is a directory ``DIR/`` holding ``metadata.yaml`` (rosbag2 storage version 9) and
``DIR/<name>_0.mcap`` (MCAP profile ``ros2``: ``ros2msg`` schemas with the full message
definitions, ``cdr`` channels whose metadata carries ``offered_qos_profiles`` and
``topic_type_hash``), i.e. what ``ros2 bag record -s mcap`` writes; Foxglove, ``ros2 bag info``,
rosbags' ``AnyReader`` and the ``mcap`` library all open it.

Crash safety (SIGKILL, power cut of the companion computer): the recorder finishes the
current MCAP chunk and flushes it to the file every ``flush_period_s`` (0.25 s), and rewrites
``metadata.yaml`` atomically every second, so a killed recorder leaves a file that is complete
up to the last flushed chunk but has no summary/footer. rosbags' reader refuses such a file
("File end magic is invalid") and the ``mcap`` library's seeking reader does too; its streaming
reader reads up to the cut. :func:`reindex` (``deckland bag reindex DIR``) copies every complete
record into a fresh, indexed MCAP and regenerates ``metadata.yaml``; ``bag info`` and
``bag play`` do that automatically for an unfinished bag that no recorder holds any more
(the recorder holds an ``flock`` on ``DIR/.recording.lock``, which the kernel releases when the
process dies, so a live recording is never rewritten under its writer).

Modules: :mod:`.writer` (MCAP + metadata), :mod:`.recorder` (rclpy subscriptions),
:mod:`.repair` (scan, lock, reindex), :mod:`.info`, :mod:`.play`, :mod:`.cli`. The names below
are the package's API.
"""

from deckland.ros.bag.cli import main, register
from deckland.ros.bag.info import BagInfo, TopicInfo, bag_info, format_info
from deckland.ros.bag.play import iter_messages, play
from deckland.ros.bag.recorder import Recorder
from deckland.ros.bag.repair import (
    ScanResult,
    ensure_readable,
    is_recording,
    mcap_is_finished,
    needs_reindex,
    reindex,
    scan_mcap,
)
from deckland.ros.bag.writer import (
    DEFAULT_EXCLUDES,
    LOCK_NAME,
    MCAP_MAGIC,
    BagWriter,
    metadata_dict,
    write_metadata,
)

__all__ = [
    'DEFAULT_EXCLUDES', 'LOCK_NAME', 'MCAP_MAGIC', 'BagInfo', 'BagWriter', 'Recorder',
    'ScanResult', 'TopicInfo', 'bag_info', 'ensure_readable', 'format_info', 'is_recording',
    'iter_messages', 'main', 'mcap_is_finished', 'metadata_dict', 'needs_reindex', 'play',
    'register', 'reindex', 'scan_mcap', 'write_metadata',
]
