"""
Equilibrium timings of the simulated rig, for ``bench_sim``: run as a script, print JSON.

Uses only the public simulator API (SimRig, SolverError), so that ``bench_sim`` can run the
same script against another checkout (``SIM_BENCH_REFERENCE``) side by side in one run.
One process, one thread: wall and CPU time per solve; a few solves first load (or compile)
the kernels, untimed.

    python benchmarks/sim_equilibria.py N_FREE N_CONTACT
"""

import json
import os
import sys
import time

import numpy as np

from softshape_ros.config import load_rig_config
from softshape_ros.scene import load_session
from softshape_ros.sim import SimRig, SolverError


def _stats(times: list) -> dict:
    if not times:
        return {'median_ms': None, 'p90_ms': None}
    t = 1e3 * np.asarray(times)
    return {'median_ms': float(np.median(t)), 'p90_ms': float(np.percentile(t, 90)),
            'max_ms': float(t.max()), 'n': len(t)}


def run(n_free: int, n_contact: int) -> dict:
    cfg = load_rig_config()
    scenes = load_session(os.path.join(os.path.dirname(cfg.source), 'session_sim.yaml'))
    limits = np.array(cfg.max_pressures_pa)
    warm = SimRig(cfg)                       # first calls: kernels loaded, not timed
    warm.set_scene(scenes[0])
    for p in (limits * 0.5, limits):
        warm.solve(p)
    rng = np.random.default_rng(0)
    rig = SimRig(cfg)
    free_wall, free_cpu = [], []
    for _ in range(n_free):
        p = rng.uniform(0, 1, 6) * limits
        t0, c0 = time.perf_counter(), time.process_time()
        rig.solve(p)
        free_wall.append(time.perf_counter() - t0)
        free_cpu.append(time.process_time() - c0)
    per_object, touch_wall, touch_cpu = {}, [], []
    for scene in scenes:
        rig.set_scene(scene)
        fails, touch, pen, iters = 0, 0, 0.0, []
        for _ in range(n_contact):
            p = rng.uniform(0, 1, 6) * limits
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                st = rig.solve(p)
            except SolverError:
                fails += 1
                continue
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if any(c.gap_m < 0 for c in st.contacts):
                touch += 1
                touch_wall.append(wall)
                touch_cpu.append(cpu)
                iters.append(st.iterations)
            pen = max(pen, st.max_penetration_m)
        per_object[scene.label] = {'actuations': n_contact, 'failures': fails,
                                   'touch_share': touch / max(n_contact, 1),
                                   'max_penetration_mm': 1e3 * pen,
                                   'newton_iterations_touching_median':
                                       float(np.median(iters)) if iters else None}
    return {'free_wall': _stats(free_wall), 'free_cpu': _stats(free_cpu),
            'touching_wall': _stats(touch_wall), 'touching_cpu': _stats(touch_cpu),
            'per_object': per_object}


if __name__ == '__main__':
    print(json.dumps(run(int(sys.argv[1]), int(sys.argv[2]))))
