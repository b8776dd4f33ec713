"""
Compile every simulator kernel once, so that later processes load them from numba's cache.

``python -m softshape_ros.sim.warmup`` (``make build`` runs it): on a fresh checkout the
kernels take ~30 s of CPU to compile, afterwards a process loads them in ~0.4 s. Without it
the first simulator call of each cold cache (a test, a dataset worker, the mock hardware)
pays the compilation instead.
"""

from __future__ import annotations

import sys
import time


def compile_kernels() -> float:
    """Run one of each kind of solve (free, each obstacle, tendons, loads); return seconds."""
    t0 = time.perf_counter()
    import numpy as np

    from softshape_ros.config import load_rig_config
    from softshape_ros.scene import Scene
    from softshape_ros.sim.equilibrium import solve_equilibrium
    from softshape_ros.sim.objects import Sphere
    from softshape_ros.sim.rig import SimRig

    cfg = load_rig_config()
    rig = SimRig(cfg)
    rig.solve([1e5, 0.0, 0.0, 0.0, 5e4, 0.0])
    rig.set_scene(Scene(id=0, object='cylinder', position_m=(0.022, 0.0, 0.02),
                        dims={'radius_m': 0.008, 'height_m': 0.05}))
    rig.solve([0.0, 1.5e5, 0.0, 0.0, 1.5e5, 0.0])
    solve_equilibrium(cfg, tensions_n=[0.3, 0.0, 0.0, 0.0, 0.2, 0.0],
                      loads=[(0.03, (0.01, 0.0, 0.0), (0.0, 0.001, 0.0))])
    Sphere(0.01).sdf_hessian(np.zeros((1, 3)))
    rig.rod.strain(np.zeros(rig.rod.n), [0.01])
    rig.rod.phi([0], [0.01])
    return time.perf_counter() - t0


def main() -> int:
    print(f'simulator kernels ready in {compile_kernels():.1f} s', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
