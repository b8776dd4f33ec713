"""
recorder: write the rig's topics to a standard rosbag2 bag (MCAP, or sqlite3).

Like ``ros2 bag record`` (which this environment lacks): topics by name list and regex,
discovered while running, subscribed raw (CDR bytes, never deserialised) with a QoS that
matches their publishers; one writer thread behind a bounded queue (softshape_ros.data.
recording). Services ``~/pause``, ``~/resume``, ``~/split_bagfile`` (std_srvs/Trigger);
``/diagnostics`` every second with messages, bytes, drops and the current file, and per
topic the messages received and the newest one's source stamp (``received``/``newest <topic>``).
"""

from __future__ import annotations

import datetime
import importlib
import re
import signal
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from std_srvs.srv import Trigger

from softshape_ros.data.bag_writer import BagError, BagWriter, TopicSpec
from softshape_ros.data.recording import Recording
from softshape_ros.nodes.clocks import steady_timer
from softshape_ros.nodes.common import declare_rig_config, main_wrapper
from softshape_ros.nodes.diagnostics import (ERROR, OK, WARN, Updater, fill, newest_key,
                                             received_key)
from softshape_ros.nodes.parameters import Param, declare

PARAMETERS = [
    Param('output', '', "bag directory ('' = ./rosbag2_YYYY_MM_DD-HH_MM_SS)"),
    Param('storage', 'mcap', 'storage plugin: mcap or sqlite3'),
    Param('compression', 'none', 'none or zstd (mcap only)'),
    Param('rig_topics', True, 'record every topic named in rig.yaml topics:'),
    Param('topics', [''], 'more topic names'),
    Param('regex', '', 'and topics matching this (like ros2 bag record -e)'),
    Param('exclude_regex', '', 'never topics matching this'),
    Param('all_topics', False, 'everything in the graph'),
    Param('max_bag_size_mb', 0.0, 'split after this size (0 = never)', (0.0, 1e9)),
    Param('max_bag_duration_s', 0.0, 'split after this long (0 = never)', (0.0, 1e9)),
    Param('flush_interval_s', 1.0, 'at most this much received data is lost to a kill -9',
          (0.0, 3600.0)),
    Param('fsync', False, 'also fsync at each flush (power loss, not just crashes)'),
    Param('queue_messages', 2000, 'writer queue bound; a full queue drops (counted)',
          (1, 10**8)),
    Param('queue_mb', 512.0, 'writer queue bound, MiB', (0.001, 1e6)),
    Param('qos_depth', 50, 'subscription depth', (1, 10**6)),
    Param('discovery_period_s', 0.5, 'look for new topics this often (steady time)',
          (0.01, 3600.0)),
]


def rig_topic_names(cfg) -> list[str]:
    """Every topic the rig config names (per-camera templates expanded), minus predictions."""
    t = cfg.topics
    names = [t.pressure_command, t.pressure_measured, t.trigger, t.sample, t.scene,
             t.diagnostics]
    for cam in cfg.camera_names:
        names += [t.camera('camera_image', cam), t.camera('camera_info', cam),
                  t.camera('capture_time', cam)]
    return names


def message_class(msgtype: str):
    """'sensor_msgs/msg/Image' -> the rclpy message class (its type support)."""
    pkg, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.{kind}'), name)


_PRIMITIVES = {'boolean': 'bool', 'octet': 'byte', 'float': 'float32', 'double': 'float64'}


def _msg_field_type(t: str) -> str:
    """Turn a rosidl Python field type ('sequence<uint8, 4>', 'double') into .msg syntax."""
    m = re.fullmatch(r'sequence<(.+?)(?:, (\d+))?>', t)
    if m:
        return _msg_field_type(m.group(1)) + (f'[<={m.group(2)}]' if m.group(2) else '[]')
    m = re.fullmatch(r'(.+)\[(\d+)\]', t)
    if m:
        return f'{_msg_field_type(m.group(1))}[{m.group(2)}]'
    return _PRIMITIVES.get(t, t)


def spec_from_class(topic: str, msgtype: str, cls, qos=()) -> TopicSpec:
    """
    Build the stored definition of a type the Jazzy typestore lacks from its Python class.

    rosidl classes list their fields (``get_fields_and_field_types``); nested types are
    added the same way, so any decoder can read the recorded messages.
    """
    from rosbags.typesys import get_types_from_msg
    from softshape_ros.data.rosbag2_format import jazzy_typestore
    base = jazzy_typestore()
    types, todo = {}, [(msgtype, cls)]
    while todo:
        name, c = todo.pop()
        if name in types or name in base.fielddefs:
            continue
        lines = []
        for field, ftype in c.get_fields_and_field_types().items():
            mtype = _msg_field_type(ftype)
            inner = re.sub(r'\[.*\]$', '', mtype)
            if '/' in inner:
                pkg, typ = inner.split('/')[0], inner.split('/')[-1]
                full = f'{pkg}/msg/{typ}'
                todo.append((full, message_class(full)))
            lines.append(f'{mtype} {field}')
        types.update(get_types_from_msg('\n'.join(lines), name))
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register(types)
    return TopicSpec.from_typestore(topic, msgtype, qos, typestore=ts)


def _rb_time(d) -> QosTime:
    return QosTime(int(d.nanoseconds // 1_000_000_000), int(d.nanoseconds % 1_000_000_000))


def to_rosbags_qos(q) -> Qos:
    """Convert an rclpy QoSProfile to the rosbags Qos stored as offered_qos_profiles."""
    return Qos(QosHistory[q.history.name], int(q.depth), QosReliability[q.reliability.name],
               QosDurability[q.durability.name], _rb_time(q.deadline), _rb_time(q.lifespan),
               QosLiveliness[q.liveliness.name], _rb_time(q.liveliness_lease_duration),
               bool(q.avoid_ros_namespace_conventions))


def adapted_qos(offered: list, depth: int) -> QoSProfile:
    """
    Choose a subscription QoS every publisher is compatible with (as rosbag2 does).

    Reliable only if all publishers are reliable; transient-local only if all are,
    so latched topics (the scene) deliver their last message to the recorder too.
    """
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE
                                     for q in offered)
    latched = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                    for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        liveliness=LivelinessPolicy.AUTOMATIC)


class Recorder(Node):
    """Record matching topics into one bag until shut down."""

    def __init__(self, **kwargs):
        super().__init__('recorder', **kwargs)
        # A file-size limit (ulimit -f) must become a write error, not a killed process.
        if hasattr(signal, 'SIGXFSZ'):
            try:
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            except ValueError:      # not the main thread (tests): nothing to change
                pass
        cfg = declare_rig_config(self)
        p = declare(self, PARAMETERS)
        output = p.output
        self.storage = p.storage
        self.topic_list = [t for t in p.topics if t]
        regex, exclude = p.regex, p.exclude_regex
        self.include_rig = p.rig_topics
        self.all_topics = p.all_topics
        self.depth = p.qos_depth
        try:
            self.regex = re.compile(regex) if regex else None
            self.exclude = re.compile(exclude) if exclude else None
        except re.error as exc:
            raise ValueError(f'regex parameter is not a valid regular expression: {exc}') from None
        self.wanted = set(self.topic_list)
        if self.include_rig:
            self.wanted |= set(rig_topic_names(cfg))
        if not output:
            stamp = datetime.datetime.now().strftime('%Y_%m_%d-%H_%M_%S')
            output = f'rosbag2_{stamp}'
        self.bag_path = Path(output).expanduser().resolve()
        writer = BagWriter(self.bag_path, storage=self.storage, compression=p.compression,
                           max_bytes=int(p.max_bag_size_mb * 2**20),
                           max_duration_s=p.max_bag_duration_s, fsync=p.fsync)
        self.recording = Recording(writer, queue_messages=p.queue_messages,
                                   queue_bytes=int(p.queue_mb * 2**20),
                                   flush_interval_s=p.flush_interval_s)
        self.subs = {}
        self.sub_qos = {}            # topic -> (message class, QoS profile in use)
        # topic -> when the newest message queued for the bag was published (source
        # timestamp, ns): everything one publisher sent before that instant has arrived
        self.last_source_ns = {}
        self.skipped = {}            # topic -> why it is not recorded
        self.create_service(Trigger, '~/pause', self._pause)
        self.create_service(Trigger, '~/resume', self._resume)
        self.create_service(Trigger, '~/split_bagfile', self._split)
        steady_timer(self, p.discovery_period_s, self._discover)
        self.diagnostics = Updater(self)
        self.diagnostics.setHardwareID(str(self.bag_path))
        self.diagnostics.add('bag', self._diagnose)
        self._reported_error = ''
        self.get_logger().info(f'recording to {self.bag_path} ({self.storage})')
        self._discover()

    # -- topics ----------------------------------------------------------------------------
    def matches(self, topic: str) -> bool:
        if self.exclude is not None and self.exclude.search(topic):
            return False
        if topic in self.wanted or self.all_topics:
            return True
        return self.regex is not None and self.regex.search(topic) is not None

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs:
                self._readapt(topic)
                continue
            if topic in self.skipped or not self.matches(topic):
                continue
            if len(types) != 1:
                self._skip(topic, f'{len(types)} types on one topic: {types}')
                continue
            msgtype = types[0]
            offered = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
            if not offered:
                continue                    # only subscribers so far: wait for a publisher
            qos = [to_rosbags_qos(q) for q in offered]
            try:
                cls = message_class(msgtype)
                try:
                    spec = TopicSpec.from_typestore(topic, msgtype, qos)
                except BagError:
                    spec = spec_from_class(topic, msgtype, cls, qos)
            except Exception as exc:    # unknown package, odd IDL: skip it, say why
                self._skip(topic, f'cannot record {msgtype}: {exc}')
                continue
            self.recording.add_topic(spec)
            self._subscribe(topic, cls, adapted_qos(offered, self.depth))
            self.get_logger().info(f'recording {topic} [{msgtype}]')

    def _subscribe(self, topic, cls, qos) -> None:
        self.subs[topic] = self.create_subscription(cls, topic, self._callback(topic), qos,
                                                    raw=True)
        self.sub_qos[topic] = (cls, qos)

    def _readapt(self, topic: str) -> None:
        """Weaken a subscription's QoS when a less strict publisher joins (never miss one)."""
        cls, qos = self.sub_qos[topic]
        offered = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)
                   if i.node_name != self.get_name()]
        if not offered:
            return
        new = adapted_qos(offered, self.depth)
        if (new.reliability, new.durability) == (qos.reliability, qos.durability):
            return
        stronger = (new.reliability == ReliabilityPolicy.RELIABLE
                    and qos.reliability != ReliabilityPolicy.RELIABLE) or \
            (new.durability == DurabilityPolicy.TRANSIENT_LOCAL
             and qos.durability != DurabilityPolicy.TRANSIENT_LOCAL)
        if stronger:
            return      # only ever weaken (a re-latched message would be recorded twice)
        self.destroy_subscription(self.subs.pop(topic))
        self._subscribe(topic, cls, new)
        self.get_logger().info(f'{topic}: QoS re-matched to its publishers '
                               f'({new.reliability.name}, {new.durability.name})')

    def _skip(self, topic: str, why: str) -> None:
        self.skipped[topic] = why
        self.get_logger().warn(f'not recording {topic}: {why}')

    def _callback(self, topic: str):
        offer = self.recording.offer
        clock = self.get_clock()
        last_source = self.last_source_ns

        def cb(data, info):
            t = source = None
            if isinstance(info, dict):
                t, source = info.get('received_timestamp'), info.get('source_timestamp')
            if offer(topic, t or clock.now().nanoseconds, data) and source:
                last_source[topic] = source         # the newest message queued for the bag
        return cb

    # -- services --------------------------------------------------------------------------
    def _pause(self, req, res):
        self.recording.pause()
        res.success, res.message = True, 'paused'
        return res

    def _resume(self, req, res):
        self.recording.resume()
        res.success, res.message = True, 'recording'
        return res

    def _split(self, req, res):
        st = self.recording.stats()
        if st['error']:
            res.success, res.message = False, st['error']
            return res
        self.recording.split()
        res.success, res.message = True, f'split requested (was {st["current_file"]})'
        return res

    # -- diagnostics -----------------------------------------------------------------------
    def _diagnose(self, stat):
        st = self.recording.stats()
        if st['error']:
            level, msg = ERROR, st['error']
            if st['error'] != self._reported_error:
                self._reported_error = st['error']
                self.get_logger().error(st['error'])
        elif st['dropped_queue_full'] or self.skipped:
            level = WARN
            msg = f'{st["dropped_queue_full"]} messages dropped (queue full)' \
                if st['dropped_queue_full'] else f'{len(self.skipped)} topics not recordable'
        else:
            level, msg = OK, st['state']
        by_topic = st.pop('received_by_topic')
        values = dict(st, bag=str(self.bag_path), topics=len(self.subs),
                      skipped='; '.join(f'{k}: {v}' for k, v in self.skipped.items()))
        # Per topic. A writer delivers in order, so whoever stops the recorder can first wait
        # until each topic's newest message was published after what must be in the bag.
        values.update({received_key(t): n for t, n in by_topic.items()})
        values.update({newest_key(t): n for t, n in sorted(self.last_source_ns.items())})
        return fill(stat, level, msg, values)

    def on_shutdown(self) -> None:
        meta = self.recording.stop()
        info = meta['rosbag2_bagfile_information']
        st = self.recording.stats()
        self.get_logger().info(
            f'bag {self.bag_path}: {info["message_count"]} messages in '
            f'{len(info["relative_file_paths"])} file(s), {st["dropped_queue_full"]} dropped'
            + (f'; ERROR: {st["error"]}' if st['error'] else ''))


main = main_wrapper(Recorder)

if __name__ == '__main__':
    main()
