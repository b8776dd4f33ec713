"""
Evaluate a checkpoint on dataset rows; draw the paper's Fig. 4 style prediction panels.

Figures are matplotlib PNGs (Agg backend, no display needed).
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib
import numpy as np

from softshape_ros.data import load_dataset
from softshape_ros.model.data import no_contact_why, touching_flags
from softshape_ros.model.metrics import RobotSilhouette, evaluate_arrays, yellow_mask
from softshape_ros.model.predictor import Predictor

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402

YELLOW = np.array([255, 220, 0], dtype=np.uint8)


def predict_rows(pred: Predictor, ds, idx, batch: int = 256) -> np.ndarray:
    """Predictions for dataset rows ``idx`` (N x V x C x S x S uint8)."""
    out = []
    for i in range(0, len(idx), batch):
        rows = idx[i:i + batch]
        out.append(pred.predict_batch(np.asarray(ds.initial[rows]),
                                      np.asarray(ds.pressure[rows], dtype=np.float64)))
    shape = (0,) + pred.image_shape
    return np.concatenate(out) if out else np.zeros(shape, np.uint8)


def check_compatible(pred: Predictor, ds) -> None:
    """Refuse a dataset the model was not built for, naming what differs."""
    want = {'views': list(pred.views), 'channels': pred.channels,
            'image size': pred.image_size}
    got = {'views': list(ds.views), 'channels': ds.channels,
           'image size': int(ds.meta.get('image_size', 64))}
    bad = [f'{k} {got[k]} (the model expects {want[k]})' for k in want if want[k] != got[k]]
    if bad:
        raise ValueError(f'{ds.path}: the dataset has {"; ".join(bad)}')


def evaluate(checkpoint, dataset, indices=None, out_dir=None, panels: int = 6,
             silhouette: RobotSilhouette | None = None) -> dict:
    """
    Metrics of ``checkpoint`` on ``dataset`` rows (default all); figures to ``out_dir``.

    Every metric over all rows, and split into touching / free rows where the dataset
    records contact (``metrics.json``: ``model``, ``copy``, ``touching``, ``free``).
    """
    pred = Predictor.from_checkpoint(checkpoint)
    ds = load_dataset(dataset) if isinstance(dataset, (str, Path)) else dataset
    check_compatible(pred, ds)
    idx = np.arange(len(ds)) if indices is None else np.sort(np.asarray(indices))
    if len(idx) == 0:
        raise ValueError(f'{ds.path}: no rows to evaluate')
    initial, target = np.asarray(ds.initial[idx]), np.asarray(ds.target[idx])
    predicted = predict_rows(pred, ds, idx)
    sil = silhouette or RobotSilhouette.fit(np.asarray(ds.initial))
    result = evaluate_arrays(initial, target, predicted, sil, touching_flags(ds, idx),
                             no_contact_why(ds))
    result.update(checkpoint=str(checkpoint), dataset=str(ds.path), arch=pred.config['arch'],
                  views=pred.views, silhouette_threshold=sil.threshold)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / 'metrics.json').write_text(json.dumps(result, indent=2))
        pick = np.linspace(0, len(idx) - 1, min(panels, len(idx))).astype(int)
        prediction_panels(initial[pick], target[pick], predicted[pick], pred.views,
                          out / 'panels.png', title=f'{pred.config["arch"]}: {ds.path.name}')
    return result


def _rgb(img: np.ndarray) -> np.ndarray:
    """C x S x S uint8 -> S x S x 3 for display."""
    return np.repeat(img, 3, axis=0).transpose(1, 2, 0) if img.shape[0] == 1 \
        else img.transpose(1, 2, 0)


def prediction_panels(initial, target, predicted, views, path, title: str = '',
                      row_labels=None) -> Path:
    """Fig. 4 layout: per sample and view, initial | ground truth | prediction | yellow mask."""
    n, v = initial.shape[:2]
    cols = ['initial', 'ground truth', 'prediction', 'error mask']
    fig, axes = plt.subplots(n, 4 * v, figsize=(1.6 * 4 * v, 1.7 * n + 0.4), squeeze=False)
    masks = yellow_mask(predicted, target)
    for i in range(n):
        for j in range(v):
            overlay = _rgb(predicted[i, j]).copy()
            overlay[masks[i, j]] = YELLOW
            for k, img in enumerate((_rgb(initial[i, j]), _rgb(target[i, j]),
                                     _rgb(predicted[i, j]), overlay)):
                ax = axes[i, 4 * j + k]
                ax.imshow(img, interpolation='nearest')
                ax.set_xticks([])
                ax.set_yticks([])
                if i == 0:
                    ax.set_title(f'{views[j]}: {cols[k]}', fontsize=7)
            if row_labels is not None and j == 0:
                axes[i, 0].set_ylabel(row_labels[i], fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)
