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

Where the robot lies along an object (flat gap profile) the minima come and go in pairs
with a maximum between them; the penalty at each such interior maximum ("ridge") is
subtracted, so the potential is the rise of the penalty along the backbone and stays
continuous (and the force too) when a pair appears. Apart from such line contacts
the ridges are outside the cutoff and the model is the paper's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import spence

from softshape_ros.sim.lie import ad, cross, skew
from softshape_ros.sim.rod import XI_STAR
from softshape_ros.sim.statics import LoadTerm

DEFAULT_STIFFNESS_N_M = 2.0e4
DEFAULT_SMOOTHING_M = 2.0e-5
STIFFENING_DEPTH_M = 2.0e-4     # p0: the penalty doubles its stiffness at 0.2 mm
_NEAR_M = 3e-3          # refine minima of sampled gaps below this (samples <= 4.5 mm apart)
_SUB = 8                # gap slope samples per node interval (<= 0.6 mm apart)
# A Newton step may press a free node (or a lifted contact) this deep, linearised: one
# smoothing length. At 0.1 mm the penalty overshoots (~3 N, tangent indefinite) and the next
# step jumps back out.
STEP_DEPTH_M = 2e-5
# Polish steps up to this long move the contact frame to first order (error ~1e-12 m);
# longer ones (1 in 10) evaluate the rod there again.
_MOVE_M = 1e-7
_POLISH_STEPS = 4       # exact-rod Newton steps at most (a flat gap takes 2-3)
_CUTOFF = 30.0          # gaps beyond 30 smoothing lengths carry no force (< 1e-13 k delta)
# Quintic Hermite basis (rows) in powers of s: control values p0, h p0', h^2 p0'', h^2 p1'',
# h p1', p1. With the exact curvature at the nodes its minimiser is ~1e-8 m from the rod's.
_QUINTIC = np.array([[1, 0, 0, -10, 15, -6], [0, 1, 0, -6, 8, -3],
                     [0, 0, 0.5, -1.5, 1.5, -0.5], [0, 0, 0, 0.5, -1, 0.5],
                     [0, 0, 0, -4, 7, -3], [0, 0, 0, 10, -15, 6]], dtype=float)
_POW = np.arange(6.0)
_DPOW = np.arange(2.0, 6.0) * np.arange(1.0, 5.0)
_S_SUB = np.arange(_SUB) / _SUB
_W_SUB = (_S_SUB[:, None] ** _POW) @ _QUINTIC.T                          # p at the samples
_DW_SUB = ((_S_SUB[:, None] ** _POW)[:, :5] * _POW[1:]) @ _QUINTIC[:, 1:].T   # dp/ds


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
    ridge: bool = False     # a gap maximum between two contacts: its force is subtracted

    def to_dict(self) -> dict:
        return {'s_m': self.s_m, 'point_m': self.point_m.tolist(),
                'normal': self.normal.tolist(), 'force_n': self.force_n.tolist(),
                'gap_m': self.gap_m, 'penetration_m': max(0.0, -self.gap_m),
                'object': self.object_index, 'ridge': self.ridge}


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
        self._grid_cache = None

    def step_constraints(self, rod, kin, info=None, depth: float = STEP_DEPTH_M):
        """
        Return (A, lo): linearised gaps that a Newton step must keep, ``A dq >= lo``.

        Each node now outside may press at most ``depth`` in (``gap + a dq >= -depth``):
        a full Newton step from a free or touching shape otherwise swings the rest of the
        tube deep into the object, where the stiffening penalty overshoots and the line
        search backtracks through several assemblies. Each contact may press to
        ``depth`` or double its penetration: where it lifts off its penalty is nearly
        flat and the Newton model alone would send it millimetres deep.
        """
        rows, lo = [], []
        if info and info.get('contacts'):
            gap = np.array([c.gap_m for c in info['contacts']])
            keep = ~np.array([c.ridge for c in info['contacts']])
            rows.append(info['gap_grad'][keep])
            lo.append(np.minimum(2.0 * gap[keep], -depth) - gap[keep])
        for gap, n in self.node_gaps(rod, kin):
            k = np.nonzero(gap > 0)[0]
            if len(k):
                rows.append((n[k, None, :] @ kin.g[k, :3, :3] @ kin.J[k, 3:, :])[:, 0, :])
                lo.append(-depth - gap[k])
        if not rows:
            return np.zeros((0, rod.n)), np.zeros(0)
        return np.vstack(rows), np.concatenate(lo)

    def node_gaps(self, rod, kin):
        """Return (gap (N,), normal (N, 3)) of the tube at the nodes, for each object."""
        pts = kin.g[:, :3, 3]
        rad = self._grid(rod)[4]
        out = []
        for obj in self.obstacles:
            d, n = obj.sdf(pts)
            out.append((d - rad, n))
        return out

    @staticmethod
    def _hermite(C, X0, h, x):
        """Return p, p', p'' (P, 3) at x of the quintic Hermite backbone on [X0, X0 + h]."""
        pw = ((x - X0) / h)[:, None] ** _POW                             # (P, 6)
        # Basis weights for p, p', p'' (P, 6 each) on the control values C (P, 6, 3).
        w = pw @ _QUINTIC.T
        dw = (pw[:, :5] * _POW[1:]) @ _QUINTIC[:, 1:].T
        ddw = (pw[:, :4] * _DPOW) @ _QUINTIC[:, 2:].T
        return (np.einsum('pk,pkj->pj', w, C), np.einsum('pk,pkj->pj', dw, C) / h[:, None],
                np.einsum('pk,pkj->pj', ddw, C) / (h * h)[:, None])

    def _grid(self, rod):
        """
        Return the sample arc lengths and tube radii, the sampling matrices, node radii.

        Samples are the nodes and the Hermite points between. Positions and slopes there
        are linear in the node positions, tangents and curvatures stacked as (3N, 3):
        ``Pa = MP @ [P; T; A]``, ``Ta = MT @ [P; T; A]`` (one product each).
        """
        if self._grid_cache is None or self._grid_cache[0] is not rod:
            Xs = rod.node_X
            h = np.diff(Xs)
            Xa = np.append((Xs[:-1, None] + h[:, None] * _S_SUB).ravel(), Xs[-1])
            N, m = len(Xs), len(h)
            MP = np.zeros((m * _SUB + 1, 3 * N))
            MT = np.zeros((m * _SUB + 1, 3 * N))
            for i in range(m):
                r = slice(i * _SUB, (i + 1) * _SUB)
                # Control values p0, h p0', h^2 p0'', h^2 p1'', h p1', p1 -> columns.
                for k, (col, scale) in enumerate([(i, 1.0), (N + i, h[i]), (2 * N + i, h[i] ** 2),
                                                  (2 * N + i + 1, h[i] ** 2),
                                                  (N + i + 1, h[i]), (i + 1, 1.0)]):
                    MP[r, col] += _W_SUB[:, k] * scale
                    MT[r, col] += _DW_SUB[:, k] * scale / h[i]
            MP[-1, N - 1] = 1.0
            MT[-1, 2 * N - 1] = 1.0
            self._grid_cache = (rod, Xa, rod.radii[rod.locate(Xa)[0]], MP, MT,
                                rod.radii[rod.locate(Xs)[0]])
        return self._grid_cache[1:]

    def find(self, rod, kin):
        """
        Return the gap's critical points near the objects: X, object, sign, bracket.

        sign +1: a minimum (or the tip when the gap falls towards it), -1: an interior
        maximum. Brackets come from sign changes of the gap's slope at the nodes and the
        Hermite points between (<= 0.6 mm apart), so the result depends on q only.
        """
        Xs = rod.node_X
        P = kin.g[:, :3, 3]
        xi = rod.phi_nodes @ kin.q + XI_STAR
        R = kin.g[:, :3, :3]
        T = np.einsum('kij,kj->ki', R, xi[:, 3:])
        A = np.einsum('kij,kj->ki', R, cross(xi[:, :3], xi[:, 3:]))
        # Nodes and _SUB - 1 Hermite points inside each interval (fixed weights).
        Xa, rad, MP, MT, _ = self._grid(rod)
        PTA = np.concatenate([P, T, A])
        Pa, Ta = MP @ PTA, MT @ PTA
        h = C = None
        out = []
        for oi, obj in enumerate(self.obstacles):
            d, nrm = obj.sdf(Pa)
            gap = d - rad
            slope = np.einsum('ki,ki->k', nrm, Ta)
            up = slope >= 0
            near = np.minimum(gap[:-1], gap[1:]) < _NEAR_M
            is_min = ~up[:-1] & up[1:] & near
            is_max = up[:-1] & ~up[1:] & near
            k = np.nonzero(is_min | is_max)[0]
            if len(k):
                if C is None:
                    # Control values p0, h p0', h^2 p0'', h^2 p1'', h p1', p1 (m, 6, 3).
                    h = np.diff(Xs)
                    hh = h[:, None]
                    C = np.stack([P[:-1], T[:-1] * hh, A[:-1] * hh * hh, A[1:] * hh * hh,
                                  T[1:] * hh, P[1:]], axis=1)
                sign = np.where(is_min[k], 1.0, -1.0)
                x = self._refine(obj, (Xs, h, C), Xa, slope, k, sign)
                out += [(xx, oi, sg, a, b) for xx, sg, a, b in zip(x, sign, Xa[k], Xa[k + 1])]
            if not up[-1] and gap[-1] < _NEAR_M:
                out.append((rod.length, oi, 1.0, rod.length, rod.length))
        return out

    def _refine(self, obj, nodes, Xa, slope, k, sign):
        """
        Solve d phi(p(X)) / dX = 0 in each bracket [Xa[k], Xa[k + 1]] (safeguarded Newton).

        p(X) is the quintic Hermite interpolant of the backbone at the nodes (positions,
        tangents and curvatures), so no kinematics per step.
        """
        Xs, h, C = nodes
        lo, hi = Xa[k].copy(), Xa[k + 1].copy()
        iv = k // _SUB
        args = (C[iv], Xs[iv], h[iv])
        sa, sb = slope[k], slope[k + 1]
        den = np.where(sa != sb, sa - sb, 1.0)
        x = np.clip(lo + (hi - lo) * np.where(sa != sb, sa / den, 0.5), lo, hi)
        for _ in range(40):
            p, dp, ddp = self._hermite(*args, x)
            _, n, H = obj.sdf_hessian(p)
            d1 = np.einsum('pi,pi->p', n, dp)
            d2 = (np.einsum('pi,pi->p', dp, np.einsum('pij,pj->pi', H, dp))
                  + np.einsum('pi,pi->p', n, ddp))
            right = sign * d1 < 0
            lo = np.where(right, x, lo)
            hi = np.where(right, hi, x)
            good = sign * d2 > 1e-12
            newton = x - d1 / np.where(good, d2, 1.0)
            ok = good & (newton >= lo) & (newton <= hi)
            xn = np.where(ok, newton, 0.5 * (lo + hi))
            # A Newton step under 1e-10 m leaves x ~1e-17 m from the root (quadratic).
            done = (ok & (np.abs(xn - x) < 1e-10)) | (hi - lo < 1e-13)
            x = xn
            if done.all():
                break
        return x

    def _sdf_hessian(self, oi, p):
        """Return distance, normal and Hessian at points ``p`` of the objects ``oi``."""
        d = np.zeros(len(p))
        nn = np.zeros((len(p), 3))
        H = np.zeros((len(p), 3, 3))
        for o, obj in enumerate(self.obstacles):
            m = oi == o
            if m.all():
                return obj.sdf_hessian(p)
            if m.any():
                d[m], nn[m], H[m] = obj.sdf_hessian(p[m])
        return d, nn, H

    def _at(self, rod, kin, X, oi):
        """Return the rod and the object at arc lengths X: frames, strain and distance."""
        g, J = rod.at(kin, X)
        seg, xloc = rod.locate(X)
        phi = rod.phi(seg, xloc)
        xi = phi @ kin.q + XI_STAR
        d, nn, H = self._sdf_hessian(oi, g[:, :3, 3])
        return [g, J, phi, xi, seg, d, nn, H]

    def _polish(self, rod, kin, X, oi, sign, lo, hi):
        """
        Newton on the exact rod from the Hermite minimiser: return X and the state there.

        The Hermite minimiser is ~1e-8 m from the rod's, so one step is usually enough and
        the frame, Jacobian and distance move there to first order (error ~1e-12 m, no
        second rod evaluation; the strain-based sliding terms, tangent only, stay). A step
        longer than 0.1 um (a flat gap profile, the robot lying along the object)
        evaluates the rod there and steps again: the tangent's sliding term is exact at
        the rod's own gap minimum only, and left short of it Newton converges linearly.
        """
        state = self._at(rod, kin, X, oi)
        g, J, phi, xi, seg, d, nn, H = state
        R = g[:, :3, :3]
        tv, pp, Htv, gxx = self._along(R, xi, nn, H)
        dX = self._newton_dX(X, nn, tv, gxx, sign, lo, hi, rod.length)
        far = np.abs(dX) > _MOVE_M
        if far.any():
            rows = np.nonzero(far)[0]
            for sweep in range(_POLISH_STEPS):
                X[rows] += dX[rows]
                sub = self._at(rod, kin, X[rows], oi[rows])
                for a, v in zip(state, sub):
                    a[rows] = v
                tv[rows], pp[rows], Htv[rows], gxx[rows] = self._along(
                    g[rows, :3, :3], xi[rows], nn[rows], H[rows])
                dX[rows] = self._newton_dX(X[rows], nn[rows], tv[rows], gxx[rows],
                                           sign[rows], lo[rows], hi[rows], rod.length)
                if sweep == _POLISH_STEPS - 1:
                    dX[rows] = 0.0
                rows = rows[np.abs(dX[rows]) > _MOVE_M]
                if not len(rows):
                    break
        if np.any(dX != 0.0):
            c = dX[:, None]
            dp = c * tv
            J = J + c[:, :, None] * (phi - ad(xi) @ J)
            g = g.copy()
            g[:, :3, :3] += c[:, :, None] * (R @ skew(xi[:, :3]))
            g[:, :3, 3] += dp
            d = d + np.einsum('pi,pi->p', nn, dp)
            nn = nn + np.einsum('pij,pj->pi', H, dp)
            X = X + dX
        return X, (g, J, phi, xi, seg, d, nn, H, tv, Htv, gxx)

    @staticmethod
    def _along(R, xi, nn, H):
        """Return p', p'' (strain-based), H p' and the gap's d2/dX2 at contact frames R."""
        tv = np.einsum('pij,pj->pi', R, xi[:, 3:])
        pp = np.einsum('pij,pj->pi', R, cross(xi[:, :3], xi[:, 3:]))
        Htv = np.einsum('pij,pj->pi', H, tv)
        return tv, pp, Htv, np.einsum('pi,pi->p', tv, Htv) + np.einsum('pi,pi->p', nn, pp)

    @staticmethod
    def _newton_dX(X, nn, tv, gxx, sign, lo, hi, length):
        """Return the Newton step on d phi(p(X)) / dX = 0, kept in the bracket."""
        d1 = np.einsum('pi,pi->p', nn, tv)
        good = (X < length - 1e-12) & (sign * gxx > 1e-12)
        return np.where(good, np.clip(X - d1 / np.where(good, gxx, 1.0), lo, hi) - X, 0.0)

    def __call__(self, rod, kin):
        """
        Return the contact load term and info (contacts, penetration, potential).

        The potential is the rise of the penalty along the backbone from the base: the
        penalty at every gap minimum minus that at every interior gap maximum. A robot
        lying along an object then keeps a continuous potential (and force) when its flat
        gap profile grows a new minimum-maximum pair, where counting minima alone jumps by
        a whole contact and Newton cannot settle (a tube along the parallel cylinder).
        """
        cands = self.find(rod, kin)
        info = {'contacts': [], 'max_penetration_m': 0.0, 'energy': 0.0}
        if not cands:
            return None, info
        X = np.array([c[0] for c in cands])
        oi = np.array([c[1] for c in cands])
        sign = np.array([c[2] for c in cands])
        lo = np.array([c[3] for c in cands])
        hi = np.array([c[4] for c in cands])
        X, (g, J, phi, xi, seg, d, nn, H, tv, Htv, gxx) = self._polish(rod, kin, X, oi, sign,
                                                                       lo, hi)
        R, p = g[:, :3, :3], g[:, :3, 3]
        rad = rod.radii[seg]
        gap = d - rad
        k = np.nonzero(gap <= _CUTOFF * self.delta)[0]
        if not len(k):
            return None, info
        X, g, J, p, rad, phi, xi = X[k], g[k], J[k], p[k], rad[k], phi[k], xi[k]
        nn, H, gap, sign, oi = nn[k], H[k], gap[k], sign[k], oi[k]
        R, tv, Htv, gxx = R[k], tv[k], Htv[k], gxx[k]
        z = -gap / self.delta
        pen = self.delta * _softplus(z)
        lam = self.k * pen * (1.0 + pen / STIFFENING_DEPTH_M)
        dlam = -self.k * _sigmoid(z) * (1.0 + 2.0 * pen / STIFFENING_DEPTH_M)
        f = (sign * lam)[:, None] * nn
        dfdp = (sign * dlam)[:, None, None] * nn[:, :, None] * nn[:, None, :] \
            + (sign * lam)[:, None, None] * H
        # The contact point slides with q (a critical point of the gap over X): the
        # min-function's Hessian adds lambda * gXq^T gXq / gXX to the tangent.
        slide = (X < rod.length - 1e-12) & (sign * gxx > 1e-9)
        extra_k = np.zeros((rod.n, rod.n))
        if slide.any():
            s = np.nonzero(slide)[0]
            D = R[s] @ J[s, 3:, :]
            dt = R[s] @ (-skew(xi[s, 3:]) @ J[s, :3, :] + phi[s, 3:, :])
            gxq = np.einsum('pi,pin->pn', Htv[s], D) \
                + np.einsum('pi,pin->pn', nn[s], dt)
            extra_k = (gxq * (sign[s] * lam[s] / gxx[s])[:, None]).T @ gxq
        # Potential of the stiffening part taken unsmoothed (it only serves as a merit).
        e = penalty_energy(gap, self.k, self.delta) \
            + self.k * np.maximum(0.0, -gap) ** 3 / (3 * STIFFENING_DEPTH_M)
        info['energy'] = float(sign @ e)
        for j in range(len(X)):
            info['contacts'].append(Contact(float(X[j]), p[j].copy(), p[j] - rad[j] * nn[j],
                                            nn[j].copy(), f[j].copy(), float(gap[j]),
                                            int(oi[j]), bool(sign[j] < 0)))
        info['max_penetration_m'] = max(0.0, float(-gap.min()))
        info['gap_grad'] = (nn[:, None, :] @ R @ J[:, 3:, :])[:, 0, :]
        return LoadTerm(X, g, J, f, np.zeros((len(X), 3)), dfdp, extra_k), info
