"""
Rigid poses of the rig: roll-pitch-yaw rotations and 4x4 homogeneous poses.

The SE(3) algebra of the rod (exponential, tangent operator, adjoints; twists with the
angular part first) is compiled with the kinematics in :mod:`softshape_ros.sim.kernels`.
"""

from __future__ import annotations

import numpy as np


def rpy_matrix(rpy) -> np.ndarray:
    """Return R = Rz(yaw) Ry(pitch) Rx(roll), the ROS convention for fixed-axis rpy."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def pose(position, rpy) -> np.ndarray:
    """Return the 4x4 pose from a position and roll-pitch-yaw."""
    g = np.eye(4)
    g[:3, :3] = rpy_matrix(rpy)
    g[:3, 3] = np.asarray(position, dtype=float)
    return g
