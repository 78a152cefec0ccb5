"""``deckland bag info``: topics, types, counts, duration and size of a bag."""

from __future__ import annotations

from dataclasses import dataclass
import datetime
import os
from pathlib import Path
from typing import Any

from deckland.ros.bag.repair import (
    bag_files,
    ensure_readable,
    is_recording,
    needs_reindex,
    qos_from_channel,
    scan_mcap,
)


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
    files = bag_files(bag)
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
                                             qos_from_channel(ch)])
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
