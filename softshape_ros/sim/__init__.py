"""
Cosserat-rod statics simulator of the two-segment robot, with contact and rendering.

Public API (the mock hardware, the dataset generator and the demo code against it)::

    from softshape_ros.sim import SimRig, SolverError
    rig = SimRig(cfg, seed=0, image_noise_std=0.0, pressure_noise_pa=0.0)
    rig.set_scene(scene)            # softshape_ros.scene.Scene or None
    state = rig.solve(pressures_pa) # q, backbone_m, contacts, residual, iterations
    images = rig.render(state)      # {'main': H x W x 3 uint8 RGB, 'side': ...}
    images = rig.snap(pressures_pa) # solve + render

No rclpy here (core package).
"""

from softshape_ros.sim.rig import SimRig, SimState
from softshape_ros.sim.statics import SolverError

__all__ = ['SimRig', 'SimState', 'SolverError']
