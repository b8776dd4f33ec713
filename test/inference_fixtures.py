"""
Shared by the inference tests: a small simulated stereo dataset and a model trained on it.

Built once per test session (a few seconds): the simulator writes the dataset, the real
training loop trains the real ``ours`` network for a few dozen steps, the checkpoint is saved.
"""

from pathlib import Path

from softshape_ros.config import load_rig_config
from softshape_ros.model.train import TrainConfig, train
from softshape_ros.sim.generate import generate, make_plan


def make_trained_checkpoint(root: Path, views=('main', 'side'), steps: int = 30) -> Path:
    cfg = load_rig_config()
    ds_path = root / 'dataset'
    generate(cfg, make_plan(cfg, 48, 4, seed=3), ds_path, views=list(views), workers=1,
             progress=False)
    ckpt = root / 'model'
    train(str(ds_path), TrainConfig(arch='ours', max_steps=steps, batch_size=16, eval_every=10,
                                    threads=2), out=ckpt, progress=False)
    return ckpt
