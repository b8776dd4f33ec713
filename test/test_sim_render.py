"""
Renderer: occlusion both ways, projection, contrast, crops, reference images, exact outlines.

The reference images (test/data/render_reference) are the previous ray caster's; the exact
outlines come from ray-to-backbone and ray-to-sphere distances computed here, in numpy.
"""

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig, SimState
from softshape_ros.sim.camera import PinholeCamera
from softshape_ros.sim.render import render_view
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
    # supersample 0 samples the crop's own camera pixels: the camera node's input to the
    # pixel (gray rendered directly: cvtColor's rounding may move a level), where 3x3
    # samples a pixel put the edges up to a fifth of a pixel elsewhere (docs/model.md).
    same = rig.render_inputs(st, size=64, gray=True, supersample=0)
    for name, img in full.items():
        d = np.abs(same[name].astype(int) - preprocess(img, CFG.cameras[name].crop_px, 64, True))
        assert d.max() <= 1, (name, d.max())


def test_gray_render_is_the_gray_of_the_colour_render():
    """A gray view is what cv2.cvtColor makes of the colour one; noisy inputs stay seeded noise."""
    rig = SimRig(CFG)
    rig.set_scene(sphere_scene(0.035))
    st = rig.solve([0.0, 1.5e5, 0.0, 0.0, 1.0e5, 0.0])
    for name, cam in rig.cameras.items():
        for grid in (cam.grid(), cam.grid(cam.crop, (256, 256))):
            rgb = render_view(cam, st.backbone_m, st.radii_m, rig.obstacles, grid)
            gray = render_view(cam, st.backbone_m, st.radii_m, rig.obstacles, grid, gray=True)
            assert gray.shape == rgb.shape[:2] and gray.dtype == np.uint8
            d = np.abs(gray.astype(int) - cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
            # Bit-exact with this OpenCV; another version's rounding may move a level.
            assert d.max() <= 1 and d.mean() < 0.01, (name, d.max(), d.mean())
            assert len(np.unique(gray)) > 20          # shaded robot, object and background
    noisy = SimRig(CFG, seed=3, image_noise_std=4.0)
    noisy.set_scene(sphere_scene(0.035))
    again = SimRig(CFG, seed=3, image_noise_std=4.0)
    again.set_scene(sphere_scene(0.035))
    a, b = noisy.render_inputs(st), again.render_inputs(st)
    clean = rig.render_inputs(st)
    for name in a:
        assert np.array_equal(a[name], b[name])      # seeded
        assert 0.3 < np.abs(a[name].astype(int) - clean[name]).mean() < 4.0


# -- the compiled renderer against the reference images and exact geometry ----------------------
REF = Path(__file__).resolve().parent / 'data' / 'render_reference'
CASES = {c['name']: c for c in json.loads((REF / 'cases.json').read_text())}


def _state(case) -> SimState:
    """Return a SimState holding a stored backbone (render reads only it and the radii)."""
    b = np.asarray(case['backbone_m'])
    return SimState(q=np.zeros(1), pressures_pa=np.zeros(6), s_m=np.zeros(len(b)),
                    backbone_m=b, radii_m=np.asarray(case['radii_m']), tip_pose=np.eye(4),
                    residual=0.0, iterations=0)


def _rig_for(case) -> SimRig:
    rig = SimRig(CFG)
    rig.set_scene(Scene.from_dict(case['scene']) if case['scene'] else None)
    return rig


@pytest.mark.parametrize('name', sorted(CASES))
def test_images_equal_the_reference_ray_caster(name):
    """Robot alone and with each object, occlusion both ways: within 1 gray level on average."""
    case = CASES[name]
    rig = _rig_for(case)
    st = _state(case)
    images = rig.render(st)
    inputs = rig.render_inputs(st)
    for cam in ('main', 'side'):
        ref = cv2.imread(str(REF / f'{name}_{cam}.png'), cv2.IMREAD_GRAYSCALE)
        d = np.abs(to_gray(images[cam]).astype(int) - ref)
        # Outline pixels may flip; everything else is the same shading to a level or two.
        assert d.mean() < 1.0 and (d > 8).mean() < 0.005, (cam, d.mean(), (d > 8).mean())
        ref_in = cv2.imread(str(REF / f'{name}_{cam}_input.png'), cv2.IMREAD_GRAYSCALE)
        d_in = np.abs(inputs[cam][0].astype(int) - ref_in)
        assert d_in.mean() < 1.0 and d_in.max() < 32, (cam, d_in.mean(), d_in.max())


def _ray_dirs(cam):
    """Return unit world rays through every pixel centre of ``cam`` (H x W x 3)."""
    return cam.rays(cam.grid())


def _segment_distance(o, dirs, a, b):
    """Distance from each line (origin o, unit dirs) to the segment a-b, and the depth there."""
    u, w = b - a, a - o
    du, dw = dirs @ u, dirs @ w
    # |w + t u|^2 - (d.(w + t u))^2 is convex in t: its minimiser, clamped to the segment.
    t = np.clip((dw * du - w @ u) / np.maximum(u @ u - du * du, 1e-30), 0.0, 1.0)
    s = dw + t * du
    d2 = (w @ w + 2 * t * (w @ u) + t * t * (u @ u)) - s * s
    return np.sqrt(np.maximum(d2, 0.0)), s


def test_robot_outline_is_the_exact_tube_to_a_fraction_of_a_pixel():
    """
    Slow exact path (test only): a pixel is robot iff its ray passes within r of the backbone.

    Pixels clearly inside the tube (by a third of a pixel) must be robot, clearly outside
    must not: no holes, no bulges, whatever the bend.
    """
    small = dataclasses.replace(MAIN, width=160, height=120, fx=350.0, fy=350.0, cx=80.0,
                                cy=60.0, crop_px=[20, 0, 120, 120])
    cfg = dataclasses.replace(CFG, cameras={'main': small})
    case = CASES['bent_alone']
    st = _state(case)
    img = SimRig(cfg).render(st)['main']
    cam = PinholeCamera.from_config('main', small)
    dirs = _ray_dirs(cam)
    b = st.backbone_m
    best = np.full(dirs.shape[:2], np.inf)
    depth = np.zeros(dirs.shape[:2])
    for k in range(len(b) - 1):
        dist, s = _segment_distance(cam.position, dirs, b[k], b[k + 1])
        closer = dist < best
        best[closer], depth[closer] = dist[closer], s[closer]
    r = st.radii_m[0]
    margin = depth / cam.fx / 3.0                            # a third of a pixel, in metres
    robot = to_gray(img) < 120
    assert robot[best < r - margin].all()
    assert not robot[best > r + margin].any()
    assert 0.05 < robot.mean() < 0.5


def test_object_outline_is_the_exact_sphere():
    small = dataclasses.replace(MAIN, width=160, height=120, fx=350.0, fy=350.0, cx=80.0,
                                cy=60.0, crop_px=[20, 0, 120, 120])
    cfg = dataclasses.replace(CFG, cameras={'main': small})
    rig = SimRig(cfg)
    centre, radius = np.array([0.03, -0.02, 0.01]), 0.009
    rig.set_scene(Scene(id=0, object='sphere', position_m=tuple(centre),
                        dims={'radius_m': radius}))
    img = to_gray(rig.snap([0.0] * 6)['main'])
    cam = PinholeCamera.from_config('main', small)
    dirs = _ray_dirs(cam)
    oc = centre - cam.position
    s = dirs @ oc
    dist = np.sqrt(np.maximum(oc @ oc - s * s, 0.0))         # ray to centre
    margin = s / cam.fx / 3.0
    obj = (img > 120) & (img < 225)                          # robot <= ~100, background 240
    assert obj[dist < radius - margin].all()
    assert not obj[dist > radius + margin].any()


def test_bad_input_gives_clear_errors_never_an_image():
    from softshape_ros.pressure import CommandError
    from softshape_ros.sim.render import RenderError
    rig = SimRig(CFG)
    st = rig.solve([0.0] * 6)
    bad = dataclasses.replace(st, backbone_m=st.backbone_m.copy())
    bad.backbone_m[3, 1] = np.nan
    with pytest.raises(RenderError, match='finite'):
        rig.render(bad)
    with pytest.raises(RenderError, match='radii'):
        rig.render(dataclasses.replace(st, radii_m=np.zeros_like(st.radii_m)))
    with pytest.raises(RenderError, match='backbone must be'):
        rig.render(dataclasses.replace(st, backbone_m=st.backbone_m[:, :2]))
    for size, ss in ((0, 4), (64, -1), (2.5, 4), (64, 1.5)):
        with pytest.raises(RenderError, match='size must be an integer >= 1 and supersample'):
            rig.render_inputs(st, size=size, supersample=ss)
    with pytest.raises(RenderError, match='unknown camera'):
        rig.render_inputs(st, cameras=['top'])
    for p in ([float('nan')] + [0.0] * 5, [-1.0] + [0.0] * 5, [0.0] * 5):
        with pytest.raises(CommandError):
            rig.snap(p)
    # A resolution of 0 (or a camera without a view) is refused where the camera is made.
    for change in (dict(width=0), dict(height=0), dict(fx=0.0), dict(fy=float('nan'))):
        with pytest.raises(ValueError, match='camera main'):
            PinholeCamera.from_config('main', dataclasses.replace(MAIN, **change))
    # A camera inside an object: no image from it (the shape still solves; SimCameras and
    # so mock_hardware refuse such a scene and keep the previous one: test_sim_stream).
    rig.set_scene(Scene(id=9, object='sphere', position_m=(0.0, -0.2, 0.035),
                        dims={'radius_m': 0.05}))
    rig.solve([0.0] * 6)
    with pytest.raises(RenderError, match='camera main .* inside the sphere'):
        rig.check_views()
    for render in (lambda s: rig.render(s), lambda s: rig.render_inputs(s, cameras=['main'])):
        with pytest.raises(RenderError, match='inside the sphere'):
            render(st)
    assert rig.render_inputs(st, cameras=['side'])['side'].shape == (1, 64, 64)
    # The robot reaching the camera: refused, not drawn inside out.
    near = dataclasses.replace(MAIN, position_m=[0.0, -0.01, 0.035])
    with pytest.raises(RenderError, match='camera plane'):
        SimRig(dataclasses.replace(CFG, cameras={'main': near})).render(st)


def test_over_limit_pressures_are_clamped_like_the_bridge():
    rig = SimRig(CFG)
    limits = np.asarray(CFG.max_pressures_pa)
    over = rig.snap(limits * [1, 0, 0, 2, 0, 0])['main']
    assert np.array_equal(over, SimRig(CFG).snap(limits * [1, 0, 0, 1, 0, 0])['main'])


@pytest.mark.parametrize('wh', [(1, 1), (7, 5), (1920, 1080)])
def test_odd_and_large_resolutions(wh):
    w, h = wh
    s = w / 640.0
    cam = dataclasses.replace(MAIN, width=w, height=h, fx=1400.0 * s, fy=1400.0 * s,
                              cx=w / 2.0, cy=h / 2.0, crop_px=[0, 0, w, h])
    img = SimRig(dataclasses.replace(CFG, cameras={'main': cam})).snap([0.0] * 6)['main']
    assert img.shape == (h, w, 3) and img.dtype == np.uint8
    if w >= 640:
        assert (to_gray(img) < 120).mean() > 0.05              # the robot is in the picture
