"""
Compile every simulator kernel once, so that later processes load them from numba's cache.

``python -m softshape_ros.sim.warmup`` (``make build`` runs it): on a fresh checkout the
kernels take ~45 s of CPU to compile, afterwards a process loads them in well under a
second. Without it the first simulator call of each cold cache (a test, a dataset worker,
the mock hardware) pays the compilation instead. ``simulate``'s worker processes get them
from :mod:`softshape_ros.sim.preload`.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path


def compile_kernels() -> float:
    """
    Run every kind of call the simulator makes once; return the seconds it took.

    Free and contact solves (each object, tendons, loads), full frames and crops, and a
    small ``simulate`` in this process (the contact record, the dataset rows): every kernel
    with every argument type it meets, so no worker compiles one later.
    """
    t0 = time.perf_counter()
    import numpy as np

    from softshape_ros.config import load_rig_config
    from softshape_ros.scene import Scene
    from softshape_ros.sim.equilibrium import solve_equilibrium
    from softshape_ros.sim.generate import generate, make_plan
    from softshape_ros.sim.objects import Sphere
    from softshape_ros.sim.rig import SimRig

    cfg = load_rig_config()
    rig = SimRig(cfg)
    rig.solve([1e5, 0.0, 0.0, 0.0, 5e4, 0.0])
    rig.set_scene(Scene(id=0, object='cylinder', position_m=(0.022, 0.0, 0.02),
                        dims={'radius_m': 0.008, 'height_m': 0.05}))
    st = rig.solve([0.0, 1.5e5, 0.0, 0.0, 1.5e5, 0.0])
    rig.render(st)
    rig.render_inputs(st, gray=False)
    solve_equilibrium(cfg, tensions_n=[0.3, 0.0, 0.0, 0.0, 0.2, 0.0],
                      loads=[(0.03, (0.01, 0.0, 0.0), (0.0, 0.001, 0.0))])
    Sphere(0.01).sdf_hessian(np.zeros((1, 3)))
    rig.rod.strain(np.zeros(rig.rod.n), [0.01])
    rig.rod.phi([0], [0.01])
    views = list(cfg.cameras)[:2]
    with tempfile.TemporaryDirectory() as d:
        generate(cfg, make_plan(cfg, 24, 3, seed=0), Path(d) / 'ds', views, workers=1,
                 progress=False)
    return time.perf_counter() - t0


def main() -> int:
    print(f'simulator kernels ready in {compile_kernels():.1f} s', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
