"""Renderer: occlusion both ways, pinhole projection, gray contrast, fast crop == preprocess."""

import dataclasses

import cv2
import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig
from softshape_ros.sim.camera import PinholeCamera
from softshape_ros.vision.preprocess import preprocess, to_gray

CFG = load_rig_config()
MAIN = CFG.cameras['main']


def gray_at(img, uv):
    u, v = (int(round(x)) for x in uv)
    return float(to_gray(img)[v, u])


def cv_project(cam_cfg, points):
    """Project with OpenCV from the config alone (independent of PinholeCamera)."""
    pos, look, up = (np.array(v, dtype=float) for v in (cam_cfg.position_m, cam_cfg.look_at_m,
                                                        cam_cfg.up))
    z = (look - pos) / np.linalg.norm(look - pos)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_cw = np.stack([x, y, z])                     # world -> camera rows
    rvec, _ = cv2.Rodrigues(R_cw)
    tvec = -R_cw @ pos
    K = np.array([[cam_cfg.fx, 0, cam_cfg.cx], [0, cam_cfg.fy, cam_cfg.cy], [0, 0, 1.0]])
    uv, _ = cv2.projectPoints(np.asarray(points, dtype=float), rvec, tvec, K, None)
    return uv.reshape(-1, 2)


def sphere_scene(y):
    return Scene(id=0, object='sphere', position_m=(0.0, y, 0.03), dims={'radius_m': 0.006})


def test_robot_in_front_hides_object_and_behind_is_hidden():
    rig = SimRig(CFG)
    # Main camera looks along +y from y = -0.22: +y is behind the robot, -y in front.
    centre = PinholeCamera.from_config('main', MAIN).project([[0.0, 0.0, 0.03]])[0, :2]
    rig.set_scene(sphere_scene(0.04))
    behind = rig.snap([0.0] * 6)['main']
    rig.set_scene(sphere_scene(-0.04))
    front = rig.snap([0.0] * 6)['main']
    rig.set_scene(None)
    alone = rig.snap([0.0] * 6)['main']
    assert gray_at(behind, centre) == gray_at(alone, centre) < 120       # robot seen
    assert gray_at(front, centre) > 150                                   # object seen
    # Behind the robot, the sphere shows only where the robot does not cover it.
    diff = np.abs(to_gray(behind).astype(int) - to_gray(alone)).astype(bool)
    assert not diff.any()          # radius 6 mm behind a 25 mm tube: fully hidden
    rig.set_scene(Scene(id=0, object='sphere', position_m=(0.02, 0.04, 0.03),
                        dims={'radius_m': 0.006}))
    peek = rig.snap([0.0] * 6)['main']
    assert np.abs(to_gray(peek).astype(int) - to_gray(alone)).any()      # partly visible


@pytest.mark.parametrize('camera', ['main', 'side'])
def test_projected_tip_lands_where_the_pinhole_model_puts_it(camera):
    rig = SimRig(CFG)
    st = rig.solve([0.0, 1.0e5, 0.0, 0.0, 1.2e5, 0.0])
    tip = st.tip_pose[:3, 3]
    cam_cfg = CFG.cameras[camera]
    uv_cv = cv_project(cam_cfg, [tip])[0]
    uv_ours = PinholeCamera.from_config(camera, cam_cfg).project([tip])[0, :2]
    assert np.allclose(uv_cv, uv_ours, atol=1e-6)
    img = rig.render(st)[camera]
    assert gray_at(img, uv_cv) < 120              # the robot is there
    # One tube radius plus 1 mm beyond the tip (along its axis, seen side-on): background.
    ray = tip - np.array(cam_cfg.position_m)
    ray /= np.linalg.norm(ray)
    axis = st.tip_pose[:3, 0] - (st.tip_pose[:3, 0] @ ray) * ray
    axis /= np.linalg.norm(axis)
    beyond = cv_project(cam_cfg, [tip + axis * (0.0125 + 0.001)])[0]
    assert gray_at(img, beyond) > 220


def test_gray_contrast_robot_object_background():
    rig = SimRig(CFG)
    rig.set_scene(Scene(id=0, object='cylinder', position_m=(0.025, 0.0, 0.02),
                        dims={'radius_m': 0.008, 'height_m': 0.05}))
    img = to_gray(rig.snap([0.0] * 6)['main'])
    cam = PinholeCamera.from_config('main', MAIN)
    robot_px = cam.project([[0.0, -0.0125, 0.03]])[0, :2] + [0, 0]
    obj_px = cam.project([[0.025, -0.008, 0.02]])[0, :2]
    r, o = gray_at(img, robot_px), gray_at(img, obj_px)
    assert r < 120 and 150 < o < 215 and img[5, 5] > 225


def test_any_resolution():
    small = dataclasses.replace(MAIN, width=160, height=120, fx=350.0, fy=350.0, cx=80.0,
                                cy=60.0, crop_px=[20, 0, 120, 120])
    cfg = dataclasses.replace(CFG, cameras={'main': small})
    img = SimRig(cfg).snap([0.0] * 6)
    assert img['main'].shape == (120, 160, 3)
    big = SimRig(CFG).snap([0.0] * 6)['main']
    # Same scene at a quarter of the resolution: same picture, area-downsampled.
    down = cv2.resize(big, (160, 120), interpolation=cv2.INTER_AREA)
    assert np.abs(down.astype(int) - img['main']).mean() < 2.0


def test_fast_crop_render_matches_preprocess_of_full_frame():
    rig = SimRig(CFG)
    rig.set_scene(Scene(id=2, object='ring', position_m=(-0.03, 0.0, 0.025),
                        rpy_rad=(1.5707963, 0.0, 0.0),
                        dims={'major_radius_m': 0.012, 'minor_radius_m': 0.003}))
    st = rig.solve([0.0, 1.5e5, 0.0, 0.0, 1.0e5, 0.0])
    full = rig.render(st)
    fast = rig.render_inputs(st, size=64, gray=True, supersample=3)
    for name, img in full.items():
        ref = preprocess(img, CFG.cameras[name].crop_px, 64, True)
        d = np.abs(fast[name].astype(int) - ref)
        assert fast[name].shape == ref.shape == (1, 64, 64)
        assert d.mean() < 1.0 and np.percentile(d, 99) < 16, (d.mean(), np.percentile(d, 99))
