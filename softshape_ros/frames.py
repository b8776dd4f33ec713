"""
The rig's TF frames from ``config/rig.yaml``: where each camera's optical frame sits.

rig.yaml gives every camera a position, a point it looks at and an up vector in the world
frame (z up). The optical frame is OpenCV's and REP 103's ``*_optical_frame``: z forward,
x right, y down, the same axes the simulator renders with (sim/camera.py). The launch
files publish these as static transforms (tf2_ros ``static_transform_publisher``); a test
checks their numbers against this module, and ``python -m softshape_ros.frames`` prints
the arguments for a changed rig.yaml.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np

__all__ = ['WORLD_FRAME', 'StaticTransform', 'camera_rotation', 'camera_transforms',
           'quaternion_from_matrix']

#: The fixed frame rig.yaml's positions are given in.
WORLD_FRAME = 'world'


@dataclass(frozen=True)
class StaticTransform:
    """One fixed transform: ``child`` in ``parent``, translation in m, quaternion xyzw."""

    parent: str
    child: str
    translation: tuple
    rotation: tuple

    def publisher_args(self) -> list[str]:
        """Return the ``static_transform_publisher`` arguments (Jazzy's named form)."""
        names = ('--x', '--y', '--z', '--qx', '--qy', '--qz', '--qw')
        args = []
        for name, v in zip(names, tuple(self.translation) + tuple(self.rotation)):
            args += [name, repr(round(float(v), 9))]
        return args + ['--frame-id', self.parent, '--child-frame-id', self.child]


def camera_rotation(position, look_at, up) -> np.ndarray:
    """Return the 3x3 rotation world <- optical frame (columns: x right, y down, z forward)."""
    z = np.asarray(look_at, dtype=float) - np.asarray(position, dtype=float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError('up is parallel to the viewing direction')
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def quaternion_from_matrix(r: np.ndarray) -> tuple:
    """Return the unit quaternion (x, y, z, w), w >= 0, of a rotation matrix."""
    m = np.asarray(r, dtype=float)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = s / 4
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = (v[0], v[1], v[2], (m[k, j] - m[j, k]) / s)
    q = np.asarray(q) / np.linalg.norm(q)
    return tuple(float(v) for v in (q if q[3] >= 0 else -q))


def camera_transforms(cfg, parent: str = WORLD_FRAME) -> list[StaticTransform]:
    """Return one transform per camera of ``cfg`` (a RigConfig): parent -> optical frame."""
    out = []
    for cam in cfg.cameras.values():
        r = camera_rotation(cam.position_m, cam.look_at_m, cam.up)
        out.append(StaticTransform(parent, cam.frame_id,
                                   tuple(float(v) for v in cam.position_m),
                                   quaternion_from_matrix(r)))
    return out


def main(argv=None) -> int:
    """Print each camera's static_transform_publisher arguments for a rig.yaml."""
    from softshape_ros.config import load_rig_config
    argv = sys.argv[1:] if argv is None else argv
    cfg = load_rig_config(argv[0] if argv else None)
    for tf in camera_transforms(cfg):
        print(' '.join(tf.publisher_args()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
