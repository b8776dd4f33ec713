"""
One equilibrium with every knob exposed: what ``softshape sim-solve`` prints as JSON.

Pressures drive the configured chambers; tensions drive thread-like tendons at the
chambers' angles and offsets (three per segment, the paper's simulation). Point loads are
dead world forces/moments at an arc length (the tip is ``s = total length``).
"""

from __future__ import annotations

import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.pressure import check_command
from softshape_ros.sim.contact import PenaltyContact
from softshape_ros.sim.objects import obstacle_from_scene
from softshape_ros.sim.rig import chamber_actuators
from softshape_ros.sim.rod import Rod, RodSpec
from softshape_ros.sim.statics import Actuator, PointLoad, Statics


def tendon_actuators(cfg: RigConfig) -> list[Actuator]:
    """Return tendons at the chambers' angles and offsets (positive tension pulls)."""
    return [Actuator('tendon', a.segment, a.angle_rad, a.offset_m)
            for a in chamber_actuators(cfg)]


def solve_equilibrium(cfg: RigConfig, pressures_pa=None, tensions_n=None, loads=(),
                      gravity: bool = True, order: int | None = None,
                      shear: bool | None = None, stretch: bool | None = None, scene=None,
                      samples: int = 21) -> dict:
    """Solve and return a JSON-able dict (q, tip pose, backbone, residual, contacts)."""
    if pressures_pa is not None and tensions_n is not None:
        raise ValueError('give pressures or tensions, not both')
    over = {}
    if order is not None:
        over['order'] = int(order)
    if shear is not None:
        over['shear'] = bool(shear)
    if stretch is not None:
        over['stretch'] = bool(stretch)
    rod = Rod(RodSpec.from_config(cfg.robot, **over))
    if tensions_n is not None:
        u = np.asarray([float(t) for t in tensions_n])
        if u.shape != (6,) or not np.all(np.isfinite(u)):
            raise ValueError(f'tensions need 6 finite values (N), got {tensions_n}')
        acts, kind = tendon_actuators(cfg), 'tendons'
    else:
        u = check_command(pressures_pa if pressures_pa is not None else [0.0] * 6,
                          cfg.max_pressures_pa).pressures_pa
        acts, kind = chamber_actuators(cfg), 'chambers'
    st = Statics(rod, acts, gravity_on=gravity)
    obj = obstacle_from_scene(scene)
    contact = PenaltyContact.of([obj]) if obj is not None else None
    loads = [ld if isinstance(ld, PointLoad) else PointLoad(*ld) for ld in loads]
    q, asm, it = st.solve(u, loads, contact=contact)
    kin = asm.kin
    s = np.linspace(0.0, rod.length, max(int(samples), 2))
    g, _ = rod.at(kin, s, jac=False)
    result = asm.contact
    return {
        'actuation': kind, 'u': u.tolist(), 'dof': rod.n, 'order': rod.spec.order,
        'shear': bool(rod.spec.shear), 'stretch': bool(rod.spec.stretch),
        'gravity': bool(st.gravity_on),
        'q': q.tolist(), 'tip_position_m': kin.g[-1][:3, 3].tolist(),
        'tip_rotation': kin.g[-1][:3, :3].tolist(), 's_m': s.tolist(),
        'backbone_m': g[:, :3, 3].tolist(),
        'residual': asm.residual_norm, 'iterations': int(it),
        'contacts': [c.to_dict() for c in result.contacts] if result is not None else [],
        'max_penetration_m': result.max_penetration_m if result is not None else 0.0,
        'scene': None if scene is None else scene.to_json(),
    }
