"""
Bag metadata read the way rosbag2 on ROS 2 Jazzy reads it (no rosbag2 here to ask).

A port of the decoding rules, from the ros2/rosbag2 ``jazzy`` branch:

- ``rosbag2_storage/include/rosbag2_storage/yaml.hpp``: ``convert<BagMetadata>::decode``
  and the topic, file and duration converters (yaml-cpp ``as<T>()``: a missing key or a
  value of the wrong kind throws);
- ``rosbag2_storage/src/rosbag2_storage/qos.cpp``: ``convert<rclcpp::QoS>::decode``, where
  version 9 keeps ``offered_qos_profiles`` as a YAML sequence, not a string;
- ``rosbag2_transport/src/rosbag2_transport/reader_writer_factory.cpp``: ``make_reader``
  (what ``ros2 bag play`` opens a bag with): a non-empty ``compression_format`` picks the
  ``SequentialCompressionReader``, whose ``setup_decompression`` requires a mode that
  ``compression_mode_from_string`` (``rosbag2_compression/.../compression_options.cpp``)
  maps to FILE or MESSAGE (case-insensitive; "" and anything else are NONE: refused), and a
  registered decompressor plugin for the format (Jazzy ships ``zstd``);
- the storage plugins parse the metadata embedded in each file (MCAP ``rosbag2`` metadata
  record ``serialized_metadata``; sqlite3 ``metadata`` table) with the same converter.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import yaml


class Rosbag2Refuses(ValueError):
    """rosbag2 (Jazzy) would throw here; the message says where and why."""


COMPRESSION_MODES = {'': 'NONE', 'NONE': 'NONE', 'FILE': 'FILE', 'MESSAGE': 'MESSAGE'}
DECOMPRESSOR_PLUGINS = {'zstd'}             # rosbag2_compression_zstd
STORAGE_PLUGINS = {'mcap', 'sqlite3'}      # rosbag2_storage_mcap, rosbag2_storage_default_plugins
# rmw qos_string_conversions (+ "unknown", which rosbag2 writes for UNKNOWN)
POLICY_STRINGS = {
    'history': {'system_default', 'keep_last', 'keep_all', 'unknown'},
    'reliability': {'system_default', 'reliable', 'best_effort', 'best_available', 'unknown'},
    'durability': {'system_default', 'transient_local', 'volatile', 'best_available', 'unknown'},
    'liveliness': {'system_default', 'automatic', 'manual_by_topic', 'best_available',
                   'unknown'},
}
HISTORY_KEEP_LAST = 1


def _get(node, key, where):
    if not isinstance(node, dict) or key not in node:
        raise Rosbag2Refuses(f'{where}.{key}: missing (yaml-cpp InvalidNode)')
    return node[key]


def as_string(node, key, where) -> str:
    v = _get(node, key, where)
    if v is None or isinstance(v, (dict, list)):
        raise Rosbag2Refuses(f'{where}.{key}: {v!r} is not a scalar (as<std::string>)')
    return v if isinstance(v, str) else str(v).lower() if isinstance(v, bool) else str(v)


def as_uint(node, key, where, bits: int = 64) -> int:
    v = _get(node, key, where)
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**bits:
        raise Rosbag2Refuses(f'{where}.{key}: {v!r} is not a uint{bits}')
    return v


def as_int(node, key, where) -> int:
    v = _get(node, key, where)
    if isinstance(v, bool) or not isinstance(v, int) or not -2**31 <= v < 2**31:
        raise Rosbag2Refuses(f'{where}.{key}: {v!r} is not an int')
    return v


def as_bool(node, key, where) -> bool:
    v = _get(node, key, where)
    if not isinstance(v, bool):
        raise Rosbag2Refuses(f'{where}.{key}: {v!r} is not a bool')
    return v


def as_sequence(node, key, where) -> list:
    v = _get(node, key, where)
    if not isinstance(v, list):
        raise Rosbag2Refuses(f'{where}.{key}: {type(v).__name__} {v!r:.60} is not a sequence')
    return v


def _policy(node, key, where, version: int):
    if version <= 8:
        return as_int(node, key, where)
    text = as_string(node, key, where)
    if text not in POLICY_STRINGS[key]:     # rmw_*_from_str: silently UNKNOWN
        raise Rosbag2Refuses(f'{where}.{key}: {text!r} is no rmw policy name')
    return text


def _rmw_time(node, key, where) -> int:
    t = _get(node, key, where)
    return as_uint(t, 'sec', f'{where}.{key}') * 10**9 + as_uint(t, 'nsec', f'{where}.{key}')


def decode_qos(q, where) -> dict:
    """Decode one QoS as convert<rclcpp::QoS>::decode: v8 (int policies) or v9 (names)."""
    h = _get(q, 'history', where)
    version = 8 if isinstance(h, int) and not isinstance(h, bool) and 0 <= h <= 3 else 9
    out = {'history': h if version == 8 else _policy(q, 'history', where, 9)}
    for key in ('reliability', 'durability', 'liveliness'):
        out[key] = _policy(q, key, where, version)
    if out['history'] in (HISTORY_KEEP_LAST, 'keep_last'):
        out['depth'] = as_int(q, 'depth', where)
    for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
        out[key] = _rmw_time(q, key, where)
    out['avoid_ros_namespace_conventions'] = as_bool(q, 'avoid_ros_namespace_conventions',
                                                     where)
    return out


def decode_qos_text(text: str, where) -> list[dict]:
    """Decode a QoS YAML string as to_rclcpp_qos_vector (channel metadata, topics table)."""
    node = {'offered_qos_profiles': yaml.safe_load(text)}
    return [decode_qos(q, f'{where}[{i}]')
            for i, q in enumerate(as_sequence(node, 'offered_qos_profiles', where))]


def decode_metadata(node, where: str = 'metadata') -> dict:
    """Decode as convert<BagMetadata>::decode; return the fields rosbag2 keeps."""
    version = as_int(node, 'version', where)
    m = {'version': version,
         'storage_identifier': as_string(node, 'storage_identifier', where),
         'duration': as_uint(_get(node, 'duration', where), 'nanoseconds', f'{where}.duration'),
         'starting_time': as_uint(_get(node, 'starting_time', where),
                                  'nanoseconds_since_epoch', f'{where}.starting_time'),
         'message_count': as_uint(node, 'message_count', where),
         'topics': []}
    for i, t in enumerate(as_sequence(node, 'topics_with_message_count', where)):
        w = f'{where}.topics_with_message_count[{i}]'
        tm = _get(t, 'topic_metadata', w)
        topic = {k: as_string(tm, k, f'{w}.topic_metadata')
                 for k in ('name', 'type', 'serialization_format')}
        if version >= 9:
            topic['qos'] = [decode_qos(q, f'{w}.offered_qos_profiles[{j}]') for j, q in
                            enumerate(as_sequence(tm, 'offered_qos_profiles', w))]
        elif version >= 4:
            topic['qos'] = decode_qos_text(as_string(tm, 'offered_qos_profiles', w), w)
        if version >= 7:
            topic['type_description_hash'] = as_string(tm, 'type_description_hash', w)
        topic['message_count'] = as_uint(t, 'message_count', w)
        m['topics'].append(topic)
    paths = as_sequence(node, 'relative_file_paths', where)
    m['relative_file_paths'] = [as_string({'p': p}, 'p', f'{where}.relative_file_paths')
                                for p in paths]
    if version >= 3:
        m['compression_format'] = as_string(node, 'compression_format', where)
        m['compression_mode'] = as_string(node, 'compression_mode', where)
    if version >= 5:
        m['files'] = []
        for i, f in enumerate(as_sequence(node, 'files', where)):
            w = f'{where}.files[{i}]'
            m['files'].append({
                'path': as_string(f, 'path', w),
                'starting_time': as_uint(_get(f, 'starting_time', w),
                                         'nanoseconds_since_epoch', w),
                'duration': as_uint(_get(f, 'duration', w), 'nanoseconds', w),
                'message_count': as_uint(f, 'message_count', w)})
    if version >= 6:
        custom = _get(node, 'custom_data', where)   # rosbag2's own converter: any map or null
        if custom is not None and not isinstance(custom, dict):
            raise Rosbag2Refuses(f'{where}.custom_data: {custom!r} is not a map')
        m['custom_data'] = {str(k): as_string(custom, k, f'{where}.custom_data')
                            for k in (custom or {})}
    if version >= 8:
        m['ros_distro'] = as_string(node, 'ros_distro', where)
    return m


def compression_mode_from_string(text: str) -> str:
    """Map a mode as rosbag2_compression's compression_mode_from_string does (unknown: NONE)."""
    return COMPRESSION_MODES.get(text.upper(), 'NONE')


def play_reader(meta: dict) -> str:
    """
    Return the reader ``ros2 bag play`` opens the bag with, or raise as it would.

    ``meta`` is :func:`decode_metadata`'s result.
    """
    if meta['storage_identifier'] not in STORAGE_PLUGINS:
        raise Rosbag2Refuses(f'no storage plugin {meta["storage_identifier"]!r}')
    if not meta.get('compression_format'):
        return 'SequentialReader'
    mode = compression_mode_from_string(meta['compression_mode'])
    if mode == 'NONE':
        raise Rosbag2Refuses(
            f'compression_format {meta["compression_format"]!r} with compression_mode '
            f'{meta["compression_mode"]!r} (= NONE): "SequentialCompressionReader should not '
            f'be initialized with NONE compression mode."')
    if meta['compression_format'] not in DECOMPRESSOR_PLUGINS:
        raise Rosbag2Refuses(f'no registered plugin for compression format '
                             f'{meta["compression_format"]!r}')
    return 'SequentialCompressionReader'


def embedded_metadata(path: Path) -> list[str]:
    """Return the metadata texts a storage file carries (what its storage plugin parses)."""
    if path.suffix == '.mcap':
        from mcap.reader import make_reader
        with path.open('rb') as f:
            return [m.metadata.get('serialized_metadata', '')
                    for m in make_reader(f).iter_metadata() if m.name == 'rosbag2']
    con = sqlite3.connect(path)
    try:
        return [text for (text,) in con.execute('SELECT metadata FROM metadata ORDER BY id')]
    finally:
        con.close()


def stored_qos_texts(path: Path) -> dict[str, str]:
    """Map topic -> offered_qos_profiles string as the file stores it (channel or row)."""
    if path.suffix == '.mcap':
        from mcap.reader import make_reader
        with path.open('rb') as f:
            summary = make_reader(f).get_summary()
        return {c.topic: c.metadata['offered_qos_profiles'] for c in summary.channels.values()}
    con = sqlite3.connect(path)
    try:
        return dict(con.execute('SELECT name, offered_qos_profiles FROM topics'))
    finally:
        con.close()


def check_bag(bag: Path) -> dict:
    """
    Read a bag's metadata.yaml and every file's own metadata as rosbag2 Jazzy does.

    Returns the decoded metadata.yaml plus ``reader`` (what ``ros2 bag play`` would use);
    raises :class:`Rosbag2Refuses` where rosbag2 would throw.
    """
    bag = Path(bag)
    doc = yaml.safe_load((bag / 'metadata.yaml').read_text())
    meta = decode_metadata(_get(doc, 'rosbag2_bagfile_information', 'metadata.yaml'),
                           'metadata.yaml')
    meta['reader'] = play_reader(meta)
    for name in meta['relative_file_paths']:
        path = bag / name
        if not path.is_file():
            raise Rosbag2Refuses(f'{name}: listed in metadata.yaml but missing')
        for i, text in enumerate(embedded_metadata(path)):
            if text:            # MCAP: empty means "pre-v9 writer", which rosbag2 accepts
                play_reader(decode_metadata(yaml.safe_load(text), f'{name}[{i}]'))
        for topic, text in stored_qos_texts(path).items():
            decode_qos_text(text, f'{name} {topic} offered_qos_profiles')
    return meta
