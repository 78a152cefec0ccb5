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
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Iterator
import contextlib
from dataclasses import dataclass, field
import datetime
import fcntl
import os
from pathlib import Path
import sys
import threading
import time
from typing import Any

import yaml

from deckland import rosio

MCAP_MAGIC = b'\x89MCAP0\r\n'
LOCK_NAME = '.recording.lock'
#: Topics that ``--all`` leaves out (ROS-internal noise, as rosbag2 users usually exclude).
DEFAULT_EXCLUDES = ('/rosout', '/parameter_events')


# ===================================================================================== writing


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


# ==================================================================================== recorder


class Recorder:
    """Records topics into a rosbag2 MCAP bag with raw (CDR) subscriptions.

    ``topics``: names to record (subscribed as soon as each appears); ``all_topics``: every
    topic, including ones that appear later (discovery every ``discovery_period_s``).
    Subscriptions match the publishers' QoS (:func:`rosio.subscription_qos`). ``context``:
    an initialised rclpy context to create the node in (e.g. ``deckland up``'s); by default a
    private one. :meth:`start` spins in a background thread; :meth:`stop` finishes the bag.
    """

    def __init__(self, out_dir: str | os.PathLike[str], topics: list[str] | None = None,
                 all_topics: bool = False, context: Any = None, *,
                 discovery_period_s: float = 1.0, flush_period_s: float = 0.25,
                 metadata_period_s: float = 1.0, depth: int = 100,
                 exclude: Iterable[str] = DEFAULT_EXCLUDES,
                 node_name: str = 'deckland_recorder') -> None:
        if not topics and not all_topics:
            raise ValueError('Recorder needs topics or all_topics=True')
        for name, value in (('discovery_period_s', discovery_period_s),
                            ('flush_period_s', flush_period_s),
                            ('metadata_period_s', metadata_period_s)):
            if not value > 0:
                raise ValueError(f'{name} must be > 0, got {value!r}')
        if depth < 1:
            raise ValueError(f'depth must be >= 1, got {depth!r}')
        self.out_dir = Path(out_dir)
        self.topics = [rosio.normalize_topic(t) for t in (topics or [])]
        self.all_topics = all_topics
        self.exclude = {rosio.normalize_topic(t) for t in exclude}
        self.discovery_period_s = discovery_period_s
        self.flush_period_s = flush_period_s
        self.metadata_period_s = metadata_period_s
        self.depth = depth
        self._context = context
        self._node_name = node_name
        self._session: rosio.RosSession | None = None
        self._writer: BagWriter | None = None
        self._lock_file: Any = None
        self._subscriptions: dict[str, Any] = {}
        self.skipped: dict[str, str] = {}
        self._timers: list[Any] = []

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic so far."""
        if self._writer is None:
            return {}
        return {t: c.count for t, c in self._writer.channels.items()}

    @property
    def subscribed(self) -> list[str]:
        return sorted(self._subscriptions)

    def start(self) -> Recorder:
        if self._session is not None:
            raise RuntimeError('Recorder already started')
        self._writer = BagWriter(self.out_dir)
        self._lock_file = open(self.out_dir / LOCK_NAME, 'w')  # noqa: SIM115
        fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._lock_file.write(f'{os.getpid()}\n')
        self._lock_file.flush()
        self._session = rosio.RosSession(self._node_name, self._context)
        node = self._session.node
        self._discover()
        self._timers = [node.create_timer(self.discovery_period_s, self._discover),
                        node.create_timer(self.flush_period_s, self._writer.flush),
                        node.create_timer(self.metadata_period_s, self._writer.update_metadata)]
        self._session.spin_in_thread()
        return self

    def wait_for_subscriptions(self, n: int, timeout_s: float = 5.0) -> bool:
        """Block until ``n`` topics are subscribed (handy in tests and launchers)."""
        deadline = time.monotonic() + timeout_s
        while len(self._subscriptions) < n:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def stop(self) -> None:
        """Finish the bag (footer, index, metadata.yaml) and release the node and lock."""
        session, self._session = self._session, None
        if session is not None:
            session.close()
        if self._writer is not None:
            self._writer.close()
        if self._lock_file is not None:
            with contextlib.suppress(OSError):
                (self.out_dir / LOCK_NAME).unlink()
            self._lock_file.close()
            self._lock_file = None

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _discover(self) -> None:
        session, writer = self._session, self._writer
        if session is None or writer is None:
            return
        available = session.topic_types()
        wanted = (sorted(t for t in available if t not in self.exclude) if self.all_topics
                  else self.topics)
        for topic in wanted:
            if topic in self._subscriptions or topic in self.skipped:
                continue
            types = available.get(topic)
            pub_qos = session.publisher_qos(topic) if types else []
            if not types or not pub_qos:
                continue  # not published (yet)
            msgtype = types[0]
            try:
                cls = rosio.import_message_type(msgtype)
            except ValueError as exc:
                self.skipped[topic] = str(exc)
                session.node.get_logger().warning(f'not recording {topic}: {exc}')
                continue
            writer.add_topic(topic, msgtype, [rosio.qos_to_rosbags(q) for q in pub_qos])
            qos = rosio.subscription_qos(pub_qos, 'auto', depth=self.depth)

            def callback(data: bytes, info: Any, _topic: str = topic) -> None:
                received = int(info.get('received_timestamp', 0)) or time.time_ns()
                writer.write(_topic, received, data, int(info.get('source_timestamp', 0))
                             or received, int(info.get('publication_sequence_number', 0)))

            self._subscriptions[topic] = session.node.create_subscription(
                cls, topic, callback, qos, raw=True)


# ============================================================================ reading, repair


@dataclass
class ScanResult:
    """What a tolerant pass over one MCAP file found."""

    schemas: dict[int, Any] = field(default_factory=dict)
    channels: dict[int, Any] = field(default_factory=dict)
    messages: list[Any] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    complete: bool = False     # footer reached
    error: str = ''            # why the scan stopped early


def mcap_is_finished(path: Path) -> bool:
    """True if the file ends with an MCAP footer and magic (a cleanly closed writer)."""
    try:
        size = path.stat().st_size
        if size < 8 + 37:
            return False
        with open(path, 'rb') as f:
            f.seek(-37, os.SEEK_END)
            tail = f.read()
    except OSError:
        return False
    return tail[-8:] == MCAP_MAGIC and tail[0] == 0x02


def scan_mcap(path: Path, keep_messages: bool = False) -> ScanResult:
    """Read every complete record of an MCAP, stopping quietly at a truncation.

    A chunk cut by a crash is dropped whole (its CRC/length cannot be satisfied); the
    messages of every earlier chunk are kept.
    """
    from mcap.records import Channel, Footer, Message, Schema
    from mcap.stream_reader import StreamReader

    res = ScanResult()
    with open(path, 'rb') as f:
        reader = StreamReader(f, validate_crcs=True)
        try:
            for record in reader.records:
                if isinstance(record, Message):
                    res.counts[record.channel_id] = res.counts.get(record.channel_id, 0) + 1
                    t = record.log_time
                    res.start_ns = t if res.start_ns is None else min(res.start_ns, t)
                    res.end_ns = t if res.end_ns is None else max(res.end_ns, t)
                    if keep_messages:
                        res.messages.append(record)
                elif isinstance(record, Schema):
                    res.schemas[record.id] = record
                elif isinstance(record, Channel):
                    res.channels[record.id] = record
                elif isinstance(record, Footer):
                    res.complete = True
        except Exception as exc:  # truncated or corrupt tail: keep what was complete
            res.error = f'{type(exc).__name__}: {exc}'.strip()
    return res


def _qos_from_channel(channel: Any) -> list[Any]:
    from rosbags.rosbag2.metadata import parse_qos

    text = channel.metadata.get('offered_qos_profiles', '')
    try:
        return parse_qos(text) if text else []
    except Exception:
        return []


def _bag_files(bag_dir: Path) -> list[Path]:
    meta = bag_dir / 'metadata.yaml'
    names: list[str] = []
    if meta.exists():
        with contextlib.suppress(Exception):
            info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
            names = [Path(p).name for p in info.get('relative_file_paths', [])]
    files = [bag_dir / n for n in names if (bag_dir / n).exists()]
    return files or sorted(bag_dir.glob('*.mcap'))


def is_recording(bag_dir: str | os.PathLike[str]) -> bool:
    """True while a live recorder holds the bag's lock (released even by SIGKILL)."""
    lock = Path(bag_dir) / LOCK_NAME
    if not lock.exists():
        return False
    with open(lock, 'a') as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return True
        fcntl.flock(f, fcntl.LOCK_UN)
    return False


def needs_reindex(bag_dir: str | os.PathLike[str]) -> bool:
    bag = Path(bag_dir)
    files = _bag_files(bag)
    return (not files or not (bag / 'metadata.yaml').exists()
            or any(not mcap_is_finished(p) for p in files))


def reindex(bag_dir: str | os.PathLike[str]) -> dict[str, int]:
    """Repair a bag whose recorder died: rewrite unfinished MCAP files with every complete
    record (plus summary, index and footer) and regenerate ``metadata.yaml`` from the files.

    Returns messages per topic. Refuses (RuntimeError) while a recorder holds the bag.
    """
    from mcap.writer import CompressionType, Writer

    bag = Path(bag_dir)
    if is_recording(bag):
        raise RuntimeError(f'{bag} is being recorded right now; not touching it')
    files = _bag_files(bag)
    if not files:
        raise FileNotFoundError(f'no .mcap file in {bag}')
    topics: dict[str, list[Any]] = {}
    file_rows = []
    for path in files:
        finished = mcap_is_finished(path)
        scan = scan_mcap(path, keep_messages=not finished)
        if not finished:
            tmp = path.with_name(path.name + '.reindex.tmp')
            with open(tmp, 'wb') as out:
                writer = Writer(out, compression=CompressionType.ZSTD)
                writer.start(profile='ros2', library='deckland-reindex')
                schema_map = {sid: writer.register_schema(s.name, s.encoding, s.data)
                              for sid, s in scan.schemas.items()}
                channel_map = {cid: writer.register_channel(
                    c.topic, c.message_encoding, schema_map.get(c.schema_id, 0), c.metadata)
                    for cid, c in scan.channels.items()}
                for m in scan.messages:
                    if m.channel_id in channel_map:
                        writer.add_message(channel_map[m.channel_id], m.log_time, m.data,
                                           m.publish_time, m.sequence)
                writer.finish()
            os.replace(tmp, path)
        file_rows.append((path.name, scan.start_ns, scan.end_ns))
        for cid, channel in scan.channels.items():
            schema = scan.schemas.get(channel.schema_id)
            msgtype = schema.name if schema is not None else ''
            row = topics.setdefault(channel.topic, [channel.topic, msgtype,
                                                    _qos_from_channel(channel),
                                                    channel.metadata.get('topic_type_hash', ''),
                                                    0])
            row[4] += scan.counts.get(cid, 0)
    write_metadata(bag, metadata_dict(file_rows, [tuple(r) for r in topics.values()]))
    with contextlib.suppress(OSError):
        (bag / LOCK_NAME).unlink()  # stale: its holder is gone (checked above)
    return {name: row[4] for name, row in topics.items()}


def ensure_readable(bag_dir: str | os.PathLike[str], log: Any = None) -> bool:
    """Reindex an unfinished bag that no recorder holds; True if it is readable now."""
    bag = Path(bag_dir)
    if not needs_reindex(bag):
        return True
    if is_recording(bag):
        return False
    if log is not None:
        print(f'{bag}: unfinished bag (recorder killed?), reindexing', file=log)
    reindex(bag)
    return True


@dataclass(frozen=True, slots=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int
    offered_qos: tuple[Any, ...]


@dataclass(frozen=True, slots=True)
class BagInfo:
    path: str
    files: tuple[str, ...]
    size_bytes: int
    storage: str
    start_ns: int
    end_ns: int
    message_count: int
    topics: tuple[TopicInfo, ...]
    recording: bool          # a live recorder holds the bag (numbers are a snapshot)

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) / 1e9


def bag_info(bag_dir: str | os.PathLike[str], recover: bool = True) -> BagInfo:
    """Topics, types, counts, times and size. A finished bag is read with rosbags'
    ``AnyReader``; an unfinished one is reindexed first (``recover``) or, while it is being
    recorded, scanned read-only."""
    bag = Path(bag_dir)
    if not bag.is_dir():
        raise FileNotFoundError(f'{bag} is not a bag directory')
    recording = is_recording(bag)
    if recover and not recording:
        ensure_readable(bag)
    files = _bag_files(bag)
    size = sum(p.stat().st_size for p in files) + (
        (bag / 'metadata.yaml').stat().st_size if (bag / 'metadata.yaml').exists() else 0)
    if not recording and not needs_reindex(bag):
        from rosbags.highlevel import AnyReader

        with AnyReader([bag]) as reader:
            per_topic: dict[str, list[Any]] = {}
            for c in reader.connections:
                row = per_topic.setdefault(c.topic, [c.msgtype, 0, c.ext.offered_qos_profiles])
                row[1] += c.msgcount
            n = reader.message_count
            start = reader.start_time if n else 0
            end = reader.end_time - 1 if n else 0
        topics = tuple(TopicInfo(t, r[0], r[1], tuple(r[2])) for t, r in per_topic.items())
        return BagInfo(str(bag), tuple(p.name for p in files), size, 'mcap', start, end, n,
                       topics, False)
    rows: dict[str, list[Any]] = {}
    starts, ends = [], []
    for path in files:
        scan = scan_mcap(path)
        if scan.start_ns is not None:
            starts.append(scan.start_ns)
            ends.append(scan.end_ns)
        for cid, ch in scan.channels.items():
            schema = scan.schemas.get(ch.schema_id)
            row = rows.setdefault(ch.topic, [schema.name if schema else '', 0,
                                             _qos_from_channel(ch)])
            row[1] += scan.counts.get(cid, 0)
    topics = tuple(TopicInfo(t, r[0], r[1], tuple(r[2])) for t, r in rows.items())
    return BagInfo(str(bag), tuple(p.name for p in files), size, 'mcap',
                   min(starts) if starts else 0, max(ends) if ends else 0,
                   sum(t.count for t in topics), topics, recording)


def format_info(info: BagInfo) -> str:
    def stamp(ns: int) -> str:
        dt = datetime.datetime.fromtimestamp(ns / 1e9, tz=datetime.UTC)
        return f'{dt:%b %d %Y %H:%M:%S}.{ns % 10**9 // 10**6:03d} UTC ({ns / 1e9:.9f})'

    size = float(info.size_bytes)
    unit = 'B'
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if size < 1024 or unit == 'GiB':
            break
        size /= 1024
    lines = [
        f'Files:             {", ".join(info.files)}',
        f'Bag size:          {size:.1f} {unit}',
        f'Storage id:        {info.storage}',
        f'Duration:          {info.duration_s:.3f}s',
        f'Start:             {stamp(info.start_ns)}',
        f'End:               {stamp(info.end_ns)}',
        f'Messages:          {info.message_count}',
    ]
    if info.recording:
        lines.append('State:             being recorded (snapshot of flushed chunks)')
    width = max((len(t.name) for t in info.topics), default=0)
    head = 'Topic information: '
    for i, t in enumerate(info.topics):
        rel = ', '.join(sorted({q.reliability.name.lower() for q in t.offered_qos})) or '?'
        dur = ', '.join(sorted({q.durability.name.lower() for q in t.offered_qos})) or '?'
        lines.append(f'{head if i == 0 else " " * len(head)}Topic: {t.name:<{width}} | '
                     f'Type: {t.msgtype} | Count: {t.count} | Serialization Format: cdr | '
                     f'QoS: {rel}/{dur}')
    if not info.topics:
        lines.append(head)
    return '\n'.join(lines)


# ======================================================================================= play


def play(bag_dir: str | os.PathLike[str], rate: float = 1.0, topics: list[str] | None = None,
         context: Any = None, *, loop: bool = False, start_offset_s: float = 0.0,
         delay_s: float = 0.0, wait_for_subscribers_s: float = 0.0,
         stop_event: threading.Event | None = None, log: Any = None) -> int:
    """Republish a bag's raw CDR data with the recorded timing; returns messages published.

    Timing is relative to the first message played (after ``start_offset_s``), scaled by
    ``1/rate``; publishers use the QoS of the recorded offered profiles
    (:func:`rosio.publisher_qos_from_offered`). ``wait_for_subscribers_s`` waits up to that
    long for every publisher to be matched before the first message (discovery takes a few
    hundred ms). ``stop_event`` ends playback early (also between loops).
    """
    from rosbags.highlevel import AnyReader

    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate!r}')
    if start_offset_s < 0:
        raise ValueError(f'start_offset_s must be >= 0, got {start_offset_s!r}')
    bag = Path(bag_dir)
    if not ensure_readable(bag, log):
        raise RuntimeError(f'{bag} is still being recorded; play it when it is finished')
    stop = stop_event or threading.Event()
    wanted = {rosio.normalize_topic(t) for t in topics} if topics else None
    published = 0
    session = rosio.RosSession('deckland_player', context)
    try:
        with AnyReader([bag]) as reader:
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            publishers: dict[str, Any] = {}
            for c in conns:
                if c.topic in publishers:
                    continue
                try:
                    cls = rosio.import_message_type(c.msgtype)
                except ValueError as exc:
                    if log is not None:
                        print(f'skipping {c.topic}: {exc}', file=log)
                    continue
                offered = [q for cc in conns if cc.topic == c.topic
                           for q in cc.ext.offered_qos_profiles]
                publishers[c.topic] = session.node.create_publisher(
                    cls, c.topic, rosio.publisher_qos_from_offered(offered))
            if not publishers:
                return 0
            deadline = time.monotonic() + wait_for_subscribers_s
            while (wait_for_subscribers_s > 0 and time.monotonic() < deadline
                   and not stop.is_set()
                   and any(p.get_subscription_count() == 0 for p in publishers.values())):
                stop.wait(0.02)
            if delay_s > 0:
                stop.wait(delay_s)
            conns = [c for c in conns if c.topic in publishers]
            first_ns = reader.start_time + int(start_offset_s * 1e9)
            while not stop.is_set():
                t0_wall = time.monotonic()
                t0_bag = None
                for conn, t_ns, data in reader.messages(connections=conns, start=first_ns):
                    if t0_bag is None:
                        t0_bag = t_ns
                    due = t0_wall + (t_ns - t0_bag) / 1e9 / rate
                    wait = due - time.monotonic()
                    if wait > 0 and stop.wait(wait):
                        break
                    if stop.is_set():
                        break
                    publishers[conn.topic].publish(bytes(data))
                    published += 1
                if not loop or t0_bag is None:
                    break
    finally:
        session.close()
    return published


# ======================================================================================== CLI


def register(sub: Any) -> None:
    """Add ``bag`` with ``record``, ``play``, ``info`` and ``reindex`` to ``sub``."""
    bag = sub.add_parser('bag', help='record, play and inspect rosbag2 MCAP bags')
    bsub = bag.add_subparsers(dest='bag_command', metavar='VERB')
    bsub.required = True

    rec = bsub.add_parser('record', help='record topics into DIR (rosbag2, MCAP)')
    rec.add_argument('topics', nargs='*', metavar='TOPIC')
    rec.add_argument('-o', '--output', required=True, metavar='DIR', help='bag directory')
    rec.add_argument('-a', '--all', action='store_true',
                     help='record every topic, also ones that appear later')
    rec.add_argument('--duration', type=float, default=None, metavar='S',
                     help='stop after S seconds')
    rec.add_argument('--exclude', nargs='*', default=list(DEFAULT_EXCLUDES), metavar='TOPIC',
                     help='topics --all leaves out (default: %(default)s)')
    rec.set_defaults(func=_cmd_record)

    ply = bsub.add_parser('play', help='republish a bag with its recorded timing')
    ply.add_argument('bag', metavar='DIR')
    ply.add_argument('-r', '--rate', type=float, default=1.0)
    ply.add_argument('--topics', nargs='*', default=None, metavar='TOPIC')
    ply.add_argument('-l', '--loop', action='store_true')
    ply.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                     help='skip the first S seconds of the bag')
    ply.add_argument('--delay', type=float, default=0.0, metavar='S',
                     help='sleep S seconds before playing')
    ply.add_argument('--wait-subscribers', type=float, default=0.0, metavar='S',
                     help='wait up to S seconds until every topic has a subscriber')
    ply.set_defaults(func=_cmd_play)

    inf = bsub.add_parser('info', help='topics, types, counts, duration and size of a bag')
    inf.add_argument('bag', metavar='DIR')
    inf.add_argument('--no-recover', action='store_true',
                     help='do not reindex an unfinished bag, scan it read-only')
    inf.set_defaults(func=_cmd_info)

    rix = bsub.add_parser('reindex', help='repair a bag whose recorder was killed')
    rix.add_argument('bag', metavar='DIR')
    rix.set_defaults(func=_cmd_reindex)


def _cmd_record(args: argparse.Namespace) -> int:
    if not args.topics and not args.all:
        print('bag record: give TOPIC ... or --all', file=sys.stderr)
        return 2
    if args.duration is not None and not args.duration > 0:
        print('bag record: --duration must be > 0', file=sys.stderr)
        return 2
    stop = threading.Event()
    restore = rosio.install_stop_signals(stop.set)
    try:
        recorder = Recorder(args.output, topics=args.topics or None, all_topics=args.all,
                            exclude=args.exclude)
        recorder.start()
    except (FileExistsError, ValueError, OSError) as exc:
        restore()
        print(f'bag record: {exc}', file=sys.stderr)
        return 1
    print(f'recording to {args.output} '
          f'({"all topics" if args.all else ", ".join(recorder.topics)})', file=sys.stderr)
    try:
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not stop.is_set():
            timeout = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if timeout <= 0:
                break
            stop.wait(timeout)
    except KeyboardInterrupt:
        pass
    finally:
        recorder.stop()
        restore()
    total = sum(recorder.counts.values())
    print(f'recorded {total} messages on {len(recorder.counts)} topics to {args.output}',
          file=sys.stderr)
    return 0


def _cmd_play(args: argparse.Namespace) -> int:
    stop = threading.Event()
    restore = rosio.install_stop_signals(stop.set)
    try:
        n = play(args.bag, rate=args.rate, topics=args.topics, loop=args.loop,
                 start_offset_s=args.start_offset, delay_s=args.delay,
                 wait_for_subscribers_s=args.wait_subscribers, stop_event=stop,
                 log=sys.stderr)
    except (FileNotFoundError, RuntimeError, ValueError) as exc:
        print(f'bag play: {exc}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        restore()
    print(f'published {n} messages', file=sys.stderr)
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    try:
        info = bag_info(args.bag, recover=not args.no_recover)
    except (FileNotFoundError, RuntimeError, OSError) as exc:
        print(f'bag info: {exc}', file=sys.stderr)
        return 1
    print(format_info(info))
    return 0


def _cmd_reindex(args: argparse.Namespace) -> int:
    try:
        counts = reindex(args.bag)
    except (FileNotFoundError, RuntimeError, OSError) as exc:
        print(f'bag reindex: {exc}', file=sys.stderr)
        return 1
    print(f'reindexed {args.bag}: {sum(counts.values())} messages on {len(counts)} topics')
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m deckland.bag VERB ...`` (same as ``deckland bag VERB ...``)."""
    parser = argparse.ArgumentParser(prog='deckland')
    register(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['bag', *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args) or 0)


def iter_messages(bag_dir: str | os.PathLike[str],
                  topics: list[str] | None = None) -> Iterator[tuple[str, str, int, bytes]]:
    """``(topic, msgtype, t_ns, cdr)`` in time order (reindexing an unfinished bag first)."""
    from rosbags.highlevel import AnyReader

    bag = Path(bag_dir)
    ensure_readable(bag)
    wanted = {rosio.normalize_topic(t) for t in topics} if topics else None
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        for conn, t_ns, data in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t_ns, bytes(data)


if __name__ == '__main__':
    sys.exit(main())
