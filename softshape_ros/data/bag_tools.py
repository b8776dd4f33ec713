"""
Inspect and repair rosbag2 bags: ``softshape bag info`` and ``softshape bag recover``.

Recovery after a crash (``kill -9``, power loss) works in place: every MCAP file is
walked record by record; a file without its summary is cut back to the end of its last
complete chunk (everything the recorder flushed) and the summary, statistics and footer
are appended there, so no byte of good data is copied or lost. sqlite3 files recover
through sqlite's own journal. metadata.yaml is then rebuilt from what is really on disk.
"""

from __future__ import annotations

import datetime
import os
import sqlite3
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path

from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.storage_mcap import (Channel, McapWriter, PendingChunk, Schema,
                                          write_record, write_string, write_uint16,
                                          write_uint32, write_uint64)
from ruamel.yaml import YAML

from softshape_ros.data.bag_writer import (METADATA_VERSION, STORAGES, BagError, FileStats,
                                           TopicSpec, bag_metadata, jazzy_typestore,
                                           write_metadata_yaml)

MAGIC = b'\x89MCAP0\r\n'
_U16, _U32, _U64 = struct.Struct('<H'), struct.Struct('<I'), struct.Struct('<Q')


@dataclass
class FileScan:
    """What one storage file really holds."""

    path: Path
    storage: str
    finished: bool = False
    good_end: int = 0                 # MCAP: end of the last complete record worth keeping
    size: int = 0
    counts: dict = field(default_factory=dict)          # topic -> messages
    stats: FileStats = None
    topics: dict = field(default_factory=dict)          # topic -> TopicSpec
    # MCAP only, for rebuilding the summary:
    schemas: dict = field(default_factory=dict)         # id -> Schema
    channels: dict = field(default_factory=dict)        # id -> Channel
    chunk_index: list = field(default_factory=list)     # per chunk: offsets, times, entries
    channel_stats: dict = field(default_factory=dict)   # channel id -> messages


class _Buf:
    """Little cursor over bytes for MCAP record fields."""

    def __init__(self, data: bytes, pos: int = 0):
        self.data, self.pos = data, pos

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError('truncated field')
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u16(self):
        return _U16.unpack(self.take(2))[0]

    def u32(self):
        return _U32.unpack(self.take(4))[0]

    def u64(self):
        return _U64.unpack(self.take(8))[0]

    def string(self) -> str:
        return self.take(self.u32()).decode()


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == '':
        return data
    if compression == 'zstd':
        from rosbags.rosbag2.storage_mcap import zstd
        return zstd.decompress(data)
    if compression == 'lz4':
        from lz4.frame import decompress
        return decompress(data)
    raise ValueError(f'unsupported chunk compression {compression!r}')


def _qos_from_metadata(meta: bytes) -> list:
    b = _Buf(meta)
    while b.pos < len(meta):
        k, v = b.string(), b.string()
        if k == 'offered_qos_profiles':
            try:
                return parse_qos(v)
            except Exception:
                return []
    return []


def _digest(msgtype: str) -> str:
    ts = jazzy_typestore()
    return ts.hash_rihs01(msgtype) if msgtype in ts.fielddefs else ''


def _scan_chunk_records(raw: bytes, scan: FileScan, stats: FileStats, entries: dict):
    b = _Buf(raw)
    while b.pos < len(raw):
        at = b.pos
        op = b.take(1)[0]
        body = _Buf(b.take(b.u64()))
        if op == 0x03:
            sid = body.u16()
            scan.schemas[sid] = Schema(sid, body.string(), body.string(), body.string())
        elif op == 0x04:
            cid, sid = body.u16(), body.u16()
            topic, enc = body.string(), body.string()
            meta = body.take(body.u32())
            schema = scan.schemas.get(sid)
            scan.channels[cid] = Channel(cid, schema.name if schema else '', topic, enc, meta)
        elif op == 0x05:
            cid = body.u16()
            body.take(4)
            t = body.u64()
            entries[cid].append((t, at))
            stats.add(t)


def scan_mcap(path: Path) -> FileScan:
    """Walk an MCAP file; stop quietly at the first truncated or corrupt record."""
    path = Path(path)
    scan = FileScan(path, 'mcap', stats=FileStats(path.name))
    size = scan.size = path.stat().st_size
    per_channel = defaultdict(int)
    with path.open('rb') as f:
        if f.read(8) != MAGIC:
            raise BagError(f'{path}: not an MCAP file (bad magic)')
        pos = scan.good_end = 8
        while pos + 9 <= size:
            f.seek(pos)
            head = f.read(9)
            op, length = head[0], _U64.unpack(head[1:])[0]
            end = pos + 9 + length
            if end > size:
                break                       # the record the crash cut in half
            body = f.read(length)
            if op == 0x06:                  # Chunk
                try:
                    b = _Buf(body)
                    t0, t1, usize = b.u64(), b.u64(), b.u64()
                    b.u32()
                    comp = b.string()
                    csize = b.u64()
                    raw = _decompress(b.take(csize), comp, usize)
                    if len(raw) != usize:
                        break
                    chunk_stats, entries = FileStats(''), defaultdict(list)
                    _scan_chunk_records(raw, scan, chunk_stats, entries)
                except Exception:           # corrupt chunk: everything before it is kept
                    break
                for cid, e in entries.items():
                    per_channel[cid] += len(e)
                if chunk_stats.count:
                    scan.stats.count += chunk_stats.count
                    scan.stats.start = min(scan.stats.start, chunk_stats.start)
                    scan.stats.end = max(scan.stats.end, chunk_stats.end)
                scan.chunk_index.append({
                    't0': t0, 't1': t1, 'start': pos, 'length': end - pos, 'offsets': {},
                    'idx_start': end, 'idx_end': end, 'comp': comp, 'csize': csize,
                    'usize': usize, 'entries': entries})
            elif op == 0x07:                # MessageIndex of the last chunk
                if scan.chunk_index and len(body) >= 2:
                    scan.chunk_index[-1]['offsets'][_U16.unpack(body[:2])[0]] = pos
                    scan.chunk_index[-1]['idx_end'] = end
            elif op in (0x0F, 0x02):        # DataEnd / Footer: the file was finished
                scan.finished = True
                scan.good_end = pos
                break
            elif op in (0x03, 0x04):        # definitions outside chunks (other writers)
                _scan_chunk_records(head + body, scan, scan.stats, defaultdict(list))
            pos = end
            scan.good_end = pos
    if scan.chunk_index and not scan.finished:
        last = scan.chunk_index[-1]
        if set(last['offsets']) != {c for c, e in last['entries'].items() if e}:
            scan.good_end = last['idx_start']    # its index was cut: rebuild it
            last['offsets'], last['idx_end'] = {}, last['idx_start']
    scan.channel_stats = dict(per_channel)
    _fill_topics(scan)
    if scan.finished:
        with path.open('rb') as f:
            f.seek(max(0, size - 8))
            scan.finished = f.read(8) == MAGIC
    return scan


def _write_message_indexes(bio, idx: dict) -> None:
    """Append the MessageIndex records of a chunk whose indexes the crash cut off."""
    for cid, entries in idx['entries'].items():
        if not entries:
            continue
        idx['offsets'][cid] = bio.tell()
        rec = BytesIO()
        write_uint16(rec, cid)
        write_uint32(rec, len(entries) * 16)
        for t, off in entries:
            write_uint64(rec, t)
            write_uint64(rec, off)
        write_record(bio, 0x07, rec)
    idx['idx_end'] = bio.tell()


def _chunk_index_body(idx: dict) -> BytesIO:
    """Lay out a ChunkIndex record body as rosbags' writer does."""
    rec = BytesIO()
    write_uint64(rec, idx['t0'])
    write_uint64(rec, idx['t1'])
    write_uint64(rec, idx['start'])
    write_uint64(rec, idx['length'])
    write_uint32(rec, len(idx['offsets']) * 10)
    for cid, off in idx['offsets'].items():
        write_uint16(rec, cid)
        write_uint64(rec, off)
    write_uint64(rec, idx['idx_end'] - idx['idx_start'])
    write_string(rec, idx['comp'])
    write_uint64(rec, idx['csize'])
    write_uint64(rec, idx['usize'])
    return rec


def _fill_topics(scan: FileScan) -> None:
    for cid, ch in scan.channels.items():
        schema = next((s for s in scan.schemas.values() if s.name == ch.schema), None)
        if schema is None:
            continue
        scan.topics[ch.topic] = TopicSpec(ch.topic, schema.name, schema.data,
                                          _digest(schema.name), schema.encoding or 'ros2msg',
                                          _qos_from_metadata(ch.metadata))
        scan.counts[ch.topic] = scan.counts.get(ch.topic, 0) + scan.channel_stats.get(cid, 0)


def scan_sqlite3(path: Path) -> FileScan:
    """Read counts and topic definitions of a db3 file (sqlite rolls back a torn commit)."""
    path = Path(path)
    scan = FileScan(path, 'sqlite3', stats=FileStats(path.name), finished=True)
    scan.size = path.stat().st_size
    try:
        conn = sqlite3.connect(f'file:{path}', uri=True)
        try:
            defs = {r[0]: (r[1], r[2]) for r in conn.execute(
                'SELECT topic_type, encoding, encoded_message_definition '
                'FROM message_definitions')}
            rows = conn.execute(
                'SELECT t.name, t.type, t.offered_qos_profiles, t.type_description_hash, '
                'COUNT(m.id), MIN(m.timestamp), MAX(m.timestamp) FROM topics t '
                'LEFT JOIN messages m ON m.topic_id = t.id GROUP BY t.id').fetchall()
        finally:
            conn.close()
    except sqlite3.Error as exc:
        raise BagError(f'{path}: not a readable rosbag2 sqlite3 file: {exc}') from None
    for name, mtype, qos, digest, n, t0, t1 in rows:
        enc, text = defs.get(mtype, ('ros2msg', ''))
        try:
            qos_list = parse_qos(qos) if qos else []
        except Exception:
            qos_list = []
        scan.topics[name] = TopicSpec(name, mtype, text, digest or _digest(mtype), enc, qos_list)
        scan.counts[name] = int(n)
        if n:
            scan.stats.count += int(n)
            scan.stats.start = min(scan.stats.start, int(t0))
            scan.stats.end = max(scan.stats.end, int(t1))
    return scan


def scan_file(path) -> FileScan:
    """Scan one storage file by its extension."""
    path = Path(path)
    if path.suffix == '.mcap':
        return scan_mcap(path)
    if path.suffix == '.db3':
        return scan_sqlite3(path)
    raise BagError(f'{path}: unknown storage file (expected .mcap or .db3)')


def _storage_files(bag: Path) -> tuple[str, list[Path]]:
    if not bag.is_dir():
        raise BagError(f'{bag}: no such bag directory')
    meta = bag / 'metadata.yaml'
    listed = []
    if meta.is_file():
        try:
            info = YAML(typ='safe').load(meta.read_text())['rosbag2_bagfile_information']
            listed = [bag / p for p in info.get('relative_file_paths', [])]
        except Exception:
            listed = []
    found = []
    for ext in STORAGES.values():
        found += sorted(bag.glob(f'*{ext}'), key=_split_index)
    files = [p for p in listed if p.exists()] + [p for p in found if p not in listed]
    if not files:
        raise BagError(f'{bag}: no .mcap or .db3 files in it')
    storages = {p.suffix for p in files}
    if len(storages) > 1:
        raise BagError(f'{bag}: mixes storage formats {sorted(storages)}')
    storage = 'mcap' if files[0].suffix == '.mcap' else 'sqlite3'
    return storage, files


def _split_index(p: Path):
    stem = p.stem
    tail = stem.rsplit('_', 1)[-1]
    return (int(tail) if tail.isdigit() else -1, p.name)


def _finalise_mcap(scan: FileScan, metadata_text: str) -> None:
    """Append summary + footer at the last good byte of an unfinished MCAP file."""
    w = McapWriter.__new__(McapWriter)
    w.path = scan.path
    w.schemas = sorted(scan.schemas.values(), key=lambda s: s.id)
    w.channels = sorted(scan.channels.values(), key=lambda c: c.id)
    os.truncate(scan.path, scan.good_end)
    w.bio = scan.path.open('r+b')
    w.bio.seek(scan.good_end)
    if scan.chunk_index and not scan.chunk_index[-1]['offsets']:
        _write_message_indexes(w.bio, scan.chunk_index[-1])
    w.chunks = [_chunk_index_body(c) for c in scan.chunk_index]
    w.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
    w.compression, w.compressor = '', (lambda x: x)
    w.channel_stats = {c.id: scan.channel_stats.get(c.id, 0) for c in w.channels}
    w.message_start_time = scan.stats.start if scan.stats.count else 0
    w.message_end_time = scan.stats.end if scan.stats.count else 0
    McapWriter.close(w, METADATA_VERSION, metadata_text)


def recover_bag(path) -> dict:
    """
    Make a bag readable again after a crash; returns what was found and done.

    Finished files are left untouched; unfinished MCAP files get a summary at the end
    of their last complete chunk; metadata.yaml is rebuilt from the files' contents.
    """
    bag = Path(path)
    storage, files = _storage_files(bag)
    report = {'bag': str(bag), 'storage': storage, 'files': []}
    scans = []
    for p in files:
        scan = scan_file(p)
        entry = {'file': p.name, 'was_finished': scan.finished, 'messages': scan.stats.count}
        if storage == 'mcap' and not scan.finished:
            entry['cut_bytes'] = scan.size - scan.good_end
            _finalise_mcap(scan, '')
            scan = scan_mcap(p)
            if not scan.finished:
                raise BagError(f'{p}: could not be finalised')
        scans.append(scan)
        report['files'].append(entry)
    topics, counts = {}, defaultdict(int)
    for s in scans:
        for name, spec in s.topics.items():
            topics.setdefault(name, spec)
            counts[name] += s.counts.get(name, 0)
    meta = bag_metadata(storage, [s.stats for s in scans], list(topics.values()), counts)
    write_metadata_yaml(bag, meta)
    report['messages'] = sum(counts.values())
    report['topics'] = dict(counts)
    return report


def bag_info(path) -> dict:
    """Summarise a bag like ``ros2 bag info`` (from metadata.yaml, files checked)."""
    bag = Path(path)
    storage, files = _storage_files(bag)
    meta_path = bag / 'metadata.yaml'
    if not meta_path.is_file():
        raise BagError(f'{bag}: no metadata.yaml (did the recording crash?); '
                       f'run `softshape bag recover {bag}`')
    info = YAML(typ='safe').load(meta_path.read_text())['rosbag2_bagfile_information']
    unfinished = []
    for p in files:
        if p.suffix == '.mcap':
            with p.open('rb') as f:
                f.seek(max(0, p.stat().st_size - 8))
                if f.read(8) != MAGIC:
                    unfinished.append(p.name)
    return {
        'path': str(bag), 'storage': info.get('storage_identifier', storage),
        'files': [p.name for p in files], 'size_bytes': sum(p.stat().st_size for p in files),
        'ros_distro': info.get('ros_distro', ''),
        'start_ns': int(info['starting_time']['nanoseconds_since_epoch']),
        'duration_ns': int(info['duration']['nanoseconds']),
        'messages': int(info['message_count']),
        'topics': [{'name': t['topic_metadata']['name'], 'type': t['topic_metadata']['type'],
                    'count': int(t['message_count']),
                    'serialization_format': t['topic_metadata']['serialization_format']}
                   for t in info.get('topics_with_message_count', [])],
        'unfinished_files': unfinished,
    }


def _human_size(n: int) -> str:
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if n < 1024 or unit == 'GiB':
            return f'{n:.1f} {unit}' if unit != 'B' else f'{n} B'
        n /= 1024.0
    return str(n)


def _when(ns: int) -> str:
    t = datetime.datetime.fromtimestamp(ns / 1e9, datetime.timezone.utc)
    return f'{t:%b %d %Y %H:%M:%S}.{t.microsecond // 1000:03d} ({ns / 1e9:.9f})'


def format_info(info: dict) -> str:
    """Render :func:`bag_info` as ``ros2 bag info`` prints it."""
    lines = [
        f'Files:             {", ".join(info["files"])}',
        f'Bag size:          {_human_size(info["size_bytes"])}',
        f'Storage id:        {info["storage"]}',
        f'ROS Distro:        {info["ros_distro"]}',
        f'Duration:          {info["duration_ns"] / 1e9:.9f}s',
        f'Start:             {_when(info["start_ns"])}',
        f'End:               {_when(info["start_ns"] + info["duration_ns"])}',
        f'Messages:          {info["messages"]}',
    ]
    width = max((len(t['name']) for t in info['topics']), default=0)
    tw = max((len(t['type']) for t in info['topics']), default=0)
    for i, t in enumerate(info['topics']):
        head = 'Topic information: ' if i == 0 else ' ' * 19
        lines.append(f'{head}Topic: {t["name"]:<{width}} | Type: {t["type"]:<{tw}} | '
                     f'Count: {t["count"]} | Serialization Format: '
                     f'{t["serialization_format"]}')
    if not info['topics']:
        lines.append('Topic information: ')
    if info['unfinished_files']:
        lines.append(f'WARNING: unfinished files (recording crashed?): '
                     f'{", ".join(info["unfinished_files"])}; run `softshape bag recover`')
    return '\n'.join(lines)


__all__ = ['FileScan', 'scan_file', 'scan_mcap', 'scan_sqlite3', 'recover_bag', 'bag_info',
           'format_info']
