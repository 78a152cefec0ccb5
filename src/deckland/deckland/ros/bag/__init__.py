"""``deckland bag``: record, play, inspect and repair rosbag2 MCAP bags (rclpy + rosbags + mcap).

More in the package README, "Module notes" (`deckland.ros.bag`).
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
