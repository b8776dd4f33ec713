"""The object's depth per input pixel: a known answer, the renderer's silhouette, no object."""

import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig
from softshape_ros.sim.object_depth import object_depth

CFG = load_rig_config()
VIEWS = ('main', 'side')
# A vertical cylinder between the main camera and the robot, its axis at the image centre.
CYLINDER = Scene(3, 'cylinder', (0.0, -0.03, 0.035), (0.0, 0.0, 0.0),
                 {'radius_m': 0.005, 'height_m': 0.02})


def test_the_depth_in_front_of_the_robot_is_the_known_one():
    """Main view: the axis' near side at 0.185 m, the base at 0.22 m: f (0.185/0.22 - 1)."""
    rig = SimRig(CFG)
    cams = [rig.cameras[v] for v in VIEWS]
    depth = object_depth(cams, CYLINDER, CFG.robot.base_position_m)
    assert depth.shape == (2, 64, 64) and depth.dtype == np.float32
    f = 1400.0 * 64 / 480
    want = f * (0.185 / 0.22 - 1.0)                      # -29.7 px: nearer than the base
    assert depth[0, 31:33, 31:33] == pytest.approx(want, abs=0.05)
    # 10 mm across at 0.185 m: about 2 x 0.005 x 1400 / 0.185 x 64 / 480 = 10 px wide.
    assert 9 <= np.isfinite(depth[0, 32]).sum() <= 11
    assert np.isinf(depth[0, :, :20]).all()              # nothing left of it
    assert np.isinf(object_depth(cams, Scene(4, 'none'), CFG.robot.base_position_m)).all()
    assert np.isinf(object_depth(cams, None, CFG.robot.base_position_m)).all()


def test_the_hit_pixels_are_the_objects_silhouette_in_the_render():
    """Where the rest images change when the object is placed is where the rays hit it."""
    rig = SimRig(CFG)
    empty = rig.render_inputs(rig.solve([0.0] * 6), 64, True, 3, VIEWS)
    rig.set_scene(CYLINDER)
    placed = rig.render_inputs(rig.solve([0.0] * 6), 64, True, 3, VIEWS)
    depth = object_depth([rig.cameras[v] for v in VIEWS], CYLINDER, CFG.robot.base_position_m)
    for v, name in enumerate(VIEWS):
        changed = np.abs(placed[name][0].astype(int) - empty[name][0]) > 10
        hit = np.isfinite(depth[v])
        assert changed.sum() > 100, name
        # The edges are area-averaged in the render, sampled at the centre here: a pixel
        # column's worth either way (shifted by one column, 20 of each).
        assert (changed & ~hit).sum() <= 5 and (hit & ~changed).sum() <= 5, name
