"""
Write standard rosbag2 bags (MCAP or sqlite3) that survive crashes and full disks.

Built on the storage plugins of ``rosbags`` (the byte format is theirs), with what a
recorder needs on top: several files per bag (split by size or duration, as
``ros2 bag record`` does), a :meth:`BagWriter.flush` that makes everything written so
far readable after a ``kill -9`` (closes the MCAP chunk, or commits the sqlite
transaction), and a salvage path for write errors (full disk, file-size limit) that
cuts the file back to the last flushed byte and finalises it there.
"""

from __future__ import annotations

import os
import sqlite3
import time
from collections import defaultdict
from dataclasses import dataclass, field
from importlib.metadata import version as _pkg_version
from io import BytesIO, StringIO
from pathlib import Path

from rosbags.interfaces import (Connection, ConnectionExtRosbag2, MessageDefinition,
                                MessageDefinitionFormat)
from rosbags.rosbag2.enums import CompressionMode
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk, write_record, write_string
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

METADATA_VERSION = 9          # rosbag2 metadata version written by Jazzy
STORAGES = {'mcap': '.mcap', 'sqlite3': '.db3'}
_TYPESTORE = None


class BagError(RuntimeError):
    """A bag cannot be written or read; the message says which file and why."""


def jazzy_typestore():
    """Return the shared typestore with the Jazzy message definitions (built once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


@dataclass
class TopicSpec:
    """What a bag stores about a topic: type, full definition (for any decoder), QoS."""

    topic: str
    msgtype: str
    msgdef: str
    digest: str
    encoding: str = 'ros2msg'
    qos: list = field(default_factory=list)   # rosbags Qos tuples offered by publishers

    @classmethod
    def from_typestore(cls, topic: str, msgtype: str, qos=(), typestore=None) -> 'TopicSpec':
        ts = typestore or jazzy_typestore()
        if msgtype not in ts.fielddefs:
            raise BagError(f'{topic}: no message definition known for {msgtype}')
        msgdef, _ = ts.generate_msgdef(msgtype, ros_version=2)
        return cls(topic, msgtype, msgdef, ts.hash_rihs01(msgtype), 'ros2msg', list(qos))

    def qos_text(self) -> str:
        dumped = dump_qos_v9(list(self.qos))
        if isinstance(dumped, str):
            return dumped
        return _yaml_text(dumped).strip()


def _yaml_text(data) -> str:
    yaml = YAML(typ='safe')
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()


class _McapFile(McapWriter):
    """One MCAP file of a bag: rosbags' writer plus flush points and salvage."""

    def __init__(self, path: Path, compression: CompressionMode):
        self.path = path
        self.bio = path.open('xb')
        self.bio.write(b'\x89MCAP\x30\r\n')
        rec = BytesIO()
        write_string(rec, 'ros2')
        write_string(rec, f'rosbags-{_pkg_version("rosbags")}')
        write_record(self.bio, 0x01, rec)
        self.schemas, self.channels, self.chunks = [], [], []
        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        if compression == CompressionMode.STORAGE:
            from rosbags.rosbag2.storage_mcap import zstd
            self.compression, self.compressor = 'zstd', zstd.compress
        else:
            self.compression, self.compressor = '', (lambda x: x)
        self.message_start_time = 2**63 - 1
        self.message_end_time = 0
        self.channel_stats = {}
        self.bio.flush()
        self._snapshot()

    def _snapshot(self):
        self._good = (self.bio.tell(), len(self.chunks), dict(self.channel_stats),
                      self.message_start_time, self.message_end_time)

    @property
    def size(self) -> int:
        return self.bio.tell() + self.chunk.bio.tell()

    def flush(self, fsync: bool) -> None:
        if self.chunk.msgs:
            self.close_chunk()
        self.bio.flush()
        if fsync:
            os.fsync(self.bio.fileno())
        self._snapshot()

    def salvage(self, metadata: str) -> bool:
        """Cut back to the last flush and write the summary there; False if even that fails."""
        try:
            self.bio.close()
        except OSError:
            pass
        good, nchunks, stats, t0, t1 = self._good
        os.truncate(self.path, good)
        self.chunks = self.chunks[:nchunks]
        self.channel_stats, self.message_start_time, self.message_end_time = stats, t0, t1
        for ch in self.channels:
            self.channel_stats.setdefault(ch.id, 0)
        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        try:
            self.bio = self.path.open('r+b')
            self.bio.seek(good)
            McapWriter.close(self, METADATA_VERSION, metadata)
            return True
        except OSError:
            try:
                self.bio.close()
            except OSError:
                pass
            os.truncate(self.path, good)
            return False


class _Sqlite3File(Sqlite3Writer):
    """One sqlite3 file of a bag: a commit is a flush point (sqlite's journal does the rest)."""

    def __init__(self, path: Path, compression: CompressionMode):
        if compression == CompressionMode.STORAGE:
            raise BagError('sqlite3 storage does not support compression')
        if path.exists():
            raise BagError(f'{path}: exists already, not overwriting')
        self.path = path
        self.conn = sqlite3.connect(f'file:{path}', uri=True, check_same_thread=False)
        self.conn.executescript(self.SQLITE_SCHEMA)
        self.cursor = self.conn.cursor()
        self.bytes = 0

    @property
    def size(self) -> int:
        return self.bytes

    def write(self, connection, timestamp, data):
        super().write(connection, timestamp, data)
        self.bytes += len(data) + 24

    def flush(self, fsync: bool) -> None:
        self.conn.commit()

    def salvage(self, metadata: str) -> bool:
        try:
            self.conn.rollback()
            self.close(METADATA_VERSION, metadata)
            return True
        except sqlite3.Error:
            try:
                self.conn.close()
            except sqlite3.Error:
                pass
            return False


@dataclass
class FileStats:
    """Per-file bookkeeping for metadata.yaml."""

    name: str
    count: int = 0
    start: int = 2**63 - 1
    end: int = 0

    def add(self, t: int) -> None:
        self.count += 1
        self.start = min(self.start, t)
        self.end = max(self.end, t)

    def as_metadata(self) -> dict:
        start = self.start if self.count else 0
        return {'path': self.name, 'starting_time': {'nanoseconds_since_epoch': start},
                'duration': {'nanoseconds': max(0, self.end - self.start) if self.count else 0},
                'message_count': self.count}


def bag_metadata(storage: str, files: list[FileStats], topics: list[TopicSpec],
                 counts: dict[str, int], compression: str = '') -> dict:
    """Build the rosbag2 ``metadata.yaml`` mapping (version 9, as Jazzy writes it)."""
    used = [f for f in files if f.count]
    start = min((f.start for f in used), default=0)
    end = max((f.end for f in used), default=0)
    total = sum(f.count for f in files)
    return {'rosbag2_bagfile_information': {
        'version': METADATA_VERSION,
        'storage_identifier': storage,
        'relative_file_paths': [f.name for f in files],
        'duration': {'nanoseconds': max(0, end - start)},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': total,
        'topics_with_message_count': [
            {'topic_metadata': {'name': t.topic, 'type': t.msgtype,
                                'serialization_format': 'cdr',
                                'offered_qos_profiles': t.qos_text(),
                                'type_description_hash': t.digest},
             'message_count': int(counts.get(t.topic, 0))}
            for t in topics],
        'compression_format': compression,
        'compression_mode': 'storage' if compression else '',
        'files': [f.as_metadata() for f in files],
        'custom_data': None,
        'ros_distro': 'jazzy',
    }}


def write_metadata_yaml(bag: Path, metadata: dict) -> None:
    """Write metadata.yaml atomically (tmp + rename), so a reader never sees half of it."""
    tmp = bag / 'metadata.yaml.tmp'
    tmp.write_text(_yaml_text(metadata), 'utf8')
    os.replace(tmp, bag / 'metadata.yaml')


class BagWriter:
    """
    A rosbag2 bag directory being written: one or more storage files plus metadata.yaml.

    Not thread-safe: one thread (the recorder's writer thread) owns it. Any OSError
    while writing (full disk, EFBIG) moves it to :attr:`failed`: the current file is
    salvaged at its last flush, metadata.yaml is written, and further writes are refused.
    """

    def __init__(self, path, storage: str = 'mcap', compression: str = 'none',
                 max_bytes: int = 0, max_duration_s: float = 0.0, fsync: bool = False):
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
        if compression not in ('none', 'zstd'):
            raise BagError(f'compression must be none or zstd, got {compression!r}')
        if compression == 'zstd' and storage != 'mcap':
            raise BagError('zstd compression needs the mcap storage')
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'{self.path}: exists already, not overwriting')
        self.storage = storage
        self.compression = CompressionMode.STORAGE if compression == 'zstd' else \
            CompressionMode.NONE
        self.max_bytes, self.max_duration_ns = int(max_bytes), int(max_duration_s * 1e9)
        self.fsync = fsync
        self.topics: dict[str, TopicSpec] = {}
        self.file_counts: list[dict[str, int]] = []
        self.files: list[FileStats] = []
        self.bytes_written = 0
        self.failed: str = ''
        self.closed = False
        self._file = None
        self._conns: dict[str, Connection] = {}
        self._opened_at = 0.0
        self.path.mkdir(parents=True)
        self._open_file()

    # -- files ---------------------------------------------------------------------------
    @property
    def current_file(self) -> str:
        return str(self._file.path) if self._file is not None else ''

    @property
    def counts(self) -> dict[str, int]:
        total = defaultdict(int)      # read from other threads: iterate over copies
        for fc in list(self.file_counts):
            for k, v in list(fc.items()):
                total[k] += v
        return dict(total)

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def _open_file(self) -> None:
        name = f'{self.path.name}_{len(self.files)}{STORAGES[self.storage]}'
        cls = _McapFile if self.storage == 'mcap' else _Sqlite3File
        self._file = cls(self.path / name, self.compression)
        self.files.append(FileStats(name))
        self.file_counts.append(defaultdict(int))
        self._conns = {}
        self._added_types = set()
        self._opened_at = time.monotonic()
        for spec in self.topics.values():
            self._register(spec)
        # A bag that has a metadata.yaml from the start is readable even while recording.
        self._write_metadata()

    def _register(self, spec: TopicSpec) -> None:
        fmt = MessageDefinitionFormat.MSG if spec.encoding == 'ros2msg' else \
            MessageDefinitionFormat.IDL
        conn = Connection(id=len(self._conns) + 1, topic=spec.topic, msgtype=spec.msgtype,
                          msgdef=MessageDefinition(fmt, spec.msgdef), digest=spec.digest,
                          msgcount=0,
                          ext=ConnectionExtRosbag2('cdr', list(spec.qos)), owner=self)
        if spec.msgtype not in self._added_types:
            self._file.add_msgtype(conn)
            self._added_types.add(spec.msgtype)
        self._file.add_connection(conn, spec.qos_text())
        self._conns[spec.topic] = conn

    def _write_metadata(self) -> None:
        write_metadata_yaml(self.path, self.metadata())

    def metadata(self) -> dict:
        comp = 'zstd' if self.compression == CompressionMode.STORAGE else ''
        return bag_metadata(self.storage, self.files, list(self.topics.values()),
                            self.counts, comp)

    def _file_metadata_text(self) -> str:
        return _yaml_text(self.metadata()['rosbag2_bagfile_information']).strip()

    # -- writing -------------------------------------------------------------------------
    def add_topic(self, spec: TopicSpec) -> None:
        """Register a topic (before its first message); the definition goes into every file."""
        if self.failed or self.closed:
            return
        if spec.topic in self.topics:
            if self.topics[spec.topic].msgtype != spec.msgtype:
                raise BagError(f'{spec.topic}: already recorded as '
                               f'{self.topics[spec.topic].msgtype}, not {spec.msgtype}')
            return
        self.topics[spec.topic] = spec
        self._guard(self._register, spec)

    def write(self, topic: str, timestamp_ns: int, data) -> bool:
        """Append one serialized (CDR) message; False if the bag has failed or is closed."""
        if self.failed or self.closed:
            return False
        conn = self._conns.get(topic)
        if conn is None:
            raise BagError(f'{topic}: not registered (add_topic first)')
        if not self._guard(self._file.write, conn, int(timestamp_ns), data):
            return False
        self.file_counts[-1][topic] += 1
        self.files[-1].add(int(timestamp_ns))
        self.bytes_written += len(data)
        if self.max_bytes and self._file.size >= self.max_bytes:
            self.split()
        elif self.max_duration_ns and \
                (time.monotonic() - self._opened_at) * 1e9 >= self.max_duration_ns:
            self.split()
        return not self.failed

    def flush(self) -> bool:
        """Make everything written so far durable and readable after a crash."""
        if self.failed or self.closed:
            return False
        return self._guard(self._file.flush, self.fsync)

    def split(self) -> bool:
        """Finish the current file and continue in a new one (same bag)."""
        if self.failed or self.closed:
            return False
        if not self._guard(self._file.close, METADATA_VERSION, self._file_metadata_text()):
            return False
        self._file = None
        return self._guard(self._open_file)

    def close(self) -> dict:
        """Finalise the current file and metadata.yaml; returns the metadata mapping."""
        if not self.closed and not self.failed:
            if self._guard(self._file.close, METADATA_VERSION, self._file_metadata_text()):
                self._guard(self._write_metadata)
        self.closed = True
        return self.metadata()

    def _guard(self, fn, *args) -> bool:
        try:
            fn(*args)
            return True
        except (OSError, sqlite3.Error) as exc:
            self._fail(exc)
            return False

    def _fail(self, exc) -> None:
        """Stop writing; keep what was flushed readable (finalised if space allows)."""
        reason = getattr(exc, 'strerror', None) or str(exc)
        f = self._file
        finalised = False
        if f is not None:
            try:
                finalised = f.salvage(self._file_metadata_text())
            except OSError:
                finalised = False
        # Counts in metadata.yaml must describe what is on disk: recount after salvage.
        try:
            if f is not None:
                from softshape_ros.data.bag_tools import scan_file
                scan = scan_file(f.path)
                self.file_counts[-1] = defaultdict(int, scan.counts)
                self.files[-1] = scan.stats
            self._write_metadata()
        except Exception:  # metadata needs a few bytes too; `bag recover` rebuilds it
            pass
        where = f.path.name if f is not None else self.path.name
        self.failed = (f'write failed on {where}: {reason}; bag kept up to the last flush'
                       + ('' if finalised else ' (run `softshape bag recover` on it)'))
