"""
Every part of rosbags beyond its public Reader/Writer that softshape_ros builds on.

rosbags' public ``Writer`` writes a bag in one go into one file named after the directory.
A crash-safe recorder needs more of its storage plugins: files named and split by us, a
chunk closed on demand (a flush point), the state rolled back to the last flush after a
write error, an unfinished file resumed at its last good byte to append the summary, and
the zstd and QoS helpers those plugins use. None of that is rosbags' public API, so it all
sits here: rosbags is pinned to :data:`TESTED_ROSBAGS` in requirements.txt, and
:func:`check_private_api` (run by ``test/test_rosbags_adapter.py``) names what moved when
an upgrade breaks it. Nothing else in softshape_ros imports ``rosbags.rosbag2.storage_*``
or ``rosbags.rosbag2.metadata``.
"""

from __future__ import annotations

import inspect
import sqlite3
import tempfile
from collections import defaultdict
from dataclasses import dataclass, fields, is_dataclass
from importlib.metadata import version as _installed_version
from io import BytesIO
from pathlib import Path
from typing import BinaryIO, Sequence

from rosbags.interfaces import Qos
from rosbags.rosbag2 import metadata as _metadata
from rosbags.rosbag2 import storage_mcap as _mcap
from rosbags.rosbag2 import storage_sqlite3 as _sqlite3
from rosbags.rosbag2.enums import CompressionMode

#: rosbags versions this module was checked against (``first <= v <= last``); the same
#: range is pinned in requirements.txt.
TESTED_ROSBAGS = ('0.11.6', '0.11.9')

Schema = _mcap.Schema           # MCAP Schema record: id, name, encoding, data
Channel = _mcap.Channel         # MCAP Channel record: id, schema (name), topic, ..., metadata

UNSET_START = 2**63 - 1         # "no message yet" start time, as rosbags' writers use it

# What McapWriter.__init__ and Sqlite3Writer.__init__ set up: McapStorage and Sqlite3Storage
# build the same state themselves, so a new attribute in rosbags must show up in the check.
_MCAP_STATE = frozenset({'path', 'bio', 'schemas', 'channels', 'chunks', 'chunk', 'compression',
                         'compressor', 'message_start_time', 'message_end_time',
                         'channel_stats'})
_SQLITE_STATE = frozenset({'path', 'conn', 'cursor'})
_PENDING_CHUNK_FIELDS = ('message_start_time', 'message_end_time', 'bio', 'msgs')
_SIGNATURES = {
    (_mcap.McapWriter, 'add_msgtype'): ['self', 'connection'],
    (_mcap.McapWriter, 'add_connection'): ['self', 'connection', 'offered_qos_profiles'],
    (_mcap.McapWriter, 'write'): ['self', 'connection', 'timestamp', 'data'],
    (_mcap.McapWriter, 'close_chunk'): ['self'],
    (_mcap.McapWriter, 'close'): ['self', 'version', 'metadata'],
    (_sqlite3.Sqlite3Writer, 'add_msgtype'): ['self', 'connection'],
    (_sqlite3.Sqlite3Writer, 'add_connection'): ['self', 'connection', 'offered_qos_profiles'],
    (_sqlite3.Sqlite3Writer, 'write'): ['self', 'connection', 'timestamp', 'data'],
    (_sqlite3.Sqlite3Writer, 'close'): ['self', 'version', 'metadata'],
}


def zstd_compress(data: bytes) -> bytes:
    """Compress an MCAP chunk with the zstd binding rosbags uses."""
    return _mcap.zstd.compress(data)


def zstd_decompress(data: bytes) -> bytes:
    """Decompress a zstd MCAP chunk."""
    return _mcap.zstd.decompress(data)


def dump_qos(qos: Sequence[Qos]) -> list[dict]:
    """Return QoS profiles in the form metadata version 9 stores them (a YAML sequence)."""
    return _metadata.dump_qos_v9(list(qos))


def parse_qos(profiles) -> list[Qos]:
    """
    Parse stored QoS profiles (a YAML string, or the v9 sequence) into rosbags ``Qos``.

    Text that is not YAML or not a list of profiles raises ValueError.
    """
    try:
        return _metadata.parse_qos(profiles)
    except Exception as exc:        # rosbags raises ReaderError, or a TypeError on odd shapes
        raise ValueError(f'unreadable offered_qos_profiles: {exc}') from None


@dataclass(frozen=True)
class McapCheckpoint:
    """The writer state at a flush point: what a salvage rolls back to."""

    offset: int                     # file size at the flush
    chunks: int                     # ChunkIndex records at the flush
    channel_counts: dict            # channel id -> messages, at the flush
    start_time: int
    end_time: int


class McapStorage(_mcap.McapWriter):
    """
    One MCAP file written by rosbags' McapWriter into a file handle we opened.

    ``McapWriter.__init__`` opens ``<dir>/<dir>.mcap`` and writes the header itself, so
    this builds the same state for a file we name (a new one, header already written) or
    for an unfinished one being resumed at its last good byte (recovery).
    """

    def __init__(self, path: Path, bio: BinaryIO, zstd: bool, *,
                 schemas: Sequence[Schema] = (), channels: Sequence[Channel] = (),
                 chunk_indexes: Sequence[bytes] = (), channel_counts: dict | None = None,
                 start_time: int = UNSET_START, end_time: int = 0):
        self.path = Path(path)
        self.bio = bio
        self.schemas = list(schemas)
        self.channels = list(channels)
        self.chunks = [_filled(body) for body in chunk_indexes]   # ChunkIndex record bodies
        self.chunk = _empty_chunk()
        self.compression = 'zstd' if zstd else ''
        self.compressor = zstd_compress if zstd else _uncompressed
        self.message_start_time = start_time
        self.message_end_time = end_time
        self.channel_stats = dict(channel_counts or {})

    @property
    def pending_bytes(self) -> int:
        """Bytes of the open chunk (not in the file yet)."""
        return self.chunk.bio.tell()

    @property
    def has_pending_messages(self) -> bool:
        return bool(self.chunk.msgs)

    def checkpoint(self) -> McapCheckpoint:
        """Record the state after a flush (call with no open chunk)."""
        return McapCheckpoint(self.bio.tell(), len(self.chunks), dict(self.channel_stats),
                              self.message_start_time, self.message_end_time)

    def rollback(self, point: McapCheckpoint, bio: BinaryIO) -> None:
        """Forget everything after ``point``; go on writing into ``bio`` (at ``point.offset``)."""
        self.bio = bio
        self.chunks = self.chunks[:point.chunks]
        self.channel_stats = dict(point.channel_counts)
        for ch in self.channels:
            self.channel_stats.setdefault(ch.id, 0)
        self.message_start_time, self.message_end_time = point.start_time, point.end_time
        self.chunk = _empty_chunk()

    def finish(self, version: int, metadata_text: str) -> None:
        """Close the open chunk, append metadata, summary and footer, close the file."""
        _mcap.McapWriter.close(self, version, metadata_text)


class Sqlite3Storage(_sqlite3.Sqlite3Writer):
    """One sqlite3 file written by rosbags' Sqlite3Writer, at a path we name; commits on demand."""

    def __init__(self, path: Path):
        self.path = Path(path)
        # The recorder opens the file on its node thread and writes on its writer thread.
        self.conn = sqlite3.connect(f'file:{self.path}', uri=True, check_same_thread=False)
        self.conn.executescript(self.SQLITE_SCHEMA)
        self.cursor = self.conn.cursor()

    def commit(self) -> None:
        self.conn.commit()

    def rollback(self) -> None:
        self.conn.rollback()

    def finish(self, version: int, metadata_text: str) -> None:
        """Store the metadata, commit and close."""
        _sqlite3.Sqlite3Writer.close(self, version, metadata_text)

    def close_quietly(self) -> None:
        try:
            self.conn.close()
        except sqlite3.Error:
            pass


def _uncompressed(data: bytes) -> bytes:
    return data


def _empty_chunk():
    return _mcap.PendingChunk(UNSET_START, 0, BytesIO(), defaultdict(list))


def _filled(body: bytes) -> BytesIO:
    bio = BytesIO()
    bio.write(body)             # rosbags writes a record from tell() + getbuffer()
    return bio


def _version_tuple(text: str) -> tuple:
    return tuple(int(p) for p in text.split('.')[:3] if p.isdigit())


def check_private_api() -> list[str]:
    """
    Check that the installed rosbags still has the private API this module builds on.

    Returns one line per difference found (an empty list when everything matches).
    """
    problems = []
    installed = _installed_version('rosbags')
    lo, hi = (_version_tuple(v) for v in TESTED_ROSBAGS)
    if not lo <= _version_tuple(installed) <= hi:
        problems.append(f'rosbags {installed} is outside the tested range '
                        f'{TESTED_ROSBAGS[0]} .. {TESTED_ROSBAGS[1]}')
    for (cls, name), want in _SIGNATURES.items():
        fn = getattr(cls, name, None)
        got = list(inspect.signature(fn).parameters) if callable(fn) else None
        if got != want:
            problems.append(f'{cls.__name__}.{name}{tuple(want[1:])} is now '
                            f'{"missing" if got is None else tuple(got[1:])}')
    pending = getattr(_mcap, 'PendingChunk', None)
    got = tuple(f.name for f in fields(pending)) if is_dataclass(pending) else None
    if got != _PENDING_CHUNK_FIELDS:
        problems.append(f'storage_mcap.PendingChunk fields {_PENDING_CHUNK_FIELDS} are now {got}')
    for rec, want in ((Schema, ('id', 'name', 'encoding', 'data')),
                      (Channel, ('id', 'schema', 'topic', 'message_encoding', 'metadata'))):
        if getattr(rec, '_fields', None) != want:
            problems.append(f'storage_mcap.{rec.__name__} fields {want} are now '
                            f'{getattr(rec, "_fields", None)}')
    for name in ('compress', 'decompress'):
        if not callable(getattr(getattr(_mcap, 'zstd', None), name, None)):
            problems.append(f'storage_mcap.zstd.{name} is missing')
    for name in ('dump_qos_v9', 'parse_qos'):
        if not callable(getattr(_metadata, name, None)):
            problems.append(f'metadata.{name} is missing')
    if not isinstance(getattr(_sqlite3.Sqlite3Writer, 'SQLITE_SCHEMA', None), str):
        problems.append('Sqlite3Writer.SQLITE_SCHEMA is missing')
    if problems:
        return problems            # the writers below would fail in confusing ways
    problems += _check_writer_state()
    return problems


def _check_writer_state() -> list[str]:
    """Build rosbags' own writers and ours; the attributes they set must be the same."""
    problems = []
    with tempfile.TemporaryDirectory() as tmp:
        for mode in (CompressionMode.NONE, CompressionMode.STORAGE):
            folder = Path(tmp) / f'mcap_{mode.name.lower()}'
            folder.mkdir()
            theirs = _mcap.McapWriter(folder, mode)
            try:
                if set(vars(theirs)) != _MCAP_STATE:
                    problems.append(f'McapWriter state {sorted(_MCAP_STATE)} is now '
                                    f'{sorted(vars(theirs))}')
                want = 'zstd' if mode == CompressionMode.STORAGE else ''
                if theirs.compression != want:
                    problems.append(f'McapWriter({mode.name}).compression {want!r} is now '
                                    f'{theirs.compression!r}')
            finally:
                theirs.abort()
            ours = McapStorage(folder / 'ours.mcap', BytesIO(), mode == CompressionMode.STORAGE)
            if set(vars(ours)) != _MCAP_STATE:
                problems.append(f'McapStorage sets {sorted(vars(ours))}, not '
                                f'{sorted(_MCAP_STATE)}')
        folder = Path(tmp) / 'db3'
        folder.mkdir()
        theirs = _sqlite3.Sqlite3Writer(folder, CompressionMode.NONE)
        try:
            if set(vars(theirs)) != _SQLITE_STATE:
                problems.append(f'Sqlite3Writer state {sorted(_SQLITE_STATE)} is now '
                                f'{sorted(vars(theirs))}')
        finally:
            theirs.abort()
        ours = Sqlite3Storage(folder / 'ours.db3')
        try:
            if set(vars(ours)) != _SQLITE_STATE:
                problems.append(f'Sqlite3Storage sets {sorted(vars(ours))}, not '
                                f'{sorted(_SQLITE_STATE)}')
        finally:
            ours.close_quietly()
    return problems


__all__ = ['Channel', 'McapCheckpoint', 'McapStorage', 'Schema', 'Sqlite3Storage',
           'TESTED_ROSBAGS', 'UNSET_START', 'check_private_api', 'dump_qos', 'parse_qos',
           'zstd_compress', 'zstd_decompress']
