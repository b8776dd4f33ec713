"""
Recorded bags -> the project's dataset (``softshape build-dataset``).

A sample is keyed by its trigger stamp: the collector announces it on ``/rig/sample``
(scene, rest/actuation, settled) and fires ``/rig/trigger``; each camera stamps its frame
and its capture-time report with the same stamp. Pairing is by exact stamp only, so a
missing frame drops the sample instead of borrowing a neighbour's. The measured pressure
is the JointState nearest the trigger within ``collection.pressure_match_s``. Images are
preprocessed as they are read (crop, gray, 64x64), so memory holds only small arrays.
"""

from __future__ import annotations

import json
from bisect import bisect_left
from collections import Counter, defaultdict
from pathlib import Path
from typing import NamedTuple

import numpy as np
from rosbags.rosbag2 import Reader
from tqdm import tqdm

from softshape_ros.data.bag_tools import bag_info
from softshape_ros.data.dataset import BAG_CONTACT, BAG_SHAPE, DatasetWriter
from softshape_ros.data.rosbag2_format import BagError, jazzy_typestore
from softshape_ros.pressure import measured_in_order
from softshape_ros.scene import Scene, SceneError
from softshape_ros.vision.image_msg import decode_image, stamp_ns
from softshape_ros.vision.preprocess import ImageError, crop_for, preprocess


class _Session:
    """Everything one bag says, indexed by trigger stamp."""

    def __init__(self, cams):
        self.samples = {}                      # stamp -> sample dict (from /rig/sample)
        self.bad_samples = 0
        self.triggers = set()
        self.images = {c: defaultdict(list) for c in cams}   # stamp -> [preprocessed]
        self.bad_images = {c: set() for c in cams}
        self.capture = {c: {} for c in cams}                  # stamp -> time_ref ns
        self.pressure = []                                    # (stamp, [6 Pa])
        self.pressure_stamps = []
        self.scenes = {}                                      # id -> Scene


def _read_bag(path: Path, cfg, gray: bool, size: int, progress: bool) -> _Session:
    info = bag_info(path)
    if info['unfinished_files']:
        raise BagError(f'{path}: unfinished files {info["unfinished_files"]} (crashed '
                       f'recording?): run `softshape bag recover {path}` first')
    t = cfg.topics
    cams = cfg.camera_names
    topic_role = {t.sample: ('sample', None), t.trigger: ('trigger', None),
                  t.pressure_measured: ('pressure', None), t.scene: ('scene', None)}
    for c in cams:
        topic_role[t.camera('camera_image', c)] = ('image', c)
        topic_role[t.camera('capture_time', c)] = ('capture', c)
    s = _Session(cams)
    ts = jazzy_typestore()
    names = cfg.chamber_names
    with Reader(path) as reader:
        conns = [c for c in reader.connections if c.topic in topic_role]
        total = sum(c.msgcount for c in conns)
        bar = tqdm(total=total, desc=f'read {path.name}', unit='msg', disable=not progress)
        for conn, _, raw in reader.messages(connections=conns):
            bar.update(1)
            role, cam = topic_role[conn.topic]
            try:
                msg = ts.deserialize_cdr(raw, conn.msgtype)
            except Exception:
                if role == 'sample':
                    s.bad_samples += 1
                continue
            if role == 'trigger':
                s.triggers.add(stamp_ns(msg.stamp))
            elif role == 'sample':
                _add_sample(s, msg.data)
            elif role == 'scene':
                try:
                    sc = Scene.from_json(msg.data)
                    s.scenes[sc.id] = sc
                except SceneError:
                    pass
            elif role == 'capture':
                s.capture[cam][stamp_ns(msg.header.stamp)] = stamp_ns(msg.time_ref)
            elif role == 'pressure':
                p = measured_in_order(msg.name, msg.effort, names)
                if p is not None:
                    s.pressure.append((stamp_ns(msg.header.stamp), p))
            elif role == 'image':
                stamp = stamp_ns(msg.header.stamp)
                cc = cfg.cameras[cam]
                try:
                    crop = crop_for(cc, msg.width, msg.height)
                    s.images[cam][stamp].append(preprocess(decode_image(msg), crop, size, gray))
                except (ValueError, ImageError):
                    s.bad_images[cam].add(stamp)
        bar.close()
    s.pressure.sort(key=lambda x: x[0])
    s.pressure_stamps = [p[0] for p in s.pressure]
    return s


def _add_sample(s: _Session, text: str) -> None:
    try:
        d = json.loads(text)
        stamp = int(d['stamp_ns'])
        sample = {'stamp_ns': stamp, 'scene_id': int(d['scene_id']), 'kind': str(d['kind']),
                  'index': int(d.get('index', -1)), 'settled': bool(d['settled']),
                  'command_pa': [float(v) for v in d.get('command_pa', [])]}
        if sample['kind'] not in ('rest', 'actuation'):
            raise ValueError(sample['kind'])
    except (ValueError, KeyError, TypeError):
        s.bad_samples += 1
        return
    s.samples[stamp] = sample


def _nearest_pressure(s: _Session, stamp: int, bound_ns: int):
    keys = s.pressure_stamps
    i = bisect_left(keys, stamp)
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(keys):
            d = abs(keys[j] - stamp)
            if d <= bound_ns and (best is None or d < best[0]):
                best = (d, s.pressure[j][1])
    return None if best is None else best[1]


def _check(s: _Session, stamp: int, cams, max_skew_ns: int):
    """Return (images per camera, None) for a complete trigger, else (None, reason)."""
    if stamp not in s.triggers:
        return None, 'no_trigger'
    imgs = []
    for c in cams:
        if stamp in s.bad_images[c]:
            return None, f'bad_image_{c}'
        got = s.images[c].get(stamp, [])
        if not got:
            return None, f'missing_camera_{c}'
        if len(got) > 1:
            return None, f'duplicate_frames_{c}'
        imgs.append(got[0])
    times = []
    for c in cams:
        if stamp not in s.capture[c]:
            return None, f'missing_capture_time_{c}'
        times.append(s.capture[c][stamp])
    if max(times) - min(times) > max_skew_ns:
        return None, 'capture_skew'
    return np.stack(imgs), None


class _Row(NamedTuple):
    """One kept actuation sample, before it is written."""

    initial: dict          # camera -> rest image of its scene
    target: dict           # camera -> image after the actuation
    pressures_pa: object   # (6,) measured, nearest the trigger
    scene_index: int       # unique across bags
    stamp_ns: int


def build_dataset(bags, out, cfg, gray=None, overwrite: bool = False, progress: bool = True):
    """
    Build a dataset folder from one or more bags; returns (Dataset, report).

    The report (also in meta.json) counts triggers, kept samples, and drops by reason.
    """
    bags = [Path(b) for b in bags]
    if not bags:
        raise ValueError('no bags given')
    gray = cfg.dataset.gray if gray is None else gray
    size = cfg.dataset.image_size
    cams = cfg.camera_names
    max_skew_ns = int(cfg.collection.max_capture_skew_s * 1e9)
    bound_ns = int(cfg.collection.pressure_match_s * 1e9)
    dropped = Counter()
    rows, scene_map, used_ids, triggers = [], [], set(), 0
    for bag in bags:
        s = _read_bag(bag, cfg, gray, size, progress)
        dropped['malformed_sample_json'] += s.bad_samples
        triggers += len(s.triggers)
        rest = _rest_images(s, cams, max_skew_ns, dropped)
        local_ids = {}
        for stamp in sorted(st for st, d in s.samples.items() if d['kind'] == 'actuation'):
            d = s.samples[stamp]
            before = [r for r in rest.get(d['scene_id'], []) if r[0] < stamp]
            imgs, p, why = _actuation(s, stamp, d, cams, max_skew_ns, bound_ns, bool(before))
            if why is not None:
                dropped[why] += 1
                continue
            sid = d['scene_id']
            if sid not in local_ids:       # scene ids stay unique across bags
                gid = sid if sid not in used_ids else max(used_ids) + 1
                used_ids.add(gid)
                local_ids[sid] = gid
                scene_map.append({'bag': str(bag), 'scene_id': sid, 'index': gid,
                                  'scene': json.loads(s.scenes[sid].to_json())})
            rows.append(_Row(before[-1][1], imgs, p, local_ids[sid], stamp))
        dropped['trigger_without_sample'] += len(s.triggers - set(s.samples))
    dropped = {k: v for k, v in dropped.items() if v}
    channels = 1 if gray else 3
    meta = {
        'cameras': cams, 'gray': bool(gray),
        'crop_px': {c: list(cfg.cameras[c].crop_px) for c in cams},
        'pressure_unit': 'Pa', 'normalisation': 'pressure / max_pressure_pa',
        'provenance': {'source': 'bags', 'bags': [str(b.resolve()) for b in bags],
                       'config': cfg.source},
        'triggers': triggers, 'kept': len(rows), 'dropped': dropped, 'scenes': scene_map,
        'stamps_ns': [r.stamp_ns for r in rows],
    }
    w = DatasetWriter(out, len(rows), cams, channels, size, cfg.max_pressures_pa,
                      meta=meta, overwrite=overwrite, contact=BAG_CONTACT,
                      shape=BAG_SHAPE)
    for i, r in enumerate(tqdm(rows, desc='write dataset', unit='sample',
                               disable=not progress)):
        w.put(i, r.initial, r.target, r.pressures_pa, r.scene_index)
    ds = w.close()
    report = {'triggers': triggers, 'kept': len(rows), 'dropped': dropped}
    return ds, report


def _rest_images(s, cams, max_skew_ns: int, dropped: Counter) -> dict:
    """
    Return scene id -> [(stamp, images)] of its complete, settled rest triggers, in order.

    A sample's rest images are its scene's latest such trigger before it (a scene may be
    re-rested; a later rest never applies backwards). Rejected rests are counted.
    """
    rest = defaultdict(list)
    for stamp in sorted(st for st, d in s.samples.items() if d['kind'] == 'rest'):
        imgs, why = _check(s, stamp, cams, max_skew_ns)
        if why is None and not s.samples[stamp]['settled']:
            why = 'unsettled'
        if why is not None:
            dropped[f'rest_{why}'] += 1
            continue
        rest[s.samples[stamp]['scene_id']].append((stamp, imgs))
    return rest


def _actuation(s, stamp: int, d: dict, cams, max_skew_ns: int, bound_ns: int,
               has_rest: bool) -> tuple:
    """Return (images, pressures, None) for a usable actuation, else (.., .., why not)."""
    imgs, why = _check(s, stamp, cams, max_skew_ns)
    if why is None and not d['settled']:
        why = 'unsettled'
    if why is None and d['scene_id'] not in s.scenes:
        why = 'unknown_scene'
    if why is None and not has_rest:
        why = 'no_rest_images'
    p = None
    if why is None:
        p = _nearest_pressure(s, stamp, bound_ns)
        if p is None:
            why = 'no_pressure'
    return imgs, p, why
