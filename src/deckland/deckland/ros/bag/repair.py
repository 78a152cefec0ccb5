"""Reading and repairing bags: is an MCAP finished, is a recorder still holding the bag, and
reindexing a bag whose recorder was killed (every complete record into a fresh, indexed MCAP)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
import fcntl
import os
from pathlib import Path
from typing import Any

import yaml

from deckland.ros.bag.writer import LOCK_NAME, MCAP_MAGIC, metadata_dict, write_metadata


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


def qos_from_channel(channel: Any) -> list[Any]:
    from rosbags.rosbag2.metadata import parse_qos

    text = channel.metadata.get('offered_qos_profiles', '')
    try:
        return parse_qos(text) if text else []
    except Exception:
        return []


def bag_files(bag_dir: Path) -> list[Path]:
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
    files = bag_files(bag)
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
    files = bag_files(bag)
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
                                                    qos_from_channel(channel),
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
