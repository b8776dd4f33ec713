"""
Simulated training data like the paper's (IV-B): random object placements, random actuations.

Scenes cycle through cylinder, ring and oblique prism placed around the hanging robot at a
random azimuth, height and surface gap (0-8 mm), so that a good share of random actuations
within the chamber limits really touch the object. Every sample is drawn up front from one
seed, and each scene is simulated by one worker process from its own seed, so a dataset is
the same whatever the number of processes.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
from dataclasses import dataclass

import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.scene import Scene
from softshape_ros.sim.statics import SolverError

OBJECT_CYCLE = ('cylinder', 'ring', 'prism')
MAX_GAP_M = 0.006
MAX_RETRIES = 5


def random_scene(scene_id: int, kind: str, rng: np.random.Generator, cfg: RigConfig) -> Scene:
    """Place one object of ``kind`` next to the robot at a random azimuth, gap and height."""
    r_robot = max(s.radius_m for s in cfg.robot.segments)
    base = np.asarray(cfg.robot.base_position_m, dtype=float)
    length = cfg.robot.total_length_m
    az = rng.uniform(0.0, 2 * math.pi)
    gap = rng.uniform(0.0, MAX_GAP_M)
    radial = np.array([math.cos(az), math.sin(az), 0.0])
    z = base[2] - length * rng.uniform(0.35, 0.85)
    if kind == 'cylinder':
        radius = rng.uniform(0.005, 0.010)
        dist = r_robot + gap + radius
        dims = {'radius_m': radius, 'height_m': rng.uniform(0.035, 0.055)}
        rpy = (0.0, 0.0, 0.0)
        z = base[2] - length * rng.uniform(0.5, 1.0)
    elif kind == 'ring':
        major, minor = rng.uniform(0.009, 0.014), rng.uniform(0.0025, 0.004)
        dist = r_robot + gap + major + minor
        dims = {'major_radius_m': major, 'minor_radius_m': minor}
        # The ring stands upright in the plane through the robot axis (rim towards it).
        rpy = (math.pi / 2, 0.0, az + math.pi)
        z = base[2] - length * rng.uniform(0.45, 0.8)
    elif kind == 'prism':
        w, d = rng.uniform(0.008, 0.014), rng.uniform(0.008, 0.014)
        h, skew = rng.uniform(0.035, 0.055), rng.uniform(-0.35, 0.35)
        # The slanted faces lean by h/2 tan(skew) at the ends: keep those clear at rest.
        dist = r_robot + gap + w / 2 + h / 2 * abs(math.tan(skew))
        dims = {'width_m': w, 'depth_m': d, 'height_m': h, 'skew_rad': skew}
        rpy = (0.0, 0.0, az)
        z = base[2] - length * rng.uniform(0.5, 1.0)
    else:
        raise ValueError(f'random scenes are cylinder, ring or prism, not {kind!r}')
    pos = base[:2] + dist * radial[:2]
    return Scene(id=scene_id, object=kind, position_m=(float(pos[0]), float(pos[1]), float(z)),
                 rpy_rad=rpy, dims=dims, label=f'random {kind}')


@dataclass
class Plan:
    """Everything a dataset needs, drawn up front from the seed."""

    scenes: list
    sample_scene: np.ndarray        # (N,) index into scenes
    pressures: np.ndarray           # (N, 6) Pa
    seed: int


def make_plan(cfg: RigConfig, samples: int, scenes, seed: int) -> Plan:
    """Draw scenes (an int: how many random ones; or a list of Scene) and actuations."""
    if samples < 1:
        raise ValueError(f'--samples must be >= 1, got {samples}')
    rng = np.random.default_rng(seed)
    if isinstance(scenes, int):
        if scenes < 1:
            raise ValueError(f'--scenes must be >= 1, got {scenes}')
        scene_list = [random_scene(i, OBJECT_CYCLE[i % 3], rng, cfg) for i in range(scenes)]
    else:
        scene_list = list(scenes)
        if not scene_list:
            raise ValueError('no scenes given')
    s = len(scene_list)
    sample_scene = np.sort(np.arange(samples) % s)
    limits = np.asarray(cfg.max_pressures_pa, dtype=float)
    pressures = rng.uniform(0.0, 1.0, (samples, 6)) * limits
    return Plan(scene_list, sample_scene, pressures, seed)


# -- worker side ------------------------------------------------------------------------
_WORKER = {}


def _init_worker(cfg, size, gray, views, supersample, noise):
    os.environ.setdefault('OMP_NUM_THREADS', '1')
    _WORKER.update(cfg=cfg, size=size, gray=gray, views=views, supersample=supersample,
                   noise=noise)


def simulate_scene(job):
    """Simulate one scene: rest images, then each actuation. Runs in a worker process."""
    from softshape_ros.sim.rig import SimRig
    w = _WORKER
    scene_index, scene, indices, pressures, seed = job
    rig = SimRig(w['cfg'], seed=seed, image_noise_std=w['noise'][0],
                 pressure_noise_pa=w['noise'][1])
    rig.set_scene(scene)
    rest = rig.render_inputs(rig.solve([0.0] * 6), w['size'], w['gray'], w['supersample'],
                             w['views'])
    initial = np.stack([rest[v] for v in w['views']])
    rng = np.random.default_rng(seed + 1)
    limits = np.asarray(w['cfg'].max_pressures_pa, dtype=float)
    out_p, out_t = [], []
    stats = {'touch': 0, 'replaced': 0, 'iterations': [], 'max_penetration_m': 0.0}
    for p in pressures:
        for attempt in range(MAX_RETRIES + 1):
            try:
                st = rig.solve(p)
                break
            except SolverError:
                if attempt == MAX_RETRIES:
                    raise
                stats['replaced'] += 1
                p = rng.uniform(0.0, 1.0, 6) * limits
                rig.set_scene(scene)
        img = rig.render_inputs(st, w['size'], w['gray'], w['supersample'], w['views'])
        out_t.append(np.stack([img[v] for v in w['views']]))
        out_p.append(st.pressures_pa)
        stats['touch'] += int(any(c.gap_m < 0 for c in st.contacts))
        stats['iterations'].append(st.iterations)
        stats['max_penetration_m'] = max(stats['max_penetration_m'], st.max_penetration_m)
    return scene_index, indices, initial, np.stack(out_t), np.stack(out_p), stats


def generate(cfg: RigConfig, plan: Plan, out, views, size: int = 64, gray: bool = True,
             workers: int = 0, supersample: int = 3, noise=(0.0, 0.0), overwrite=False,
             progress: bool = True, source: str = ''):
    """Write the plan as a dataset at ``out`` (processes over scenes, tqdm progress)."""
    from tqdm import tqdm

    from softshape_ros.data.dataset import DatasetWriter
    n = len(plan.pressures)
    channels = 1 if gray else 3
    writer = DatasetWriter(out, n, list(views), channels, size, cfg.max_pressures_pa,
                           overwrite=overwrite)
    jobs = []
    for si, scene in enumerate(plan.scenes):
        idx = np.nonzero(plan.sample_scene == si)[0]
        if len(idx):
            jobs.append((si, scene, idx, plan.pressures[idx], plan.seed * 100003 + si))
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    init = (cfg, size, gray, list(views), supersample, noise)
    touch, replaced, iters, pen = 0, 0, [], 0.0
    bar = tqdm(total=n, desc='simulate', unit='sample', disable=not progress)
    try:
        if workers <= 1:
            _init_worker(*init)
            results = map(simulate_scene, jobs)
            pool = None
        else:
            pool = mp.get_context('fork').Pool(workers, _init_worker, init)
            results = pool.imap_unordered(simulate_scene, jobs)
        for si, idx, initial, target, pressure, stats in results:
            writer.put(idx, np.broadcast_to(initial, target.shape), target, pressure,
                       np.full(len(idx), plan.scenes[si].id))
            touch += stats['touch']
            replaced += stats['replaced']
            iters += stats['iterations']
            pen = max(pen, stats['max_penetration_m'])
            bar.update(len(idx))
        if pool is not None:
            pool.close()
            pool.join()
    except BaseException:
        if workers > 1 and pool is not None:
            pool.terminate()
        raise
    finally:
        bar.close()
    summary = {'samples': n, 'contact_share': touch / n, 'replaced_failed_solves': replaced,
               'median_newton_iterations': float(np.median(iters)),
               'max_penetration_m': pen}
    ds = writer.close(
        source=source or 'softshape simulate', seed=plan.seed, cameras=list(views),
        config=cfg.source, scenes=[s.to_json() for s in plan.scenes],
        normalisation='pressure / max_pressure_pa', simulator=summary,
        dropped={'count': 0, 'why': 'failed solves are redrawn, counted in '
                 'simulator.replaced_failed_solves'})
    return ds, summary
