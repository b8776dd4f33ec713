"""Evaluation metrics on hand-made images whose answers are known."""

import numpy as np
import pytest

from softshape_ros.model.metrics import (PSNR_MSE_FLOOR, RobotSilhouette, evaluate_arrays,
                                         far_end_tips, gaussian_window, intrusion, psnr, ssim,
                                         ssim_map)

BG, OBJ, ROBOT = 240, 190, 90


def _ssim_by_definition(x, y):
    """SSIM written out window by window (Wang et al. 2004, Gaussian 11x11, sigma 1.5)."""
    g = gaussian_window()
    w = np.outer(g, g)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    vals = []
    for i in range(x.shape[0] - 10):
        for j in range(x.shape[1] - 10):
            a, b = x[i:i + 11, j:j + 11], y[i:i + 11, j:j + 11]
            ma, mb = (w * a).sum(), (w * b).sum()
            va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
            cov = (w * (a - ma) * (b - mb)).sum()
            vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma ** 2 + mb ** 2 + c1)
                                                               * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_known_values():
    # Two flat images a and b: SSIM = (2ab + C1) / (a^2 + b^2 + C1) in closed form.
    a = np.full((1, 1, 1, 32, 32), 100, np.uint8)
    b = np.full((1, 1, 1, 32, 32), 150, np.uint8)
    c1 = (0.01 * 255) ** 2
    assert ssim(a, b) == pytest.approx((2 * 100 * 150 + c1) / (100 ** 2 + 150 ** 2 + c1),
                                       rel=1e-12)
    assert ssim(a, a) == pytest.approx(1.0)
    assert ssim_map(a, b).shape == (1, 1, 1, 22, 22)
    assert gaussian_window().sum() == pytest.approx(1.0) and len(gaussian_window()) == 11
    # Random images: the vectorised SSIM equals the window-by-window definition.
    rng = np.random.default_rng(0)
    x = rng.integers(0, 256, (1, 1, 1, 24, 24)).astype(np.uint8)
    y = np.clip(x.astype(int) + rng.integers(-40, 40, x.shape), 0, 255).astype(np.uint8)
    want = _ssim_by_definition(x[0, 0, 0].astype(float), y[0, 0, 0].astype(float))
    assert ssim(x, y) == pytest.approx(want, rel=1e-10)
    assert ssim(x, 255 - x) < 0      # anti-correlated structure


def test_psnr_per_image_then_mean():
    a = np.zeros((2, 1, 1, 8, 8), np.uint8)
    b = a.copy()
    b[0] = 10                                     # image 0: MSE 100; image 1: exact
    want = (10 * np.log10(255 ** 2 / 100) + 10 * np.log10(255 ** 2 / PSNR_MSE_FLOOR)) / 2
    assert psnr(b, a) == pytest.approx(want)


def _scene(robot_cols, object_cols=(40, 50), size=64):
    """One gray view: a vertical robot bar (cols) from the top, an object block at the side."""
    img = np.full((size, size), BG, np.uint8)
    img[20:60, object_cols[0]:object_cols[1]] = OBJ
    img[0:50, robot_cols[0]:robot_cols[1]] = ROBOT
    return img[None, None, None]


def test_intrusion_counts_robot_drawn_inside_the_object():
    initial = np.concatenate([_scene((20, 30))] * 4)
    target = np.concatenate([_scene((28, 38))] * 4)    # moved right, stopped by the object
    through = target.copy()
    through[:, :, :, 0:50, 38:44] = ROBOT                # drawn 6 columns into the object
    sil = RobotSilhouette.fit(initial)
    assert sil.threshold < OBJ < sil.object_threshold < BG
    obj = sil.object_mask(initial)
    assert obj.sum() == 4 * 40 * 10                      # the block, and nothing of the rim
    got = intrusion(sil.mask(through), sil.mask(target), obj)
    assert got == pytest.approx((50 - 20) * 4 / (40 * 10))   # rows 20-49 x cols 40-43
    assert intrusion(sil.mask(target), sil.mask(target), obj) == 0.0
    res = evaluate_arrays(initial, target, through, sil)
    assert res['model']['intrusion'] == pytest.approx(got)
    assert res['copy']['intrusion'] == 0.0
    assert res['split'].startswith('none')
    assert 'touching' not in res and 'free' not in res


def test_metrics_split_into_touching_and_free():
    initial = np.concatenate([_scene((20, 30))] * 4)
    target = initial.copy()
    target[2:] = _scene((28, 38))                        # rows 2, 3 move (and touch)
    pred = target.copy()
    pred[3] = _scene((22, 32))                           # row 3 predicted wrong
    touching = np.array([False, False, True, True])
    sil = RobotSilhouette.fit(initial)
    res = evaluate_arrays(initial, target, pred, sil, touching)
    assert res['touching']['samples'] == 2 and res['free']['samples'] == 2
    assert res['touching_share'] == 0.5
    free, touch = res['free']['model'], res['touching']['model']
    assert free['rmse'] == 0 and free['silhouette_iou'] == 1.0 and free['ssim'] == 1.0
    assert touch['rmse'] > 0 and touch['silhouette_iou'] < 1.0
    # row 3's tip 6 columns off, a little more measured at the square end's far corner
    # (far_end_tips: ~8.4 px); the other touching row is exact
    assert 6 / 2 <= touch['tip_error_px'] <= 9 / 2
    assert res['free']['copy']['rmse'] == 0
    # The whole-set numbers pool both halves.
    assert touch['silhouette_iou'] < res['model']['silhouette_iou'] < 1.0
    with pytest.raises(ValueError, match='touching'):
        evaluate_arrays(initial, target, pred, sil, touching[:3])


def test_far_end_tip_is_stable_where_the_furthest_pixel_jumps():
    # A vertical bar with a round end, moved sideways in 0.1 px steps: the furthest pixel
    # jumps along the cap with pixel rounding; the far-end tip follows the axis.
    yy, xx = np.mgrid[0:64, 0:64]
    far, furthest = [], []
    shifts = np.linspace(-0.5, 0.5, 11)
    for dx in shifts:
        bar = (np.abs(xx - 32 - dx) <= 9) & (yy <= 40)
        m = bar | ((xx - 32 - dx) ** 2 + (yy - 40) ** 2 <= 81)
        base = np.array([[0.0, 32.0 + dx]])
        far.append(far_end_tips(m[None, None], base)[0, 0])
        d = np.where(m, np.hypot(yy, xx - 32 - dx), -1)
        k = np.argmax(d)
        furthest.append((yy.ravel()[k], xx.ravel()[k]))
    far, furthest = np.array(far), np.array(furthest, dtype=float)
    assert np.abs(far[:, 1] - 32 - shifts).max() < 0.6
    assert np.abs(far[:, 0] - 49).max() < 2.0
    jump = np.abs(furthest[:, 1] - 32 - shifts).max()
    assert jump > np.abs(far[:, 1] - 32 - shifts).max()
