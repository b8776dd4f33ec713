"""
The project's one dataset format: a folder of memory-mappable arrays plus meta.json.

Both the simulator (`softshape simulate`) and the bag builder (`softshape build-dataset`)
write it through :class:`DatasetWriter`; everything reads it through :func:`load_dataset`.
Arrays are ``.npy`` files so ``np.load(mmap_mode='r')`` maps them without copying:

- ``initial``  N x V x C x S x S uint8 -- rest images of the sample's scene, per view
- ``target``   N x V x C x S x S uint8 -- images at the trigger
- ``pressure`` N x 6 float32, Pa      -- measured chamber pressures at the trigger
- ``scene``    N int64                -- scene index (for split-by-scene)
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT = 'softshape-dataset'
VERSION = 1
ARRAYS = ('initial', 'target', 'pressure', 'scene')


class DatasetError(ValueError):
    """A dataset folder is missing, incomplete or inconsistent."""


@dataclass
class Dataset:
    """Read-only view of a dataset folder (arrays are memory-mapped)."""

    path: Path
    initial: np.ndarray
    target: np.ndarray
    pressure: np.ndarray
    scene: np.ndarray
    meta: dict

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


class DatasetWriter:
    """
    Create a dataset of known size and fill it row by row (or in slices).

    Writes go to ``<path>.partial`` and the folder is renamed into place on
    :meth:`close`, so a crash never leaves something that looks complete.
    """

    def __init__(self, path, n: int, views: list[str], channels: int, size: int,
                 max_pressure_pa, meta: dict | None = None, overwrite: bool = False):
        if n < 0:
            raise DatasetError(f'dataset size must be >= 0, got {n}')
        if channels not in (1, 3):
            raise DatasetError(f'channels must be 1 (gray) or 3 (RGB), got {channels}')
        if len(max_pressure_pa) != 6:
            raise DatasetError(f'max_pressure_pa needs 6 values, got {len(max_pressure_pa)}')
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise DatasetError(f'{self.path}: already exists (pass overwrite)')
        self.tmp = self.path.with_name(self.path.name + '.partial')
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        self.tmp.mkdir(parents=True)
        self.n, self.views, self.channels, self.size = n, list(views), channels, size
        shape = (n, len(views), channels, size, size)
        mm = np.lib.format.open_memmap
        self.initial = mm(self.tmp / 'initial.npy', 'w+', np.uint8, shape)
        self.target = mm(self.tmp / 'target.npy', 'w+', np.uint8, shape)
        self.pressure = mm(self.tmp / 'pressure.npy', 'w+', np.float32, (n, 6))
        self.scene = mm(self.tmp / 'scene.npy', 'w+', np.int64, (n,))
        self.meta = dict(meta or {})
        self.meta.update(format=FORMAT, version=VERSION, views=self.views, channels=channels,
                         image_size=size,
                         max_pressure_pa=[float(v) for v in max_pressure_pa])
        self.overwrite = overwrite

    def put(self, i, initial, target, pressure, scene) -> None:
        """Store sample(s) at index or slice ``i``; checks shapes and finiteness."""
        p = np.asarray(pressure, dtype=np.float32)
        if not np.all(np.isfinite(p)):
            raise DatasetError(f'sample {i}: pressure is not finite: {p}')
        self.initial[i] = initial
        self.target[i] = target
        self.pressure[i] = p
        self.scene[i] = scene

    def close(self, **extra_meta) -> Dataset:
        """Flush, write meta.json and move the folder into place."""
        self.meta.update(extra_meta)
        self.meta['count'] = self.n
        for a in (self.initial, self.target, self.pressure, self.scene):
            a.flush()
        del self.initial, self.target, self.pressure, self.scene
        (self.tmp / 'meta.json').write_text(json.dumps(self.meta, indent=2, sort_keys=True))
        if self.path.exists():
            shutil.rmtree(self.path)
        os.replace(self.tmp, self.path)
        return load_dataset(self.path)


def write_dataset(path, initial, target, pressure, scene, max_pressure_pa, views,
                  meta: dict | None = None, overwrite: bool = False) -> Dataset:
    """Write whole in-memory arrays as a dataset (convenience over DatasetWriter)."""
    initial = np.asarray(initial)
    if initial.ndim != 5:
        raise DatasetError(f'initial must be N x V x C x S x S, got shape {initial.shape}')
    n, v, c, s, _ = initial.shape
    w = DatasetWriter(path, n, views, c, s, max_pressure_pa, meta, overwrite)
    if n:
        w.put(slice(None), initial, target, pressure, scene)
    return w.close()


def load_dataset(path) -> Dataset:
    """Open a dataset folder; arrays are memory-mapped read-only and cross-checked."""
    p = Path(path)
    if not p.is_dir():
        raise DatasetError(f'{p}: no such dataset folder')
    try:
        meta = json.loads((p / 'meta.json').read_text())
    except FileNotFoundError:
        raise DatasetError(f'{p}: meta.json missing (incomplete dataset?)') from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f'{p}/meta.json: not valid JSON: {exc}') from None
    if meta.get('format') != FORMAT:
        raise DatasetError(f'{p}: not a {FORMAT} folder (format={meta.get("format")!r})')
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
    return Dataset(path=p, meta=meta, **arrays)
