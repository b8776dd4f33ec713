"""
The placement path as a predictor: read the placement, fit it, predict the shape, draw it.

Per rest image set (once, cached): the tube model's scene description gives a reading,
``sim.placement_fit`` fits it to the rest images (a few seconds). Per actuation: the
placement head (``experiments.placement_head``) predicts the keypoints, which the tube model
draws over its own background, object and visibility. Same inputs and outputs as
:class:`~softshape_ros.model.predictor.Predictor`, so the inference node serves it as it
serves a checkpoint (its ``placement_head`` parameter).

An object one view shows only behind the robot (the fit's ``hidden`` views) has no depth
in the rest images: any point of a ray some 10 mm long fits them, and the head would draw
the robot confidently for one of them. The tube model, trained over such placements,
draws its own prediction there, which spreads its bet (docs/model.md, "Where the images do
not hold the placement"). So it does for a placement farther from the robot than any the
head learned from (``ShapePredictor.reach_m``), where the head extrapolates.

Simulated rig only as it stands: the fit reads images with the simulator's renderer. Told
the placement (:meth:`PlacementPredictor.know`: the session's record of it, ``/rig/scene``),
it skips reading and fitting.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import torch

from softshape_ros.config import RigConfig
from softshape_ros.model.checkpoint import load_checkpoint
from softshape_ros.model.data import scene_from_vector
from softshape_ros.experiments.placement_head import (PlacementHeadError, ShapePredictor,
                                                      read_facing_out)
from softshape_ros.model.predictor import Predictor, to_uint8
from softshape_ros.scene import Scene

CACHED_PLACEMENTS = 8


class PlacementPredictor(Predictor):
    """A tube checkpoint drawing what a placement head predicts for the fitted placement."""

    def __init__(self, model, config: dict, shape: ShapePredictor, cfg: RigConfig):
        super().__init__(model, config)
        if not hasattr(model, 'keypoints'):
            raise PlacementHeadError(f'the placement path draws with a tube model, not '
                                     f'{config.get("arch")!r}')
        if list(shape.projection.views) != self.views or shape.projection.size != \
                self.image_size or self.channels != 1:
            raise PlacementHeadError(
                f'the placement head draws views {shape.projection.views} at '
                f'{shape.projection.size} px gray; the checkpoint has {self.views} at '
                f'{self.image_size} px, {self.channels} channel(s)')
        from softshape_ros.sim.placement_fit import PlacementFit
        self.shape = shape
        self.fit = PlacementFit(cfg, self.views, self.image_size)
        self._placements: OrderedDict[bytes, tuple[Scene, tuple]] = OrderedDict()
        self.known: Scene | None = None
        self.alone = ''             # why the tube model drew the last placement itself, if it did

    def know(self, scene: Scene | None) -> None:
        """
        Take ``scene`` as the placement of the rest images from now on, instead of fitting.

        Where a session records what it placed (``/rig/scene``), that is the placement the
        head is told; ``None`` fits again. PlacementHeadError (and nothing changed) for an
        object the head does not know.
        """
        from softshape_ros.sim.placement_fit import UPRIGHT
        if scene is not None and scene.object not in UPRIGHT:
            raise PlacementHeadError(f'the placement head predicts for {sorted(UPRIGHT)}, '
                                     f'not {scene.object!r} (scene {scene.id})')
        self.known = scene

    @classmethod
    def from_paths(cls, checkpoint, head, cfg: RigConfig) -> 'PlacementPredictor':
        """Load a tube checkpoint and a placement head for rig ``cfg`` (errors name the file)."""
        model, config = load_checkpoint(checkpoint)
        return cls(model, config, ShapePredictor.load(head, cfg), cfg)

    def placement(self, initial: np.ndarray) -> Scene:
        """Read and fit the placement of V x C x S x S uint8 rest images (cached per image set)."""
        return self._placement(initial)[0]

    @torch.inference_mode()
    def _placement(self, initial: np.ndarray) -> tuple[Scene, tuple]:
        """(placement, views its object is hidden in); told the placement, nothing hidden."""
        imgs = self._images(initial, batch=False)
        if self.known is not None:
            return self.known, ()
        key = hashlib.sha1(imgs.tobytes()).digest()
        if key in self._placements:
            self._placements.move_to_end(key)
            return self._placements[key]
        v, c, s, _ = imgs.shape
        x = torch.from_numpy(imgs.reshape(1, v * c, s, s).astype(np.float32) / 255)
        p = torch.zeros(1, len(self.max_pressure_pa))
        described = self.model(x, p, parts='keypoints')[2]
        if described is None:
            raise PlacementHeadError('the checkpoint does not describe placements (trained '
                                     'without the scene loss): nothing to start the fit from')
        reading = read_facing_out(scene_from_vector(described[0].numpy()), self.shape.sym)
        r = self.fit.fit(imgs, reading)
        self._placements[key] = (r.scene, r.hidden)
        if len(self._placements) > CACHED_PLACEMENTS:
            self._placements.popitem(last=False)
        return r.scene, r.hidden

    @torch.inference_mode()
    def predict_batch(self, initial_b, pressures_b) -> np.ndarray:
        """B x V x C x S x S uint8 + B x 6 Pa -> B x V x C x S x S uint8."""
        imgs, p, x = self._batch(initial_b, pressures_b)
        if not len(imgs):
            return imgs.copy()
        fits = [self._placement(i) for i in imgs]
        why = [alone_because(self.fit, self.shape, scene, hidden) for scene, hidden in fits]
        self.alone = why[-1]
        pt = torch.from_numpy(p.astype(np.float32))
        kp = self.shape.keypoints([s for s, _ in fits], p * self.max_pressure_pa)  # B x V x K x 4
        y = self.model(x, pt, truth=kp, parts=True).teacher              # B x V*C x S x S
        own = [b for b, w in enumerate(why) if w]
        if own:                     # the head cannot know these: the tube model's own bet
            y[own] = self.model(x[own], pt[own])
        return to_uint8(y, imgs.shape)


def alone_because(fit, shape: ShapePredictor, scene: Scene, hidden=()) -> str:
    """
    Say why the tube model should draw ``scene``'s robot itself ('': the head draws it).

    ``hidden``: the views the fit found the object hidden in (its depth is not in the rest
    images); farther from the rest robot than the head's ``reach_m`` for the kind, the head
    extrapolates.
    """
    if hidden:
        return f'hidden in {", ".join(hidden)}'
    reach = shape.reach_m.get(scene.object)
    if reach is not None:
        clear = fit.clearance(scene)
        if clear > reach:
            return f'{clear * 1e3:.1f} mm clear, beyond the head\'s {reach * 1e3:.1f} mm'
    return ''
