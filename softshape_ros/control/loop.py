"""
The closed loop without any I/O: plan, (someone commands and films), observe, correct, re-plan.

The ``shape_controller`` node and ``softshape control-eval`` drive the same object: the node
between ROS messages, the evaluation against the simulator. After each observation the
objective is corrected by the camera's residual against the model's at the same pressures
and anchored near the last command (the correction is only valid nearby), and the next plan
starts from there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from softshape_ros.control.features import SceneContext
from softshape_ros.control.goal import Goal
from softshape_ros.control.objective import CostWeights, Objective
from softshape_ros.control.planner import Bank, Planner, PlanResult


#: A re-plan this close (in every chamber, fraction of the limit) to a tried command repeats it.
REPEAT_U = 0.01


@dataclass(frozen=True)
class Tolerance:
    """When a goal counts as reached (issue 16: tip within 2 px in every view, IoU >= 0.9)."""

    tip_px: float = 2.0
    iou: float = 0.9


@dataclass
class Observation:
    """The camera's verdict on one commanded plan."""

    iteration: int
    tip_error_px: list
    iou: float | None
    success: bool
    pressures_pa: np.ndarray
    residual: float = float('nan')      # the camera images' cost (the loop's merit)

    def to_dict(self) -> dict:
        return {'iteration': self.iteration, 'tip_error_px': self.tip_error_px,
                'iou': self.iou, 'success': self.success, 'residual': self.residual,
                'pressures_pa': [float(p) for p in self.pressures_pa]}


def reached(score: dict, kind: str, tol: Tolerance) -> bool:
    """Whether a hard score (tip errors, IoU) is within tolerance for a goal of ``kind``."""
    tips = score.get('tip_error_px', [])
    ok = bool(tips) and all(np.isfinite(e) and e <= tol.tip_px for e in tips)
    if kind != 'tip':
        ok = ok and score.get('iou', 0.0) >= tol.iou
    return ok


@dataclass
class ShapeLoop:
    """One goal in one scene: the plans made, what was seen, whether it is reached."""

    forward: object
    ctx: SceneContext
    goal: Goal
    planner: Planner
    bank: Bank | None = None
    tolerance: Tolerance = Tolerance()
    max_iterations: int = 3
    trust: float = 1.0
    weights: CostWeights = CostWeights()
    secant: bool = True
    plans: list = field(default_factory=list)
    observations: list = field(default_factory=list)

    def __post_init__(self):
        self.objective = Objective(self.ctx, self.goal, self.weights)
        self._best = None           # (real cost, u, camera images) of the best command seen
        self._best_index = -1
        self._tip_corrections = []  # (u, tip part of the correction) per observation
        self._trust = 0.0

    @property
    def iteration(self) -> int:
        return len(self.observations)

    @property
    def success(self) -> bool:
        return bool(self.observations) and self.observations[-1].success

    @property
    def best(self) -> int:
        """Index of the best observation so far (the last one if it reached the goal)."""
        return len(self.observations) - 1 if self.success else self._best_index

    @property
    def done(self) -> bool:
        return self.success or self.iteration >= self.max_iterations

    def plan(self) -> PlanResult:
        """Plan the next command (the first from the bank, later ones corrected and local)."""
        if len(self.plans) > len(self.observations):
            raise RuntimeError('observe the last plan before planning again')
        warm = self._best[1] if self._best is not None else None
        result = self.planner.plan(self.objective, self.forward, self.bank, warm=warm)
        tried = [p.u for p in self.plans]
        if tried and min(np.abs(result.u - u).max() for u in tried) < REPEAT_U:
            # The corrected model sees nothing better near the best command: commanding it
            # again would only film it again. Start once more, from the best bank entry
            # away from every command tried, free of the trust region.
            anchor, self.objective.anchor = self.objective.anchor, None
            try:
                again = self.planner.plan(self.objective, self.forward, self.bank,
                                          exclude=tried)
            finally:
                self.objective.anchor = anchor
            again.plan_ms += result.plan_ms
            again.evaluations += result.evaluations
            result = again
        self.plans.append(result)
        return result

    def observe(self, images: np.ndarray) -> Observation:
        """
        Score the camera images (V x C x S x S uint8) of the last plan; correct the model.

        A trust region on the real rig: the correction is taken at the best command seen so
        far, and re-plans are held near it, the tighter the more often a re-plan did worse.
        """
        if len(self.plans) != len(self.observations) + 1:
            raise RuntimeError('no plan to observe: call plan() first')
        last = self.plans[-1]
        score = self.objective.describe(images)
        ok = reached(score, self.goal.kind, self.tolerance)
        obs = Observation(self.iteration + 1, score.get('tip_error_px', []), score.get('iou'),
                          ok, last.pressures_pa)
        self.observations.append(obs)
        cost = self.objective.real_cost(images, last.u)
        obs.residual = cost
        if self._best is None or cost < self._best[0]:
            self._best = (cost, last.u, images)
            self._best_index = len(self.observations) - 1
            self._trust = max(self.trust, self._trust / 2) if self._trust else self.trust
        else:
            self._trust *= 2.0
        if not ok:
            def model_at(u):
                return self.forward(torch.from_numpy(u.astype(np.float32))[None])[0]
            self._tip_corrections.append(
                (last.u, self.objective.set_correction(images, model_at(last.u), last.u,
                                                       keep=True)))
            _, u, seen = self._best
            c_best = self.objective.set_correction(seen, model_at(u), u)
            self.objective.anchor_at(u, self._trust)
            if self.secant:
                self.objective.set_tip_secant(u, self._secant(u, c_best))
        return obs

    def _secant(self, u_best, c_best):
        """Rank-1 slope of the tip correction between the best and another observed command."""
        for u, c in reversed(self._tip_corrections):
            du = torch.from_numpy((u - u_best).astype(np.float32))
            if float(du.abs().max()) >= REPEAT_U:
                return ((c - c_best)[:, None] * du[None, :] / du.square().sum()).numpy()
        return None
