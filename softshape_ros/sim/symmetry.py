"""
The rig's symmetry: the same physics turned about the robot's axis or mirrored.

The robot hangs along world z (gravity along its axis) with each segment's chambers at
equal angles, the same in every segment. Turning a placement by one chamber spacing about
the axis and handing each chamber's pressure to the chamber it lands on gives the same
equilibrium turned; so does mirroring about the vertical plane of a chamber's bend. A
model that learns in one *fold* (a sector of 360 / (2 x chambers per segment) degrees,
60 on the STIFF-FLOP rig) sees every placement that many times as densely: the placement
head (``experiments/placement_head.py``) learns there. ``test_symmetry`` checks on the simulator
that the turned and mirrored equilibria match to rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.scene import Scene
from softshape_ros.sim.lie import rpy_matrix


class SymmetryError(ValueError):
    """The rig's geometry has no turn-and-mirror symmetry to fold placements with."""


@dataclass(frozen=True)
class Fold:
    """One symmetry: ``matrix`` (3 x 3, about the robot's axis) and the chambers' handover."""

    matrix: np.ndarray          # folded <- world, applied about ``base``
    perm: np.ndarray            # (6,) int: chamber i's pressure goes to chamber perm[i]
    base: np.ndarray            # (3,) a point on the robot's axis
    turn_rad: float             # the turn (after the mirror, if any)
    mirror_rad: float | None    # the mirror plane's azimuth, None: no mirror

    def pressures(self, p) -> np.ndarray:
        """(..., 6) pressures -> the same actuation for the folded robot."""
        p = np.asarray(p, dtype=float)
        out = np.empty_like(p)
        out[..., self.perm] = p
        return out

    def points(self, pts) -> np.ndarray:
        """(..., 3) world points -> the folded scene's."""
        return (np.asarray(pts, dtype=float) - self.base) @ self.matrix.T + self.base

    def unfold_points(self, pts) -> np.ndarray:
        """(..., 3) points of the folded scene -> the world's (the inverse of :meth:`points`)."""
        return (np.asarray(pts, dtype=float) - self.base) @ self.matrix + self.base

    def scene(self, scene: Scene) -> Scene:
        """
        Turn (and mirror) a placement with the robot.

        A mirror turns the object's frame inside out in its own y; every object the rig
        uses (cylinder, ring, prism skewed along its x) is its own mirror image there, so
        the mirrored object is the same object with roll negated and yaw mirrored.
        """
        pos = self.points(np.asarray(scene.position_m, dtype=float))
        roll, pitch, yaw = (float(v) for v in scene.rpy_rad)
        if self.mirror_rad is not None:
            roll, yaw = -roll, 2 * self.mirror_rad - yaw
        yaw = math.remainder(yaw + self.turn_rad, 2 * math.pi)
        return replace(scene, position_m=tuple(float(v) for v in pos),
                       rpy_rad=(roll, pitch, yaw))


@dataclass(frozen=True)
class RigSymmetry:
    """The rig's turns and mirrors, and the fold every placement is taken into."""

    base: np.ndarray            # (3,) the robot's base, on its axis
    mirror_angle: float         # rad: a chamber's bend direction, the mirror plane's
    order: int                  # chambers per segment: turns by 2 pi / order
    turn_perm: np.ndarray       # (6,) the handover for one turn
    mirror_perm: np.ndarray     # (6,) the handover for the mirror

    @classmethod
    def from_config(cls, cfg: RigConfig) -> 'RigSymmetry':
        """Derive the symmetry from the rig's geometry; SymmetryError says what breaks it."""
        from softshape_ros.sim.generate import bend_directions
        axis = rpy_matrix(cfg.robot.base_rpy_rad)[:, 0]
        g = np.asarray(cfg.robot.gravity_m_s2, dtype=float)
        if not np.allclose(axis, [0, 0, -1], atol=1e-6):
            raise SymmetryError(f'the robot does not hang along world -z (axis {axis.round(4)})')
        if np.linalg.norm(g[:2]) > 1e-9 * max(1.0, np.linalg.norm(g)):
            raise SymmetryError(f'gravity {g.tolist()} is not along the robot axis')
        chambers = list(cfg.chambers)
        segments = sorted({c.segment for c in chambers})
        per = [[i for i, c in enumerate(chambers) if c.segment == s] for s in segments]
        order = len(per[0])
        if order < 2 or any(len(p) != order for p in per):
            raise SymmetryError('every segment needs the same number (>= 2) of chambers')
        bend = bend_directions(cfg)
        angles = np.arctan2(bend[:, 1], bend[:, 0])

        def handover(f) -> np.ndarray:
            perm = np.empty(len(chambers), dtype=np.int64)
            for i, c in enumerate(chambers):
                a = f(angles[i])
                same = [j for j in per[segments.index(c.segment)]
                        if abs(math.remainder(a - angles[j], 2 * math.pi)) < 1e-6]
                twin = chambers[same[0]] if same else None
                if twin is None or (twin.offset_m, twin.area_m2, twin.max_pressure_pa) != (
                        c.offset_m, c.area_m2, c.max_pressure_pa):
                    raise SymmetryError(f'chamber {c.name} has no equal chamber where a turn '
                                        f'or mirror of the rig takes it')
                perm[i] = same[0]
            return perm

        step = 2 * math.pi / order
        mirror_angle = float(angles[0])
        return cls(np.asarray(cfg.robot.base_position_m, dtype=float), mirror_angle, order,
                   handover(lambda a: a + step), handover(lambda a: 2 * mirror_angle - a))

    @property
    def size(self) -> int:
        """How many symmetries (turns x mirrors): the fold is 1 / size of the turn."""
        return 2 * self.order

    def element(self, turns: int, mirrored: bool) -> Fold:
        """Mirror (if ``mirrored``), then turn ``turns`` chamber spacings."""
        t = (turns % self.order) * 2 * math.pi / self.order
        c, s = math.cos(t), math.sin(t)
        m = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        perm = np.arange(len(self.turn_perm))
        if mirrored:
            c2, s2 = math.cos(2 * self.mirror_angle), math.sin(2 * self.mirror_angle)
            m = m @ np.array([[c2, s2, 0.0], [s2, -c2, 0.0], [0.0, 0.0, 1.0]])
            perm = self.mirror_perm.copy()
        for _ in range(turns % self.order):
            perm = self.turn_perm[perm]
        return Fold(m, perm, self.base, t, self.mirror_angle if mirrored else None)

    def azimuth(self, point) -> float:
        """Return a point's azimuth about the robot's axis (rad)."""
        d = np.asarray(point, dtype=float)[:2] - self.base[:2]
        return math.atan2(d[1], d[0])

    def fold_of(self, point) -> Fold:
        """Return the symmetry taking ``point`` into the fold (azimuth mirror .. mirror + 60)."""
        rel = (self.azimuth(point) - self.mirror_angle) % (2 * math.pi)
        step = 2 * math.pi / self.order
        turns = (-int(rel // step)) % self.order
        rel = (rel + turns * step) % (2 * math.pi)
        if rel <= step / 2:
            return self.element(turns, False)
        # mirror (rel0 -> -rel0), then turn t: t step - rel0 = (t + turns) step - rel, which
        # is step - rel, inside the fold, for t = 1 - turns
        return self.element((1 - turns) % self.order, True)
