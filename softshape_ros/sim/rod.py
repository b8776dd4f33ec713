"""
Geometric-variable-strain Cosserat rod: strain basis, stiffness, kinematics and Jacobian.

Strain ``xi(X) = Phi(X) q + xi*`` with angular components first (SoRoSim order
``[k1, k2, k3, nu1, nu2, nu3]``, rest strain ``xi* = [0, 0, 0, 1, 0, 0]``). Each segment has
its two bending strains (k2, k3) on a Legendre basis of order ``order`` (order + 1 modes
each), optionally stretch (nu1) and shear (nu2, nu3) on the same basis. Torsion is not a
mode: nothing on this robot twists it (tendons, chambers and frictionless contact all act
through or parallel to the axis).

Forward kinematics: each segment is cut at its Gauss-Legendre points (the quadrature
nodes of the generalised forces); between consecutive nodes a 4th-order Magnus expansion
on the two Zanna points gives the step ``exp(Omega)``, and the body Jacobian follows from
the same pass, ``J+ = Ad_{exp(-Omega)} J + T(Omega) dOmega/dq``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softshape_ros.sim.lie import ad, ad_inv_pose, exp_dexp_se3, exp_se3, skew

XI_STAR = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
_Z1, _Z2 = 0.5 - np.sqrt(3.0) / 6.0, 0.5 + np.sqrt(3.0) / 6.0
_C4 = np.sqrt(3.0) / 12.0


@dataclass(frozen=True)
class RodSpec:
    """Geometry and material of a rod of segments in series (SI units)."""

    lengths: tuple
    radii: tuple
    youngs_modulus: float
    poisson_ratio: float = 0.5
    density: float = 0.0
    gravity: tuple = (0.0, 0.0, 0.0)
    order: int = 4
    shear: bool = False
    stretch: bool = False
    base: tuple = ((1.0, 0, 0, 0), (0, 1.0, 0, 0), (0, 0, 1.0, 0), (0, 0, 0, 1.0))
    n_gauss: int = 0           # Gauss nodes per segment; 0 = order + 4

    @classmethod
    def from_config(cls, robot, **overrides) -> 'RodSpec':
        """Build from ``RigConfig.robot`` (overrides: order, shear, stretch, gravity...)."""
        from softshape_ros.sim.lie import pose
        kw = dict(
            lengths=tuple(s.length_m for s in robot.segments),
            radii=tuple(s.radius_m for s in robot.segments),
            youngs_modulus=robot.youngs_modulus_pa, poisson_ratio=robot.poisson_ratio,
            density=robot.density_kg_m3, gravity=tuple(robot.gravity_m_s2),
            order=robot.basis_order, shear=robot.shear, stretch=robot.stretch,
            base=tuple(map(tuple, pose(robot.base_position_m, robot.base_rpy_rad))))
        kw.update(overrides)
        return cls(**kw)


@dataclass
class Kinematics:
    """One forward pass: poses and body Jacobians at the nodes, strains at the Gauss nodes."""

    q: np.ndarray
    g: np.ndarray          # (N, 4, 4) node poses (node 0 = base, then each interval end)
    J: np.ndarray          # (N, 6, n) body Jacobians at the nodes
    xi_gauss: np.ndarray   # (NG, 6) strain at the Gauss nodes


class Rod:
    """The discretised rod; stateless apart from precomputed basis tables."""

    def __init__(self, spec: RodSpec):
        if len(spec.lengths) != len(spec.radii) or not spec.lengths:
            raise ValueError('RodSpec: lengths and radii must be non-empty and equally long')
        self.spec = spec
        self.nseg = len(spec.lengths)
        self.lengths = np.asarray(spec.lengths, dtype=float)
        self.radii = np.asarray(spec.radii, dtype=float)
        self.offsets = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.length = float(self.offsets[-1])
        self.base = np.asarray(spec.base, dtype=float)
        self.gravity = np.asarray(spec.gravity, dtype=float)
        E, G = spec.youngs_modulus, spec.youngs_modulus / (2.0 * (1.0 + spec.poisson_ratio))
        self.comps = [1, 2] + ([3] if spec.stretch else []) + ([4, 5] if spec.shear else [])
        nm = spec.order + 1
        self.nmodes = nm
        self.dofs_per_seg = nm * len(self.comps)
        self._comp_rows = np.repeat(self.comps, nm)
        self._col_off = np.arange(nm * len(self.comps))
        self._mode_idx = np.tile(np.arange(nm), len(self.comps))
        # Legendre polynomials as monomial coefficients (columns): two numpy calls per
        # evaluation instead of a recurrence (per-call overhead dominates these sizes).
        self._legmono = np.zeros((nm, nm))
        for j in range(nm):
            c = np.polynomial.legendre.leg2poly(np.eye(nm)[j])
            self._legmono[:len(c), j] = c
        self._pow = np.arange(nm, dtype=float)
        self.n = self.dofs_per_seg * self.nseg
        # Section stiffness diag(GJ, EI, EI, EA, GA, GA) and the generalised stiffness K
        # (Legendre modes are orthogonal: int_0^L P_i P_j dX = L / (2j + 1) delta_ij).
        self.area = np.pi * self.radii ** 2
        inertia = np.pi * self.radii ** 4 / 4.0
        self.section = np.array([[G * 2 * i, E * i, E * i, E * a, G * a, G * a]
                                 for i, a in zip(inertia, self.area)])
        kdiag = np.zeros(self.n)
        for s in range(self.nseg):
            for ci, c in enumerate(self.comps):
                for j in range(nm):
                    kdiag[self._col(s, ci, j)] = (self.section[s, c] * self.lengths[s]
                                                  / (2 * j + 1))
        self.K = np.diag(kdiag)
        # Quadrature nodes and Magnus intervals.
        ng = spec.n_gauss or spec.order + 4
        xg, wg = np.polynomial.legendre.leggauss(ng)
        self.leg_x, self.leg_w = xg, wg           # the Gauss rule on [-1, 1], reused
        seg_i, a_loc, b_loc, gauss_X, gauss_w, gauss_seg, gauss_node = [], [], [], [], [], [], []
        node = 0
        for s, L in enumerate(self.lengths):
            pts = np.concatenate([[0.0], L * (xg + 1) / 2, [L]])
            for k in range(ng + 1):
                seg_i.append(s)
                a_loc.append(pts[k])
                b_loc.append(pts[k + 1])
                node += 1
                if k < ng:
                    gauss_X.append(self.offsets[s] + pts[k + 1])
                    gauss_w.append(L * wg[k] / 2)
                    gauss_seg.append(s)
                    gauss_node.append(node)
        self.int_seg = np.array(seg_i)
        self.int_a = np.array(a_loc)
        self.int_b = np.array(b_loc)
        self.int_h = self.int_b - self.int_a
        self.node_X = np.concatenate([[0.0], self.offsets[self.int_seg] + self.int_b])
        self.gauss_X = np.array(gauss_X)
        self.gauss_w = np.array(gauss_w)
        self.gauss_seg = np.array(gauss_seg)
        self.gauss_node = np.array(gauss_node)
        z1 = self.int_a + _Z1 * self.int_h
        z2 = self.int_a + _Z2 * self.int_h
        self.phi_z1 = self.phi(self.int_seg, z1)
        self.phi_z2 = self.phi(self.int_seg, z2)
        self.phi_g = self.phi(self.gauss_seg, self.gauss_X - self.offsets[self.gauss_seg])
        node_seg = np.concatenate([[0], self.int_seg])
        self.phi_nodes = self.phi(node_seg, self.node_X - self.offsets[node_seg])

    # -- basis -------------------------------------------------------------------------
    def _col(self, seg: int, comp_index: int, j: int) -> int:
        return seg * self.dofs_per_seg + comp_index * self.nmodes + j

    def phi(self, seg, x) -> np.ndarray:
        """Return Phi (P, 6, n) at local abscissae ``x`` of segments ``seg``."""
        seg = np.atleast_1d(np.asarray(seg, dtype=int))
        x = np.atleast_1d(np.asarray(x, dtype=float))
        P = ((2.0 * x / self.lengths[seg] - 1.0)[:, None] ** self._pow) @ self._legmono
        out = np.zeros((len(x), 6, self.n))
        rows = np.arange(len(x))[:, None]
        out[rows, self._comp_rows[None, :], (seg * self.dofs_per_seg)[:, None]
            + self._col_off[None, :]] = P[:, self._mode_idx]
        return out

    def locate(self, X) -> tuple:
        """Return (segment, local abscissa) of global arc lengths ``X`` (clipped to the rod)."""
        X = np.clip(np.atleast_1d(np.asarray(X, dtype=float)), 0.0, self.length)
        seg = np.clip(np.searchsorted(self.offsets, X, side='right') - 1, 0, self.nseg - 1)
        return seg, X - self.offsets[seg]

    def strain(self, q, X) -> np.ndarray:
        """Return xi (P, 6) at global arc lengths ``X``."""
        seg, x = self.locate(X)
        return self.phi(seg, x) @ q + XI_STAR

    # -- kinematics --------------------------------------------------------------------
    def _magnus(self, q, phi1, phi2, h, jac=True, adinv=True):
        x1 = phi1 @ q + XI_STAR
        x2 = phi2 @ q + XI_STAR
        hh = h[:, None]
        ad1 = ad(x1)
        omega = hh / 2 * (x1 + x2) + _C4 * hh ** 2 * np.einsum('mij,mj->mi', ad1, x2)
        if not jac:
            return exp_se3(omega), None, None
        E, AdInv, T = exp_dexp_se3(omega, adinv)
        ad2 = ad(x2)
        S = (hh[:, :, None] / 2 * (phi1 + phi2)
             + _C4 * hh[:, :, None] ** 2 * (ad1 @ phi2 - ad2 @ phi1))
        return E, AdInv, T @ S

    def forward(self, q, jac: bool = True) -> Kinematics:
        """Run the forward pass: node poses and (if ``jac``) body Jacobians."""
        q = np.asarray(q, dtype=float)
        E, _, TS = self._magnus(q, self.phi_z1, self.phi_z2, self.int_h, jac, adinv=False)
        m = len(self.int_h)
        # Poses relative to the base: a prefix product (log2(m) batched products instead
        # of m single ones; numpy's per-call cost dominates these sizes).
        gr = np.empty((m + 1, 4, 4))
        gr[0] = np.eye(4)
        gr[1:] = E
        step = 1
        while step <= m:
            gr[step:] = gr[:-step] @ gr[step:]
            step *= 2
        g = self.base @ gr
        J = None
        if jac:
            # Body Jacobian by its spatial (base-frame) form, a running sum:
            # J_s[k+1] = J_s[k] + Ad_{g_k+1} TS_k, then J[k] = Ad_{g_k}^-1 J_s[k].
            Rk, pk = gr[1:, :3, :3], gr[1:, :3, 3]
            Ad = np.zeros((m, 6, 6))
            Ad[:, :3, :3] = Rk
            Ad[:, 3:, 3:] = Rk
            Ad[:, 3:, :3] = skew(pk) @ Rk
            J = np.zeros((m + 1, 6, self.n))
            np.cumsum(Ad @ TS, axis=0, out=J[1:])
            J[1:] = ad_inv_pose(gr[1:]) @ J[1:]
        xi_g = self.phi_g @ q + XI_STAR
        return Kinematics(q=q, g=g, J=J, xi_gauss=xi_g)

    def at(self, kin: Kinematics, X, jac: bool = True):
        """Return poses (P, 4, 4) and, if ``jac``, body Jacobians (P, 6, n) at arc lengths X."""
        X = np.clip(np.atleast_1d(np.asarray(X, dtype=float)), 0.0, self.length)
        k = np.minimum(np.searchsorted(self.node_X, X), len(self.node_X) - 1)
        if np.all(self.node_X[k] == X):
            # All at nodes (a tip load): the forward pass has them already.
            return kin.g[k], (kin.J[k] if jac else None)
        # Interval m spans node m -> node m + 1.
        m = np.clip(np.searchsorted(self.node_X, X, side='right') - 1, 0, len(self.int_h) - 1)
        a = self.node_X[m]
        h = X - a
        seg = self.int_seg[m]
        xa = self.int_a[m]
        ph = self.phi(np.concatenate([seg, seg]), np.concatenate([xa + _Z1 * h, xa + _Z2 * h]))
        E, AdInv, TS = self._magnus(kin.q, ph[:len(X)], ph[len(X):], h, jac)
        g = kin.g[m] @ E
        if not jac:
            return g, None
        return g, AdInv @ kin.J[m] + TS

    def positions(self, kin: Kinematics, X) -> np.ndarray:
        """Return backbone points (P, 3) at arc lengths ``X`` (no Jacobian)."""
        return self.at(kin, X, jac=False)[0][:, :3, 3]
