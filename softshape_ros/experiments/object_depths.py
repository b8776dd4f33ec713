"""
The rows' object depth maps, cast from their recorded placements: a depth-test model's targets.

Here, above model/ and sim/, because casting needs the simulator's objects and cameras and
model/ does not import sim/ (test_layers). ``softshape train`` and ``softshape pretrain``
hand :func:`object_depths` to training (``train(..., object_depths=...)``).
"""

from __future__ import annotations

import os

import numpy as np
import torch
from tqdm import tqdm

from softshape_ros.config import load_rig_config
from softshape_ros.model.data import ObjectDepths, placements
from softshape_ros.sim.camera import PinholeCamera
from softshape_ros.sim.object_depth import object_depth


def object_depths(ds, idx, cfg=None, progress: bool = False) -> ObjectDepths | None:
    """
    Return rows ``idx`` (sorted, as ``model.data.to_tensors``) as ``ObjectDepths``, or None.

    Cast from each placement the meta records through the rig's cameras
    (:func:`~softshape_ros.sim.object_depth.object_depth`; ``cfg``: the rig config, else
    the one the dataset was simulated or recorded with, else the package's). None where any
    row's placement is unknown or the dataset's views are not the config's cameras.
    """
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    table = placements(ds, idx)
    if table is None:
        return None
    if cfg is None:                 # simulate records its config, build-dataset the bags'
        prov = ds.meta.get('provenance')
        path = ds.meta.get('config') or (prov.get('config') if isinstance(prov, dict) else None)
        cfg = load_rig_config(path if isinstance(path, str) and os.path.exists(path) else None)
    if not all(v in cfg.cameras for v in ds.views):
        return None
    cams = [PinholeCamera.from_config(v, cfg.cameras[v]) for v in ds.views]
    size = int(ds.meta.get('image_size', 64))
    ids = np.asarray(ds.scene)[idx]
    unique, row_map = np.unique(ids, return_inverse=True)
    maps = np.empty((len(unique), len(cams), size, size), np.float16)
    for k, sid in enumerate(tqdm(unique, desc='object depth', disable=not progress,
                                 leave=False, dynamic_ncols=True)):
        maps[k] = object_depth(cams, table[int(sid)], cfg.robot.base_position_m, size)
    return ObjectDepths(torch.from_numpy(maps), torch.from_numpy(row_map))
