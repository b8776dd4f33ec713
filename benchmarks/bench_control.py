"""
Shape control: planning time per closed-loop step on one CPU thread.

Every plan runs its whole budget (no early stop), so the figure is the worst case a step
can cost, whatever the model's quality: the bank scored against the goal, then the
Levenberg-Marquardt steps (7 images per step). Re-plans carry a correction and a trust
region, as after a camera observation. The model is ``$SOFTSHAPE_BENCH_MODEL`` or
``demo_out/model`` when there is one, else an untrained ``ours`` network with random
weights (the same arithmetic). Beside it, in the same run, the model's batch-1 prediction
time: the reference for how loaded the machine was.
"""

import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from softshape_ros.config import load_rig_config
from softshape_ros.control import Bank, Goal, GoalSpec, Planner, PlannerConfig, SceneContext
from softshape_ros.control.evaluate import make_goals
from softshape_ros.control.forward import NetworkForward
from softshape_ros.control.objective import Objective
from softshape_ros.model import Predictor, build_network, save_checkpoint


def _model(tmp: Path) -> tuple[Predictor, str]:
    path = os.environ.get('SOFTSHAPE_BENCH_MODEL') or 'demo_out/model'
    if (Path(path) / 'config.json').is_file():
        return Predictor.from_checkpoint(path), path
    torch.manual_seed(0)
    net = build_network('ours', 2, 1)
    with torch.no_grad():
        for p in net.parameters():          # zero-initialised FiLM/head would copy the input
            p.normal_(0.0, 0.05)
    ck = save_checkpoint(tmp / 'ours', net, {
        'arch': 'ours', 'arch_params': {}, 'views': ['main', 'side'], 'channels': 1,
        'image_size': 64, 'max_pressure_pa': [150000.0] * 6})
    return Predictor.from_checkpoint(ck), 'untrained ours (random weights)'


def _ms(ts) -> dict:
    a = np.asarray(ts) * 1e3
    return {'median': round(float(np.median(a)), 1),
            'p90': round(float(np.percentile(a, 90)), 1)}


def run() -> dict:
    restore = torch.get_num_threads()
    torch.set_num_threads(1)
    cfg = load_rig_config()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            pred, which = _model(Path(tmp))
            goals = make_goals(cfg, 6, seed=0, views=pred.views, progress=False)
            planner = Planner(PlannerConfig(min_gain=0.0))      # always the whole budget
            spec = GoalSpec.of(pred)
            first, replan, bank_ms, evals = [], [], [], []
            for g in goals:
                net = NetworkForward(pred, g.rest, cfg.max_pressures_pa)
                ctx = SceneContext.from_initial(g.rest)
                bank = Bank.for_scene(net, ctx, planner.cfg.bank_size)
                bank_ms.append(bank.build_ms / 1e3)
                obj = Objective(ctx, Goal.images(spec, g.images))
                t0 = time.perf_counter()
                plan = planner.plan(obj, net, bank)
                first.append(time.perf_counter() - t0)
                evals.append(plan.evaluations)
                # As after an observation: the camera saw the goal's own images.
                obj.set_correction(g.images, net(torch.from_numpy(plan.u[None]).float())[0],
                                   plan.u)
                obj.anchor_at(plan.u, 1.0)
                t0 = time.perf_counter()
                planner.plan(obj, net, bank, warm=plan.u)
                replan.append(time.perf_counter() - t0)
            x, p = goals[0].rest, goals[0].pressures_pa
            for _ in range(10):
                pred.predict(x, p)
            ts = []
            for _ in range(100):
                t0 = time.perf_counter()
                pred.predict(x, p)
                ts.append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(restore)
    return {'model': which, 'threads': 1, 'plans': len(first),
            'plan_ms_first_step': _ms(first), 'plan_ms_replan': _ms(replan),
            'model_images_per_plan': int(np.median(evals)),
            'bank_build_ms': _ms(bank_ms), 'bank_size': planner.cfg.bank_size,
            'reference_predict_batch1_ms': _ms(ts),
            'load_average_1min': round(os.getloadavg()[0], 2)}
