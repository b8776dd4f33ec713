"""
The rosbag2 bag format as ROS 2 Jazzy writes and reads it: constants, records, metadata.yaml.

A bag is a directory of storage files (MCAP or sqlite3) plus ``metadata.yaml``; each file
also carries the bag's metadata (MCAP: the ``rosbag2`` metadata record; sqlite3: the
``metadata`` table), which rosbag2 parses with the same rules (rosbag2_storage ``yaml.hpp``).
Writer (:mod:`.bag_writer`) and scanner (:mod:`.bag_tools`) both build on this module.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from io import StringIO
from pathlib import Path

from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from softshape_ros.data.rosbags_adapter import UNSET_START, dump_qos

METADATA_VERSION = 9            # rosbag2 metadata version written by Jazzy
ROS_DISTRO = 'jazzy'
STORAGES = {'mcap': '.mcap', 'sqlite3': '.db3'}    # storage identifier -> file suffix
COMPRESSIONS = ('none', 'zstd')  # what the writer offers: MCAP chunk compression
MCAP_MAGIC = b'\x89MCAP0\r\n'   # starts and ends every MCAP file


class McapOp:
    """MCAP record opcodes (https://mcap.dev/spec) that bags use."""

    HEADER = 0x01
    FOOTER = 0x02
    SCHEMA = 0x03
    CHANNEL = 0x04
    MESSAGE = 0x05
    CHUNK = 0x06
    MESSAGE_INDEX = 0x07
    CHUNK_INDEX = 0x08
    DATA_END = 0x0F


U16, U32, U64 = struct.Struct('<H'), struct.Struct('<I'), struct.Struct('<Q')
_TYPESTORE = None


class BagError(RuntimeError):
    """A bag cannot be written or read; the message says which file and why."""


def jazzy_typestore():
    """Return the shared typestore with the Jazzy message definitions (built once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def mcap_string(text: str) -> bytes:
    """Encode an MCAP string field (u32 length + UTF-8)."""
    data = text.encode()
    return U32.pack(len(data)) + data


def mcap_record(op: int, body: bytes) -> bytes:
    """Encode one MCAP record: opcode, u64 length, body."""
    return bytes((op,)) + U64.pack(len(body)) + body


def mcap_header(library: str) -> bytes:
    """Return the bytes every rosbag2 MCAP file starts with: magic + Header (profile ros2)."""
    return MCAP_MAGIC + mcap_record(McapOp.HEADER, mcap_string('ros2') + mcap_string(library))


def mcap_is_finished(path: Path) -> bool:
    """Tell whether an MCAP file ends with its closing magic (its summary was written)."""
    size = path.stat().st_size
    with path.open('rb') as f:
        f.seek(max(0, size - len(MCAP_MAGIC)))
        return size >= 2 * len(MCAP_MAGIC) and f.read() == MCAP_MAGIC


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

    def qos_profiles(self) -> list[dict]:
        """Return the QoS as metadata.yaml version 9 holds it: a sequence of mappings."""
        return dump_qos(self.qos)

    def qos_text(self) -> str:
        """Return the QoS as a YAML string: MCAP channel metadata and the sqlite3 topics table."""
        return yaml_text(self.qos_profiles()).strip()


@dataclass
class FileStats:
    """Per-file bookkeeping for metadata.yaml."""

    name: str
    count: int = 0
    start: int = UNSET_START
    end: int = 0

    def add(self, t: int) -> None:
        self.count += 1
        self.start = min(self.start, t)
        self.end = max(self.end, t)

    def merge(self, other: 'FileStats') -> None:
        """Add another span of messages (a chunk's) to this one."""
        if other.count:
            self.count += other.count
            self.start = min(self.start, other.start)
            self.end = max(self.end, other.end)

    def as_metadata(self) -> dict:
        start = self.start if self.count else 0
        return {'path': self.name, 'starting_time': {'nanoseconds_since_epoch': start},
                'duration': {'nanoseconds': max(0, self.end - self.start) if self.count else 0},
                'message_count': self.count}


def bag_metadata(storage: str, files: list[FileStats], topics: list[TopicSpec],
                 counts: dict[str, int]) -> dict:
    """
    Build the rosbag2 ``metadata.yaml`` mapping (version 9, as Jazzy writes it).

    ``compression_format`` and ``compression_mode`` stay empty: they name rosbag2's own
    file or message compression (modes FILE or MESSAGE, decompressed by
    rosbag2_compression), which this package never writes. MCAP chunk compression is
    described inside the file, and rosbag2 records it the same way; a non-empty format
    would make ``ros2 bag play`` look for a compression mode and refuse the bag.
    """
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
                                'offered_qos_profiles': t.qos_profiles(),
                                'type_description_hash': t.digest},
             'message_count': int(counts.get(t.topic, 0))}
            for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'files': [f.as_metadata() for f in files],
        'custom_data': None,
        'ros_distro': ROS_DISTRO,
    }}


def yaml_text(data) -> str:
    """Dump plain data as block-style YAML."""
    yaml = YAML(typ='safe')
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()


def metadata_text(metadata: dict) -> str:
    """Serialise the metadata as a storage file embeds it (the mapping under the top key)."""
    return yaml_text(metadata['rosbag2_bagfile_information']).strip()


def write_metadata_yaml(bag: Path, metadata: dict) -> None:
    """Write metadata.yaml atomically (tmp + rename), so a reader never sees half of it."""
    tmp = bag / 'metadata.yaml.tmp'
    tmp.write_text(yaml_text(metadata), 'utf8')
    os.replace(tmp, bag / 'metadata.yaml')


def read_metadata_yaml(bag: Path) -> dict:
    """
    Return the ``rosbag2_bagfile_information`` mapping of a bag's ``metadata.yaml``.

    A missing file or one that is not rosbag2 metadata raises :class:`BagError`.
    """
    path = Path(bag) / 'metadata.yaml'
    try:
        info = YAML(typ='safe').load(path.read_text())['rosbag2_bagfile_information']
    except FileNotFoundError:
        raise BagError(f'{bag}: no metadata.yaml (did the recording crash?); '
                       f'run `softshape bag recover {bag}`') from None
    except Exception as exc:
        raise BagError(f'{path}: not rosbag2 metadata ({type(exc).__name__}: {exc})') from None
    if not isinstance(info, dict):
        raise BagError(f'{path}: not rosbag2 metadata (no rosbag2_bagfile_information mapping)')
    return info
