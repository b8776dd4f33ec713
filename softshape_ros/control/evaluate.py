"""
``softshape control-eval``: the closed loop on the simulated rig, against two baselines.

Goals are the simulator's own images of random actuations (uniform in the limits, like the
training data) in held-out object placements, half of them touching the object. Each goal
is run three ways with the same loop and tolerance: the planner through the learned model,
random search with the same budget through the same model, and the planner through the
simulator itself (the oracle: what a perfect model would allow). The plant is always the
simulator, filmed the way the dataset is (crop, gray, 64 x 64).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from softshape_ros.config import RigConfig
from softshape_ros.control.features import SceneContext
from softshape_ros.control.forward import NetworkForward, SimForward
from softshape_ros.control.goal import Goal, GoalSpec
from softshape_ros.control.loop import ShapeLoop, Tolerance
from softshape_ros.control.planner import Bank, Planner, PlannerConfig, RandomSearch
from softshape_ros.scene import Scene

HELD_OUT_ID = 5000           # scene ids of the evaluation placements
MAX_DRAWS = 300              # actuations tried per scene for a touching / free goal
MIN_PRESS_M = 0.002          # a touching goal's tip is this far from its free position
METHODS = ('model', 'random', 'oracle')


@dataclass
class EvalGoal:
    """One goal: a placement, the actuation that made it, its images, whether it touches."""

    scene: Scene
    pressures_pa: np.ndarray
    images: np.ndarray               # V x C x S x S uint8
    touching: bool
    rest: np.ndarray                 # V x C x S x S uint8, the scene's initial images


@dataclass
class EvalSettings:
    """What shapes a control evaluation."""

    goals: int = 20
    seed: int = 0
    goals_per_scene: int = 2
    max_iterations: int = 3
    tolerance: Tolerance = field(default_factory=Tolerance)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    methods: tuple = METHODS
    contact_goals: bool = False     # ask touching goals to touch, free ones to stay clear
    threads: int = 1


def make_goals(cfg: RigConfig, n: int, seed: int, views, size: int = 64, gray: bool = True,
               per_scene: int = 2, progress: bool = True) -> list[EvalGoal]:
    """
    Draw ``n`` goals, alternately touching and free, ``per_scene`` per held-out placement.

    A touching goal is pressed against the object: its tip is at least
    :data:`MIN_PRESS_M` from where the robot would be without the object (a graze that
    leaves the shape as it is would be a free goal in all but name). A free goal touches
    nothing.
    """
    from softshape_ros.sim import SimRig
    from softshape_ros.sim.generate import OBJECT_CYCLE, random_scene
    rng = np.random.default_rng(seed + 7919)
    limits = np.asarray(cfg.max_pressures_pa, dtype=np.float64)
    goals: list[EvalGoal] = []
    k = 0
    bar = tqdm(total=n, desc='goals', unit='goal', disable=not progress)
    while len(goals) < n:
        scene = random_scene(HELD_OUT_ID + k, OBJECT_CYCLE[k % 3], rng, cfg)
        k += 1
        sim = SimForward(cfg, scene, views, limits, size, gray)
        free = SimRig(cfg, contact=False)
        rest = sim.images(np.zeros(6))
        for _ in range(per_scene):
            if len(goals) == n:
                break
            want = len(goals) % 2 == 0                   # touching first, then free
            got = None
            for _ in range(MAX_DRAWS):
                p = rng.uniform(0.0, 1.0, 6) * limits
                try:
                    st = sim.rig.solve(p)
                except Exception:
                    sim.rig.set_scene(scene)
                    continue
                touching = any(c.gap_m < 0 for c in st.contacts)
                if touching and want:
                    press = np.linalg.norm(free.solve(p).tip_pose[:3, 3] - st.tip_pose[:3, 3])
                    touching = press >= MIN_PRESS_M
                    if not touching:
                        continue                         # a graze: neither kind
                if touching == want:
                    img = sim.rig.render_inputs(st, size, gray, sim.supersample, views)
                    got = EvalGoal(scene, st.pressures_pa.copy(),
                                   np.stack([img[v] for v in views]), want, rest)
                    break
            if got is None:
                break                                    # this placement cannot: next one
            goals.append(got)
            bar.update(1)
    bar.close()
    return goals


def _run_loop(loop: ShapeLoop, plant: SimForward) -> dict:
    """Close the loop on the simulator; return what happened per iteration and the best."""
    steps, seen, touched = [], [], []
    while not loop.done:
        plan = loop.plan()
        seen.append(plant.images(plan.pressures_pa))
        touched.append(plant.touching)
        obs = loop.observe(seen[-1])
        steps.append({'plan_ms': plan.plan_ms, 'evaluations': plan.evaluations,
                      'predicted_cost': plan.cost, 'predicted_error': plan.predicted_error,
                      'touching': touched[-1], **obs.to_dict()})
    b = loop.best
    return {'success': loop.success, 'iterations': loop.iteration, 'steps': steps,
            'best': b, 'reached': seen[b], 'plan': loop.plans[b], 'touching': touched[b]}


def pressure_errors(p, goal_p) -> dict:
    """Pressure error in kPa: raw, and without each segment's common mode (which bends nothing)."""
    d = (np.asarray(p) - np.asarray(goal_p)) / 1e3
    seg = d.reshape(2, 3)
    diff = seg - seg.mean(axis=1, keepdims=True)
    return {'rms_kpa': float(np.sqrt(np.mean(d ** 2))),
            'differential_rms_kpa': float(np.sqrt(np.mean(diff ** 2)))}


def evaluate_control(predictor, cfg: RigConfig, settings: EvalSettings, out_dir=None,
                     progress: bool = True) -> dict:
    """Run every goal with every method; write ``control.json`` and ``control.png``."""
    import torch
    if settings.threads:
        torch.set_num_threads(settings.threads)
    spec = GoalSpec.of(predictor)
    views = list(spec.views)
    limits = np.asarray(cfg.max_pressures_pa, dtype=np.float64)
    goals = make_goals(cfg, settings.goals, settings.seed, views, spec.size,
                       spec.channels == 1, settings.goals_per_scene, progress)
    methods = [m for m in METHODS if m in settings.methods]
    if 'random' in methods and 'model' not in methods:
        raise ValueError('random search takes its budget from the model planner: '
                         'run "model" too')
    planner = Planner(settings.planner)
    rows = {m: [] for m in methods}
    banks: dict = {}
    build_ms = {m: [] for m in methods if m != 'random'}
    bar = tqdm(total=len(goals) * len(methods), desc='control', unit='loop',
               disable=not progress)
    for gi, g in enumerate(goals):
        ctx = SceneContext.from_initial(g.rest)
        contact = ('touch' if g.touching else 'clear') if settings.contact_goals else 'any'
        goal = Goal.images(spec, g.images, contact)
        plant = SimForward(cfg, g.scene, views, limits, spec.size, spec.channels == 1)
        net = NetworkForward(predictor, g.rest, limits)
        if g.scene.id not in banks:
            # One scene at a time: its banks are dropped when the next scene starts.
            banks = {g.scene.id: _scene_banks(methods, net, ctx, cfg, g.scene, views, limits,
                                              spec, settings, build_ms)}
        bank = banks[g.scene.id]
        for m in methods:
            t0 = time.perf_counter()
            if m == 'model':
                loop = ShapeLoop(net, ctx, goal, planner, bank['model'],
                                 settings.tolerance, settings.max_iterations)
            elif m == 'random':
                budget = settings.planner.bank_size + (
                    _budget(rows['model'][-1]) if rows['model'] else 0)
                loop = ShapeLoop(net, ctx, goal, RandomSearch(budget, settings.seed + gi),
                                 bank['model'], settings.tolerance, settings.max_iterations)
            else:
                oracle_bank, sim = bank['oracle']
                loop = ShapeLoop(sim, ctx, goal, planner, oracle_bank, settings.tolerance,
                                 settings.max_iterations)
            rows[m].append(_row(gi, g, _run_loop(loop, plant), settings.max_iterations,
                                time.perf_counter() - t0))
            bar.update(1)
    bar.close()
    summary = summarise(rows, settings)
    summary['goals'] = len(goals)
    summary['bank_build_ms_median'] = {m: float(np.median(v)) for m, v in build_ms.items() if v}
    if out_dir is not None:
        summary['figure'] = _write(Path(out_dir), summary, goals, rows, views)
    return summary


def _scene_banks(methods, net, ctx, cfg, scene, views, limits, spec, settings,
                 build_ms: dict) -> dict:
    """Build the start banks of one scene: the model's and the simulator oracle's."""
    banks = {}
    if 'model' in methods:
        banks['model'] = Bank.for_scene(net, ctx, settings.planner.bank_size,
                                        settings.planner.seed)
        build_ms['model'].append(banks['model'].build_ms)
    if 'oracle' in methods:
        sim = SimForward(cfg, scene, views, limits, spec.size, spec.channels == 1)
        banks['oracle'] = (Bank.for_scene(sim, ctx, settings.planner.bank_size,
                                          settings.planner.seed), sim)
        build_ms['oracle'].append(banks['oracle'][0].build_ms)
    return banks


def _row(gi: int, g, res: dict, max_iterations: int, seconds: float) -> dict:
    """Return one goal's record for one method (keys with ``_`` stay out of the JSON)."""
    best = res['steps'][res['best']]
    return {
        'goal': gi, 'scene': int(g.scene.id), 'object': g.scene.object,
        'touching': g.touching, 'success': res['success'],
        'iterations': res['iterations'],
        'success_within': [bool(any(s['success'] for s in res['steps'][:i + 1]))
                           for i in range(max_iterations)],
        'plan_ms': [s['plan_ms'] for s in res['steps']],
        'evaluations': [s['evaluations'] for s in res['steps']],
        'final_tip_error_px': best['tip_error_px'], 'final_iou': best['iou'],
        'final_contact_as_goal': res['touching'] == g.touching,
        'pressure_error': pressure_errors(res['plan'].pressures_pa, g.pressures_pa),
        'goal_pressures_pa': g.pressures_pa, 'steps': res['steps'],
        'seconds': seconds, '_reached': res['reached'], '_plan': res['plan'].predicted}


def _write(out: Path, summary: dict, goals, rows: dict, views) -> str:
    """Write ``control.json`` (summary and every goal) and the figure; return its path."""
    out.mkdir(parents=True, exist_ok=True)
    clean = {m: [{k: v for k, v in r.items() if not k.startswith('_')} for r in rs]
             for m, rs in rows.items()}
    (out / 'control.json').write_text(json.dumps({'summary': summary, 'goals': clean},
                                                 indent=2, default=_json))
    return str(goal_figure(goals, rows, views, out / 'control.png'))


def _budget(row: dict) -> int:
    """Return the model calls of the model planner's first plan beyond its bank."""
    return int(row['evaluations'][0])


def _json(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    raise TypeError(type(o).__name__)


def summarise(rows: dict, settings: EvalSettings) -> dict:
    """Success rates (all, touching, free, within 1..N iterations), medians, per method."""
    out = {'tolerance': {'tip_px': settings.tolerance.tip_px, 'iou': settings.tolerance.iou},
           'max_iterations': settings.max_iterations, 'contact_goals': settings.contact_goals}
    for m, rs in rows.items():
        if not rs:
            continue
        succ = np.array([r['success'] for r in rs])
        touch = np.array([r['touching'] for r in rs])
        plan_ms = [ms for r in rs for ms in r['plan_ms']]
        out[m] = {
            'success_rate': float(succ.mean()),
            'success_rate_touching': float(succ[touch].mean()) if touch.any() else None,
            'success_rate_free': float(succ[~touch].mean()) if (~touch).any() else None,
            'success_within_iterations': [float(np.mean([r['success_within'][i] for r in rs]))
                                          for i in range(settings.max_iterations)],
            'iterations_median': float(np.median([r['iterations'] for r in rs])),
            'plan_ms_median': float(np.median(plan_ms)),
            'plan_ms_p90': float(np.percentile(plan_ms, 90)),
            'evaluations_median': float(np.median([e for r in rs for e in r['evaluations']])),
            'final_tip_error_px_median': float(np.median([max(r['final_tip_error_px'])
                                                          for r in rs])),
            'final_iou_median': float(np.median([r['final_iou'] for r in rs])),
            'final_contact_as_goal_rate': float(np.mean([r['final_contact_as_goal']
                                                         for r in rs])),
            'final_pressure_error_kpa_median': float(np.median(
                [r['pressure_error']['rms_kpa'] for r in rs])),
            'final_differential_pressure_error_kpa_median': float(np.median(
                [r['pressure_error']['differential_rms_kpa'] for r in rs])),
        }
    if 'model' in out and 'oracle' in out:
        out['gap_to_oracle_points'] = 100 * (out['oracle']['success_rate']
                                             - out['model']['success_rate'])
    return out


def goal_figure(goals, rows, views, path, n: int = 6) -> Path:
    """Goal | model plan (predicted) | reached, per method, for a few goals (PNG)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    pick = np.linspace(0, len(goals) - 1, min(n, len(goals))).astype(int)
    methods = list(rows)
    cols = ['goal'] + [f'{m}: {w}' for m in methods for w in ('plan', 'reached')]
    v = len(views)
    fig, axes = plt.subplots(len(pick) * v, len(cols),
                             figsize=(1.5 * len(cols), 1.55 * len(pick) * v + 0.5),
                             squeeze=False)
    for i, gi in enumerate(pick):
        g = goals[gi]
        for j in range(v):
            row = i * v + j
            imgs = [g.images[j]]
            labels = [f'{"touch" if g.touching else "free"} {views[j]}']
            for m in methods:
                r = rows[m][gi]
                imgs += [r['_plan'][j], r['_reached'][j]]
                labels += ['', f'{"ok" if r["success"] else "miss"} it {r["iterations"]}']
            for k, img in enumerate(imgs):
                ax = axes[row, k]
                ax.imshow(img[0] if img.shape[0] == 1 else img.transpose(1, 2, 0),
                          cmap='gray', vmin=0, vmax=255, interpolation='nearest')
                ax.set_xticks([])
                ax.set_yticks([])
                if row == 0:
                    ax.set_title(cols[k], fontsize=7)
                if labels[k]:
                    ax.set_xlabel(labels[k], fontsize=6)
    fig.suptitle('interaction-shape control: goal / plan / reached', fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)
