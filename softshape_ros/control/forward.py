"""
What the planner searches through: pressures -> images, batched, counted.

Pressures travel as ``u`` in [0, 1]^6, the fraction of each chamber's usable maximum (the
lower of the rig's configured limit and the model's training maximum), so a plan can never
leave the limits. :class:`NetworkForward` runs the learned model (differentiable, batched);
:class:`SimForward` runs the simulator itself (the oracle: the upper bound of any planner).
"""

from __future__ import annotations

import numpy as np
import torch

from softshape_ros.pressure import N_CHAMBERS


def usable_limits(rig_limits_pa, model_max_pa=None) -> np.ndarray:
    """Per chamber: the highest pressure a plan may use (Pa)."""
    lim = np.asarray(rig_limits_pa, dtype=np.float64)
    if lim.shape != (N_CHAMBERS,) or not np.all(np.isfinite(lim)) or np.any(lim < 0):
        raise ValueError(f'limits must be {N_CHAMBERS} finite values >= 0, got {lim.tolist()}')
    if model_max_pa is not None:
        lim = np.minimum(lim, np.asarray(model_max_pa, dtype=np.float64))
    return lim


class NetworkForward:
    """The learned forward model on one scene's initial images."""

    differentiable = True

    def __init__(self, predictor, initial: np.ndarray, limits_pa):
        self.predictor = predictor
        self.model = predictor.model
        self.limits = usable_limits(limits_pa, predictor.max_pressure_pa)
        v, c, s, _ = predictor.image_shape
        a = np.asarray(initial)
        if a.shape != (v, c, s, s) or a.dtype != np.uint8:
            raise ValueError(f'initial images must be {(v, c, s, s)} uint8, got {a.shape} '
                             f'{a.dtype}')
        self.shape = (v, c, s, s)
        self.x = torch.from_numpy(a.reshape(1, v * c, s, s).astype(np.float32) / 255)
        # u (fraction of the usable limit) -> the model's normalised pressure.
        self.to_model = torch.from_numpy(
            (self.limits / predictor.max_pressure_pa).astype(np.float32))
        self.evaluations = 0

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """B x 6 in [0, 1] -> B x V x C x S x S in [0, 1] (no gradient)."""
        with torch.inference_mode():
            return self.run(u).clone()

    def run(self, u: torch.Tensor) -> torch.Tensor:
        """As ``__call__``, inside whatever autograd mode the caller chose."""
        b = u.shape[0]
        self.evaluations += b
        y = self.model(self.x.expand(b, -1, -1, -1), u * self.to_model)
        return y.clamp(0.0, 1.0).reshape((b,) + self.shape)

    def pressures(self, u) -> np.ndarray:
        return np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0) * self.limits


class SimForward:
    """The simulator as a forward model: solve + render the network's images (the oracle)."""

    differentiable = False

    def __init__(self, cfg, scene, views, limits_pa, size: int = 64, gray: bool = True,
                 supersample: int = 3):
        from softshape_ros.sim import SimRig
        self.rig = SimRig(cfg)
        self.rig.set_scene(scene)
        self.views, self.size, self.gray, self.supersample = list(views), size, gray, supersample
        self.limits = usable_limits(limits_pa)
        self.evaluations = 0
        self.failures = 0
        self.touching = False       # whether the last solve touched the object

    def images(self, pressures_pa) -> np.ndarray:
        """Return the V x C x S x S uint8 network images of the rig at ``pressures_pa``."""
        st = self.rig.solve(pressures_pa)
        self.touching = any(c.gap_m < 0 for c in st.contacts)
        img = self.rig.render_inputs(st, self.size, self.gray, self.supersample, self.views)
        return np.stack([img[v] for v in self.views])

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        from softshape_ros.sim import SolverError
        out = []
        for row in np.asarray(u, dtype=np.float64):
            self.evaluations += 1
            try:
                out.append(self.images(self.pressures(row)).astype(np.float32) / 255)
            except SolverError:
                # An unsolvable actuation is no candidate: a blank image scores far away.
                self.failures += 1
                self.rig.set_scene(self.rig.scene)
                c = 1 if self.gray else 3
                out.append(np.ones((len(self.views), c, self.size, self.size), np.float32))
        return torch.from_numpy(np.stack(out))

    def pressures(self, u) -> np.ndarray:
        return np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0) * self.limits
