"""
Checkpoints: a folder with ``model.safetensors`` (weights) and ``config.json`` (everything else).

Loading never unpickles. ``config.json`` records the SHA-256 of the weights file, so a
truncated, corrupted or swapped weights file is refused with the file named, and the
weights must match the declared architecture exactly (names, shapes, dtypes).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save

from softshape_ros.model.networks import ARCHS, build_network

FORMAT = 'softshape-checkpoint'
VERSION = 1
WEIGHTS = 'model.safetensors'
CONFIG = 'config.json'
REQUIRED = {'format': str, 'version': int, 'arch': str, 'arch_params': dict, 'views': list,
            'channels': int, 'image_size': int, 'max_pressure_pa': list,
            'weights_sha256': str}


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt, tampered with or does not match its config."""


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def checkpoint_dir(path) -> Path:
    """Accept the folder or either file in it."""
    p = Path(path)
    if p.name in (WEIGHTS, CONFIG) or p.suffix in ('.json', '.safetensors'):
        return p.parent
    return p


def save_checkpoint(path, model: torch.nn.Module, config: dict) -> Path:
    """Write weights then config (with the weights' hash); returns the folder."""
    d = checkpoint_dir(path)
    d.mkdir(parents=True, exist_ok=True)
    weights = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tmp = d / (WEIGHTS + '.tmp')
    # Written by Python, not safetensors' save_file, whose files are private (0600): a
    # checkpoint must be readable by the node's user as config.json is (the umask decides).
    tmp.write_bytes(save(weights, metadata={'format': FORMAT}))
    os.replace(tmp, d / WEIGHTS)
    cfg = dict(config, format=FORMAT, version=VERSION, weights_file=WEIGHTS,
               weights_sha256=_sha256(d / WEIGHTS))
    tmp = d / (CONFIG + '.tmp')
    tmp.write_text(json.dumps(cfg, indent=2, sort_keys=True))
    os.replace(tmp, d / CONFIG)
    return d


def read_config(path) -> dict:
    """Read and check ``config.json`` of a checkpoint folder."""
    f = checkpoint_dir(path) / CONFIG
    try:
        cfg = json.loads(f.read_text())
    except FileNotFoundError:
        raise CheckpointError(f'{f}: checkpoint config missing') from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f'{f}: unreadable checkpoint config: {exc}') from None
    if not isinstance(cfg, dict):
        raise CheckpointError(f'{f}: expected a JSON object')
    for key, typ in REQUIRED.items():
        if not isinstance(cfg.get(key), typ):
            raise CheckpointError(f'{f}: field {key!r} missing or not {typ.__name__}')
    if cfg['format'] != FORMAT or cfg['version'] != VERSION:
        raise CheckpointError(f'{f}: not a {FORMAT} v{VERSION} file')
    if cfg['arch'] not in ARCHS:
        raise CheckpointError(f'{f}: unknown architecture {cfg["arch"]!r}')
    if cfg['channels'] not in (1, 3) or not cfg['views'] or cfg['image_size'] != 64:
        raise CheckpointError(f'{f}: bad views/channels/image_size')
    mp = cfg['max_pressure_pa']
    if len(mp) != 6 or not all(isinstance(v, (int, float)) and v > 0 for v in mp):
        raise CheckpointError(f'{f}: max_pressure_pa must be 6 positive numbers')
    return cfg


def load_checkpoint(path):
    """Return (model in eval mode, config) from a checkpoint folder; raise CheckpointError."""
    d = checkpoint_dir(path)
    cfg = read_config(d)
    wf = d / WEIGHTS
    if not wf.is_file():
        raise CheckpointError(f'{wf}: checkpoint weights missing')
    if _sha256(wf) != cfg['weights_sha256']:
        raise CheckpointError(f'{wf}: weights do not match the hash in {CONFIG} '
                              '(truncated, corrupted or replaced)')
    try:
        weights = load_file(str(wf))
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f'{wf}: unreadable safetensors file: {exc}') from None
    try:
        model = build_network(cfg['arch'], len(cfg['views']), cfg['channels'],
                              **cfg['arch_params'])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f'{d / CONFIG}: bad arch_params: {exc}') from None
    expected = model.state_dict()
    if set(weights) != set(expected):
        missing = sorted(set(expected) - set(weights))[:3]
        extra = sorted(set(weights) - set(expected))[:3]
        raise CheckpointError(f'{wf}: tensors do not match the {cfg["arch"]} network '
                              f'(missing {missing}, unexpected {extra})')
    for k, v in expected.items():
        if weights[k].shape != v.shape or weights[k].dtype != v.dtype:
            raise CheckpointError(f'{wf}: tensor {k} is {tuple(weights[k].shape)} '
                                  f'{weights[k].dtype}, expected {tuple(v.shape)} {v.dtype}')
    model.load_state_dict(weights, strict=True)
    model.eval()
    return model, cfg
