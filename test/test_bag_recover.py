"""
Crash safety: a recorder killed with SIGKILL, a recorder that fills its disk, torn files.

The recorder runs as its own process (as ``ros2 run`` starts it); the bag is repaired with
the ``softshape bag recover`` command and read back with the independent ``mcap`` reader.
The full disk is a real file-size limit (RLIMIT_FSIZE) on the recorder process.
"""

import os
import resource
import signal
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.qos import QoSProfile, ReliabilityPolicy

from softshape_ros.data.bag_tools import bag_info, recover_bag
from softshape_ros.data.bag_writer import BagWriter, TopicSpec
from softshape_ros.nodes.common import numpy_to_image, ns_to_stamp
from waits import call, round_trip

RELIABLE = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)


def start_recorder(bag, *params, limit_bytes=None):
    args = [sys.executable, '-c', 'from softshape_ros.nodes.recorder import main; main()',
            '--ros-args', '-p', f'output:={bag}', '-p', 'rig_topics:=false',
            '-p', 'discovery_period_s:=0.1', '-p', 'diagnostic_updater.period:=0.1']
    for p in params:
        args += ['-p', p]

    def limit():
        if limit_bytes:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=limit)


class RecorderStatus:
    """The recorder process's 'recorder: bag' diagnostics, as key -> value."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        self.error_level = DiagnosticStatus.ERROR
        self.last = {}
        self.errors = []
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on, 10)

    def _on(self, array):
        for s in array.status:
            if s.name == 'recorder: bag':
                self.last = {kv.key: kv.value for kv in s.values}
                if s.level == self.error_level:
                    self.errors.append(s)


def first_recorded(ros, publisher, status, proc, publish_next, timeout=40.0) -> int:
    """
    Publish messages of the sequence until the recorder has one; return how many were sent.

    Our publisher sees a subscription, but that alone proves little across processes: it
    may be a recorder killed a moment ago whose participant lingers in the graph until its
    lease ends. The recorder's own end of the match is proven by a message arriving there
    (its diagnostics count it); from then on nothing is lost to the match. Messages sent
    before it may be lost: they were sent to no one.
    """
    ros.wait_for(lambda: publisher.get_subscription_count() > 0 or proc.poll() is not None,
                 timeout=timeout, what='the recorder process to subscribe')
    assert proc.poll() is None, proc.communicate()[0]
    k = round_trip(ros, lambda k: publish_next(),
                   lambda: int(status.last.get('received', 0)) >= 1 or proc.poll() is not None,
                   what='the first message at the recorder', timeout=timeout)
    assert proc.poll() is None, proc.communicate()[0]
    return k


def cli(*args):
    return subprocess.run([sys.executable, '-m', 'softshape_ros.cli', *args],
                          capture_output=True, text=True, timeout=120)


def read_frame_ids(bag, topic):
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    ids = []
    if meta['storage_identifier'] == 'sqlite3':       # plain sqlite3 + rclpy's CDR decoder
        from rclpy.serialization import deserialize_message
        from std_msgs.msg import Header
        for name in meta['relative_file_paths']:
            con = sqlite3.connect(bag / name)
            ids += [int(deserialize_message(d, Header).frame_id) for (d,) in con.execute(
                'SELECT m.data FROM messages m JOIN topics t ON t.id = m.topic_id '
                'WHERE t.name = ? ORDER BY m.timestamp', (topic,))]
            con.close()
        return meta, ids
    for name in meta['relative_file_paths']:
        with open(bag / name, 'rb') as f:
            for _, ch, _, msg in make_reader(
                    f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
                if ch.topic == topic:
                    ids.append(int(msg.header.frame_id if hasattr(msg, 'header')
                                   else msg.frame_id))
    return meta, ids


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_sigkill_then_recover_keeps_everything_older_than_flush_interval(ros, tmp_path,
                                                                         storage):
    from std_msgs.msg import Header
    bag = tmp_path / 'killed'
    flush_s = 0.5
    topic = f'/kill/{storage}'          # not the topic of a recorder killed a moment ago
    proc = start_recorder(bag, f'regex:=^{topic}$', f'flush_interval_s:={flush_s}',
                          f'storage:={storage}')
    node = ros.node(f'kill_pub_{storage}')
    pub = node.create_publisher(Header, topic, RELIABLE)
    status = RecorderStatus(node)
    sent = []

    def publish_next():
        i = len(sent)
        pub.publish(Header(frame_id=str(i), stamp=ns_to_stamp(i)))
        sent.append(time.monotonic())
    try:
        probes = first_recorded(ros, pub, status, proc, publish_next)
        t_end = time.monotonic() + 2.5
        while time.monotonic() < t_end:
            publish_next()
            time.sleep(0.005)                 # pacing: a 200 Hz stream for 2.5 s
        t_kill = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    if storage == 'mcap':
        with pytest.raises(Exception):        # unfinished: not readable by a summary reader
            with open(next(bag.glob('*.mcap')), 'rb') as f:
                list(make_reader(f).iter_messages())
    r = cli('bag', 'recover', str(bag))
    assert r.returncode == 0, r.stderr
    assert 'unfinished: finalised' in r.stdout or storage == 'sqlite3'
    meta, ids = read_frame_ids(bag, topic)
    # The bound holds from receive time; allow 0.5 s of delivery delay on a loaded machine.
    must = [i for i, t in enumerate(sent) if probes <= i and t < t_kill - flush_s - 0.5]
    assert len(must) > 100
    assert set(must) <= set(ids), f'lost {sorted(set(must) - set(ids))[:10]}...'
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    assert meta['message_count'] == len(ids)
    assert cli('bag', 'recover', str(bag)).returncode == 0       # idempotent
    assert read_frame_ids(bag, topic)[1] == ids
    info = cli('bag', 'info', str(bag))
    assert info.returncode == 0 and f'Count: {len(ids)}' in info.stdout


def test_full_disk_keeps_node_alive_and_bag_readable(ros, tmp_path):
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger
    bag = tmp_path / 'full'
    proc = start_recorder(bag, 'regex:=^/full/', 'flush_interval_s:=0.2',
                          limit_bytes=3 * 2**20)
    node = ros.node('full_pub')
    pub = node.create_publisher(Image, '/full/image', RELIABLE)
    status = RecorderStatus(node)
    errors = status.errors
    rng = np.random.default_rng(1)

    def publish(i):
        pub.publish(numpy_to_image(rng.integers(0, 256, (200, 500), dtype=np.uint8),
                                   ns_to_stamp(i), str(i)))
    sent = []

    def publish_next():
        sent.append(len(sent))
        publish(sent[-1])
    try:
        probes = first_recorded(ros, pub, status, proc, publish_next)
        while len(sent) < 60:                     # 60 x 100 kB > 3 MB limit
            publish_next()
            time.sleep(0.03)                      # pacing: a 33 Hz camera
        ros.wait_for(lambda: errors, timeout=20, what='an ERROR diagnostic from the recorder')
        assert 'write failed' in errors[-1].message
        assert proc.poll() is None, 'recorder died on a full disk'
        client = node.create_client(Trigger, '/recorder/split_bagfile')
        assert client.wait_for_service(timeout_sec=10)
        # the graph may still list the service of the recorder killed before this test
        res = call(ros, client, Trigger.Request(), 'split response', timeout=10)
        assert not res.success and 'write failed' in res.message
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    meta, ids = read_frame_ids(bag, '/full/image')
    assert 5 <= len(ids) < 60
    # a clean prefix, nothing torn (from the first probe that reached the recorder)
    assert ids[0] < probes and ids == list(range(ids[0], ids[0] + len(ids)))
    assert meta['message_count'] == len(ids)
    assert sum(f.stat().st_size for f in bag.glob('*.mcap')) <= 3 * 2**20


def _writer_with_torn_tail(path, cut: int):
    w = BagWriter(path)
    w.add_topic(TopicSpec.from_typestore('/s', 'std_msgs/msg/String'))
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    String = ts.types['std_msgs/msg/String']
    for i in range(3000):
        raw = ts.serialize_cdr(String(data=f'{i:06d}' + 'x' * 500), 'std_msgs/msg/String')
        w.write('/s', 1000 + i, raw)
        if i in (999, 1999):
            w.flush()
    w._file.bio.flush()             # "crash": the pending chunk never reaches the disk
    f = next(path.glob('*.mcap'))
    os.truncate(f, f.stat().st_size - cut)
    return f


@pytest.mark.parametrize('cut', [0, 1, 40, 300_000])
def test_recover_cuts_torn_records_and_rebuilds_indexes(tmp_path, cut):
    bag = tmp_path / 'torn'
    _writer_with_torn_tail(bag, cut)
    (bag / 'metadata.yaml').unlink()
    with pytest.raises(Exception, match='metadata'):
        bag_info(bag)
    report = recover_bag(bag)
    expect = 2000 if cut < 300_000 else 1000   # the big cut tears the second chunk
    assert report['messages'] == expect
    from rosbags.rosbag2 import Reader
    with Reader(bag) as r:                      # the rosbags reader uses the indexes
        got = [raw for _, _, raw in r.messages()]
    assert len(got) == expect
    info = bag_info(bag)
    assert info['messages'] == expect and not info['unfinished_files']
