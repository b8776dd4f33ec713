"""
The object's depth in each camera's input image: what the robot must be nearer than to show.

Per pixel of the ``size`` x ``size`` input crop (pixel centres as ``render_inputs`` and the
shape record put them), the ray through it is cast at the scene's object; the hit's depth
is given in the shape record's units (``generate.measure_shape``): px further from the
camera than the robot's base, ``f (z / z_base - 1)``. Pixels whose ray misses the object
hold ``inf``. Why: the tube model hides the robot by comparing its own depth with this
(docs/model.md, "A depth test"), and a placement (``Scene``) is all it takes to make it, so
any simulated dataset, old or new, has it.
"""

from __future__ import annotations

import numpy as np

from softshape_ros.scene import Scene
from softshape_ros.sim.camera import PinholeCamera
from softshape_ros.sim.objects import obstacle_from_scene


def object_depth(cameras: list[PinholeCamera], scene: Scene | None, base_m, size: int = 64
                 ) -> np.ndarray:
    """
    Return V x size x size float32: the object's front depth per input pixel (inf: none).

    ``cameras``: the views, in the dataset's order; ``scene``: the placement (None or
    object 'none': inf everywhere); ``base_m``: the robot base's world position (m), the
    depths' zero; ``size``: the input images' side (px).
    """
    out = np.full((len(cameras), size, size), np.inf, np.float32)
    obj = obstacle_from_scene(scene)
    if obj is None:
        return out
    base = np.asarray(base_m, dtype=float).reshape(1, 3)
    for v, cam in enumerate(cameras):
        z_base = cam.project(base)[0, 2]
        rays = cam.rays(cam.grid(cam.crop, (size, size))).reshape(-1, 3)
        t, _ = obj.raycast(cam.position, rays)
        hit = np.isfinite(t)
        z = (t[hit, None] * rays[hit]) @ cam.R[:, 2]                 # camera-frame depth
        out[v].reshape(-1)[hit] = cam.input_depth_px(z, z_base, size)
    return out
