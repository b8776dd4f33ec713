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
the same pass, ``J+ = Ad_{exp(-Omega)} J + T(Omega) dOmega/dq`` (``kernels.forward``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softshape_ros.sim import kernels

XI_STAR = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
BENDING, STRETCH, SHEAR = (1, 2), (3,), (4, 5)     # strain components of each kind of mode


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
    J: np.ndarray | None   # (N, 6, n) body Jacobians at the nodes (None: not computed)
    xi_gauss: np.ndarray   # (K, 6) strain at the Gauss nodes


class Rod:
    """The discretised rod; stateless apart from precomputed basis tables."""

    def __init__(self, spec: RodSpec):
        if len(spec.lengths) != len(spec.radii) or not spec.lengths:
            raise ValueError('RodSpec: lengths and radii must be non-empty and equally long')
        values = np.array([*spec.lengths, *spec.radii, spec.youngs_modulus], dtype=float)
        if not np.all(np.isfinite(values)) or np.any(values <= 0):
            raise ValueError(f'RodSpec: lengths, radii and the modulus must be positive, '
                             f'got {spec}')
        if int(spec.order) < 0:
            raise ValueError(f'RodSpec: basis order must be >= 0, got {spec.order}')
        self.spec = spec
        self.nseg = len(spec.lengths)
        self.lengths = np.asarray(spec.lengths, dtype=float)
        self.radii = np.asarray(spec.radii, dtype=float)
        self.offsets = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.length = float(self.offsets[-1])
        self.base = np.asarray(spec.base, dtype=float)
        self.gravity = np.asarray(spec.gravity, dtype=float)
        self.comps = list(BENDING) + (list(STRETCH) if spec.stretch else []) \
            + (list(SHEAR) if spec.shear else [])
        self.nmodes = spec.order + 1
        self.dofs_per_seg = self.nmodes * len(self.comps)
        self.n = self.dofs_per_seg * self.nseg
        self._stiffness()
        self._quadrature(spec.n_gauss or spec.order + 4)
        self.phi_g = self.phi(self.gauss_seg, self.gauss_X - self.offsets[self.gauss_seg])

    def _stiffness(self) -> None:
        """Section stiffness diag(GJ, EI, EI, EA, GA, GA) and the generalised stiffness K."""
        E = self.spec.youngs_modulus
        G = E / (2.0 * (1.0 + self.spec.poisson_ratio))
        self.area = np.pi * self.radii ** 2
        inertia = np.pi * self.radii ** 4 / 4.0
        self.section = np.array([[G * 2 * i, E * i, E * i, E * a, G * a, G * a]
                                 for i, a in zip(inertia, self.area)])
        # Legendre modes are orthogonal: int_0^L P_i P_j dX = L / (2j + 1) delta_ij.
        nm = self.nmodes
        self.kdiag = np.array([self.section[s, c] * self.lengths[s] / (2 * j + 1)
                               for s in range(self.nseg) for c in self.comps
                               for j in range(nm)])
        self.K = np.diag(self.kdiag)

    def _quadrature(self, ng: int) -> None:
        """Gauss nodes per segment, the Magnus intervals between them and the kernels' tables."""
        xg, wg = np.polynomial.legendre.leggauss(ng)
        self.leg_x, self.leg_w = xg, wg           # the Gauss rule on [-1, 1], reused
        # Per segment: interval ends at 0, the ng Gauss points, L; node k + 1 ends interval k.
        pts = [np.concatenate([[0.0], L * (xg + 1) / 2, [L]]) for L in self.lengths]
        self.int_seg = np.repeat(np.arange(self.nseg), ng + 1)
        self.int_a = np.concatenate([p[:-1] for p in pts])
        self.int_b = np.concatenate([p[1:] for p in pts])
        self.int_h = self.int_b - self.int_a
        self.node_X = np.concatenate([[0.0], self.offsets[self.int_seg] + self.int_b])
        self.gauss_seg = np.repeat(np.arange(self.nseg), ng)
        self.gauss_X = np.concatenate([self.offsets[s] + p[1:-1] for s, p in enumerate(pts)])
        self.gauss_w = np.concatenate([L * wg / 2 for L in self.lengths])
        self.gauss_node = np.concatenate([s * (ng + 1) + 1 + np.arange(ng)
                                          for s in range(self.nseg)])
        node_seg = np.concatenate([[0], self.int_seg])
        self.layout = kernels.RodTables(
            seg_len=self.lengths, offsets=self.offsets, radii=self.radii,
            comps=np.array(self.comps, dtype=np.int64), n_modes=int(self.nmodes),
            base=self.base, node_X=self.node_X, node_seg=node_seg.astype(np.int64),
            int_seg=self.int_seg.astype(np.int64), int_a=self.int_a, int_h=self.int_h,
            gauss_X=self.gauss_X, gauss_node=self.gauss_node.astype(np.int64),
            gauss_seg=self.gauss_seg.astype(np.int64), gauss_w=self.gauss_w,
            rule_x=xg, rule_w=wg)
        self.tables = kernels.pack_tables(self.layout)     # (tf, ti), as kernels take them

    # -- basis -------------------------------------------------------------------------
    def phi(self, seg, x) -> np.ndarray:
        """Return Phi (P, 6, n) at local abscissae ``x`` of segments ``seg``."""
        seg = np.atleast_1d(np.asarray(seg, dtype=np.int64))
        x = np.atleast_1d(np.asarray(x, dtype=float))
        return kernels.basis_matrices(*self.tables, seg, x, self.n)

    def locate(self, X) -> tuple:
        """Return (segment, local abscissa) of global arc lengths ``X`` (clipped to the rod)."""
        X = np.clip(np.atleast_1d(np.asarray(X, dtype=float)), 0.0, self.length)
        seg = np.clip(np.searchsorted(self.offsets, X, side='right') - 1, 0, self.nseg - 1)
        return seg, X - self.offsets[seg]

    def strain(self, q, X) -> np.ndarray:
        """Return xi (P, 6) at global arc lengths ``X``."""
        return kernels.strains(*self.tables, np.asarray(q, dtype=float),
                               np.atleast_1d(np.asarray(X, dtype=float)))

    # -- kinematics --------------------------------------------------------------------
    def forward(self, q, jac: bool = True) -> Kinematics:
        """Run the forward pass: node poses and (if ``jac``) body Jacobians."""
        q = np.ascontiguousarray(q, dtype=float)
        g, J, xi = kernels.forward(*self.tables, q, jac)
        return Kinematics(q=q, g=g, J=J if jac else None, xi_gauss=xi)

    def at(self, kin: Kinematics, X, jac: bool = True):
        """Return poses (P, 4, 4) and, if ``jac``, body Jacobians (P, 6, n) at arc lengths X."""
        X = np.atleast_1d(np.asarray(X, dtype=float))
        if jac and kin.J is None:
            raise ValueError('Rod.at: Jacobians asked of a forward pass run without them')
        J_nodes = kin.J if kin.J is not None else np.zeros((0, 6, self.n))
        g, J = kernels.point_frames(*self.tables, kin.q, kin.g, J_nodes, X, jac)
        return g, (J if jac else None)

    def positions(self, kin: Kinematics, X) -> np.ndarray:
        """Return backbone points (P, 3) at arc lengths ``X`` (no Jacobian)."""
        return self.at(kin, X, jac=False)[0][:, :3, 3]
