"""
The tube model: its renderer, one full-loss training step and its predictions, one thread.

What the 20 000-sample pre-training and ``softshape evaluate`` spend their time on (issue
18: train to early stopping in <= 30 min); the reader step also with the encoder in
bfloat16 (``--encoder-bf16``), the full-loss step also with the encoder in bfloat16 as the
recipe trains it, with ObjectNet and BackgroundNet too (``--scene-nets-bf16``), and with
the renderer compiled (``--compile-renderer``; its build, about 20 s, is not timed), with
all three and Adam fused (the recipe's full phase, ``full_loss_step_pretrain_s``), and
Adam's update alone, a loop over the parameters or fused (``--fused-adam``). Data:
128 stereo samples of the default contact-rich plan over 8 placements, simulated here
(shape record, contact record and placements, as training sees them, and the object depth
maps where the network has the depth test); network: the shipped checkpoint
(``run(checkpoint)``: another): its first training's for the steps, the whole checkpoint's
for the predictions.
"""

import tempfile
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_model import _latency
from softshape_ros.config import load_rig_config
from softshape_ros.demo.pipeline import PRETRAINED
from softshape_ros.model import Predictor
from softshape_ros.model.ensemble import first_training
from softshape_ros.experiments.object_depths import object_depths
from softshape_ros.model.data import scene_targets, shape_tensors, to_tensors
from softshape_ros.model.losses import TubeLoss
from softshape_ros.model.tube_net import (
    compiled_renderer, cpu_bf16_native, draw_field, encoder_bf16, scene_nets_bf16)
from softshape_ros.sim.generate import generate, make_plan

BATCH = 64


def _median_s(fn, n: int, warm: int = 2) -> float:
    """Return the median seconds of ``fn`` over ``n`` calls after ``warm``."""
    return _latency(fn, n=n, warm=warm)['median_ms'] / 1000


def _alternated(step, n: int, options=(False, True), rounds: int = 3) -> tuple[float, ...]:
    """Return the median seconds of ``step(option)`` per option, the options taken in turns."""
    times = {o: [] for o in options}
    for _ in range(rounds):
        for o in options:
            times[o].append(_median_s(lambda: step(o), n))
    return tuple(float(np.median(times[o])) for o in options)


def run(checkpoint=PRETRAINED) -> dict:
    restore = torch.get_num_threads()
    torch.set_num_threads(1)
    cfg = load_rig_config()
    with tempfile.TemporaryDirectory() as tmp:
        ds, _ = generate(cfg, make_plan(cfg, 128, 8, seed=11), Path(tmp) / 'ds',
                         ['main', 'side'], workers=1, progress=False)
        pred = Predictor.from_checkpoint(checkpoint)
        # The steps train one training, as the recipe's phases do (the shipped checkpoint is
        # two averaged); the predictions below are the checkpoint's own.
        net, _ = first_training(checkpoint)
        rows = np.arange(BATCH)
        x, t, p = to_tensors(ds, rows, ds.max_pressure_pa)
        truth, free = shape_tensors(ds, rows)
        scene = scene_targets(ds, rows)
        objects = object_depths(ds, rows)[rows] if net.depth_test else None
        out = {'batch': BATCH, 'threads': 1, 'depth_test': net.depth_test}

        def render(compiled=False):
            kp = truth.clone().requires_grad_(True)
            with compiled_renderer(compiled):
                f = draw_field(kp, 64)
            (f.sd.sum() + f.nz.sum() + f.depth.sum()).backward()
        out['render_fwd_bwd_ms'], out['render_fwd_bwd_compiled_ms'] = (
            round(1000 * v, 1) for v in _alternated(render, 10))

        objective = TubeLoss(threshold=pred.config['silhouette']['threshold'] / 255, channels=1)
        opt = torch.optim.Adam(net.parameters(), lr=1e-5)

        def step():
            net.train()
            loss, _ = objective(net, x, p, t, truth, free, scene, objects)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        s = _median_s(step, 6)
        out['full_loss_step_s'] = round(s, 3)
        out['full_loss_rows_per_s'] = round(BATCH / s, 1)

        # The reader phase's step (the scene term alone: the encoder), float32 and with its
        # convolutions in bfloat16 (TrainConfig.encoder_bf16); then the full-loss step with
        # the encoder in bfloat16 (the recipe), and with ObjectNet and BackgroundNet too
        # (TrainConfig.scene_nets_bf16), or with the renderer compiled
        # (TrainConfig.compile_renderer). Each set alternated. The recipe's batches of 64
        # rows hold about 64 placements, these 8: each row made its own by faint noise.
        reader = TubeLoss(scene_only=True, channels=1)
        xr = x + 1e-3 * torch.rand(x.shape, generator=torch.Generator().manual_seed(0))

        adams = {False: opt, True: torch.optim.Adam(net.parameters(), lr=1e-5, fused=True)}

        def train_step(loss_fn, encoder, nets, compiled=False, fused=False):
            net.train()
            with encoder_bf16(encoder), scene_nets_bf16(nets), compiled_renderer(compiled):
                loss, _ = loss_fn(net, xr, p, t, truth, free, scene, objects)
            adams[fused].zero_grad(set_to_none=True)
            loss.backward()
            adams[fused].step()
        reader_s = _alternated(lambda bf16: train_step(reader, bf16, False), 4)
        out['reader_step_s'], out['reader_step_bf16_s'] = (round(v, 4) for v in reader_s)
        # The last: all three with Adam fused, the step `softshape pretrain --arch tube`'s
        # full phase takes (its defaults since docs/model.md, "The 30 minutes").
        full_s = _alternated(lambda extra: train_step(objective, True, *extra), 3,
                             options=((False, False, False), (True, False, False),
                                      (False, True, False), (True, True, True)))
        (out['full_loss_step_encoder_bf16_s'], out['full_loss_step_scene_nets_bf16_s'],
         out['full_loss_step_compiled_renderer_s'],
         out['full_loss_step_pretrain_s']) = (round(v, 3) for v in full_s)
        # Adam's update alone, the last step's gradients in place: the loop over the
        # parameters (the default) and one fused kernel (TrainConfig.fused_adam).
        out['adam_step_ms'], out['adam_step_fused_ms'] = (
            round(1000 * v, 2) for v in _alternated(lambda fused: adams[fused].step(), 20))
        out['cpu_bf16_supported'] = cpu_bf16_native()
        net.eval()
        initial = np.asarray(ds.initial[:BATCH])
        pressures = list(np.asarray(ds.pressure[:BATCH]))
        with torch.no_grad():
            out['predict_batch64_ms'] = round(1000 * _median_s(
                lambda: pred.predict_batch(initial, pressures), 10), 1)
            out['predict_batch1_ms'] = round(1000 * _median_s(
                lambda: pred.predict(initial[0], pressures[0]), 50, warm=5), 2)
    torch.set_num_threads(restore)
    return out
