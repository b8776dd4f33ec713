"""
rosbags' private storage API, as data/rosbags_adapter.py expects it: fails loudly on upgrade.

The recorder, its crash salvage and ``softshape bag recover`` build on rosbags internals
(McapWriter's state, PendingChunk, Sqlite3Writer, its zstd and QoS helpers). These tests
name what changed, so an upgrade breaks here with a reason and not as a torn bag later.
"""

import re
from dataclasses import dataclass
from importlib.metadata import version
from io import BytesIO
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.interfaces import (Connection, ConnectionExtRosbag2, MessageDefinition,
                                MessageDefinitionFormat)
from rosbags.rosbag2 import storage_mcap

from softshape_ros.data import rosbags_adapter
from softshape_ros.data.rosbag2_format import TopicSpec, mcap_header, mcap_is_finished
from softshape_ros.data.rosbags_adapter import (TESTED_ROSBAGS, McapStorage, check_private_api,
                                                zstd_compress, zstd_decompress)

ROOT = Path(__file__).resolve().parent.parent


def test_rosbags_private_api_is_what_the_adapter_builds_on():
    problems = check_private_api()
    assert not problems, (
        f'rosbags {version("rosbags")} changed the private API that '
        f'softshape_ros/data/rosbags_adapter.py builds on:\n  ' + '\n  '.join(problems)
        + f'\nInstall a tested rosbags ({TESTED_ROSBAGS[0]} .. {TESTED_ROSBAGS[1]}, pinned in '
        'requirements.txt) or update the adapter and TESTED_ROSBAGS together.')


def test_requirements_pin_rosbags_to_the_tested_range():
    line = next(ln for ln in (ROOT / 'requirements.txt').read_text().splitlines()
                if re.match(r'rosbags\b', ln))
    spec = line.split('#')[0].replace(' ', '')
    lo, hi = TESTED_ROSBAGS
    want = f'rosbags=={lo}' if lo == hi else f'rosbags>={lo},<={hi}'
    assert spec == want, f'requirements.txt has {spec!r}; the adapter is tested for {want!r}'


def test_the_check_names_a_changed_api(monkeypatch):
    @dataclass
    class PendingChunk:             # as if a rosbags release renamed a field
        start: int
        end: int
        bio: BytesIO
        msgs: dict

    monkeypatch.setattr(storage_mcap, 'PendingChunk', PendingChunk)
    monkeypatch.setattr(storage_mcap.McapWriter, 'close', lambda self, metadata: None)
    problems = check_private_api()
    assert any('PendingChunk' in p and "'start'" in p for p in problems), problems
    assert any(p.startswith("McapWriter.close('version', 'metadata') is now ('metadata',)")
               for p in problems), problems


def test_the_check_sees_new_writer_state(monkeypatch):
    original = storage_mcap.McapWriter.__init__

    def init(self, path, compression):
        original(self, path, compression)
        self.chunk_crc = True       # as if rosbags grew state its methods rely on

    monkeypatch.setattr(storage_mcap.McapWriter, '__init__', init)
    problems = check_private_api()
    assert any('McapWriter state' in p and 'chunk_crc' in p for p in problems), problems


def test_mcap_storage_round_trip_with_rollback(tmp_path):
    """Write, flush, write more, roll back to the flush, finish: readers see the flushed part."""
    spec = TopicSpec.from_typestore('/h', 'std_msgs/msg/String')
    msgdef = MessageDefinition(MessageDefinitionFormat.MSG, spec.msgdef)
    conn = Connection(1, '/h', spec.msgtype, msgdef, spec.digest, 0,
                      ConnectionExtRosbag2('cdr', []), None)
    path = tmp_path / 'x.mcap'
    bio = path.open('xb')
    bio.write(mcap_header('test'))
    mcap = McapStorage(path, bio, zstd=True)
    mcap.add_msgtype(conn)
    mcap.add_connection(conn, spec.qos_text())
    data = b'\x00\x01\x00\x00\x06\x00\x00\x00hello\x00'
    for i in range(10):
        mcap.write(conn, 100 + i, data)
    mcap.close_chunk()
    point = mcap.checkpoint()
    assert point.chunks == 1 and point.channel_counts == {1: 10}
    for i in range(5):
        mcap.write(conn, 200 + i, data)
    mcap.close_chunk()
    assert len(mcap.chunks) == 2 and mcap.pending_bytes == 0
    bio.truncate(point.offset)
    bio.seek(point.offset)
    mcap.rollback(point, bio)
    assert len(mcap.chunks) == 1 and mcap.channel_stats == {1: 10}
    assert (mcap.message_start_time, mcap.message_end_time) == (100, 109)
    mcap.finish(9, '')
    assert mcap_is_finished(path)
    with path.open('rb') as f:
        reader = make_reader(f)
        assert [m.log_time for _, _, m in reader.iter_messages()] == list(range(100, 110))
        assert {c.compression for c in reader.get_summary().chunk_indexes} == {'zstd'}
    assert zstd_decompress(zstd_compress(b'abc' * 100)) == b'abc' * 100


def test_nothing_else_imports_rosbags_internals():
    inner = re.compile(r'rosbags\.rosbag2\.(storage_\w+|metadata)\b|'
                       r'from rosbags\.rosbag2 import .*\b(storage_\w+|metadata)\b')
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / 'softshape_ros').rglob('*.py')
                 if p.name != Path(rosbags_adapter.__file__).name
                 and inner.search(p.read_text())]
    assert not offenders, f'import rosbags internals through data/rosbags_adapter: {offenders}'


@pytest.mark.parametrize('zstd', [False, True])
def test_adapter_state_matches_rosbags_writer(tmp_path, zstd):
    ours = McapStorage(tmp_path / 'x.mcap', BytesIO(), zstd)
    assert ours.compression == ('zstd' if zstd else '')
    assert ours.compressor(b'x' * 1000) != b'x' * 1000 if zstd else \
        ours.compressor(b'x') == b'x'
