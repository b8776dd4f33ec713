"""SimRig, the public simulator API the mock hardware and the dataset generator use."""

import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.pressure import CommandError
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig, SolverError

CFG = load_rig_config()


def test_api_shapes_and_rest_pose():
    rig = SimRig(CFG)
    rig.set_scene(None)
    st = rig.solve([0.0] * 6)
    # Hanging straight down from the base (gravity only shortens nothing: stretch off).
    base = np.array(CFG.robot.base_position_m)
    assert np.allclose(st.tip_pose[:3, 3], base - [0, 0, CFG.robot.total_length_m], atol=1e-9)
    assert st.residual < 1e-9 and st.contacts == []
    images = rig.render(st)
    assert set(images) == set(CFG.cameras)
    for name, img in images.items():
        cam = CFG.cameras[name]
        assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
        # The robot is in the picture: dark pixels exist, background is light.
        gray = img.mean(axis=2)
        assert (gray < 120).sum() > 1000 and np.median(gray) > 200


def test_snap_deterministic_for_a_seed_and_noise_changes_it():
    p = [0.0, 0.0, 1.0e5, 0.0, 5.0e4, 0.0]
    a = SimRig(CFG, seed=3, image_noise_std=2.0, pressure_noise_pa=500.0).snap(p)
    b = SimRig(CFG, seed=3, image_noise_std=2.0, pressure_noise_pa=500.0).snap(p)
    c = SimRig(CFG, seed=4, image_noise_std=2.0, pressure_noise_pa=500.0).snap(p)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(a['main'], c['main'])


def test_bad_pressures_rejected_and_clamped():
    rig = SimRig(CFG)
    with pytest.raises(CommandError):
        rig.solve([0.0] * 5)
    with pytest.raises(CommandError):
        rig.solve([float('nan')] + [0.0] * 5)
    over = rig.solve([1e9, 0, 0, 0, 0, 0])
    at_limit = rig.solve([CFG.chambers[0].max_pressure_pa, 0, 0, 0, 0, 0])
    assert np.allclose(over.q, at_limit.q)
    assert issubclass(SolverError, RuntimeError)


def test_pressure_bends_away_from_chamber():
    rig = SimRig(CFG)
    st = rig.solve([CFG.chambers[0].max_pressure_pa, 0, 0, 0, 0, 0])
    # Chamber 1 (angle 0) sits on the world +y side (body y = world y): the robot bends to -y.
    assert st.tip_pose[1, 3] < -0.01


def test_set_scene_type_checked():
    rig = SimRig(CFG)
    with pytest.raises(TypeError):
        rig.set_scene({'object': 'cylinder'})
    rig.set_scene(Scene(id=1, object='sphere', position_m=(0.0, 0.0, -0.05),
                        dims={'radius_m': 0.01}))
    assert rig.solve([0.0] * 6).contacts == []


def test_scenes_that_cannot_be_placed_are_rejected_and_the_last_one_kept():
    from softshape_ros.scene import SceneError
    rig = SimRig(CFG)
    good = Scene(id=1, object='cylinder', position_m=(0.03, 0.0, 0.02),
                 dims={'radius_m': 0.008, 'height_m': 0.05})
    rig.set_scene(good)
    through_robot = Scene(id=2, object='cylinder', position_m=(0.015, 0.0, 0.03),
                          dims={'radius_m': 0.008, 'height_m': 0.05})
    with pytest.raises(SceneError, match='overlaps the robot at rest'):
        rig.set_scene(through_robot)
    assert rig.scene is good
    with pytest.raises(SceneError, match='minor radius'):
        rig.set_scene(Scene(id=3, object='ring', position_m=(0.05, 0.0, 0.02),
                            dims={'major_radius_m': 0.004, 'minor_radius_m': 0.005}))
    with pytest.raises(SceneError, match='skew'):
        rig.set_scene(Scene(id=4, object='prism', position_m=(0.05, 0.0, 0.02),
                            dims={'width_m': 0.01, 'depth_m': 0.01, 'height_m': 0.04,
                                  'skew_rad': 1.5}))
    assert issubclass(SceneError, ValueError)


def test_bad_loads_and_contact_numbers_are_value_errors():
    from softshape_ros.sim.contact import PenaltyContact
    from softshape_ros.sim.objects import Sphere
    from softshape_ros.sim.statics import PointLoad
    rig = SimRig(CFG)
    with pytest.raises(CommandError):
        rig.solve([-1.0, 0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match='finite'):
        rig.statics.solve(np.zeros(6), [PointLoad(0.04, force_n=(float('nan'), 0, 0))])
    with pytest.raises(ValueError, match='0 <= s'):
        rig.statics.solve(np.zeros(6), [PointLoad(0.5, force_n=(0.1, 0, 0))])
    with pytest.raises(ValueError, match='positive'):
        PenaltyContact.of([Sphere(0.01)], stiffness=0.0)
