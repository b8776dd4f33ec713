"""
Write standard rosbag2 bags (MCAP or sqlite3) that survive crashes and full disks.

Built on the storage plugins of ``rosbags`` (the byte format is theirs, reached through
:mod:`.rosbags_adapter`), with what a recorder needs on top: several files per bag (split
by size or duration, as ``ros2 bag record`` does), a :meth:`BagWriter.flush` that makes
everything written so far readable after a ``kill -9`` (closes the MCAP chunk, or commits
the sqlite transaction), and a salvage path for write errors (full disk, file-size limit)
that cuts the file back to the last flushed byte and finalises it there.
"""

from __future__ import annotations

import os
import sqlite3
import time
from collections import defaultdict
from collections.abc import Callable
from importlib.metadata import version as _pkg_version
from pathlib import Path

from rosbags.interfaces import (Connection, ConnectionExtRosbag2, MessageDefinition,
                                MessageDefinitionFormat)

from softshape_ros.data.bag_tools import scan_file
from softshape_ros.data.rosbag2_format import (COMPRESSIONS, METADATA_VERSION, STORAGES,
                                               BagError, FileStats, TopicSpec, bag_metadata,
                                               mcap_header, metadata_text, write_metadata_yaml)
from softshape_ros.data.rosbags_adapter import McapStorage, Sqlite3Storage


class _McapFile:
    """One MCAP file of a bag: rosbags' MCAP writer plus flush points and salvage."""

    def __init__(self, path: Path, zstd: bool):
        self.path = path
        bio = path.open('xb')
        bio.write(mcap_header(f'rosbags-{_pkg_version("rosbags")}'))
        self.mcap = McapStorage(path, bio, zstd)
        bio.flush()
        self._good = self.mcap.checkpoint()     # the last flush point

    @property
    def bio(self):
        return self.mcap.bio

    @property
    def size(self) -> int:
        return self.mcap.bio.tell() + self.mcap.pending_bytes

    def add_msgtype(self, conn: Connection) -> None:
        self.mcap.add_msgtype(conn)

    def add_connection(self, conn: Connection, qos_text: str) -> None:
        self.mcap.add_connection(conn, qos_text)

    def write(self, conn: Connection, timestamp: int, data) -> None:
        self.mcap.write(conn, timestamp, data)

    def flush(self, fsync: bool) -> None:
        if self.mcap.has_pending_messages:
            self.mcap.close_chunk()
        self.mcap.bio.flush()
        if fsync:
            os.fsync(self.mcap.bio.fileno())
        self._good = self.mcap.checkpoint()

    def close(self, metadata: str) -> None:
        self.mcap.finish(METADATA_VERSION, metadata)

    def salvage(self, metadata: str) -> bool:
        """Cut back to the last flush and write the summary there; False if even that fails."""
        try:
            self.mcap.bio.close()
        except OSError:
            pass
        good = self._good.offset
        os.truncate(self.path, good)
        try:
            bio = self.path.open('r+b')
            bio.seek(good)
            self.mcap.rollback(self._good, bio)
            self.mcap.finish(METADATA_VERSION, metadata)
            return True
        except OSError:
            try:
                self.mcap.bio.close()
            except OSError:
                pass
            os.truncate(self.path, good)
            return False


class _Sqlite3File:
    """One sqlite3 file of a bag: a commit is a flush point (sqlite's journal does the rest)."""

    def __init__(self, path: Path, zstd: bool):
        if zstd:
            raise BagError('sqlite3 storage does not support compression')
        if path.exists():
            raise BagError(f'{path}: exists already, not overwriting')
        self.path = path
        self.db = Sqlite3Storage(path)
        self.size = 0               # message bytes + row overhead, for the size split

    def add_msgtype(self, conn: Connection) -> None:
        self.db.add_msgtype(conn)

    def add_connection(self, conn: Connection, qos_text: str) -> None:
        self.db.add_connection(conn, qos_text)

    def write(self, conn: Connection, timestamp: int, data) -> None:
        self.db.write(conn, timestamp, data)
        self.size += len(data) + 24

    def flush(self, fsync: bool) -> None:
        self.db.commit()

    def close(self, metadata: str) -> None:
        self.db.finish(METADATA_VERSION, metadata)

    def salvage(self, metadata: str) -> bool:
        try:
            self.db.rollback()
            self.db.finish(METADATA_VERSION, metadata)
            return True
        except sqlite3.Error:
            self.db.close_quietly()
            return False


class BagWriter:
    """
    A rosbag2 bag directory being written: one or more storage files plus metadata.yaml.

    Not thread-safe: one thread (the recorder's writer thread) owns it. Any OSError
    while writing (full disk, EFBIG) moves it to :attr:`failed`: the current file is
    salvaged at its last flush, metadata.yaml is written, and further writes are refused.
    A context manager: leaving the ``with`` block closes the bag (also on an exception,
    which keeps everything written so far).

    ``path`` is the bag directory to create (must not exist); ``storage`` is ``mcap`` or
    ``sqlite3``; ``compression`` ``none`` or ``zstd`` (MCAP chunk compression); a new file
    starts at ``max_bytes`` or after ``max_duration_s`` (0: never) on the steady ``clock``
    (seconds; tests pass their own); ``fsync`` makes every flush survive power loss too,
    not only a crash.
    """

    def __init__(self, path, storage: str = 'mcap', compression: str = 'none',
                 max_bytes: int = 0, max_duration_s: float = 0.0, fsync: bool = False,
                 clock: Callable[[], float] = time.monotonic):
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
        if compression not in COMPRESSIONS:
            raise BagError(f'compression must be none or zstd, got {compression!r}')
        if compression == 'zstd' and storage != 'mcap':
            raise BagError('zstd compression needs the mcap storage (chunk compression); '
                           'sqlite3 bags would need rosbag2\'s file or message compression, '
                           'which this writer does not do')
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'{self.path}: exists already, not overwriting')
        self.storage = storage
        self.compression = compression
        self.max_bytes, self.max_duration_ns = int(max_bytes), int(max_duration_s * 1e9)
        self.fsync = fsync
        self.clock = clock
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
        self._file = cls(self.path / name, self.compression == 'zstd')
        self.files.append(FileStats(name))
        self.file_counts.append(defaultdict(int))
        self._conns = {}
        self._added_types = set()
        self._opened_at = self.clock()
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
        """Return the metadata.yaml mapping of what is written so far."""
        return bag_metadata(self.storage, self.files, list(self.topics.values()), self.counts)

    def _file_metadata_text(self) -> str:
        return metadata_text(self.metadata())

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
                (self.clock() - self._opened_at) * 1e9 >= self.max_duration_ns:
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
        if not self._guard(self._file.close, self._file_metadata_text()):
            return False
        self._file = None
        return self._guard(self._open_file)

    def close(self) -> dict:
        """Finalise the current file and metadata.yaml; returns the metadata mapping."""
        if not self.closed and not self.failed:
            if self._guard(self._file.close, self._file_metadata_text()):
                self._guard(self._write_metadata)
        self.closed = True
        return self.metadata()

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

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
                scan = scan_file(f.path)
                self.file_counts[-1] = defaultdict(int, scan.counts)
                self.files[-1] = scan.stats
            self._write_metadata()
        except Exception:  # metadata needs a few bytes too; `bag recover` rebuilds it
            pass
        where = f.path.name if f is not None else self.path.name
        self.failed = (f'write failed on {where}: {reason}; bag kept up to the last flush'
                       + ('' if finalised else ' (run `softshape bag recover` on it)'))


__all__ = ['BagError', 'BagWriter', 'TopicSpec']
