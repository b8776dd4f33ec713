"""
Dataset rows -> network tensors, and the two ways of holding data out.

``random`` is the paper's 80/20 split; ``scene`` holds out whole object placements, so the
validation (or test) images show scenes the network has never seen.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from softshape_ros.scene import OBJECT_DIMS, Scene, SceneError

SPLITS = ('random', 'scene')
#: What :func:`scene_targets` says of an object placement, in this order (17 numbers).
SCENE_FEATURES = (*(f'is_{kind}' for kind in OBJECT_DIMS), 'x_mm', 'y_mm', 'z_mm',
                  'roll', 'pitch', 'sin_2yaw', 'cos_2yaw', 'dim0', 'dim1', 'dim2', 'dim3')
# Objects that look the same at every yaw: their yaw is not in the images.
_ROUND = ('none', 'cylinder', 'sphere', 'plane')
_UNIT = 5.0             # one-hot and angle features in units comparable to millimetres


def split_indices(scene, idx, mode: str, fraction: float, seed: int):
    """Split row indices ``idx`` into (kept, held_out) with about ``fraction`` held out."""
    idx = np.asarray(idx, dtype=np.int64)
    if not 0.0 < fraction < 1.0:
        raise ValueError(f'held-out fraction must be in (0, 1), got {fraction}')
    rng = np.random.default_rng(seed)
    if mode == 'random':
        perm = rng.permutation(idx)
        k = max(1, int(round(fraction * len(idx))))
        return np.sort(perm[k:]), np.sort(perm[:k])
    if mode == 'scene':
        scenes = np.unique(np.asarray(scene)[idx])
        if len(scenes) < 2:
            raise ValueError(f'split by scene needs at least 2 scenes, got {len(scenes)}')
        k = min(len(scenes) - 1, max(1, int(round(fraction * len(scenes)))))
        held = rng.permutation(scenes)[:k]
        mask = np.isin(np.asarray(scene)[idx], held)
        return idx[~mask], idx[mask]
    raise ValueError(f'unknown split {mode!r} (choose from {", ".join(SPLITS)})')


def stack_views(images: np.ndarray) -> np.ndarray:
    """N x V x C x S x S -> N x (V*C) x S x S (views stacked as channels)."""
    n, v, c, s, _ = images.shape
    return images.reshape(n, v * c, s, s)


def to_float(images: torch.Tensor) -> torch.Tensor:
    """Return uint8 image tensors as float in [0, 1] (float ones unchanged)."""
    return images.to(torch.float32) / 255 if images.dtype == torch.uint8 else images


def to_tensors(ds, idx, max_pressure_pa, as_uint8: bool = False):
    """
    Load rows ``idx`` of a dataset as (initial, target, pressure) tensors.

    Images N x (V*C) x S x S as float in [0, 1], or kept uint8 with ``as_uint8`` (a quarter
    of the memory for large sets; :func:`to_float` converts a batch); pressures N x 6 float
    in max-pressure units.
    """
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    initial = torch.from_numpy(stack_views(np.asarray(ds.initial[idx])))
    target = torch.from_numpy(stack_views(np.asarray(ds.target[idx])))
    if not as_uint8:
        initial, target = to_float(initial), to_float(target)
    p = np.asarray(ds.pressure[idx], dtype=np.float32) / np.asarray(max_pressure_pa, np.float32)
    return initial, target, torch.from_numpy(p)


def shape_tensors(ds, idx):
    """
    Return rows ``idx`` (sorted, as :func:`to_tensors`) of the shape record, or (None, None).

    (keypoints N x V x K x 4 float: x, y, radius, depth in px; free N bool: the sample
    touches nothing, or None where the dataset has no contact record).
    """
    shape = getattr(ds, 'shape', None)
    if shape is None:
        return None, None
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    kp = np.concatenate([np.asarray(shape.keypoints_px[idx]),
                         np.asarray(shape.radius_px[idx])[..., None],
                         np.asarray(shape.depth_px[idx])[..., None]], -1)
    flags = touching_flags(ds, idx)
    free = None if flags is None else torch.from_numpy(~np.asarray(flags))
    return torch.from_numpy(kp.astype(np.float32)), free


def touching_flags(ds, idx=None):
    """
    Return the rows' touching flags (N bool) from the dataset's contact record, or None.

    None when the dataset has no record (older datasets, recorded bags): metrics are then
    reported unsplit.
    """
    contact = getattr(ds, 'contact', None)
    if contact is None:
        return None
    flags = np.asarray(contact.touching, dtype=bool)
    return flags if idx is None else flags[np.asarray(idx, dtype=np.int64)]


def no_contact_why(ds) -> str:
    """Say why a dataset has no contact record (the reason its loader recorded)."""
    why = (ds.meta.get('contact') or {}).get('why') if isinstance(ds.meta, dict) else None
    return f'no contact record ({why})' if why else 'the dataset has no contact record'


def scene_vector(scene: Scene) -> list[float]:
    """
    Return one placement as the :data:`SCENE_FEATURES` numbers the tube model learns to see.

    Kind one-hot, position and dimensions in mm, roll and pitch, yaw as sin/cos of twice
    it (rings and prisms look the same turned by half a turn; round objects get 0), every
    angle and the one-hot x 5 so that each is weighed like a few millimetres; sizes in the
    sorted order of their names.
    """
    kind = [_UNIT * (scene.object == k) for k in OBJECT_DIMS]
    roll, pitch, yaw = scene.rpy_rad
    turn = [0.0, 0.0] if scene.object in _ROUND else [_UNIT * math.sin(2 * yaw),
                                                      _UNIT * math.cos(2 * yaw)]
    # Sizes in their names' sorted order, whatever order the scene lists them in: the order
    # of Scene.to_json, which every simulated dataset's placements came through (a session
    # YAML's order used to slip in for recorded bags).
    dims = [scene.dims[k] * (1000.0 if k.endswith('_m') else _UNIT) for k in sorted(scene.dims)]
    return (kind + [1000.0 * v for v in scene.position_m] + [_UNIT * roll, _UNIT * pitch]
            + turn + dims + [0.0] * (4 - len(dims)))


def scene_from_vector(vec, scene_id: int = 0, min_size_m: float = 5e-4) -> Scene:
    """
    Return the placement :data:`SCENE_FEATURES` numbers describe (:func:`scene_vector` undone).

    For a reader's description: the kind with the largest one-hot, sizes at least
    ``min_size_m``; of yaw only its half-turn class is seen, so it comes back within
    +-90 degrees (``sim.placement_fit.twin`` gives a prism's other description).
    """
    v = [float(x) for x in vec]
    kinds = list(OBJECT_DIMS)
    kind = kinds[int(np.argmax(v[:len(kinds)]))]
    n = len(kinds)
    pos = tuple(x / 1000.0 for x in v[n:n + 3])
    roll, pitch = v[n + 3] / _UNIT, v[n + 4] / _UNIT
    yaw = 0.0 if kind in _ROUND else 0.5 * math.atan2(v[n + 5], v[n + 6])
    dims = {k: (max(x / 1000.0, min_size_m) if k.endswith('_m') else x / _UNIT)
            for k, x in zip(sorted(OBJECT_DIMS[kind]), v[n + 7:])}
    return Scene(id=scene_id, object=kind, position_m=pos, rpy_rad=(roll, pitch, yaw),
                 dims=dims, label='read')


def scene_targets(ds, idx):
    """
    Return rows ``idx`` (sorted) as N x 17 :data:`SCENE_FEATURES` of their placement, or None.

    From the placements the dataset's meta records (simulated datasets: every scene;
    datasets built from bags: the session YAML's scenes). None where any row's placement
    is unknown: the tube model then learns the scene from the images alone.
    """
    table = placements(ds, idx)
    if table is None:
        return None
    ids = np.asarray(ds.scene)[np.sort(np.asarray(idx, dtype=np.int64))]
    vec = {i: scene_vector(sc) for i, sc in table.items()}
    return torch.tensor([vec[int(i)] for i in ids], dtype=torch.float32)


def placements(ds, idx) -> dict | None:
    """Return {placement id: Scene} from the dataset's meta, or None if a row's is unknown."""
    scenes = ds.meta.get('scenes') if isinstance(ds.meta, dict) else None
    if not isinstance(scenes, list) or not scenes:
        return None
    table = {}
    try:
        for i, s in enumerate(scenes):
            if isinstance(s, str):                  # simulate: the scenes' JSON, in id order
                table[i] = Scene.from_json(s)
            elif isinstance(s, dict) and 'index' in s:   # build-dataset: index -> scene
                table[int(s['index'])] = Scene.from_dict(s['scene'])
            else:
                return None
    except (SceneError, KeyError, TypeError, ValueError):
        return None
    ids = np.asarray(ds.scene)[np.asarray(idx, dtype=np.int64)]
    if not all(int(i) in table for i in np.unique(ids)):
        return None
    return table


class ObjectDepths:
    """
    Rows' object depth maps, one per placement: ``[idx]`` -> N x V x S x S float (inf: none).

    A placement's rows share its map, so it is held once (float16, a 20 000-row dataset of
    10 000 placements in 160 MB) and rows index it. Made by
    :func:`softshape_ros.experiments.object_depths.object_depths` (casting needs sim/).
    """

    def __init__(self, maps: torch.Tensor, row_map: torch.Tensor):
        self.maps, self.row_map = maps, row_map

    def __len__(self) -> int:
        return len(self.row_map)

    def __getitem__(self, idx) -> torch.Tensor:
        return self.maps[self.row_map[idx]].float()

    def rows(self, idx) -> 'ObjectDepths':
        """Return the same maps for rows ``idx`` of these (a validation slice)."""
        return ObjectDepths(self.maps, self.row_map[idx])
