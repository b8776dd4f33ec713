"""
The recorder node over real DDS, read back by independent readers.

MCAP files are read with the ``mcap`` + ``mcap-ros2-support`` packages (schemas from the
file itself), db3 files with plain ``sqlite3``; each stored payload must deserialise to
exactly the message that was published (CDR padding bytes are unspecified, so the
comparison is by message, not by byte).
"""

import sqlite3
import time

import numpy as np
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_srvs.srv import Trigger

from softshape_ros.nodes.common import SENSOR_QOS, numpy_to_image, ns_to_stamp
from softshape_ros.nodes.diagnostics import newest_key, received_key
from waits import wait_matched

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def read_mcap_bag(bag):
    """{topic: [(log_time, publish stamp ns or None, raw bytes, decoded)]} over all files."""
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    out = {}
    for name in meta['relative_file_paths']:
        with open(bag / name, 'rb') as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for schema, channel, message, decoded in reader.iter_decoded_messages():
                out.setdefault(channel.topic, []).append(
                    (message.log_time, message.data, decoded, schema.name))
    return meta, out


def call(ros, node, service, timeout=10.0):
    client = node.create_client(Trigger, service)
    assert client.wait_for_service(timeout_sec=timeout), f'{service} not available'
    fut = client.call_async(Trigger.Request())
    ros.wait_for(fut.done, timeout=timeout, what=f'{service} response')
    return fut.result()


def make_recorder(ros, **params):
    from softshape_ros.nodes.recorder import Recorder
    params.setdefault('discovery_period_s', 0.1)
    return ros.add(Recorder(parameter_overrides=[Parameter(k, value=v)
                                                 for k, v in params.items()]))


def test_records_camera_rate_streams_mcap_roundtrip(ros, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header
    pub = ros.node('cam_pub')
    main = pub.create_publisher(Image, '/rig/camera_main/image_raw', RELIABLE)
    side = pub.create_publisher(Image, '/rig/camera_side/image_raw', SENSOR_QOS)
    trig = pub.create_publisher(Header, '/rig/trigger', RELIABLE)
    diags = []
    pub.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    bag = tmp_path / 'cams'
    rec = make_recorder(ros, output=str(bag), **{'diagnostic_updater.period': 0.2})
    want = {'/rig/camera_main/image_raw', '/rig/camera_side/image_raw', '/rig/trigger'}
    ros.wait_for(lambda: want <= set(rec.subs), timeout=20, what='subscriptions')
    wait_matched(ros, [main, side, trig], [rec.subs[t] for t in want])
    rng = np.random.default_rng(0)
    sent = {t: {} for t in want}
    t0 = time.time_ns()
    n = 45                                         # 1.5 s at 30 Hz, 320x240 RGB
    for i in range(n):
        t_last = time.time_ns()                    # before the last trigger is published
        stamp = ns_to_stamp(10**18 + i * 33_333_333)
        h = Header(frame_id='rig', stamp=stamp)
        trig.publish(h)
        sent['/rig/trigger'][i] = h
        for topic, p in (('/rig/camera_main/image_raw', main),
                         ('/rig/camera_side/image_raw', side)):
            m = numpy_to_image(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), stamp,
                               'cam')
            p.publish(m)
            sent[topic][i] = m
        if i == n // 2:
            assert call(ros, pub, '/recorder/split_bagfile').success
        time.sleep(1 / 30)                         # pacing: a 30 Hz camera
    ros.wait_for(lambda: rec.recording.received['/rig/camera_main/image_raw'] >= n
                 and rec.recording.received['/rig/trigger'] >= n, timeout=20,
                 what='every reliable message at the recorder')

    def status():
        statuses = [s for a in list(diags) for s in a.status if s.name == 'recorder: bag']
        return {k.key: k.value for k in statuses[-1].values} if statuses else {}
    # the writer thread reports on /diagnostics what it wrote: every reliable message
    ros.wait_for(lambda: int(status().get('messages_written', 0)) >= 2 * n, timeout=20,
                 what=lambda: f'recorder diagnostics with {2 * n} messages written: {status()}')
    kv = status()
    assert kv['current_file'].startswith(str(bag))
    assert kv['dropped_queue_full'] == '0'
    # Per topic: how many arrived, and when the newest was published (its source stamp), so
    # a process that stops the recorder can first wait for what must be in the bag.
    reliable = ('/rig/camera_main/image_raw', '/rig/trigger')
    ros.wait_for(lambda: all(status().get(received_key(x)) == str(n) for x in reliable),
                 timeout=20, what=lambda: f'diagnostics counting {n} of each: {status()}')
    kv = status()
    for topic in reliable:
        assert t_last <= int(kv[newest_key(topic)]) <= time.time_ns()
    rec.recording.stop()
    t1 = time.time_ns()

    meta, got = read_mcap_bag(bag)
    assert len(meta['relative_file_paths']) == 2, 'split service did not start a new file'
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in meta['topics_with_message_count']}
    for topic in ('/rig/camera_main/image_raw', '/rig/trigger'):       # reliable: all, equal
        cls = Header if topic == '/rig/trigger' else Image
        assert [deserialize_message(m[1], cls) for m in got[topic]] == \
            list(sent[topic].values()), topic
        assert counts[topic] == n
    side_got = got['/rig/camera_side/image_raw']                       # best effort: exact
    assert len(side_got) >= n * 0.8                                    # where present
    for log_time, data, decoded, schema in side_got:
        i = round((decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec - 10**18)
                  / 33_333_333)
        assert deserialize_message(data, Image) == sent['/rig/camera_side/image_raw'][i]
        assert schema == 'sensor_msgs/msg/Image' and decoded.width == 320
        assert t0 <= log_time <= t1
    assert got['/rig/trigger'][3][2].frame_id == 'rig'


def test_sqlite3_storage_pause_resume_and_topic_selection(ros, tmp_path):
    from std_msgs.msg import Header, String
    pub = ros.node('sel_pub')
    extra = pub.create_publisher(Header, '/extra/stamps', RELIABLE)
    secret = pub.create_publisher(String, '/extra/secret', RELIABLE)
    listed = pub.create_publisher(String, '/listed', RELIABLE)
    bag = tmp_path / 'sq'
    rec = make_recorder(ros, output=str(bag), storage='sqlite3', rig_topics=False,
                        topics=['/listed'], regex='^/extra/', exclude_regex='secret')
    ros.wait_for(lambda: {'/extra/stamps', '/listed'} <= set(rec.subs), timeout=20,
                 what='subscriptions')
    wait_matched(ros, [extra, listed], [rec.subs['/extra/stamps'], rec.subs['/listed']])
    topics = ('/extra/stamps', '/listed')

    def arrived(counts, n):
        # each message of the phase reached the recorder before the next service call
        ros.wait_for(lambda: all(counts[t] >= n for t in topics), timeout=10,
                     what=lambda: f'{n} messages per topic: {dict(counts)}')
    recorded = []
    for i in range(30):
        if i == 10:
            arrived(rec.recording.received, 10)
            assert call(ros, pub, '/recorder/pause').success
        if i == 20:
            arrived(rec.recording.paused_skipped, 10)
            assert call(ros, pub, '/recorder/resume').success
        h = Header(frame_id=f'h{i}', stamp=ns_to_stamp(i))
        extra.publish(h)
        secret.publish(String(data=f's{i}'))
        listed.publish(String(data=f'l{i}'))
        if not 10 <= i < 20:
            recorded.append(h)
    arrived(rec.recording.received, 20)
    rec.recording.stop()
    assert dict(rec.recording.received) == {t: 20 for t in topics}
    assert dict(rec.recording.paused_skipped) == {t: 10 for t in topics}
    assert '/extra/secret' not in rec.subs
    db = next(bag.glob('*.db3'))
    con = sqlite3.connect(db)
    rows = con.execute('SELECT t.name, m.data FROM messages m JOIN topics t '
                       'ON t.id = m.topic_id ORDER BY m.timestamp').fetchall()
    defs = dict(con.execute('SELECT topic_type, encoded_message_definition '
                            'FROM message_definitions').fetchall())
    con.close()
    assert [deserialize_message(d, Header) for t, d in rows if t == '/extra/stamps'] == recorded
    assert sum(t == '/listed' for t, _ in rows) == 20
    assert not any(t == '/extra/secret' for t, _ in rows)
    assert 'string frame_id' in defs['std_msgs/msg/Header']
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['storage_identifier'] == 'sqlite3' and meta['message_count'] == len(rows)


def test_qos_rematched_when_a_best_effort_publisher_joins(ros, tmp_path):
    from std_msgs.msg import String
    pub = ros.node('qos_pub')
    reliable = pub.create_publisher(String, '/qos/mixed', RELIABLE)
    rec = make_recorder(ros, output=str(tmp_path / 'q'), rig_topics=False, regex='^/qos/')
    ros.wait_for(lambda: '/qos/mixed' in rec.subs, timeout=20, what='subscription')
    assert rec.sub_qos['/qos/mixed'][1].reliability == ReliabilityPolicy.RELIABLE
    late = pub.create_publisher(String, '/qos/mixed', SENSOR_QOS)
    ros.wait_for(lambda: rec.sub_qos['/qos/mixed'][1].reliability
                 == ReliabilityPolicy.BEST_EFFORT, timeout=20, what='QoS re-match')
    wait_matched(ros, [reliable, late], [rec.subs['/qos/mixed']], timeout=10)
    ros.wait_for(lambda: rec.subs['/qos/mixed'].get_publisher_count() >= 2, timeout=10,
                 what='the recorder matched with both publishers')
    reliable.publish(String(data='from reliable'))
    late.publish(String(data='from best effort'))
    ros.wait_for(lambda: rec.recording.received['/qos/mixed'] >= 2, timeout=10,
                 what='both publishers recorded')
