"""
The inference-side API: uint8 images + pressures in Pa in, uint8 images out.

Inputs are checked the way every pressure path in the project checks them
(:func:`softshape_ros.pressure.check_command`: 6 finite, non-negative values,
clamped to the model's training maxima).
"""

from __future__ import annotations

import numpy as np
import torch

from softshape_ros.pressure import check_command
from softshape_ros.model.checkpoint import load_checkpoint


def to_uint8(y: torch.Tensor, shape=None) -> np.ndarray:
    """Round a network's 0..1 images to uint8 gray levels (reshaped to ``shape`` if given)."""
    out = torch.clamp(y * 255 + 0.5, 0, 255).to(torch.uint8).numpy()
    return out if shape is None else out.reshape(shape)


class Predictor:
    """A loaded forward model with the shapes and units it expects."""

    def __init__(self, model: torch.nn.Module, config: dict):
        self.model = model.eval()
        if hasattr(model, 'cache'):     # tube: scene code and background once per rest image
            model.cache = True
        self.config = config
        self.views = list(config['views'])
        self.channels = int(config['channels'])
        self.image_size = int(config['image_size'])
        self.max_pressure_pa = np.asarray(config['max_pressure_pa'], dtype=np.float64)

    @classmethod
    def from_checkpoint(cls, path) -> 'Predictor':
        """Load a checkpoint folder; raises CheckpointError naming the bad file."""
        model, config = load_checkpoint(path)
        return cls(model, config)

    @property
    def image_shape(self) -> tuple:
        return (len(self.views), self.channels, self.image_size, self.image_size)

    def _images(self, images: np.ndarray, batch: bool) -> np.ndarray:
        a = np.asarray(images)
        want = self.image_shape
        if batch:
            ok = a.ndim == 5 and a.shape[1:] == want
            want = ('B',) + want
        else:
            ok = a.shape == want
        if not ok:
            raise ValueError(f'initial images must be {want} uint8, got shape {a.shape}')
        if a.dtype != np.uint8:
            raise ValueError(f'initial images must be uint8, got {a.dtype}')
        return a

    def _pressures(self, pressures) -> np.ndarray:
        p = check_command(pressures, self.max_pressure_pa).pressures_pa
        return (p / self.max_pressure_pa).astype(np.float32)

    def _batch(self, initial_b, pressures_b) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
        """Check a batch: (B x V x C x S x S uint8, B x 6 in max-pressure units, network input)."""
        imgs = self._images(initial_b, batch=True)
        plist = list(pressures_b)
        if len(plist) != imgs.shape[0]:
            raise ValueError(f'{imgs.shape[0]} image sets but {len(plist)} pressure vectors')
        p = np.stack([self._pressures(v) for v in plist]) if plist else np.zeros((0, 6))
        b, v, c, s, _ = imgs.shape
        x = torch.from_numpy(imgs.reshape(b, v * c, s, s).astype(np.float32) / 255)
        return imgs, p, x

    @torch.inference_mode()
    def predict_batch(self, initial_b, pressures_b) -> np.ndarray:
        """B x V x C x S x S uint8 + B x 6 Pa -> B x V x C x S x S uint8."""
        imgs, p, x = self._batch(initial_b, pressures_b)
        return to_uint8(self.model(x, torch.from_numpy(p.astype(np.float32))), imgs.shape)

    def predict(self, initial, pressures_pa) -> np.ndarray:
        """V x C x S x S uint8 + 6 pressures (Pa) -> V x C x S x S uint8."""
        imgs = self._images(initial, batch=False)
        return self.predict_batch(imgs[None], [pressures_pa])[0]
