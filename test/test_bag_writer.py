"""BagWriter without ROS in the loop: splitting, compression, stored definitions, bad input."""

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from softshape_ros.data.bag_tools import bag_info, format_info
from softshape_ros.data.bag_writer import BagError, BagWriter, TopicSpec

TS = get_typestore(Stores.ROS2_JAZZY)


def header(i):
    H, T = TS.types['std_msgs/msg/Header'], TS.types['builtin_interfaces/msg/Time']
    return TS.serialize_cdr(H(stamp=T(sec=i, nanosec=7), frame_id=f'{i:05d}' + 'p' * 1000),
                            'std_msgs/msg/Header')


def mcap_messages(bag):
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    out = []
    for name in meta['relative_file_paths']:
        with open(bag / name, 'rb') as f:
            out += [(c.topic, m.log_time, d) for _, c, m, d in
                    make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    return meta, out


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_split_by_size_every_file_readable(tmp_path, compression):
    bag = tmp_path / 'split'
    w = BagWriter(bag, max_bytes=200_000, compression=compression)
    w.add_topic(TopicSpec.from_typestore('/h', 'std_msgs/msg/Header'))
    for i in range(600):
        assert w.write('/h', 10**9 + i, header(i))
    meta = w.close()['rosbag2_bagfile_information']
    files = meta['relative_file_paths']
    assert len(files) >= 3 if compression == 'none' else len(files) >= 1
    assert [f['message_count'] for f in meta['files']] and meta['message_count'] == 600
    _, msgs = mcap_messages(bag)
    assert [int(d.frame_id[:5]) for _, _, d in msgs] == list(range(600))
    assert [t for _, t, _ in msgs] == [10**9 + i for i in range(600)]
    with Reader(bag) as r:
        assert sum(1 for _ in r.messages()) == 600
    text = format_info(bag_info(bag))
    assert 'Count: 600' in text and 'std_msgs/msg/Header' in text


def test_split_by_duration_and_on_request(tmp_path):
    bag = tmp_path / 'dur'
    now = [100.0]                        # the writer's steady clock, in seconds
    w = BagWriter(bag, max_duration_s=0.2, clock=lambda: now[0])
    w.add_topic(TopicSpec.from_typestore('/h', 'std_msgs/msg/Header'))
    w.write('/h', 1, header(1))
    now[0] += 0.15
    w.write('/h', 2, header(2))          # 0.15 s: the same file
    now[0] += 0.1
    w.write('/h', 3, header(3))          # 0.25 s: this write passes the duration, new file after
    w.write('/h', 4, header(4))
    assert w.split()
    w.write('/h', 5, header(5))
    meta = w.close()['rosbag2_bagfile_information']
    assert [f['message_count'] for f in meta['files']] == [3, 1, 1]
    assert [int(d.frame_id[:5]) for _, _, d in mcap_messages(bag)[1]] == [1, 2, 3, 4, 5]


def test_type_missing_from_typestore_is_stored_from_its_class(tmp_path):
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Goals
    from rclpy.serialization import serialize_message

    from softshape_ros.nodes.recorder import message_class, spec_from_class
    assert 'nav_msgs/msg/Goals' not in TS.fielddefs
    spec = spec_from_class('/goals', 'nav_msgs/msg/Goals', message_class('nav_msgs/msg/Goals'))
    msg = Goals()
    msg.header.frame_id = 'map'
    for k in range(3):
        p = PoseStamped()
        p.pose.position.x = float(k)
        p.header.frame_id = f'g{k}'
        msg.goals.append(p)
    w = BagWriter(tmp_path / 'goals')
    w.add_topic(spec)
    w.write('/goals', 5, serialize_message(msg))
    w.close()
    _, msgs = mcap_messages(tmp_path / 'goals')
    d = msgs[0][2]
    assert d.header.frame_id == 'map' and [g.pose.position.x for g in d.goals] == [0, 1, 2]
    assert [g.header.frame_id for g in d.goals] == ['g0', 'g1', 'g2']


def test_bad_input_is_refused_clearly(tmp_path):
    with pytest.raises(BagError, match='storage must be'):
        BagWriter(tmp_path / 'x', storage='rosbag1')
    with pytest.raises(BagError, match='zstd compression needs the mcap'):
        BagWriter(tmp_path / 'y', storage='sqlite3', compression='zstd')
    w = BagWriter(tmp_path / 'z')
    with pytest.raises(BagError, match='not registered'):
        w.write('/nope', 0, b'')
    with pytest.raises(BagError, match='no message definition'):
        TopicSpec.from_typestore('/t', 'my_pkg/msg/Nothing')
    w.add_topic(TopicSpec.from_typestore('/h', 'std_msgs/msg/Header'))
    with pytest.raises(BagError, match='already recorded as'):
        w.add_topic(TopicSpec.from_typestore('/h', 'std_msgs/msg/String'))
    w.close()
    with pytest.raises(BagError, match='exists already'):
        BagWriter(tmp_path / 'z')
    assert not w.write('/h', 1, header(1))       # closed: refused, not crashed
    with pytest.raises(BagError, match='no such bag'):
        bag_info(tmp_path / 'missing')


FULL_DISK_SCRIPT = r'''
import json, resource, signal, sys
from softshape_ros.data.bag_writer import BagWriter, TopicSpec
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, 1_000_000))
w = BagWriter(sys.argv[1], storage=sys.argv[2])
w.add_topic(TopicSpec.from_typestore('/b', 'std_msgs/msg/String'))
ok = 0
for i in range(400):
    data = b'\x00\x01\x00\x00' + (5001).to_bytes(4, 'little') + b'%05d' % i + b'z' * 4995 + b'\0'
    if not w.write('/b', 10**9 + i, data):
        break
    ok += 1
    if i % 20 == 19:
        w.flush()
w.close()
print(json.dumps({'accepted': ok, 'failed': w.failed, 'counts': w.counts}))
'''


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_full_disk_stops_cleanly_and_leaves_a_readable_bag(tmp_path, storage):
    import json
    import sqlite3
    import subprocess
    import sys
    bag = tmp_path / 'full'
    proc = subprocess.run([sys.executable, '-c', FULL_DISK_SCRIPT, str(bag), storage],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out['failed'] and 'write failed' in out['failed'] and out['accepted'] < 400
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    if storage == 'mcap':
        _, msgs = mcap_messages(bag)
        ids = [int(d.data[:5]) for _, _, d in msgs]
    else:
        con = sqlite3.connect(next(bag.glob('*.db3')))
        ids = [int(bytes(d)[8:13]) for (d,) in
               con.execute('SELECT data FROM messages ORDER BY timestamp')]
        con.close()
    assert len(ids) >= 20 and ids == list(range(len(ids)))     # a clean, flushed prefix
    assert meta['message_count'] == len(ids) == out['counts'].get('/b', 0)
