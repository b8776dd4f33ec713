"""
Frictionless contact between the robot (a tube of its real radius, rounded tip) and rigid objects.

Model (the paper's): each object pushes on the robot with concentrated forces. For every
local minimum along the backbone of the gap ``gamma(X) = phi(p(X)) - r`` (phi: the object's
signed distance) the contact point is refined to the true minimiser ``X_c`` by Newton on
``d phi(p(X)) / dX = 0`` (not snapped to a node), and a smooth penalty force
``f = k pen (1 + pen / p0) grad phi``, ``pen = delta softplus(-gamma / delta)`` (a smooth
penetration), acts there along the surface normal; it stiffens with depth so the robot
stays within a fraction of a millimetre of the surface even when pressed hard.
The normal passes through the backbone, so the force is applied at ``p(X_c)`` with no
moment. Its Jacobian ``df/dp = lambda' n n^T + lambda H`` goes into the Newton tangent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import spence

from softshape_ros.sim.lie import cross, skew
from softshape_ros.sim.statics import LoadTerm

DEFAULT_STIFFNESS_N_M = 2.0e4
DEFAULT_SMOOTHING_M = 2.0e-5
STIFFENING_DEPTH_M = 2.0e-4     # p0: the penalty doubles its stiffness at 0.2 mm
_NEAR_M = 3e-3          # refine minima of sampled gaps below this (samples <= 4.5 mm apart)
_CUTOFF = 30.0          # gaps beyond 30 smoothing lengths carry no force (< 1e-13 k delta)


@dataclass
class Contact:
    """One contact: arc length, backbone point, surface point, normal, force, gap."""

    s_m: float
    backbone_m: np.ndarray
    point_m: np.ndarray
    normal: np.ndarray
    force_n: np.ndarray
    gap_m: float
    object_index: int

    def to_dict(self) -> dict:
        return {'s_m': self.s_m, 'point_m': self.point_m.tolist(),
                'normal': self.normal.tolist(), 'force_n': self.force_n.tolist(),
                'gap_m': self.gap_m, 'penetration_m': max(0.0, -self.gap_m),
                'object': self.object_index}


def _softplus(x):
    return np.where(x > 30, x, np.log1p(np.exp(np.minimum(x, 30))))


def penalty_energy(gap, k, delta):
    """Return the penalty potential int_gap^inf lambda: k delta^2 (-Li2(-e^z)), z = -gap/delta."""
    z = -np.asarray(gap, dtype=float) / delta
    big = z > 30
    zs = np.where(big, 0.0, z)
    small = -spence(1.0 + np.exp(zs))
    large = z ** 2 / 2 + np.pi ** 2 / 6 - np.exp(-np.where(big, z, 30.0))
    return k * delta ** 2 * np.where(big, large, small)


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


class ContactModel:
    """Callable used by :meth:`Statics.assemble`: ``(rod, kin) -> (LoadTerm, info)``."""

    def __init__(self, obstacles, stiffness: float = DEFAULT_STIFFNESS_N_M,
                 smoothing: float = DEFAULT_SMOOTHING_M):
        self.obstacles = [o for o in obstacles if o is not None]
        self.k, self.delta = float(stiffness), float(smoothing)
        self._last = []         # contact arc lengths of the previous call: warm starts

    @staticmethod
    def _hermite(Xs, P, T, x):
        """Return p, p', p'' at x of the cubic Hermite backbone through samples (P, T)."""
        i = int(np.clip(np.searchsorted(Xs, x, side='right') - 1, 0, len(Xs) - 2))
        h = Xs[i + 1] - Xs[i]
        s = (x - Xs[i]) / h
        p0, p1, m0, m1 = P[i], P[i + 1], T[i] * h, T[i + 1] * h
        h00, h10, h01, h11 = (2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s,
                              -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2)
        d00, d10, d01, d11 = (6 * s ** 2 - 6 * s, 3 * s ** 2 - 4 * s + 1, -6 * s ** 2 + 6 * s,
                              3 * s ** 2 - 2 * s)
        e00, e10, e01, e11 = 12 * s - 6, 6 * s - 4, -12 * s + 6, 6 * s - 2
        p = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
        dp = (d00 * p0 + d10 * m0 + d01 * p1 + d11 * m1) / h
        ddp = (e00 * p0 + e10 * m0 + e01 * p1 + e11 * m1) / h ** 2
        return p, dp, ddp

    def _refine(self, Xs, P, T, obj, lo, hi, x0):
        """
        Minimise phi(p(X)) on [lo, hi] from x0 by safeguarded Newton; return X.

        p(X) is the cubic Hermite interpolant of the backbone at the nodes (positions and
        tangents <= 4.5 mm apart: within ~1e-10 m of the rod), so no kinematics per step.
        """
        x = x0
        for _ in range(30):
            p, dp, ddp = self._hermite(Xs, P, T, x)
            _, n, H = obj.sdf_hessian(p[None])
            d1 = float(n[0] @ dp)
            d2 = float(dp @ H[0] @ dp + n[0] @ ddp)
            if d2 > 1e-12:
                step = -d1 / d2
            else:
                step = -np.sign(d1) * 0.25 * (hi - lo)
            xn = min(max(x + step, lo), hi)
            if abs(xn - x) < 1e-13:
                x = xn
                break
            x = xn
        return x

    def find(self, rod, kin):
        """Return contacts as (X, object index) candidates, refined to the gap minima."""
        # Samples: the kinematic nodes (free from the forward pass), <= 4.5 mm apart.
        Xs = rod.node_X
        g = kin.g
        pts = g[:, :3, 3]
        nu = (rod.phi_nodes[:, 3:, :] @ kin.q) + np.array([1.0, 0.0, 0.0])
        tangents = np.einsum('kij,kj->ki', g[:, :3, :3], nu)
        seg, _ = rod.locate(Xs)
        rad = rod.radii[seg]
        found = []
        for oi, obj in enumerate(self.obstacles):
            gap = obj.sdf(pts)[0] - rad
            n = len(Xs)
            for i in range(1, n):
                left = gap[i - 1] if i > 0 else np.inf
                right = gap[i + 1] if i + 1 < n else np.inf
                if not (gap[i] <= left and gap[i] < right):
                    continue
                if gap[i] > _NEAR_M:
                    continue
                lo, hi = Xs[i - 1], Xs[min(i + 1, n - 1)]
                x0 = Xs[i]
                for xl, ol in self._last:
                    if ol == oi and lo < xl < hi:
                        x0 = xl
                x = self._refine(Xs, pts, tangents, obj, lo, hi, x0)
                found.append((x, oi))
        self._last = found
        return found

    def __call__(self, rod, kin):
        cands = self.find(rod, kin)
        info = {'contacts': [], 'max_penetration_m': 0.0, 'energy': 0.0}
        if not cands:
            return None, info
        X = np.array([c[0] for c in cands])
        g, J = rod.at(kin, X)
        p = g[:, :3, 3]
        seg, _ = rod.locate(X)
        rad = rod.radii[seg]
        f = np.zeros((len(X), 3))
        dfdp = np.zeros((len(X), 3, 3))
        extra_k = np.zeros((rod.n, rod.n))
        xi = rod.strain(kin.q, X)
        phi = rod.phi(*rod.locate(X))
        keep = []
        for j, (x, oi) in enumerate(cands):
            obj = self.obstacles[oi]
            d, n, H = obj.sdf_hessian(p[j][None])
            H = H[0]
            gap = float(d[0]) - rad[j]
            if gap > _CUTOFF * self.delta:
                continue
            z = -gap / self.delta
            pen = self.delta * float(_softplus(z))
            lam = self.k * pen * (1.0 + pen / STIFFENING_DEPTH_M)
            dlam = -self.k * float(_sigmoid(z)) * (1.0 + 2.0 * pen / STIFFENING_DEPTH_M)
            nn = n[0]
            f[j] = lam * nn
            dfdp[j] = dlam * np.outer(nn, nn) + lam * H
            if x < rod.length - 1e-12:
                # The contact point slides with q (gap minimum over X): the min-function's
                # Hessian adds lambda * gXq^T gXq / gXX to the tangent.
                Rj = g[j, :3, :3]
                tv = Rj @ xi[j, 3:]
                gxx = float(tv @ H @ tv + nn @ (Rj @ cross(xi[j, :3], xi[j, 3:])))
                if gxx > 1e-9:
                    D = Rj @ J[j, 3:, :]
                    dt = Rj @ (-skew(xi[j, 3:]) @ J[j, :3, :] + phi[j, 3:, :])
                    gxq = (H @ tv) @ D + nn @ dt
                    extra_k += lam * np.outer(gxq, gxq) / gxx
            keep.append(j)
            # Potential of the stiffening part taken unsmoothed (it only serves as a merit).
            info['energy'] += float(penalty_energy(gap, self.k, self.delta)
                                    + self.k * max(0.0, -gap) ** 3 / (3 * STIFFENING_DEPTH_M))
            info['contacts'].append(Contact(float(x), p[j].copy(), p[j] - rad[j] * nn, nn.copy(),
                                            f[j].copy(), gap, oi))
            info['max_penetration_m'] = max(info['max_penetration_m'], -gap)
        if not keep:
            return None, info
        k = np.array(keep)
        return LoadTerm(X[k], g[k], J[k], f[k], np.zeros((len(k), 3)), dfdp[k], extra_k), info
