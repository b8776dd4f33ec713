"""
The project's one dataset format: a folder of memory-mappable arrays plus meta.json.

Both the simulator (`softshape simulate`) and the bag builder (`softshape build-dataset`)
write it through :class:`DatasetWriter`; everything reads it through :func:`load_dataset`.
Arrays are ``.npy`` files so ``np.load(mmap_mode='r')`` maps them without copying:

- ``initial``  N x V x C x S x S uint8 -- rest images of the sample's scene, per view
- ``target``   N x V x C x S x S uint8 -- images at the trigger
- ``pressure`` N x 6 float32, Pa      -- measured chamber pressures at the trigger
- ``scene``    N int64                -- scene index (for split-by-scene)

and, where contact is known (the simulator; format version 2), the contact record:

- ``touching``        N bool    -- the robot's surface is inside the object's
- ``contact_arc_m``   N float32 -- backbone length in contact (m), 0 if free
- ``contact_force_n`` N float32 -- magnitude of the object's net force on the robot (N)
- ``penetration_m``   N float32 -- deepest penetration of the robot into the object (m)

A dataset without those files (a real rig's, from bags, or one written before the record
existed) loads with ``contact = None`` and ``meta['contact']`` saying why.

and, where the robot's shape is known (the simulator; format version 3), the shape record:

- ``backbone_px`` N x V x K x 2 float32 -- K backbone points per view, equally spaced in arc
  length from base to tip, in the S x S image's pixels (x = column, y = row; pixel centres
  at integer coordinates)
- ``radius_px``   N x V x K float32     -- the tube's apparent radius there (px)
- ``depth_px``    N x V x K float32     -- how much further from the camera than the base,
  in pixels at the base's depth (focal length x (depth / base depth - 1))

A dataset without them loads with ``shape = None`` and ``meta['shape']`` saying why.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT = 'softshape-dataset'
VERSION = 3                 # 2: the optional contact record; 3: the optional shape record
ARRAYS = ('initial', 'target', 'pressure', 'scene')
CONTACT_ARRAYS = ('touching', 'contact_arc_m', 'contact_force_n', 'penetration_m')
NO_CONTACT_RECORD = 'not recorded: written before datasets carried a contact record'
NOT_GIVEN = 'not recorded by the program that wrote this dataset'
BAG_CONTACT = 'unknown: built from recorded bags (the rig does not measure contact)'
BAG_SHAPE = "unknown: built from recorded bags (the rig does not measure the robot's backbone)"
SHAPE_ARRAYS = ('backbone_px', 'radius_px', 'depth_px')
NO_SHAPE_RECORD = 'not recorded: written before datasets carried a shape record'

log = logging.getLogger(__name__)


class DatasetError(ValueError):
    """A dataset folder is missing, incomplete or inconsistent."""


@dataclass(frozen=True)
class ContactRecord:
    """Per-sample contact: flag, arc length (m), net force (N), max penetration (m)."""

    touching: np.ndarray        # (N,) bool
    arc_m: np.ndarray           # (N,) float32
    force_n: np.ndarray         # (N,) float32
    penetration_m: np.ndarray   # (N,) float32

    def __len__(self) -> int:
        return int(self.touching.shape[0])

    def __getitem__(self, idx) -> 'ContactRecord':
        """Return the record of rows ``idx`` (an index array, mask or slice)."""
        return ContactRecord(self.touching[idx], self.arc_m[idx], self.force_n[idx],
                             self.penetration_m[idx])

    @property
    def touching_share(self) -> float:
        return float(np.mean(self.touching)) if len(self) else 0.0


@dataclass(frozen=True)
class ShapeRecord:
    """Per-sample robot shape in each view's image: K backbone points, radii, depths (px)."""

    keypoints_px: np.ndarray    # (N, V, K, 2) float32, x = column, y = row
    radius_px: np.ndarray       # (N, V, K) float32
    depth_px: np.ndarray        # (N, V, K) float32, 0 at the base

    def __len__(self) -> int:
        return int(self.keypoints_px.shape[0])

    def __getitem__(self, idx) -> 'ShapeRecord':
        """Return the record of rows ``idx`` (an index array, mask or slice)."""
        return ShapeRecord(self.keypoints_px[idx], self.radius_px[idx], self.depth_px[idx])

    @property
    def keypoints(self) -> int:
        return int(self.keypoints_px.shape[2])


def check_shape(keypoints_px, radius_px, depth_px, views: int, where: str = '') -> None:
    """Raise DatasetError unless the three arrays form a valid shape record for ``views``."""
    kp, r, z = np.asarray(keypoints_px), np.asarray(radius_px), np.asarray(depth_px)
    at = f'{where}: ' if where else ''
    if kp.ndim != 4 or kp.shape[1] != views or kp.shape[3] != 2 or kp.shape[2] < 2:
        raise DatasetError(f'{at}backbone_px must be N x {views} x K x 2 (K >= 2), got '
                           f'{kp.shape}')
    for name, a in (('radius_px', r), ('depth_px', z)):
        if a.shape != kp.shape[:3]:
            raise DatasetError(f'{at}{name} has shape {a.shape}, backbone_px {kp.shape}')
    if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(r)) and np.all(np.isfinite(z))):
        raise DatasetError(f'{at}the shape record is not finite')
    if np.any(r <= 0):
        raise DatasetError(f'{at}radius_px must be > 0, got {float(r.min())}')


def check_contact(touching, arc_m, force_n, penetration_m, where: str = '') -> None:
    """Raise DatasetError unless the four arrays form a valid contact record."""
    t = np.asarray(touching)
    vals = {'contact_arc_m': np.asarray(arc_m), 'contact_force_n': np.asarray(force_n),
            'penetration_m': np.asarray(penetration_m)}
    at = f'{where}: ' if where else ''
    flag = t.dtype == np.bool_ or (np.issubdtype(t.dtype, np.integer) and np.isin(t, (0, 1)).all())
    if not flag:
        raise DatasetError(f'{at}touching must be true/false, got {t.dtype} values')
    t = t.astype(bool)
    for name, v in vals.items():
        if v.shape != t.shape:
            raise DatasetError(f'{at}{name} has shape {v.shape}, touching {t.shape}')
        if not np.all(np.isfinite(v)):
            raise DatasetError(f'{at}{name} is not finite')
        if np.any(v < 0):
            raise DatasetError(f'{at}{name} must be >= 0, got {float(v.min())}')
    free = ~t
    for name in ('contact_arc_m', 'penetration_m'):
        if np.any(vals[name][free] != 0):
            raise DatasetError(f'{at}{name} must be 0 where the robot does not touch')
    if np.any(vals['contact_arc_m'][t] <= 0):
        raise DatasetError(f'{at}contact_arc_m must be > 0 where the robot touches')


@dataclass
class Dataset:
    """Read-only view of a dataset folder (arrays are memory-mapped)."""

    path: Path
    initial: np.ndarray
    target: np.ndarray
    pressure: np.ndarray
    scene: np.ndarray
    meta: dict
    contact: ContactRecord | None = None
    shape: ShapeRecord | None = None

    def __len__(self) -> int:
        return int(self.pressure.shape[0])

    @property
    def views(self) -> list[str]:
        return list(self.meta['views'])

    @property
    def channels(self) -> int:
        return int(self.meta['channels'])

    @property
    def max_pressure_pa(self) -> np.ndarray:
        return np.asarray(self.meta['max_pressure_pa'], dtype=np.float32)


@dataclass(frozen=True)
class DatasetRows:
    """
    Where a dataset being written keeps its arrays: enough to write rows from any process.

    Each :meth:`put` maps only the rows it writes and unmaps them again, so writers in
    several processes share one folder and none of them grows with the dataset.
    """

    folder: Path
    n: int
    shapes: dict                # array name -> (row shape, dtype str)

    def _rows(self, name: str, start: int, stop: int) -> np.memmap:
        shape, dtype = self.shapes[name]
        f = self.folder / f'{name}.npy'
        with open(f, 'rb') as fh:
            np.lib.format.read_magic(fh)
            np.lib.format.read_array_header_1_0(fh)
            header = fh.tell()
        row = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        return np.memmap(f, dtype=dtype, mode='r+', offset=header + start * row,
                         shape=(stop - start, *shape))

    def put(self, i, initial, target, pressure, scene, contact=None, shape=None) -> None:
        """
        Store sample(s) at index or slice ``i``; checks finiteness and the records.

        ``contact``: (touching, arc_m, force_n, penetration_m) for those rows, required
        when the dataset has a contact record and refused when it has none; ``shape``:
        (backbone_px, radius_px, depth_px) for those rows, likewise.
        """
        p = np.asarray(pressure, dtype=np.float32)
        if not np.all(np.isfinite(p)):
            raise DatasetError(f'sample {i}: pressure is not finite: {p}')
        has = 'touching' in self.shapes
        if has and contact is None:
            raise DatasetError(f'sample {i}: this dataset records contact; none given')
        if contact is not None and not has:
            raise DatasetError(f'sample {i}: this dataset has no contact record')
        if contact is not None:
            contact = [np.atleast_1d(np.asarray(a)) for a in contact]
            check_contact(*contact, where=f'sample {i}')
        has = 'backbone_px' in self.shapes
        if has and shape is None:
            raise DatasetError(f'sample {i}: this dataset records the shape; none given')
        if shape is not None and not has:
            raise DatasetError(f'sample {i}: this dataset has no shape record')
        start, stop = self._span(i)
        if shape is not None:
            views = self.shapes['backbone_px'][0][0]
            shape = [np.asarray(a, np.float32).reshape((stop - start, *self.shapes[n][0]))
                     for a, n in zip(shape, SHAPE_ARRAYS)]
            check_shape(*shape, views, where=f'sample {i}')
        values = {'initial': initial, 'target': target, 'pressure': p, 'scene': scene}
        if contact is not None:
            values.update(zip(CONTACT_ARRAYS, contact))
        if shape is not None:
            values.update(zip(SHAPE_ARRAYS, shape))
        for name, v in values.items():
            # Unmapped, not flushed: the pages are the file's in the page cache (every
            # process sees them); msync per block would cost ~5 ms. close() syncs once.
            mm = self._rows(name, start, stop)
            mm[...] = v
            del mm

    def _span(self, i) -> tuple[int, int]:
        if isinstance(i, slice):
            start, stop, step = i.indices(self.n)
            if step != 1:
                raise DatasetError(f'rows must be contiguous, got step {step}')
        elif isinstance(i, (int, np.integer)):
            start = int(i) + (self.n if i < 0 else 0)
            stop = start + 1
        else:
            idx = np.asarray(i)
            if idx.ndim != 1 or not len(idx) or np.any(np.diff(idx) != 1):
                raise DatasetError('rows must be an index, a slice or a contiguous range')
            start, stop = int(idx[0]), int(idx[-1]) + 1
        if not 0 <= start <= stop <= self.n:
            raise DatasetError(f'rows {start}:{stop} outside a dataset of {self.n}')
        return start, stop


class DatasetWriter:
    """
    Create a dataset of known size and fill it row by row (or in slices, from any process).

    Writes go to ``<path>.partial`` and the folder is renamed into place on
    :meth:`close`, so a crash never leaves something that looks complete. ``contact``:
    whether the dataset carries the contact record (True for simulated data) or a string
    saying why not (e.g. a real rig does not measure contact). ``shape``: the number of
    backbone points per view of the shape record (the simulator), or a string saying why
    there is none.
    """

    def __init__(self, path, n: int, views: list[str], channels: int, size: int,
                 max_pressure_pa, meta: dict | None = None, overwrite: bool = False,
                 contact: bool | str = NOT_GIVEN, shape: int | str = NOT_GIVEN):
        if n < 0:
            raise DatasetError(f'dataset size must be >= 0, got {n}')
        if channels not in (1, 3):
            raise DatasetError(f'channels must be 1 (gray) or 3 (RGB), got {channels}')
        if len(max_pressure_pa) != 6:
            raise DatasetError(f'max_pressure_pa needs 6 values, got {len(max_pressure_pa)}')
        if contact is False or (isinstance(contact, str) and not contact.strip()):
            raise DatasetError('a dataset without a contact record must say why (a string)')
        if isinstance(shape, bool) or not (isinstance(shape, str) and shape.strip()
                                           or isinstance(shape, int) and shape >= 2):
            raise DatasetError('shape must be the keypoints per view (>= 2) or say why there '
                               f'is no shape record (a string), got {shape!r}')
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise DatasetError(f'{self.path}: already exists (pass overwrite)')
        self.tmp = self.path.with_name(self.path.name + '.partial')
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        self.tmp.mkdir(parents=True)
        self.n, self.views, self.channels, self.size = n, list(views), channels, size
        image = (len(views), channels, size, size)
        shapes = {'initial': (image, 'uint8'), 'target': (image, 'uint8'),
                  'pressure': ((6,), 'float32'), 'scene': ((), 'int64')}
        if contact is True:
            shapes.update(touching=((), 'bool'), contact_arc_m=((), 'float32'),
                          contact_force_n=((), 'float32'), penetration_m=((), 'float32'))
        if isinstance(shape, int):
            shapes.update(backbone_px=((len(views), shape, 2), 'float32'),
                          radius_px=((len(views), shape), 'float32'),
                          depth_px=((len(views), shape), 'float32'))
        for name, (dims, dtype) in shapes.items():
            # Header and size only: rows are mapped when written (DatasetRows.put).
            mm = np.lib.format.open_memmap(self.tmp / f'{name}.npy', 'w+', dtype, (n, *dims))
            del mm
        self.rows = DatasetRows(self.tmp, n, shapes)
        self.contact = contact
        self.meta = dict(meta or {})
        self.meta.update(format=FORMAT, version=VERSION, views=self.views, channels=channels,
                         image_size=size,
                         max_pressure_pa=[float(v) for v in max_pressure_pa])
        if contact is not True:
            self.meta['contact'] = {'recorded': False, 'why': contact}
        if isinstance(shape, int):
            self.meta['shape'] = {
                'recorded': True, 'keypoints': shape, 'arrays': list(SHAPE_ARRAYS),
                'definition': 'backbone_px: per view, K backbone points equally spaced in '
                              'arc length from base to tip, projected into the image (x = '
                              'column, y = row, pixel centres at integers); radius_px: the '
                              "tube's apparent radius there (focal length x radius / depth); "
                              'depth_px: how much further from the camera than the base, in '
                              "pixels at the base's depth"}
        else:
            self.meta['shape'] = {'recorded': False, 'why': shape}
        self.overwrite = overwrite

    def put(self, i, initial, target, pressure, scene, contact=None, shape=None) -> None:
        """Store sample(s) at index or slice ``i`` (see :meth:`DatasetRows.put`)."""
        self.rows.put(i, initial, target, pressure, scene, contact, shape)

    def abort(self) -> None:
        """Remove the partial folder (a failed write leaves nothing behind)."""
        shutil.rmtree(self.tmp, ignore_errors=True)

    def close(self, **extra_meta) -> Dataset:
        """Write meta.json (with the touching share) and move the folder into place."""
        self.meta.update(extra_meta)
        self.meta['count'] = self.n
        if self.contact is True:
            touching = np.load(self.tmp / 'touching.npy', mmap_mode='r')
            share = float(np.mean(touching)) if self.n else 0.0
            self.meta['touching_share'] = share
            self.meta['contact'] = {
                'recorded': True, 'touching_share': share,
                'arrays': list(CONTACT_ARRAYS),
                'definition': 'touching: the tube surface is inside the object somewhere; '
                              'contact_arc_m: backbone length where it is; contact_force_n: '
                              '|net force of the object on the robot|; penetration_m: '
                              'deepest penetration'}
            del touching
        for name in self.rows.shapes:
            # On disk before the folder is renamed into place (a crash never leaves zeros
            # behind a complete-looking folder).
            fd = os.open(self.tmp / f'{name}.npy', os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        (self.tmp / 'meta.json').write_text(json.dumps(self.meta, indent=2, sort_keys=True))
        if self.path.exists():
            shutil.rmtree(self.path)
        os.replace(self.tmp, self.path)
        return load_dataset(self.path)


def write_dataset(path, initial, target, pressure, scene, max_pressure_pa, views,
                  meta: dict | None = None, overwrite: bool = False,
                  contact=None, shape=None) -> Dataset:
    """
    Write whole in-memory arrays as a dataset (convenience over DatasetWriter).

    ``contact``: a :class:`ContactRecord` (or 4-tuple of arrays), or None for no record;
    ``shape``: a :class:`ShapeRecord` (or (backbone_px, radius_px, depth_px)), or None.
    """
    initial = np.asarray(initial)
    if initial.ndim != 5:
        raise DatasetError(f'initial must be N x V x C x S x S, got shape {initial.shape}')
    n, v, c, s, _ = initial.shape
    if isinstance(contact, ContactRecord):
        contact = (contact.touching, contact.arc_m, contact.force_n, contact.penetration_m)
    if isinstance(shape, ShapeRecord):
        shape = (shape.keypoints_px, shape.radius_px, shape.depth_px)
    w = DatasetWriter(path, n, views, c, s, max_pressure_pa, meta, overwrite,
                      contact=True if contact is not None else NOT_GIVEN,
                      shape=np.asarray(shape[0]).shape[2] if shape is not None else NOT_GIVEN)
    if n:
        w.put(slice(None), initial, target, pressure, scene, contact, shape)
    return w.close()


def _record_arrays(p: Path, meta: dict, kind: str, names, why_none: str) -> dict | None:
    """
    Map-read the arrays of an optional per-sample record (``kind``: 'contact', 'shape').

    Returns None, noting ``why_none`` in ``meta`` unless it says why already, if none of
    them is there; one missing or unreadable is a DatasetError naming it.
    """
    present = [name for name in names if (p / f'{name}.npy').exists()]
    if not present:
        if kind not in meta:
            meta[kind] = {'recorded': False, 'why': why_none}
        log.info('%s: no %s record (%s)', p, kind, meta[kind].get('why'))
        return None
    if len(present) != len(names):
        missing = sorted(set(names) - set(present))
        raise DatasetError(f'{p}: {kind} record incomplete, missing {", ".join(missing)}')
    arrays = {}
    for name in names:
        f = p / f'{name}.npy'
        try:
            arrays[name] = np.load(f, mmap_mode='r', allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DatasetError(f'{f}: cannot read: {exc}') from None
    return arrays


def _load_contact(p: Path, meta: dict, n: int) -> ContactRecord | None:
    arrays = _record_arrays(p, meta, 'contact', CONTACT_ARRAYS, NO_CONTACT_RECORD)
    if arrays is None:
        return None
    for name in CONTACT_ARRAYS:
        f = p / f'{name}.npy'
        want = np.bool_ if name == 'touching' else np.float32
        if arrays[name].shape != (n,) or arrays[name].dtype != want:
            raise DatasetError(f'{f}: {arrays[name].dtype} {arrays[name].shape}, expected '
                               f'{np.dtype(want)} ({n},)')
    check_contact(*(arrays[name] for name in CONTACT_ARRAYS), where=str(p))
    return ContactRecord(arrays['touching'], arrays['contact_arc_m'],
                         arrays['contact_force_n'], arrays['penetration_m'])


def _load_shape(p: Path, meta: dict, n: int, views: int) -> ShapeRecord | None:
    arrays = _record_arrays(p, meta, 'shape', SHAPE_ARRAYS, NO_SHAPE_RECORD)
    if arrays is None:
        return None
    for name in SHAPE_ARRAYS:
        f = p / f'{name}.npy'
        if arrays[name].dtype != np.float32 or arrays[name].shape[:2] != (n, views):
            raise DatasetError(f'{f}: {arrays[name].dtype} {arrays[name].shape}, expected '
                               f'float32 ({n}, {views}, ...)')
    kp, r, z = arrays['backbone_px'], arrays['radius_px'], arrays['depth_px']
    # Checked in blocks: a large record is not read into memory at once.
    for i in range(0, max(n, 1), 4096):
        check_shape(kp[i:i + 4096], r[i:i + 4096], z[i:i + 4096], views, where=str(p))
    return ShapeRecord(kp, r, z)


def load_dataset(path) -> Dataset:
    """
    Open a dataset folder; arrays are memory-mapped read-only and cross-checked.

    ``ds.contact`` is the :class:`ContactRecord`, or None where the dataset has none
    (``ds.meta['contact']['why']`` says why); ``ds.shape`` the :class:`ShapeRecord`, or
    None likewise (``ds.meta['shape']['why']``).
    """
    p = Path(path)
    if not p.is_dir():
        raise DatasetError(f'{p}: no such dataset folder')
    try:
        meta = json.loads((p / 'meta.json').read_text())
    except FileNotFoundError:
        raise DatasetError(f'{p}: meta.json missing (incomplete dataset?)') from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f'{p}/meta.json: not valid JSON: {exc}') from None
    if not isinstance(meta, dict) or meta.get('format') != FORMAT:
        fmt = meta.get('format') if isinstance(meta, dict) else None
        raise DatasetError(f'{p}: not a {FORMAT} folder (format={fmt!r})')
    if meta.get('version', 1) not in range(1, VERSION + 1):
        raise DatasetError(f'{p}: format version {meta.get("version")!r}, this softshape_ros '
                           f'reads 1..{VERSION}')
    arrays = {}
    for name in ARRAYS:
        f = p / f'{name}.npy'
        try:
            arrays[name] = np.load(f, mmap_mode='r', allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DatasetError(f'{f}: cannot read: {exc}') from None
    n = arrays['pressure'].shape[0]
    v, c, s = len(meta['views']), int(meta['channels']), int(meta['image_size'])
    expect = {'initial': (n, v, c, s, s), 'target': (n, v, c, s, s),
              'pressure': (n, 6), 'scene': (n,)}
    for name, shape in expect.items():
        if arrays[name].shape != shape:
            raise DatasetError(f'{p}/{name}.npy: shape {arrays[name].shape}, expected {shape}')
    contact = _load_contact(p, meta, n)
    shape = _load_shape(p, meta, n, v)
    return Dataset(path=p, meta=meta, contact=contact, shape=shape, **arrays)
