"""
Bags whose metadata rosbag2 (Jazzy) accepts: decoded with rosbag2's rules, read by readers.

``rosbag2_jazzy`` ports rosbag2's metadata decoding and ``ros2 bag play``'s choice of
reader; the negative cases show the rules refuse what rosbag2 refuses (the metadata this
writer used to produce among them), so a pass means something.
"""

import copy
import random
import string as letters

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbag2_jazzy import (Rosbag2Refuses, check_bag, compression_mode_from_string,
                           decode_metadata, play_reader)
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from softshape_ros.data.bag_tools import recover_bag
from softshape_ros.data.bag_writer import BagWriter, TopicSpec
from softshape_ros.nodes.common import SENSOR_QOS
from softshape_ros.nodes.recorder import to_rosbags_qos

TS = get_typestore(Stores.ROS2_JAZZY)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def string(i: int) -> bytes:
    noise = ''.join(random.Random(i).choices(letters.ascii_letters, k=2000))  # zstd: ~25 %
    return TS.serialize_cdr(TS.types['std_msgs/msg/String'](data=f'{i:05d}' + noise),
                            'std_msgs/msg/String')


def write_bag(path, storage='mcap', compression='none', n=200) -> BagWriter:
    with BagWriter(path, storage=storage, compression=compression,
                   max_bytes=150_000) as w:
        w.add_topic(TopicSpec.from_typestore('/latched', 'std_msgs/msg/String',
                                             [to_rosbags_qos(LATCHED)]))
        w.add_topic(TopicSpec.from_typestore('/stream', 'std_msgs/msg/String',
                                             [to_rosbags_qos(SENSOR_QOS)] * 2))
        w.write('/latched', 10**9, string(0))
        for i in range(n):
            assert w.write('/stream', 10**9 + i, string(i))
            if i % 50 == 49:
                assert w.flush()
    return w


@pytest.mark.parametrize('storage,compression', [('mcap', 'none'), ('mcap', 'zstd'),
                                                 ('sqlite3', 'none')])
def test_ros2_bag_play_would_open_what_the_writer_writes(tmp_path, storage, compression):
    bag = tmp_path / 'bag'
    w = write_bag(bag, storage, compression)
    assert w.closed and not w.failed                  # the with block closed it
    meta = check_bag(bag)                             # metadata.yaml + each file's own
    assert meta['reader'] == 'SequentialReader'
    assert meta['compression_format'] == meta['compression_mode'] == ''
    assert meta['version'] == 9 and meta['storage_identifier'] == storage
    assert len(meta['relative_file_paths']) >= 2 and meta['message_count'] == 201
    topics = {t['name']: t for t in meta['topics']}
    assert topics['/stream']['message_count'] == 200
    latched = topics['/latched']['qos']
    assert [(q['reliability'], q['durability'], q['depth']) for q in latched] == \
        [('reliable', 'transient_local', 1)]
    assert [q['reliability'] for q in topics['/stream']['qos']] == ['best_effort'] * 2
    with Reader(bag) as r:                            # the standard rosbags reader
        got = [(c.topic, t) for c, t, _ in r.messages()]
    assert len(got) == 201 and sorted(t for c, t in got if c == '/stream') == \
        [10**9 + i for i in range(200)]
    if storage == 'mcap':                             # and the mcap reader, file by file
        seen, chunk_compressions = [], set()
        for name in meta['relative_file_paths']:
            with open(bag / name, 'rb') as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                chunk_compressions |= {c.compression
                                       for c in reader.get_summary().chunk_indexes}
                seen += [int(m.data[:5]) for _, ch, _, m in reader.iter_decoded_messages()
                         if ch.topic == '/stream']
        assert seen == list(range(200))
        # the chunks really are compressed as asked: the file says so, not metadata.yaml
        assert chunk_compressions == {'zstd' if compression == 'zstd' else ''}


def test_recovered_bag_is_accepted_too(tmp_path):
    bag = tmp_path / 'crashed'
    w = BagWriter(bag, compression='zstd')
    w.add_topic(TopicSpec.from_typestore('/s', 'std_msgs/msg/String',
                                         [to_rosbags_qos(SENSOR_QOS)]))
    for i in range(120):
        w.write('/s', 1000 + i, string(i))
        if i == 99:
            w.flush()
    w._file.bio.flush()                     # "crash": the open chunk never reaches the disk
    (bag / 'metadata.yaml').unlink()
    assert recover_bag(bag)['messages'] == 100
    meta = check_bag(bag)
    assert meta['reader'] == 'SequentialReader' and meta['message_count'] == 100
    assert [q['reliability'] for q in meta['topics'][0]['qos']] == ['best_effort']


def test_the_rules_refuse_what_rosbag2_refuses(tmp_path):
    write_bag(tmp_path / 'bag', 'mcap', 'zstd', n=10)
    doc = yaml.safe_load((tmp_path / 'bag' / 'metadata.yaml').read_text())
    good = doc['rosbag2_bagfile_information']
    assert play_reader(decode_metadata(good)) == 'SequentialReader'

    old = copy.deepcopy(good)               # what the recorder wrote for zstd before
    old['compression_format'], old['compression_mode'] = 'zstd', 'storage'
    with pytest.raises(Rosbag2Refuses, match='NONE compression mode'):
        play_reader(decode_metadata(old))
    assert compression_mode_from_string('storage') == 'NONE'
    assert compression_mode_from_string('') == 'NONE'

    for mode in ('file', 'FILE', 'message'):  # rosbag2's own compressed bags are opened
        ok = copy.deepcopy(good)
        ok['compression_format'], ok['compression_mode'] = 'zstd', mode
        assert play_reader(decode_metadata(ok)) == 'SequentialCompressionReader'
    lz4 = copy.deepcopy(good)
    lz4['compression_format'], lz4['compression_mode'] = 'lz4', 'FILE'
    with pytest.raises(Rosbag2Refuses, match='no registered plugin'):
        play_reader(decode_metadata(lz4))

    as_text = copy.deepcopy(good)           # version 9 wants the QoS as a sequence
    tm = as_text['topics_with_message_count'][0]['topic_metadata']
    tm['offered_qos_profiles'] = yaml.safe_dump(tm['offered_qos_profiles'])
    with pytest.raises(Rosbag2Refuses, match='is not a sequence'):
        decode_metadata(as_text)
    for key, value in (('compression_mode', None), ('message_count', -1),
                       ('ros_distro', ['jazzy'])):
        bad = copy.deepcopy(good)
        bad[key] = value
        with pytest.raises(Rosbag2Refuses, match=key):
            decode_metadata(bad)
    missing = copy.deepcopy(good)
    del missing['files'][0]['duration']
    with pytest.raises(Rosbag2Refuses, match='missing'):
        decode_metadata(missing)
