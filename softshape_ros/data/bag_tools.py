"""
Scan, inspect and repair rosbag2 bags: ``softshape bag info`` and ``softshape bag recover``.

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
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from softshape_ros.data.rosbag2_format import (MCAP_MAGIC, METADATA_VERSION, STORAGES, U16,
                                               U32, U64, BagError, FileStats, McapOp,
                                               TopicSpec, bag_metadata, jazzy_typestore,
                                               mcap_is_finished, mcap_record, mcap_string,
                                               metadata_text, read_metadata_yaml,
                                               write_metadata_yaml)
from softshape_ros.data.rosbags_adapter import (Channel, McapStorage, Schema, parse_qos,
                                                zstd_decompress)

_RECORD_HEAD = 9                # opcode + u64 length


@dataclass
class ChunkRecord:
    """A complete Chunk record found in an MCAP file: what its ChunkIndex record needs."""

    start_time: int
    end_time: int
    offset: int                     # where the Chunk record starts
    length: int                     # its length, head included
    compression: str
    compressed_size: int
    uncompressed_size: int
    entries: dict = field(default_factory=dict)         # channel id -> [(log time, offset)]
    index_offsets: dict = field(default_factory=dict)   # channel id -> its MessageIndex at
    index_start: int = 0            # MessageIndex records follow the chunk from here ...
    index_end: int = 0              # ... to here

    @property
    def index_complete(self) -> bool:
        """Every channel with messages in the chunk has its MessageIndex record."""
        return set(self.index_offsets) == {c for c, e in self.entries.items() if e}

    def message_indexes(self, at: int) -> bytes:
        """Encode the MessageIndex records of this chunk, written from file offset ``at``."""
        out = bytearray()
        self.index_offsets, self.index_start = {}, at
        for cid, entries in self.entries.items():
            if not entries:
                continue
            self.index_offsets[cid] = at + len(out)
            body = U16.pack(cid) + U32.pack(len(entries) * 16) + b''.join(
                U64.pack(t) + U64.pack(off) for t, off in entries)
            out += mcap_record(McapOp.MESSAGE_INDEX, body)
        self.index_end = at + len(out)
        return bytes(out)

    def index_body(self) -> bytes:
        """Lay out the body of this chunk's ChunkIndex record (MCAP spec, as rosbags does)."""
        offsets = b''.join(U16.pack(c) + U64.pack(o) for c, o in self.index_offsets.items())
        return (U64.pack(self.start_time) + U64.pack(self.end_time) + U64.pack(self.offset)
                + U64.pack(self.length) + U32.pack(len(offsets)) + offsets
                + U64.pack(self.index_end - self.index_start) + mcap_string(self.compression)
                + U64.pack(self.compressed_size) + U64.pack(self.uncompressed_size))


@dataclass
class FileScan:
    """What one storage file really holds."""

    path: Path
    storage: str
    stats: FileStats
    finished: bool = False
    good_end: int = 0               # MCAP: end of the last complete record worth keeping
    size: int = 0
    counts: dict = field(default_factory=dict)          # topic -> messages
    topics: dict = field(default_factory=dict)          # topic -> TopicSpec
    # MCAP only, for rebuilding the summary:
    schemas: dict = field(default_factory=dict)         # id -> Schema
    channels: dict = field(default_factory=dict)        # id -> Channel
    chunks: list = field(default_factory=list)          # ChunkRecord, in file order
    channel_counts: dict = field(default_factory=dict)  # channel id -> messages


class _Fields:
    """Cursor over the fields of an MCAP record body; ValueError past the end."""

    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    @property
    def left(self) -> int:
        return len(self.data) - self.pos

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError('truncated field')
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return U16.unpack(self.take(2))[0]

    def u32(self) -> int:
        return U32.unpack(self.take(4))[0]

    def u64(self) -> int:
        return U64.unpack(self.take(8))[0]

    def string(self) -> str:
        return self.take(self.u32()).decode()


def _decompress(data: bytes, compression: str) -> bytes:
    if compression == '':
        return data
    if compression == 'zstd':
        return zstd_decompress(data)
    if compression == 'lz4':
        from lz4.frame import decompress
        return decompress(data)
    raise ValueError(f'unsupported chunk compression {compression!r}')


def _qos_from_channel(meta: bytes) -> list:
    b = _Fields(meta)
    while b.left:
        k, v = b.string(), b.string()
        if k == 'offered_qos_profiles':
            try:
                return parse_qos(v)
            except ValueError:
                return []
    return []


def _digest(msgtype: str) -> str:
    ts = jazzy_typestore()
    return ts.hash_rihs01(msgtype) if msgtype in ts.fielddefs else ''


def _scan_records(raw: bytes, scan: FileScan, stats: FileStats, entries: dict) -> None:
    """Read Schema, Channel and Message records (a chunk's contents, or top-level ones)."""
    b = _Fields(raw)
    while b.left:
        at = b.pos
        op = b.take(1)[0]
        body = _Fields(b.take(b.u64()))
        if op == McapOp.SCHEMA:
            sid = body.u16()
            scan.schemas[sid] = Schema(sid, body.string(), body.string(), body.string())
        elif op == McapOp.CHANNEL:
            cid, sid = body.u16(), body.u16()
            topic, enc = body.string(), body.string()
            meta = body.take(body.u32())
            schema = scan.schemas.get(sid)
            scan.channels[cid] = Channel(cid, schema.name if schema else '', topic, enc, meta)
        elif op == McapOp.MESSAGE:
            cid = body.u16()
            body.take(4)                # sequence
            t = body.u64()              # log time
            entries[cid].append((t, at))
            stats.add(t)


def _read_chunk(body: bytes, scan: FileScan, offset: int, length: int) -> ChunkRecord | None:
    """Parse a Chunk record and the records in it; None if it is corrupt."""
    try:
        b = _Fields(body)
        t0, t1, usize = b.u64(), b.u64(), b.u64()
        b.u32()                         # uncompressed CRC (rosbags writes 0)
        comp = b.string()
        csize = b.u64()
        raw = _decompress(b.take(csize), comp)
        if len(raw) != usize:
            return None
        stats, entries = FileStats(''), defaultdict(list)
        _scan_records(raw, scan, stats, entries)
    except Exception:                   # corrupt chunk: everything before it is kept
        return None
    scan.stats.merge(stats)
    end = offset + length
    return ChunkRecord(t0, t1, offset, length, comp, csize, usize, dict(entries),
                       index_start=end, index_end=end)


def scan_mcap(path: Path) -> FileScan:
    """Walk an MCAP file; stop quietly at the first truncated or corrupt record."""
    path = Path(path)
    scan = FileScan(path, 'mcap', FileStats(path.name))
    size = scan.size = path.stat().st_size
    with path.open('rb') as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise BagError(f'{path}: not an MCAP file (bad magic)')
        pos = scan.good_end = len(MCAP_MAGIC)
        while pos + _RECORD_HEAD <= size:
            f.seek(pos)
            head = f.read(_RECORD_HEAD)
            op, length = head[0], U64.unpack(head[1:])[0]
            end = pos + _RECORD_HEAD + length
            if end > size:
                break                       # the record the crash cut in half
            body = f.read(length)
            if op == McapOp.CHUNK:
                chunk = _read_chunk(body, scan, pos, end - pos)
                if chunk is None:
                    break
                scan.chunks.append(chunk)
            elif op == McapOp.MESSAGE_INDEX:     # belongs to the chunk just before it
                if scan.chunks and len(body) >= 2:
                    scan.chunks[-1].index_offsets[U16.unpack(body[:2])[0]] = pos
                    scan.chunks[-1].index_end = end
            elif op in (McapOp.DATA_END, McapOp.FOOTER):    # the file was finished
                scan.finished = True
                scan.good_end = pos
                break
            elif op in (McapOp.SCHEMA, McapOp.CHANNEL):     # outside chunks (other writers)
                _scan_records(head + body, scan, scan.stats, defaultdict(list))
            pos = end
            scan.good_end = pos
    if scan.chunks and not scan.finished and not scan.chunks[-1].index_complete:
        last = scan.chunks[-1]               # its index was cut: rebuild it
        scan.good_end = last.index_start
        last.index_offsets, last.index_end = {}, last.index_start
    for chunk in scan.chunks:
        for cid, e in chunk.entries.items():
            scan.channel_counts[cid] = scan.channel_counts.get(cid, 0) + len(e)
    _fill_topics(scan)
    if scan.finished:
        scan.finished = mcap_is_finished(path)
    return scan


def _fill_topics(scan: FileScan) -> None:
    for cid, ch in scan.channels.items():
        schema = next((s for s in scan.schemas.values() if s.name == ch.schema), None)
        if schema is None:
            continue
        scan.topics[ch.topic] = TopicSpec(ch.topic, schema.name, schema.data,
                                          _digest(schema.name), schema.encoding or 'ros2msg',
                                          _qos_from_channel(ch.metadata))
        scan.counts[ch.topic] = scan.counts.get(ch.topic, 0) + scan.channel_counts.get(cid, 0)


def scan_sqlite3(path: Path) -> FileScan:
    """Read counts and topic definitions of a db3 file (sqlite rolls back a torn commit)."""
    path = Path(path)
    scan = FileScan(path, 'sqlite3', FileStats(path.name), finished=True)
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
        except ValueError:
            qos_list = []
        scan.topics[name] = TopicSpec(name, mtype, text, digest or _digest(mtype), enc, qos_list)
        scan.counts[name] = int(n)
        if n:
            scan.stats.merge(FileStats('', int(n), int(t0), int(t1)))
    return scan


def scan_file(path) -> FileScan:
    """Scan one storage file by its extension."""
    path = Path(path)
    if path.suffix == STORAGES['mcap']:
        return scan_mcap(path)
    if path.suffix == STORAGES['sqlite3']:
        return scan_sqlite3(path)
    raise BagError(f'{path}: unknown storage file (expected .mcap or .db3)')


def _storage_files(bag: Path) -> tuple[str, list[Path]]:
    if not bag.is_dir():
        raise BagError(f'{bag}: no such bag directory')
    listed = []
    if (bag / 'metadata.yaml').is_file():
        try:
            listed = [bag / p for p in read_metadata_yaml(bag).get('relative_file_paths', [])]
        except (BagError, TypeError):
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
    storage = next(s for s, ext in STORAGES.items() if ext == files[0].suffix)
    return storage, files


def _split_index(p: Path):
    tail = p.stem.rsplit('_', 1)[-1]
    return (int(tail) if tail.isdigit() else -1, p.name)


def _finalise_mcap(scan: FileScan, text: str) -> None:
    """Append summary + footer at the last good byte of an unfinished MCAP file."""
    os.truncate(scan.path, scan.good_end)
    bio = scan.path.open('r+b')
    bio.seek(scan.good_end)
    if scan.chunks and not scan.chunks[-1].index_offsets:
        bio.write(scan.chunks[-1].message_indexes(scan.good_end))
    stats = scan.stats
    channels = sorted(scan.channels.values(), key=lambda c: c.id)
    McapStorage(
        scan.path, bio, zstd=False,
        schemas=sorted(scan.schemas.values(), key=lambda s: s.id), channels=channels,
        chunk_indexes=[c.index_body() for c in scan.chunks],
        channel_counts={c.id: scan.channel_counts.get(c.id, 0) for c in channels},
        start_time=stats.start if stats.count else 0, end_time=stats.end if stats.count else 0,
    ).finish(METADATA_VERSION, text)


def _bag_metadata_of(storage: str, scans: list[FileScan]) -> dict:
    topics, counts = {}, defaultdict(int)
    for s in scans:
        for name, spec in s.topics.items():
            topics.setdefault(name, spec)
            counts[name] += s.counts.get(name, 0)
    return bag_metadata(storage, [s.stats for s in scans], list(topics.values()), counts)


def recover_bag(path) -> dict:
    """
    Make a bag readable again after a crash; returns what was found and done.

    Finished files are left untouched; unfinished MCAP files get a summary at the end
    of their last complete chunk; metadata.yaml is rebuilt from the files' contents.
    """
    bag = Path(path)
    storage, files = _storage_files(bag)
    report = {'bag': str(bag), 'storage': storage, 'files': []}
    scans = [scan_file(p) for p in files]
    meta = _bag_metadata_of(storage, scans)
    for i, scan in enumerate(scans):
        entry = {'file': scan.path.name, 'was_finished': scan.finished,
                 'messages': scan.stats.count}
        if storage == 'mcap' and not scan.finished:
            entry['cut_bytes'] = scan.size - scan.good_end
            _finalise_mcap(scan, metadata_text(meta))
            scans[i] = scan_mcap(scan.path)
            if not scans[i].finished:
                raise BagError(f'{scan.path}: could not be finalised')
        report['files'].append(entry)
    meta = _bag_metadata_of(storage, scans)
    write_metadata_yaml(bag, meta)
    report['topics'] = {t['topic_metadata']['name']: t['message_count']
                        for t in meta['rosbag2_bagfile_information']['topics_with_message_count']}
    report['messages'] = sum(report['topics'].values())
    return report


def bag_info(path) -> dict:
    """Summarise a bag like ``ros2 bag info`` (from metadata.yaml, files checked)."""
    bag = Path(path)
    storage, files = _storage_files(bag)
    info = read_metadata_yaml(bag)
    unfinished = [p.name for p in files if p.suffix == STORAGES['mcap']
                  and not mcap_is_finished(p)]
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


__all__ = ['ChunkRecord', 'FileScan', 'scan_file', 'scan_mcap', 'scan_sqlite3', 'recover_bag',
           'bag_info', 'format_info']
