"""
Rigid objects of a scene as signed distance functions (for contact) and ray casts (for rendering).

Each object lives in its own frame (``Scene.position_m`` / ``rpy_rad`` give its pose in the
world): cylinder and prism axis +z, centred; ring (torus) in the local x-y plane around +z;
plane ``z = 0`` with +z out of the solid; sphere at the origin. The oblique prism is a
parallelepiped whose sections shift along x by ``z tan(skew)``; its distance is a smooth
exact distance too (nearest face interior or edge outside, largest face distance inside).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softshape_ros.scene import Scene, SceneError
from softshape_ros.sim import kernels
from softshape_ros.sim.lie import pose

MAX_PRISM_SKEW_RAD = np.deg2rad(80.0)   # steeper faces than this are not a placeable prism


class Obstacle:
    """
    Base: world <-> local transforms; subclasses give their kind code and parameter row.

    Distances, gradients and Hessians come from one compiled kernel per kind
    (``kernels._sdf_local``), for contact and for any caller alike.
    """

    kind = 'none'
    code = kernels.PLANE

    def __init__(self, position=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)):
        self.g = pose(position, rpy)
        self.R = self.g[:3, :3]
        self.t = self.g[:3, 3]
        self._row = None

    def params(self) -> np.ndarray:
        """Return the kind's numbers as the row the kernels read (length PRISM_PARAMS)."""
        return np.zeros(kernels.PRISM_PARAMS)

    @property
    def row(self) -> np.ndarray:
        """Return the kernels' parameters, built on first use (after the subclass sets sizes)."""
        if self._row is None:
            self._row = self.params()
        return self._row

    def sdf(self, p: np.ndarray):
        """Return signed distance (P,) and unit gradient (P, 3) at world points ``p``."""
        d, n, _ = kernels.sdf_points(self.code, self.row, self.g, _points(p), False)
        return d, n

    def sdf_hessian(self, p: np.ndarray):
        """Return distance (P,), gradient (P, 3) and Hessian (P, 3, 3) in one evaluation."""
        return kernels.sdf_points(self.code, self.row, self.g, _points(p), True)

    def _sdf(self, p):
        """Return distance and gradient at points ``p`` of the object's own frame."""
        return kernels.sdf_points(self.code, self.row, np.eye(4), _points(p), False)[:2]

    def _sdf_hessian(self, p):
        """Return distance, gradient and Hessian (closed form) in the object's own frame."""
        return kernels.sdf_points(self.code, self.row, np.eye(4), _points(p), True)

    def raycast(self, origin: np.ndarray, dirs: np.ndarray):
        """Return hit distance (P,) (inf = miss) and world normals (P, 3) for unit rays."""
        o = (np.asarray(origin, dtype=float) - self.t) @ self.R
        d = np.einsum('pi,ij->pj', dirs, self.R)       # einsum: far faster than @ for (N,3)
        t, n = self._raycast(o, d)
        return t, np.einsum('pi,ji->pj', n, self.R)

    def bounding_radius(self) -> float:
        return np.inf


def _points(p) -> np.ndarray:
    return np.ascontiguousarray(np.atleast_2d(np.asarray(p, dtype=float)))


def _norm(v):
    return np.sqrt(np.einsum('...i,...i->...', v, v))


def _normalise(v):
    return v / np.maximum(_norm(v)[..., None], 1e-300)


class Sphere(Obstacle):
    kind = 'sphere'
    code = kernels.SPHERE

    def __init__(self, radius_m, **kw):
        super().__init__(**kw)
        self.r = radius_m

    def params(self):
        row = super().params()
        row[0] = self.r
        return row

    def _raycast(self, o, d):
        b = d @ o
        c = o @ o - self.r ** 2
        disc = b * b - c
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        t = np.where((disc >= 0) & (t > 0), t, np.inf)
        hit = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        return t, _normalise(hit)

    def bounding_radius(self):
        return self.r


class Plane(Obstacle):
    kind = 'plane'
    code = kernels.PLANE

    def _raycast(self, o, d):
        with np.errstate(divide='ignore', invalid='ignore'):
            t = -o[2] / d[:, 2]
        t = np.where(np.isfinite(t) & (t > 0) & (o[2] > 0), t, np.inf)
        n = np.zeros_like(d)
        n[:, 2] = 1.0
        return t, n


class Cylinder(Obstacle):
    kind = 'cylinder'
    code = kernels.CYLINDER

    def __init__(self, radius_m, height_m, **kw):
        super().__init__(**kw)
        self.r, self.hh = radius_m, height_m / 2

    def params(self):
        row = super().params()
        row[:2] = self.r, self.hh
        return row

    def _raycast(self, o, d):
        P = len(d)
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = d[:, 0] * o[0] + d[:, 1] * o[1]
        c = o[0] ** 2 + o[1] ** 2 - self.r ** 2
        disc = b * b - a * c
        with np.errstate(divide='ignore', invalid='ignore'):
            ts = (-b - np.sqrt(np.maximum(disc, 0))) / a
        zs = o[2] + ts * d[:, 2]
        ts = np.where((disc >= 0) & (a > 1e-300) & (ts > 0) & (np.abs(zs) <= self.hh), ts, np.inf)
        with np.errstate(divide='ignore', invalid='ignore'):
            tc = (np.sign(o[2]) * self.hh - o[2]) / d[:, 2]
            xc = o[0] + tc * d[:, 0]
            yc = o[1] + tc * d[:, 1]
        tc = np.where(np.isfinite(tc) & (tc > 0) & (xc ** 2 + yc ** 2 <= self.r ** 2)
                      & (abs(o[2]) > self.hh), tc, np.inf)
        t = np.minimum(ts, tc)
        n = np.zeros((P, 3))
        side = ts <= tc
        hit = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        n[side, :2] = hit[side, :2] / self.r
        n[~side, 2] = np.sign(o[2])
        return t, n

    def bounding_radius(self):
        return float(np.hypot(self.r, self.hh))


class Ring(Obstacle):
    kind = 'ring'
    code = kernels.RING

    def __init__(self, major_radius_m, minor_radius_m, **kw):
        super().__init__(**kw)
        self.R0, self.r = major_radius_m, minor_radius_m

    def params(self):
        row = super().params()
        row[:2] = self.R0, self.r
        return row

    def _raycast(self, o, d):
        # Sphere tracing from the bounding sphere (the torus distance is exact).
        P = len(d)
        Rb = self.R0 + self.r
        b = d @ o
        c = o @ o - Rb ** 2
        disc = b * b - c
        cand = disc > 0
        t = np.full(P, np.inf)
        n = np.zeros((P, 3))
        idx = np.nonzero(cand)[0]
        if len(idx) == 0:
            return t, n
        tt = np.maximum(-b[idx] - np.sqrt(disc[idx]), 0.0)
        tmax = -b[idx] + np.sqrt(disc[idx])
        dd = d[idx]
        live = np.arange(len(idx))
        for _ in range(80):
            pts = o + tt[live, None] * dd[live]
            dist, _ = self._sdf(pts)
            tt[live] += dist
            keep = (dist > 1e-7) & (tt[live] <= tmax[live])
            live = live[keep]
            if len(live) == 0:
                break
        pts = o + tt[:, None] * dd
        dist, nn = self._sdf(pts)
        ok = (np.abs(dist) < 1e-6) & (tt <= tmax)
        t[idx[ok]] = tt[ok]
        n[idx[ok]] = nn[ok]
        return t, n

    def bounding_radius(self):
        return self.R0 + self.r


class Prism(Obstacle):
    kind = 'prism'
    code = kernels.PRISM

    def __init__(self, width_m, depth_m, height_m, skew_rad, **kw):
        super().__init__(**kw)
        c, s = np.cos(skew_rad), np.sin(skew_rad)
        self.normals = np.array([[c, 0, -s], [-c, 0, s], [0, 1, 0], [0, -1, 0],
                                 [0, 0, 1], [0, 0, -1]], dtype=float)
        self.offsets = np.array([width_m / 2 * c, width_m / 2 * c, depth_m / 2, depth_m / 2,
                                 height_m / 2, height_m / 2])
        self.size = (width_m, depth_m, height_m, skew_rad)

    def _features(self):
        w, dp, h, sk = self.size
        ts = np.tan(sk)
        V = np.array([[sx * w / 2 + sz * h / 2 * ts, sy * dp / 2, sz * h / 2]
                      for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        edges = [(i, j) for i in range(8) for j in range(i + 1, 8)
                 if bin(i ^ j).count('1') == 1]
        # Faces as (corner, edge1, edge2): vertex index bits are (sx, sy, sz).
        faces = []
        for bit in (4, 2, 1):
            others = [b for b in (4, 2, 1) if b != bit]
            for side in (0, bit):
                faces.append((V[side], V[side | others[0]] - V[side],
                              V[side | others[1]] - V[side]))
        self._ea = V[[e[0] for e in edges]]                          # (12, 3)
        self._eab = V[[e[1] for e in edges]] - self._ea
        self._fa = np.array([f[0] for f in faces])                    # (6, 3)
        self._fe = np.array([[f[1], f[2]] for f in faces])            # (6, 2, 3)
        G = np.einsum('fai,fbi->fab', self._fe, self._fe)
        self._fginv = np.linalg.inv(G)                                # (6, 2, 2)
        # Face coordinates of a point: ab = (E E^T)^-1 E (p - a), as one (12, 3) matrix.
        self._fproj = np.einsum('fab,fbi->fai', self._fginv, self._fe).reshape(12, 3)
        self._eab2 = np.einsum('ei,ei->e', self._eab, self._eab)
        self._fa_ab = np.einsum('fai,fi->fa', self._fproj.reshape(6, 2, 3), self._fa)
        self._ea_eab = np.einsum('ei,ei->e', self._ea, self._eab)
        self._ea2 = np.einsum('ei,ei->e', self._ea, self._ea)
        fn = np.cross(self._fe[:, 0], self._fe[:, 1])
        self._fn = fn / np.linalg.norm(fn, axis=1, keepdims=True)       # unit face normals
        self._fn_a = np.einsum('fi,fi->f', self._fn, self._fa)

    def params(self):
        """Faces (normals, offsets) and the edge and face tables of the exact distance."""
        self._features()
        k = kernels
        row = super().params()
        row[k.PRISM_NORMALS:k.PRISM_OFFSETS] = self.normals.ravel()
        row[k.PRISM_OFFSETS:k.PRISM_EA] = self.offsets
        row[k.PRISM_EA:k.PRISM_EAB] = self._ea.ravel()
        row[k.PRISM_EAB:k.PRISM_EAB2] = self._eab.ravel()
        row[k.PRISM_EAB2:k.PRISM_EA_EAB] = self._eab2
        row[k.PRISM_EA_EAB:k.PRISM_EA2] = self._ea_eab
        row[k.PRISM_EA2:k.PRISM_FPROJ] = self._ea2
        row[k.PRISM_FPROJ:k.PRISM_FA_AB] = self._fproj.ravel()
        row[k.PRISM_FA_AB:k.PRISM_FN] = self._fa_ab.ravel()
        row[k.PRISM_FN:k.PRISM_FN_A] = self._fn.ravel()
        row[k.PRISM_FN_A:k.PRISM_PARAMS] = self._fn_a
        return row

    def _raycast(self, o, d):
        den = d @ self.normals.T                          # (P, 6)
        num = self.offsets - self.normals @ o             # (6,)
        with np.errstate(divide='ignore', invalid='ignore'):
            tk = num[None, :] / den
        enter = np.where(den < 0, tk, -np.inf)
        leave = np.where(den > 0, tk, np.inf)
        parallel_out = (den == 0) & (num[None, :] < 0)
        t0 = enter.max(axis=1)
        t1 = leave.min(axis=1)
        hit = (t0 <= t1) & (t0 > 0) & ~parallel_out.any(axis=1)
        t = np.where(hit, t0, np.inf)
        n = self.normals[np.argmax(enter, axis=1)]
        return t, n

    def bounding_radius(self):
        w, dp, h, sk = self.size
        return float(0.5 * np.sqrt((w + h * abs(np.tan(sk))) ** 2 + dp ** 2 + h ** 2))


def obstacle_from_scene(scene: Scene | None) -> Obstacle | None:
    """
    Return the scene's object as an :class:`Obstacle` (None for no object).

    Raises :class:`~softshape_ros.scene.SceneError` for a shape that has no body: a ring
    whose tube is as thick as its radius, a prism skewed flat.
    """
    if scene is None or scene.object == 'none':
        return None
    dims = scene.dims
    if scene.object == 'ring' and dims['minor_radius_m'] >= dims['major_radius_m']:
        raise SceneError(f'scene {scene.id}: ring minor radius {dims["minor_radius_m"]} m '
                         f'must be below its major radius {dims["major_radius_m"]} m')
    if scene.object == 'prism' and not abs(float(dims['skew_rad'])) <= MAX_PRISM_SKEW_RAD:
        raise SceneError(f'scene {scene.id}: prism skew {dims["skew_rad"]} rad is beyond '
                         f'+-{MAX_PRISM_SKEW_RAD:.3f} rad')
    kw = dict(position=scene.position_m, rpy=scene.rpy_rad)
    cls = {'sphere': Sphere, 'plane': Plane, 'cylinder': Cylinder, 'ring': Ring,
           'prism': Prism}[scene.object]
    return cls(**dims, **kw)


@dataclass(frozen=True)
class ObstacleSet:
    """The obstacles as the kernels read them: kind codes, parameter rows, poses."""

    obstacles: tuple
    kinds: np.ndarray        # (O,) int
    rows: np.ndarray         # (O, PRISM_PARAMS)
    poses: np.ndarray        # (O, 4, 4)

    @classmethod
    def of(cls, obstacles) -> 'ObstacleSet':
        obs = tuple(o for o in obstacles if o is not None)
        rows = np.array([o.row for o in obs]).reshape(len(obs), kernels.PRISM_PARAMS)
        return cls(obs, np.array([o.code for o in obs], dtype=np.int64), rows,
                   np.array([o.g for o in obs]).reshape(len(obs), 4, 4))

    def __len__(self) -> int:
        return len(self.obstacles)

    def least_gap(self, points: np.ndarray, radii: np.ndarray) -> float:
        """Return the least ``distance - radius`` of tube points (P, 3) to any obstacle."""
        return float(kernels.least_gap(self.kinds, self.rows, self.poses, _points(points),
                                       np.asarray(radii, dtype=float)))
