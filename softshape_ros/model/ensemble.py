"""
Trainings averaged: one tube checkpoint that draws the mean of several trainings' keypoints.

Two trainings of one recipe miss a new placement's push differently, and the mean of their
keypoints misses less than either (docs/model.md, "Trainings averaged"). The ensemble keeps
the first checkpoint whole (its scene encoder, background, object and shading networks:
what draws) and the others' keypoint networks (each with its own scene encoder, template
and statistics: what they learnt to see); it predicts the first's image of the mean shape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softshape_ros.model.checkpoint import (
    CheckpointError, checkpoint_dir, load_checkpoint, save_checkpoint)
from softshape_ros.model.networks import build_network

#: What every member must share with the first: the images and pressures it reads.
SAME = ('views', 'channels', 'image_size')


def ensemble(checkpoints, out) -> Path:
    """
    Write to ``out`` the ensemble of the tube ``checkpoints`` (at least two), the first drawing.

    ``checkpoints``: checkpoint folders (or either file in one), each one training of the
    tube model; the first one's renderer draws. ``out``: the folder to write, a checkpoint
    any :class:`~softshape_ros.model.Predictor` loads; returned. Raises
    :class:`CheckpointError` where a member is unreadable, not tube, already an ensemble, or
    reads other views, channels, image size, pressure maxima or keypoint count than the
    first (the mismatch named).
    """
    paths = [checkpoint_dir(c) for c in checkpoints]
    if len(paths) < 2:
        raise CheckpointError(f'an ensemble needs two checkpoints or more, got {len(paths)}')
    loaded = [load_checkpoint(p) for p in paths]
    for path, (net, cfg) in zip(paths, loaded):
        if cfg['arch'] != 'tube':
            raise CheckpointError(f'{path}: architecture {cfg["arch"]!r}; ensembles average '
                                  'the tube model\'s keypoints')
        if len(net.members):
            raise CheckpointError(f'{path}: already an ensemble of {len(net.members) + 1}; '
                                  'give its members instead')
    first_net, first = loaded[0]
    for path, (net, cfg) in zip(paths[1:], loaded[1:]):
        bad = [f'{k} {cfg[k]!r} (first: {first[k]!r})' for k in SAME if cfg[k] != first[k]]
        if not np.allclose(cfg['max_pressure_pa'], first['max_pressure_pa'], rtol=1e-6):
            bad.append(f'max_pressure_pa {cfg["max_pressure_pa"]} '
                       f'(first: {first["max_pressure_pa"]})')
        if net.keypoints.template.shape != first_net.keypoints.template.shape:
            bad.append(f'keypoints {net.keypoints.k} (first: {first_net.keypoints.k})')
        if bad:
            raise CheckpointError(f'{path}: cannot join {paths[0]}\'s ensemble: it has '
                                  f'{"; ".join(bad)}')
    params = dict(first['arch_params'], members=len(paths))
    model = build_network('tube', len(first['views']), first['channels'], **params)
    state = dict(first_net.state_dict())
    for i, (net, _) in enumerate(loaded[1:]):
        state.update({f'members.{i}.{k}': v for k, v in net.keypoints.state_dict().items()})
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:         # a member's keypoint network of another size
        raise CheckpointError(f'cannot join {", ".join(map(str, paths))}: their keypoint '
                              f'networks differ: {exc}') from None
    config = {k: v for k, v in first.items()
              if k not in ('format', 'version', 'weights_file', 'weights_sha256')}
    config['arch_params'] = params
    config['ensemble'] = [{'checkpoint': str(p), 'weights_sha256': cfg['weights_sha256'],
                           'seed': cfg.get('training', {}).get('seed')}
                          for p, (_, cfg) in zip(paths, loaded)]
    return save_checkpoint(out, model, config)


def first_training(checkpoint):
    """
    Return (model, config) of ``checkpoint``'s first training alone (itself if not an ensemble).

    What a member looks like to the recipe's phases (they train one): the same tensors but
    the other members', the same config but ``members`` and the ``ensemble`` list.
    """
    model, cfg = load_checkpoint(checkpoint)
    if not len(getattr(model, 'members', ())):
        return model, cfg
    params = {k: v for k, v in cfg['arch_params'].items() if k != 'members'}
    one = build_network('tube', len(cfg['views']), cfg['channels'], **params)
    one.load_state_dict({k: v for k, v in model.state_dict().items()
                         if not k.startswith('members.')}, strict=True)
    cfg = {k: v for k, v in cfg.items() if k != 'ensemble'}
    return one.eval(), dict(cfg, arch_params=params)
