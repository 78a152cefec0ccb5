"""Writing rosbag2 MCAP bags: raw CDR messages into ``DIR/<name>_0.mcap`` and a current
``metadata.yaml`` (rosbag2 storage version 9)."""

from __future__ import annotations

from dataclasses import dataclass
import os
from pathlib import Path
import threading
from typing import Any

import yaml

from deckland.ros import rosio

MCAP_MAGIC = b'\x89MCAP0\r\n'
LOCK_NAME = '.recording.lock'
#: Topics that ``--all`` leaves out (ROS-internal noise, as rosbag2 users usually exclude).
DEFAULT_EXCLUDES = ('/rosout', '/parameter_events')



@dataclass
class _Channel:
    topic: str
    msgtype: str
    offered_qos: list[Any]
    type_hash: str
    channel_id: int
    count: int = 0


class BagWriter:
    """Appends raw CDR messages to ``DIR/<name>_0.mcap`` and keeps ``metadata.yaml`` current.

    Thread-safe (one lock). :meth:`flush` ends the current chunk and flushes it to the file:
    everything written before the last flush survives a SIGKILL (see module docstring).
    """

    def __init__(self, out_dir: str | os.PathLike[str]) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(out_dir)
        if self.path.exists() and any(self.path.iterdir()):
            raise FileExistsError(f'{self.path} exists and is not empty; not overwriting')
        self.path.mkdir(parents=True, exist_ok=True)
        self.mcap_path = self.path / f'{self.path.name}_0.mcap'
        self._stream = open(self.mcap_path, 'xb')  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._stream, compression=CompressionType.ZSTD,
                              chunk_size=4 * 1024 * 1024)
        self._writer.start(profile='ros2', library='deckland')
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self.channels: dict[str, _Channel] = {}
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.closed = False
        self._write_metadata()

    def add_topic(self, topic: str, msgtype: str, offered_qos: list[Any]) -> None:
        """Register a channel (once per topic); ``offered_qos`` are rosbags ``Qos`` records."""
        with self._lock:
            if topic in self.channels or self.closed:
                return
            msgdef, type_hash = rosio.message_definition(msgtype)
            schema_id = self._schemas.get(msgtype)
            if schema_id is None:
                schema_id = self._writer.register_schema(
                    name=msgtype, encoding='ros2msg', data=msgdef.encode())
                self._schemas[msgtype] = schema_id
            qos = list(offered_qos) or [rosio.default_offered_qos()]
            channel_id = self._writer.register_channel(
                topic=topic, message_encoding='cdr', schema_id=schema_id,
                metadata={'offered_qos_profiles': rosio.offered_qos_yaml(qos),
                          'topic_type_hash': type_hash})
            self.channels[topic] = _Channel(topic, msgtype, qos, type_hash, channel_id)

    def write(self, topic: str, t_ns: int, data: bytes, publish_ns: int | None = None,
              sequence: int = 0) -> None:
        with self._lock:
            channel = self.channels.get(topic)
            if channel is None or self.closed:
                return
            self._writer.add_message(channel.channel_id, log_time=t_ns, data=bytes(data),
                                     publish_time=t_ns if publish_ns is None else publish_ns,
                                     sequence=sequence & 0xFFFFFFFF)
            channel.count += 1
            self.start_ns = t_ns if self.start_ns is None else min(self.start_ns, t_ns)
            self.end_ns = t_ns if self.end_ns is None else max(self.end_ns, t_ns)

    def flush(self) -> None:
        """Finish the current chunk and push it to the OS (survives the process dying)."""
        with self._lock:
            if not self.closed:
                self._writer.flush()

    def update_metadata(self) -> None:
        with self._lock:
            if not self.closed:
                self._write_metadata()

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self._writer.add_metadata('rosbag2', {'serialized_metadata': yaml.safe_dump(
                self._metadata()['rosbag2_bagfile_information'], sort_keys=False)})
            self._writer.finish()
            self._stream.close()
            self.closed = True
            self._write_metadata()

    def _metadata(self) -> dict[str, Any]:
        topics = [(c.topic, c.msgtype, c.offered_qos, c.type_hash, c.count)
                  for c in self.channels.values()]
        return metadata_dict([(self.mcap_path.name, self.start_ns, self.end_ns)], topics)

    def _write_metadata(self) -> None:
        write_metadata(self.path, self._metadata())


def metadata_dict(files: list[tuple[str, int | None, int | None]],
                  topics: list[tuple[str, str, list[Any], str, int]]) -> dict[str, Any]:
    """rosbag2 ``metadata.yaml`` (version 9, MCAP) for files ``(name, start_ns, end_ns)`` and
    topics ``(name, type, offered rosbags Qos list, RIHS01 hash, count)``."""
    from rosbags.rosbag2.metadata import dump_qos_v9

    starts = [s for _, s, _ in files if s is not None]
    ends = [e for _, _, e in files if e is not None]
    start = min(starts) if starts else 0
    duration = max(ends) - start if ends else 0
    count = sum(t[4] for t in topics)
    return {'rosbag2_bagfile_information': {
        'version': 9,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': [
            {'topic_metadata': {'name': name, 'type': msgtype, 'serialization_format': 'cdr',
                                'offered_qos_profiles': dump_qos_v9(list(qos)),
                                'type_description_hash': type_hash},
             'message_count': n}
            for name, msgtype, qos, type_hash, n in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [name for name, _, _ in files],
        'files': [{'path': name,
                   'starting_time': {'nanoseconds_since_epoch': s or 0},
                   'duration': {'nanoseconds': (e - s) if s is not None and e is not None
                                else 0},
                   'message_count': count if len(files) == 1 else 0}
                  for name, s, e in files],
        'custom_data': {'recorded_by': 'deckland'},
        'ros_distro': 'jazzy',
    }}


def write_metadata(bag_dir: Path, metadata: dict[str, Any]) -> None:
    """Atomic write of ``metadata.yaml`` (a reader never sees half a file)."""
    tmp = bag_dir / 'metadata.yaml.tmp'
    tmp.write_text(yaml.safe_dump(metadata, sort_keys=False, default_flow_style=False))
    os.replace(tmp, bag_dir / 'metadata.yaml')
