"""
A drawn stand-in for the simulator: a two-segment bending rod stopped by a cylinder.

Used by the model's tests and benchmark, so they run without ``softshape simulate``. It is
deterministic and learnable (the shape follows the six pressures by piecewise-constant
curvature and the rod stops where it would touch the object), not noise. Views: ``main``
looks along +y, ``side`` is rotated 45 degrees about the vertical, both orthographic.
"""

from __future__ import annotations

import numpy as np

from softshape_ros.data import write_dataset

SIZE = 64
MAX_PA = 150000.0
ANGLES = np.deg2rad([0.0, 120.0, 240.0])
EXTENT = (-1.1, 1.1, -1.95, 0.25)     # u min, u max, z min, z max (robot length 1)
ROD_RADIUS = 0.09
GRAY = {'background': 215, 'robot': 55, 'object': 140}
RGB = {'background': (235, 235, 230), 'robot': (150, 45, 35), 'object': (120, 170, 220)}
VIEW_YAW = {'main': 0.0, 'side': np.deg2rad(45.0)}


def centreline(pressure_pa, scale: float = 1.0, n: int = 24) -> np.ndarray:
    """Points (n x 3) of the rod hanging from the origin for ``pressure_pa`` x ``scale``."""
    p = np.asarray(pressure_pa, dtype=np.float64) / MAX_PA * scale
    pts = [np.zeros(3)]
    ax = ay = 0.0
    ds = 1.0 / n
    for k in range(n):
        seg = 0 if k < n // 2 else 1
        q = p[3 * seg:3 * seg + 3]
        # A chamber bends the segment away from itself: up to ~1.6 rad per segment.
        ax += -3.2 * float(np.dot(q, np.sin(ANGLES))) * ds
        ay += -3.2 * float(np.dot(q, np.cos(ANGLES))) * ds
        t = np.array([np.sin(ay) * np.cos(ax), np.sin(ax), -np.cos(ay) * np.cos(ax)])
        pts.append(pts[-1] + ds * t)
    return np.array(pts)


def _clearance(points, obj) -> float:
    ox, oy, r = obj
    d = np.hypot(points[:, 0] - ox, points[:, 1] - oy)
    return float(np.min(d - r - ROD_RADIUS))


def contact_shape(pressure_pa, obj) -> np.ndarray:
    """Rod points for the actuation, scaled back until the rod just touches the object."""
    full = centreline(pressure_pa)
    if obj is None or _clearance(full, obj) >= 0:
        return full
    lo, hi = 0.0, 1.0
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        if _clearance(centreline(pressure_pa, mid), obj) >= 0:
            lo = mid
        else:
            hi = mid
    return centreline(pressure_pa, lo)


def render(points, obj, view: str, rgb: bool = False) -> np.ndarray:
    """Draw rod + object for one view -> C x 64 x 64 uint8 (nearest surface wins)."""
    yaw = VIEW_YAW[view]
    u0, u1, z0, z1 = EXTENT
    us = u0 + (np.arange(SIZE) + 0.5) * (u1 - u0) / SIZE
    zs = z1 - (np.arange(SIZE) + 0.5) * (z1 - z0) / SIZE
    U, Z = np.meshgrid(us, zs)
    c, s = np.cos(yaw), np.sin(yaw)
    pu = points[:, 0] * c + points[:, 1] * s
    pd = -points[:, 0] * s + points[:, 1] * c             # depth: larger is further
    d2 = (U[..., None] - pu) ** 2 + (Z[..., None] - points[:, 2]) ** 2
    k = np.argmin(d2, axis=-1)
    robot = np.min(d2, axis=-1) < ROD_RADIUS ** 2
    robot_depth = np.where(robot, pd[k], np.inf)
    obj_depth = np.full(U.shape, np.inf)
    if obj is not None:
        ox, oy, r = obj
        ou, od = ox * c + oy * s, -ox * s + oy * c
        du = U - ou
        inside = (np.abs(du) < r) & (Z > -1.9) & (Z < -0.25)
        obj_depth = np.where(inside, od - np.sqrt(np.clip(r * r - du * du, 0, None)), np.inf)
    colours = RGB if rgb else {k_: (v,) for k_, v in GRAY.items()}
    img = np.empty(U.shape + (len(colours['background']),), np.uint8)
    img[:] = colours['background']
    img[obj_depth < robot_depth] = colours['object']
    img[(robot_depth <= obj_depth) & robot] = colours['robot']
    return np.ascontiguousarray(img.transpose(2, 0, 1))


def touches(pressure_pa, obj) -> bool:
    """Return whether the rod of ``pressure_pa`` is stopped by the object."""
    return obj is not None and _clearance(centreline(pressure_pa), obj) < 0


def make_samples(n: int, scenes: int, views=('main',), rgb: bool = False, seed: int = 0,
                 with_touching: bool = False, gap=(0.35, 0.8)):
    """
    Return (initial, target, pressure, scene) arrays for ``n`` samples over ``scenes``.

    Objects stand ``gap`` (min, max, robot lengths) from the axis beyond their radius;
    nearer means more contact. With ``with_touching`` a fifth array: N bool, the sample's
    rod is stopped by the object.
    """
    rng = np.random.default_rng(seed)
    objs = []
    for _ in range(scenes):
        ang = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(0.12, 0.25)
        dist = rng.uniform(*gap) + r
        objs.append((dist * np.cos(ang), dist * np.sin(ang), r))
    c = 3 if rgb else 1
    shape = (n, len(views), c, SIZE, SIZE)
    initial, target = np.empty(shape, np.uint8), np.empty(shape, np.uint8)
    pressure = np.empty((n, 6), np.float32)
    scene = np.arange(n) % scenes
    rest, touching = {}, np.zeros(n, bool)
    for i in range(n):
        obj = objs[scene[i]]
        p = rng.uniform(0, MAX_PA, 6) * (rng.random(6) < 0.6)
        touching[i] = touches(p, obj)
        pts = contact_shape(p, obj)
        if scene[i] not in rest:
            r_pts = centreline(np.zeros(6))
            rest[scene[i]] = np.stack([render(r_pts, obj, v, rgb) for v in views])
        initial[i] = rest[scene[i]]
        target[i] = np.stack([render(pts, obj, v, rgb) for v in views])
        pressure[i] = p
    if with_touching:
        return initial, target, pressure, scene, touching
    return initial, target, pressure, scene


def make_dataset(path, n: int, scenes: int, views=('main',), rgb: bool = False, seed: int = 0):
    """Write a synthetic dataset folder in the project format and return it loaded."""
    initial, target, pressure, scene = make_samples(n, scenes, views, rgb, seed)
    return write_dataset(path, initial, target, pressure, scene, [MAX_PA] * 6, list(views),
                         meta={'provenance': {'generator': 'softshape_ros.model.synthetic',
                                              'seed': seed, 'scenes': scenes}},
                         overwrite=True)
