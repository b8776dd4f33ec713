"""
ONNX export with torch.onnx's dynamo exporter, checked against PyTorch before it is kept.

The ONNX graph has inputs ``image`` (B x V*C x 64 x 64 float, 0-1) and ``pressure``
(B x 6, Pa / max) and output ``predicted`` (same units as ``image``); the batch is dynamic.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch

from softshape_ros.model.checkpoint import load_checkpoint

TOLERANCE = 1e-4


def run_onnx(path, image: np.ndarray, pressure: np.ndarray) -> np.ndarray:
    """Run an exported model with onnxruntime (CPU)."""
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=['CPUExecutionProvider'])
    return sess.run(['predicted'], {'image': image.astype(np.float32),
                                    'pressure': pressure.astype(np.float32)})[0]


def export_onnx(checkpoint, out, batch: int = 4, seed: int = 0) -> dict:
    """Export ``checkpoint`` to ``out`` (.onnx); raise RuntimeError if outputs differ > 1e-4."""
    model, cfg = load_checkpoint(checkpoint)
    vc = len(cfg['views']) * cfg['channels']
    s = cfg['image_size']
    gen = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, vc, s, s, generator=gen)
    pressure = torch.rand(batch, 6, generator=gen)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    b = torch.export.Dim('batch', min=1, max=4096)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        program = torch.onnx.export(
            model, (image, pressure), dynamo=True, input_names=['image', 'pressure'],
            output_names=['predicted'], dynamic_shapes=({0: b}, {0: b}), verbose=False)
    program.save(str(out))
    meta = out.with_suffix('.json')
    with torch.no_grad():
        ref = model(image, pressure).numpy()
    got = run_onnx(out, image.numpy(), pressure.numpy())
    err = float(np.max(np.abs(got - ref)))
    if not err <= TOLERANCE:
        out.unlink(missing_ok=True)
        raise RuntimeError(f'{out}: ONNX output differs from PyTorch by {err:.2e} '
                           f'(> {TOLERANCE:g}); export discarded')
    info = {'onnx': str(out), 'max_abs_diff': err, 'batch_checked': batch,
            'inputs': {'image': ['B', vc, s, s], 'pressure': ['B', 6]},
            'outputs': {'predicted': ['B', vc, s, s]}, 'checkpoint_config': cfg}
    meta.write_text(json.dumps(info, indent=2))
    return info
