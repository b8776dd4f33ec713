"""
Search the six pressures whose predicted images best reach a goal.

Two stages, both batched through the forward model:

1. *Bank*: when a scene's initial images arrive, the model predicts a fixed, seeded set of
   actuations once (uniform in the limits, like the training data). A goal is scored against
   all of them with no further model call, and the best few distinct ones are the starts.
2. *Levenberg-Marquardt* from those starts on the residual vector of
   :class:`~softshape_ros.control.objective.Objective`: the Jacobian by forward differences,
   all starts and all perturbations in one batch (7 images per start and step), steps kept
   in the limits. The network is small, so a batch of 7 costs about what one backward pass
   does, and Gauss-Newton needs far fewer steps than gradient descent.

:class:`RandomSearch` is the baseline with the same budget: the bank plus as many more
uniform draws as LM used model calls, best by the same cost.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

N_U = 6
_FIRST_RISE = 4.0      # the damping's factor on a first rejected step (then 8, 16, ...)


@dataclass(frozen=True)
class PlannerConfig:
    """Budget and step settings (defaults: <= 100 ms per plan on one core, measured)."""

    bank_size: int = 384
    starts: int = 1
    lm_iterations: int = 4
    fd_step: float = 0.01          # of the usable limit
    lm_damping: float = 1e-2
    min_gain: float = 1e-3         # stop when an accepted step improves the cost less
    min_start_distance: float = 0.15
    seed: int = 0


@dataclass
class PlanResult:
    """A plan: what to command, what the model expects to see, and how far from the goal."""

    pressures_pa: np.ndarray        # (6,) Pa, within the limits
    u: np.ndarray                   # (6,) fraction of the usable limits
    predicted: np.ndarray           # V x C x S x S uint8, the model's images at the plan
    cost: float                     # squared residual norm (1 ~ at tolerance)
    predicted_error: dict           # hard tip error per view (px), IoU, against the goal
    evaluations: int                # forward-model images this plan computed
    plan_ms: float
    iterations: int = 0             # Levenberg-Marquardt steps taken
    history: list = field(default_factory=list)


class Bank:
    """
    One scene's predictions for a fixed seeded set of actuations (computed once per scene).

    Kept as the objective's features (soft masks, soft tips, images and their squared
    norms), so scoring a goal against the whole bank costs matrix-vector products only.
    """

    def __init__(self, forward, size: int, seed: int = 0, chunk: int = 64, threshold=None,
                 grids=None):
        from softshape_ros.control.features import soft_mask_logits, soft_tips
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed)
        self.u = torch.from_numpy(rng.uniform(0.0, 1.0, (size, N_U)).astype(np.float32))
        masks, tips, ys = [], [], []
        for i in range(0, size, chunk):
            y = forward(self.u[i:i + chunk])
            logits = soft_mask_logits(y, threshold)
            masks.append(torch.sigmoid(logits).flatten(2))
            tips.append(soft_tips(logits, *grids))
            ys.append(y.flatten(1))
        self.mask = torch.cat(masks)                    # N x V x P
        self.tips = torch.cat(tips)                     # N x V x 2
        self.y_flat = torch.cat(ys)                     # N x (V C P)
        self.mask_sq = self.mask.square().sum(-1)       # N x V
        self.y_sq = self.y_flat.square().sum(-1)        # N
        self.build_ms = (time.perf_counter() - t0) * 1e3

    @classmethod
    def for_scene(cls, forward, ctx, size: int, seed: int = 0) -> 'Bank':
        """Build the bank of ``forward`` in the scene of ``ctx`` (its threshold and grids)."""
        return cls(forward, size, seed, threshold=ctx.silhouette.threshold,
                   grids=ctx.torch_grids())

    def __len__(self) -> int:
        return len(self.u)

    def images(self, i: int, shape) -> torch.Tensor:
        return self.y_flat[i].reshape(shape)

    def costs(self, objective) -> torch.Tensor:
        with torch.no_grad():
            return objective.bank_cost(self)


def _distinct(order, u, k: int, min_dist: float, exclude=()) -> list:
    """Pick the first ``k`` entries of ``order`` apart from each other and from ``exclude``."""
    picked, away = [], [torch.as_tensor(np.asarray(e, dtype=np.float32)) for e in exclude]
    for i in order.tolist():
        if all(float((u[i] - u[j]).abs().max()) >= min_dist for j in picked) and \
                all(float((u[i] - e).abs().max()) >= min_dist for e in away):
            picked.append(i)
        if len(picked) == k:
            break
    return picked


class Planner:
    """Bank + batched Levenberg-Marquardt through a forward model (network or simulator)."""

    def __init__(self, config: PlannerConfig = PlannerConfig()):
        self.cfg = config

    def plan(self, objective, forward, bank: Bank | None = None, warm=None,
             exclude=()) -> PlanResult:
        """
        Return the best plan for ``objective``.

        ``warm`` (u) replaces the last bank start; bank starts keep ``min_start_distance``
        from each other and from every u in ``exclude`` (commands already tried).
        """
        t0 = time.perf_counter()
        ev0 = forward.evaluations
        cfg = self.cfg
        if bank is None:
            bank = Bank.for_scene(forward, objective.ctx, cfg.bank_size, cfg.seed)
        costs = bank.costs(objective)
        order = torch.argsort(costs)
        picked = _distinct(order, bank.u, cfg.starts, cfg.min_start_distance, exclude)
        starts = [bank.u[i] for i in picked] or [bank.u[int(order[0])]]
        if warm is not None:
            starts = [torch.as_tensor(np.asarray(warm, dtype=np.float32))] + starts[:-1]
        u = torch.stack(starts)
        u, cost, y, iters, hist = self._levenberg_marquardt(objective, forward, u)
        best = int(torch.argmin(cost))
        return self._result(objective, forward, u[best], y[best], float(cost[best]),
                            forward.evaluations - ev0, t0, iters, hist)

    def _levenberg_marquardt(self, objective, forward, u):
        """Run LM on K starts in parallel; return (u, cost, images, steps, cost history)."""
        cfg = self.cfg
        k = u.shape[0]
        eye = torch.eye(N_U)
        lam = torch.full((k,), cfg.lm_damping)
        nu = torch.full((k,), _FIRST_RISE)
        cur_u, cur_cost = u.clone(), torch.full((k,), float('inf'))
        cur_y = cur_r = cur_j = None
        trial = u.clone()
        hist, steps = [], 0
        done = torch.zeros(k, dtype=torch.bool)
        for it in range(cfg.lm_iterations + 1):
            # Batch: each start's trial point and its 6 forward-difference neighbours.
            h = torch.where(trial + cfg.fd_step <= 1.0, cfg.fd_step, -cfg.fd_step)   # K x 6
            pts = torch.cat([trial[:, None], trial[:, None] + torch.diag_embed(h)], 1)
            y = forward(pts.reshape(-1, N_U))
            with torch.no_grad():
                r = objective.residuals(objective.features(y), pts.reshape(-1, N_U))
            r = r.reshape(k, N_U + 1, -1)                                 # K x 7 x R
            y = y.reshape((k, N_U + 1) + y.shape[1:])
            jac = (r[:, 1:] - r[:, :1]) / h[:, :, None]                   # K x 6 x R
            cost = r[:, 0].square().sum(1)
            better = cost < cur_cost
            if cur_r is None:
                cur_y, cur_r, cur_j = y[:, 0], r[:, 0], jac
            else:
                cur_y = torch.where(better.reshape(-1, 1, 1, 1, 1), y[:, 0], cur_y)
                cur_r = torch.where(better[:, None], r[:, 0], cur_r)
                cur_j = torch.where(better[:, None, None], jac, cur_j)
            gain = (cur_cost - cost) / cost.clamp_min(1e-9)
            # Nielsen's schedule: each rejection in a row raises the damping by a growing
            # factor (4, 8, 16, ...), so a step that overshoots is cut back in a few tries.
            lam = torch.where(better, lam / 3, lam * nu)
            nu = torch.where(better, torch.full_like(nu, _FIRST_RISE), nu * 2)
            cur_u = torch.where(better[:, None], trial, cur_u)
            cur_cost = torch.where(better, cost, cur_cost)
            hist.append(float(cur_cost.min()))
            # Settled: the last step gained under min_gain, or the damping has grown so large
            # that steps no longer move (a corner of the limits, a flat region).
            settled = (it > 0) & (((gain < cfg.min_gain) & better) | (lam > 1e3))
            done = done | settled
            if it == cfg.lm_iterations or bool(done.all()):
                break
            # Gauss-Newton step with Marquardt's scaling, clipped to the limits.
            jtj = cur_j @ cur_j.transpose(1, 2)                           # K x 6 x 6
            jtr = (cur_j @ cur_r[:, :, None])[:, :, 0]                    # K x 6
            a = jtj + lam[:, None, None] * (torch.diag_embed(torch.diagonal(jtj, 0, 1, 2))
                                            + 1e-6 * eye)
            step = torch.linalg.solve(a, -jtr[:, :, None])[:, :, 0]
            trial = (cur_u + step).clamp(0.0, 1.0)
            steps += 1
        return cur_u, cur_cost, cur_y, steps, hist

    @staticmethod
    def _result(objective, forward, u, y, cost, evaluations, t0, iters, hist) -> PlanResult:
        u_np = u.detach().numpy().astype(np.float64).clip(0.0, 1.0)
        img = np.clip(np.rint(y.detach().numpy() * 255), 0, 255).astype(np.uint8)
        return PlanResult(pressures_pa=forward.pressures(u_np), u=u_np, predicted=img,
                          cost=cost, predicted_error=objective.describe(img),
                          evaluations=int(evaluations), iterations=iters, history=hist,
                          plan_ms=(time.perf_counter() - t0) * 1e3)


class RandomSearch:
    """The baseline: uniform random actuations, the best by the same cost, same budget."""

    def __init__(self, budget: int, seed: int = 0):
        self.budget = int(budget)
        self.rng = np.random.default_rng(seed)

    def plan(self, objective, forward, bank: Bank | None = None, warm=None,
             exclude=()) -> PlanResult:
        t0 = time.perf_counter()
        ev0 = forward.evaluations
        best_u, best_cost, best_y = None, float('inf'), None
        if bank is not None:
            costs = bank.costs(objective)
            i = int(torch.argmin(costs))
            shape = tuple(objective.ctx.initial.shape)
            best_u, best_cost, best_y = bank.u[i], float(costs[i]), bank.images(i, shape)
        extra = self.budget - (len(bank) if bank is not None else 0)
        cands = [torch.as_tensor(np.asarray(warm, dtype=np.float32))[None]] if warm is not None \
            else []
        if extra > 0:
            cands.append(torch.from_numpy(self.rng.uniform(0, 1, (extra, N_U)).astype(np.float32)))
        for u in (torch.cat(cands).split(64) if cands else []):
            y = forward(u)
            with torch.no_grad():
                c = objective.cost(y, u)
            i = int(torch.argmin(c))
            if float(c[i]) < best_cost:
                best_u, best_cost, best_y = u[i], float(c[i]), y[i]
        return Planner._result(objective, forward, best_u, best_y, best_cost,
                               forward.evaluations - ev0, t0, 0, [best_cost])
