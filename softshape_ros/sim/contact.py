"""
Frictionless contact between the robot (a tube of its real radius, rounded tip) and rigid objects.

A contact law is a class with one method, ``evaluate(rod, kin) -> ContactResult``
(:class:`ContactLaw`); :meth:`Statics.assemble` adds what it returns. The one law here,
:class:`PenaltyContact`, is the paper's model: each object pushes on the robot with
concentrated forces. For every local minimum along the backbone of the gap
``gamma(X) = phi(p(X)) - r`` (phi: the object's signed distance) the contact point is the
true minimiser ``X_c`` of the gap on the exact rod (not snapped to a node), and a smooth
penalty force ``f = k pen (1 + pen / p0) grad phi``, ``pen = delta softplus(-gamma / delta)``
(a smooth penetration), acts there along the surface normal; it stiffens with depth so the
robot stays within a fraction of a millimetre of the surface even when pressed hard.
The normal passes through the backbone, so the force is applied at ``p(X_c)`` with no
moment. Its Jacobian ``df/dp = lambda' n n^T + lambda H`` goes into the Newton tangent, with
the sliding of the contact point along the backbone.

Where the robot lies along an object (flat gap profile) the minima come and go in pairs
with a maximum between them; the penalty at each such interior maximum ("ridge") is
subtracted, so the potential is the rise of the penalty along the backbone (its positive
variation from the base) and stays continuous, the force too, when a pair appears. Apart
from such line contacts the ridges are outside the cutoff and the model is the paper's.
The critical points come from sign changes of the exact gap slope sampled along the rod,
each refined by safeguarded Newton inside its bracket (``kernels._find``), so a flat
profile's minima and ridges are those of the rod itself and stay put between iterations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import numpy as np

from softshape_ros.sim import kernels
from softshape_ros.sim.objects import ObstacleSet
from softshape_ros.sim.rod import Kinematics, Rod

DEFAULT_STIFFNESS_N_M = 2.0e4
DEFAULT_SMOOTHING_M = 2.0e-5
STIFFENING_DEPTH_M = 2.0e-4     # p0: the penalty doubles its stiffness at 0.2 mm
# Critical points are refined where a sample's gap is below this: one within the cutoff
# (0.6 mm) has a sample within its bracket (<= 0.53 mm of backbone, slope <= 1) below 1.13 mm.
NEAR_M = 1.5e-3
SAMPLES_PER_INTERVAL = 8        # gap slope samples per node interval (<= 0.6 mm apart)
CUTOFF_SMOOTHINGS = 30.0        # gaps beyond 30 smoothing lengths carry no force (< 1e-13 k delta)
# A Newton step may press a free node (or a lifted contact) this deep, linearised: one
# smoothing length. At 0.1 mm the penalty overshoots (~3 N, tangent indefinite) and the next
# step jumps back out.
STEP_DEPTH_M = 2e-5


@dataclass(frozen=True)
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


@dataclass(frozen=True)
class ContactResult:
    """
    What a contact law returns for one shape: its loads on the rod and the step's limits.

    Per-contact numbers are the columns of ``rows`` (C, ...), exposed as named arrays; the
    step rows are the linearised gaps a Newton step must keep, ``step_rows @ dq >=
    step_lower``.
    """

    rows: np.ndarray                # (C, kernels.C_COLS) see the properties
    poses: np.ndarray               # (C, 4, 4) rod frames at the contacts
    jacobians: np.ndarray           # (C, 6, n) body Jacobians there
    generalised_force: np.ndarray   # (n,) J^T W of the forces
    stiffness: np.ndarray           # (n, n) added to the tangent as is (material, sliding)
    energy: float                   # the penalty potential
    step_rows: np.ndarray           # (R, n)
    step_lower: np.ndarray          # (R,)
    node_gaps_m: np.ndarray         # (O, N) gap of the tube at each node, per obstacle

    @property
    def s_m(self) -> np.ndarray:
        return self.rows[:, kernels.C_X]

    @property
    def obstacle(self) -> np.ndarray:
        return self.rows[:, kernels.C_OBJ].astype(int)

    @property
    def sign(self) -> np.ndarray:
        """Return +1 for a gap minimum, -1 for a ridge (its force is subtracted)."""
        return self.rows[:, kernels.C_SIGN]

    @property
    def gap_m(self) -> np.ndarray:
        return self.rows[:, kernels.C_GAP]

    @property
    def backbone_m(self) -> np.ndarray:
        return self.rows[:, kernels.C_P:kernels.C_P + 3]

    @property
    def normal(self) -> np.ndarray:
        """Return the unit normals out of the object (C, 3)."""
        return self.rows[:, kernels.C_N:kernels.C_N + 3]

    @property
    def force_n(self) -> np.ndarray:
        """Return the world forces on the robot (C, 3)."""
        return self.rows[:, kernels.C_F:kernels.C_F + 3]

    @property
    def radius_m(self) -> np.ndarray:
        return self.rows[:, kernels.C_RAD]

    @property
    def contacts(self) -> list[Contact]:
        """Return the contacts as records (for SimState and JSON)."""
        p, n = self.backbone_m, self.normal
        return [Contact(float(r[kernels.C_X]), p[i].copy(), p[i] - r[kernels.C_RAD] * n[i],
                        n[i].copy(), self.force_n[i].copy(), float(r[kernels.C_GAP]),
                        int(r[kernels.C_OBJ]), bool(r[kernels.C_SIGN] < 0))
                for i, r in enumerate(self.rows)]

    @property
    def max_penetration_m(self) -> float:
        return max(0.0, float(-self.gap_m.min(initial=np.inf)))

    @property
    def any(self) -> bool:
        """Whether any contact point lies within the penalty's reach."""
        return len(self.rows) > 0


@runtime_checkable
class ContactLaw(Protocol):
    """A contact law: one method from a shape to the contact loads on it."""

    def evaluate(self, rod: Rod, kin: Kinematics) -> ContactResult:
        """Return the contact points, loads and step limits of the shape ``kin``."""


@dataclass(frozen=True)
class PenaltyContact:
    """The paper's concentrated penalty forces at the gap minima (module docstring)."""

    obstacles: ObstacleSet
    stiffness: float = DEFAULT_STIFFNESS_N_M
    smoothing: float = DEFAULT_SMOOTHING_M

    @classmethod
    def of(cls, obstacles, stiffness: float = DEFAULT_STIFFNESS_N_M,
           smoothing: float = DEFAULT_SMOOTHING_M) -> 'PenaltyContact':
        if not (np.isfinite(stiffness) and stiffness > 0 and np.isfinite(smoothing)
                and smoothing > 0):
            raise ValueError(f'contact stiffness and smoothing must be positive, got '
                             f'{stiffness}, {smoothing}')
        return cls(ObstacleSet.of(obstacles), float(stiffness), float(smoothing))

    def scaled(self, factor: float) -> 'PenaltyContact':
        """Return the same law with the penalty stiffness times ``factor``."""
        return replace(self, stiffness=self.stiffness * factor)

    def _params(self) -> np.ndarray:
        """Return the law's numbers as the float array the kernels read (kernels.L_*)."""
        return np.array(kernels.PenaltyParams(
            stiffness=self.stiffness, smoothing=self.smoothing, stiffening=STIFFENING_DEPTH_M,
            cutoff=CUTOFF_SMOOTHINGS * self.smoothing, near=NEAR_M,
            samples=SAMPLES_PER_INTERVAL, step_depth=STEP_DEPTH_M), dtype=float)

    def evaluate(self, rod: Rod, kin: Kinematics) -> ContactResult:
        """
        Return the contacts of the shape ``kin``: forces, their Jacobian and step limits.

        The potential is the rise of the penalty along the backbone from the base: the
        penalty at every gap minimum minus that at every interior gap maximum.
        """
        ob = self.obstacles
        rows, g, J, Q, Kc, A, lo, node_gaps = kernels.penalty_contacts(
            *rod.tables, kin.q, kin.g, kin.J, ob.kinds, ob.rows, ob.poses, self._params())
        energy = kernels.penalty_energy(rows, self.stiffness, self.smoothing,
                                        STIFFENING_DEPTH_M)
        return ContactResult(rows, g, J, Q, Kc, energy, A, lo, node_gaps)
