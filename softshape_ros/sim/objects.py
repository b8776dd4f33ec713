"""
Rigid objects of a scene as signed distance functions (for contact) and ray casts (for rendering).

Each object lives in its own frame (``Scene.position_m`` / ``rpy_rad`` give its pose in the
world): cylinder and prism axis +z, centred; ring (torus) in the local x-y plane around +z;
plane ``z = 0`` with +z out of the solid; sphere at the origin. The oblique prism is a
parallelepiped whose sections shift along x by ``z tan(skew)``; its distance is a smooth
exact distance too (nearest face interior or edge outside, largest face distance inside).
"""

from __future__ import annotations

import numpy as np

from softshape_ros.scene import Scene
from softshape_ros.sim.lie import pose


class Obstacle:
    """Base: world <-> local transforms; subclasses implement the local geometry."""

    kind = 'none'

    def __init__(self, position=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)):
        self.g = pose(position, rpy)
        self.R = self.g[:3, :3]
        self.t = self.g[:3, 3]

    def sdf(self, p: np.ndarray):
        """Return signed distance (P,) and unit gradient (P, 3) at world points ``p``."""
        pl = (np.atleast_2d(p) - self.t) @ self.R
        d, n = self._sdf(pl)
        return d, n @ self.R.T

    def sdf_hessian(self, p: np.ndarray, eps: float = 1e-6):
        """Return distance (P,), gradient (P, 3) and Hessian (P, 3, 3) in one evaluation."""
        p = np.atleast_2d(p)
        if hasattr(self, '_sdf_hessian'):
            # Closed form: the contact model calls this for every refinement step.
            d, n, H = self._sdf_hessian((p - self.t) @ self.R)
            return d, n @ self.R.T, self.R @ H @ self.R.T
        steps = np.concatenate([np.zeros((1, 3)), np.eye(3), -np.eye(3)]) * eps   # (7, 3)
        d, n = self.sdf((p[:, None, :] + steps[None]).reshape(-1, 3))
        d, n = d.reshape(len(p), 7), n.reshape(len(p), 7, 3)
        H = np.swapaxes((n[:, 1:4] - n[:, 4:]) / (2 * eps), 1, 2)
        return d[:, 0], n[:, 0], 0.5 * (H + np.swapaxes(H, 1, 2))

    def raycast(self, origin: np.ndarray, dirs: np.ndarray):
        """Return hit distance (P,) (inf = miss) and world normals (P, 3) for unit rays."""
        o = (np.asarray(origin, dtype=float) - self.t) @ self.R
        d = np.einsum('pi,ij->pj', dirs, self.R)       # einsum: far faster than @ for (N,3)
        t, n = self._raycast(o, d)
        return t, np.einsum('pi,ji->pj', n, self.R)

    def bounding_radius(self) -> float:
        return np.inf


def _norm(v):
    return np.sqrt(np.einsum('...i,...i->...', v, v))


def _normalise(v):
    return v / np.maximum(_norm(v)[..., None], 1e-300)


def _outer(a, b):
    return a[:, :, None] * b[:, None, :]


def _circle_hessian(p, n, dist, R0):
    """
    Return the Hessian of the distance ``dist`` to a circle of radius R0 around +z.

    H = [(I - n n^T) - (R0 / rho) t t^T] / dist, t the circle's tangent at p's azimuth.
    """
    rho = np.maximum(np.hypot(p[:, 0], p[:, 1]), 1e-12)
    t = np.column_stack([-p[:, 1] / rho, p[:, 0] / rho, np.zeros(len(p))])
    return (np.eye(3) - _outer(n, n) - (R0 / rho)[:, None, None] * _outer(t, t)) \
        / np.maximum(dist, 1e-12)[:, None, None]


class Sphere(Obstacle):
    kind = 'sphere'

    def __init__(self, radius_m, **kw):
        super().__init__(**kw)
        self.r = radius_m

    def _sdf(self, p):
        nrm = np.linalg.norm(p, axis=1)
        return nrm - self.r, _normalise(p)

    def _sdf_hessian(self, p):
        d, n = self._sdf(p)
        return d, n, _circle_hessian(p, n, d + self.r, 0.0)

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

    def _sdf(self, p):
        n = np.zeros_like(p)
        n[:, 2] = 1.0
        return p[:, 2], n

    def _sdf_hessian(self, p):
        d, n = self._sdf(p)
        return d, n, np.zeros((len(p), 3, 3))

    def _raycast(self, o, d):
        with np.errstate(divide='ignore', invalid='ignore'):
            t = -o[2] / d[:, 2]
        t = np.where(np.isfinite(t) & (t > 0) & (o[2] > 0), t, np.inf)
        n = np.zeros_like(d)
        n[:, 2] = 1.0
        return t, n


class Cylinder(Obstacle):
    kind = 'cylinder'

    def __init__(self, radius_m, height_m, **kw):
        super().__init__(**kw)
        self.r, self.hh = radius_m, height_m / 2

    def _sdf(self, p):
        rho = np.linalg.norm(p[:, :2], axis=1)
        dr, dz = rho - self.r, np.abs(p[:, 2]) - self.hh
        out_r, out_z = np.maximum(dr, 0), np.maximum(dz, 0)
        outside = np.hypot(out_r, out_z)
        inside = np.minimum(np.maximum(dr, dz), 0)
        d = outside + inside
        radial = _normalise(np.column_stack([p[:, :2], np.zeros(len(p))]))
        axial = np.zeros_like(p)
        axial[:, 2] = np.sign(p[:, 2]) + (p[:, 2] == 0)
        n_out = _normalise(out_r[:, None] * radial + out_z[:, None] * axial)
        n_in = np.where((dr > dz)[:, None], radial, axial)
        n = np.where((outside > 0)[:, None], n_out, n_in)
        return d, n

    def _sdf_hessian(self, p):
        # Rim (outside both): distance to the rim circle; side (outside radially, or
        # inside nearer the side): t t^T / rho; caps: flat.
        rho = np.hypot(p[:, 0], p[:, 1])
        if np.all((rho > self.r) & (np.abs(p[:, 2]) < self.hh)):
            # All beside the curved side (the usual contact): the distance to its circle.
            u = p[:, :2] / rho[:, None]
            n = np.zeros_like(p)
            n[:, :2] = u
            t = np.zeros_like(p)
            t[:, 0], t[:, 1] = -u[:, 1], u[:, 0]
            return rho - self.r, n, _outer(t, t) / rho[:, None, None]
        d, n = self._sdf(p)
        rho = np.maximum(np.hypot(p[:, 0], p[:, 1]), 1e-12)
        dr, dz = rho - self.r, np.abs(p[:, 2]) - self.hh
        rim = (dr > 0) & (dz > 0)
        side = ((dr > 0) & (dz <= 0)) | ((d <= 0) & (dr > dz))
        t = np.column_stack([-p[:, 1] / rho, p[:, 0] / rho, np.zeros(len(p))])
        H = (side / rho)[:, None, None] * _outer(t, t)
        if rim.any():
            pr = p[rim].copy()
            pr[:, 2] -= np.sign(pr[:, 2]) * self.hh
            H[rim] = _circle_hessian(pr, n[rim], d[rim], self.r)
        return d, n, H

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

    def __init__(self, major_radius_m, minor_radius_m, **kw):
        super().__init__(**kw)
        self.R0, self.r = major_radius_m, minor_radius_m

    def _sdf(self, p):
        rho = np.linalg.norm(p[:, :2], axis=1)
        radial = _normalise(np.column_stack([p[:, :2], np.zeros(len(p))]))
        centre = self.R0 * radial
        v = p - centre
        return np.linalg.norm(v, axis=1) - self.r, _normalise(v + 0.0 * rho[:, None])

    def _sdf_hessian(self, p):
        d, n = self._sdf(p)
        return d, n, _circle_hessian(p, n, d + self.r, self.R0)

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

    def _closest(self, p):
        """Return distance, normal, nearest-feature index (< 12: edge) and edge parameter."""
        # Exact distance: inside, the largest face distance; outside, the nearest point
        # among the face interiors and the 12 edges (C1 outside, so contact is smooth).
        # Distances come from (P, 12) and (P, 6) products; only the nearest feature's
        # point is built.
        if not hasattr(self, '_fa'):
            self._features()
        e = p @ self.normals.T - self.offsets
        inside_d = e.max(axis=1)
        pp = np.einsum('pi,pi->p', p, p)[:, None]
        dot = p @ self._eab.T - self._ea_eab                             # (p - a) . (b - a)
        t = np.clip(dot / self._eab2, 0.0, 1.0)
        rel2 = pp - 2.0 * (p @ self._ea.T) + self._ea2                   # |p - a|^2
        de = np.sqrt(np.maximum(rel2 - t * (2.0 * dot - t * self._eab2), 0.0))
        ab = (p @ self._fproj.T).reshape(-1, 6, 2) - self._fa_ab
        ok = ((ab >= 0) & (ab <= 1)).all(axis=2)
        h = p @ self._fn.T - self._fn_a                                 # to each face plane
        alld = np.concatenate([de, np.where(ok, np.abs(h), np.inf)], axis=1)
        k = np.argmin(alld, axis=1)
        rows = np.arange(len(p))
        ke = np.minimum(k, 11)
        kf = np.maximum(k - 12, 0)
        closest = np.where((k < 12)[:, None], self._ea[ke] + t[rows, ke, None] * self._eab[ke],
                           p - h[rows, kf, None] * self._fn[kf])
        outside = inside_d > 0
        d = np.where(outside, alld[rows, k], inside_d)
        n_out = _normalise(p - closest)
        n_in = self.normals[np.argmax(e, axis=1)]
        k = np.where(outside, k, 12)          # inside: a face (flat)
        return d, np.where(outside[:, None], n_out, n_in), k, t[rows, np.minimum(k, 11)]

    def _sdf(self, p):
        return self._closest(p)[:2]

    def _sdf_hessian(self, p):
        # Faces are flat; an edge's interior is a line (I - n n^T - e e^T) / d, its ends
        # vertices (I - n n^T) / d.
        d, n, k, t = self._closest(p)
        edge = k < 12
        H = np.zeros((len(p), 3, 3))
        if edge.any():
            ne = n[edge]
            Hm = np.eye(3) - _outer(ne, ne)
            ax = _normalise(self._eab[k[edge]])
            line = ((t[edge] > 0.0) & (t[edge] < 1.0))[:, None, None]
            H[edge] = (Hm - line * _outer(ax, ax)) / np.maximum(d[edge], 1e-12)[:, None, None]
        return d, n, H

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
    """Return the scene's object as an :class:`Obstacle` (None for no object)."""
    if scene is None or scene.object == 'none':
        return None
    kw = dict(position=scene.position_m, rpy=scene.rpy_rad)
    cls = {'sphere': Sphere, 'plane': Plane, 'cylinder': Cylinder, 'ring': Ring,
           'prism': Prism}[scene.object]
    return cls(**scene.dims, **kw)
