"""
Dataset rows -> network tensors, and the two ways of holding data out.

``random`` is the paper's 80/20 split; ``scene`` holds out whole object placements, so the
validation (or test) images show scenes the network has never seen.
"""

from __future__ import annotations

import numpy as np
import torch

SPLITS = ('random', 'scene')


def split_indices(scene, idx, mode: str, fraction: float, seed: int):
    """Split row indices ``idx`` into (kept, held_out) with about ``fraction`` held out."""
    idx = np.asarray(idx, dtype=np.int64)
    if not 0.0 < fraction < 1.0:
        raise ValueError(f'held-out fraction must be in (0, 1), got {fraction}')
    rng = np.random.default_rng(seed)
    if mode == 'random':
        perm = rng.permutation(idx)
        k = max(1, int(round(fraction * len(idx))))
        return np.sort(perm[k:]), np.sort(perm[:k])
    if mode == 'scene':
        scenes = np.unique(np.asarray(scene)[idx])
        if len(scenes) < 2:
            raise ValueError(f'split by scene needs at least 2 scenes, got {len(scenes)}')
        k = min(len(scenes) - 1, max(1, int(round(fraction * len(scenes)))))
        held = rng.permutation(scenes)[:k]
        mask = np.isin(np.asarray(scene)[idx], held)
        return idx[~mask], idx[mask]
    raise ValueError(f'unknown split {mode!r} (choose from {", ".join(SPLITS)})')


def stack_views(images: np.ndarray) -> np.ndarray:
    """N x V x C x S x S -> N x (V*C) x S x S (views stacked as channels)."""
    n, v, c, s, _ = images.shape
    return images.reshape(n, v * c, s, s)


def to_float(images: torch.Tensor) -> torch.Tensor:
    """Return uint8 image tensors as float in [0, 1] (float ones unchanged)."""
    return images.to(torch.float32) / 255 if images.dtype == torch.uint8 else images


def to_tensors(ds, idx, max_pressure_pa, as_uint8: bool = False):
    """
    Load rows ``idx`` of a dataset as (initial, target, pressure) tensors.

    Images N x (V*C) x S x S as float in [0, 1], or kept uint8 with ``as_uint8`` (a quarter
    of the memory for large sets; :func:`to_float` converts a batch); pressures N x 6 float
    in max-pressure units.
    """
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    initial = torch.from_numpy(stack_views(np.asarray(ds.initial[idx])))
    target = torch.from_numpy(stack_views(np.asarray(ds.target[idx])))
    if not as_uint8:
        initial, target = to_float(initial), to_float(target)
    p = np.asarray(ds.pressure[idx], dtype=np.float32) / np.asarray(max_pressure_pa, np.float32)
    return initial, target, torch.from_numpy(p)


def touching_flags(ds, idx=None):
    """
    Return the rows' touching flags (N bool) from the dataset's contact record, or None.

    None when the dataset has no record (older datasets, recorded bags): metrics are then
    reported unsplit.
    """
    contact = getattr(ds, 'contact', None)
    if contact is None:
        return None
    flags = np.asarray(contact.touching, dtype=bool)
    return flags if idx is None else flags[np.asarray(idx, dtype=np.int64)]


def no_contact_why(ds) -> str:
    """Say why a dataset has no contact record (the reason its loader recorded)."""
    why = (ds.meta.get('contact') or {}).get('why') if isinstance(ds.meta, dict) else None
    return f'no contact record ({why})' if why else 'the dataset has no contact record'
