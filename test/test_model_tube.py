"""The tube model: its renderer, the simulator's shape record it learns from, its training."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from softshape_ros.config import load_rig_config
from softshape_ros.data import DatasetError, DatasetWriter, load_dataset
from softshape_ros.demo.pipeline import PRETRAINED
from softshape_ros.model import CheckpointError, Predictor, build_network, load_checkpoint
from softshape_ros.model.checkpoint import save_checkpoint
from softshape_ros.model.data import SCENE_FEATURES, scene_targets, scene_vector, shape_tensors
from softshape_ros.model.metrics import RobotSilhouette
from softshape_ros.model.train import TrainConfig, train
from softshape_ros.model.tube_net import KEYPOINTS
from softshape_ros.model.tube_render import TubeShader, coverage, nearest_segment, tube_field
from softshape_ros.scene import OBJECT_DIMS, Scene
from softshape_ros.sim.generate import SHAPE_KEYPOINTS, generate, make_plan

CFG = load_rig_config()


def tube(points):
    """Return 1 x 1 x K x 4 keypoints (x, y, radius, depth) as a float64 leaf tensor."""
    return torch.tensor([[points]], dtype=torch.float64, requires_grad=True)


def test_a_known_tube_renders_a_known_disk_and_capsule():
    # Two coincident points: a disk of radius 6 at (20, 30); its coverage integrates to
    # its area within the ramp's discretisation, and it is full inside, empty outside.
    disk = coverage(tube_field(tube([[20.0, 30.0, 6.0, 0.0]] * 2), 64).sd).view(64, 64)
    disk = disk.detach()
    assert float(disk.sum()) == pytest.approx(math.pi * 36, rel=0.02)
    assert float(disk[30, 20]) == 1.0 and float(disk[30, 27]) == 0.0
    assert float(disk[30, 14]) == pytest.approx(0.5, abs=1e-3)     # on the outline
    # A straight capsule: rectangle 30 x 2r plus a disk.
    cap = tube([[32.0, 10.0, 4.0, 0.0], [32.0, 40.0, 4.0, 0.0]])
    cap = coverage(tube_field(cap, 64).sd).detach()
    assert float(cap.sum()) == pytest.approx(30 * 8 + math.pi * 16, rel=0.02)
    row = cap.view(64, 64)[25]
    assert [float(v) for v in row[27:38]] == pytest.approx(
        [0.0, 0.5] + [1.0] * 7 + [0.5, 0.0], abs=1e-3)


def test_the_learned_outline_draws_the_tube_that_far_out():
    # TubeNet(outline=True): the shader's per-view offset (px) moves the drawn outline out
    # from the keypoints' radius; it starts at zero (the plain ramp) and is learnable.
    shader = TubeShader(2, 1, outline=True).double()
    kp = tube([[20.0, 30.0, 6.0, 0.0]] * 2).expand(1, 2, 2, 4)
    field = tube_field(kp, 64)
    assert torch.equal(shader.coverage(field), coverage(field.sd))
    with torch.no_grad():
        shader.outline.copy_(torch.tensor([0.5, -1.0]))
    cov = shader.coverage(field)
    disk = cov.detach().view(2, 64, 64)
    assert float(disk[0].sum()) == pytest.approx(math.pi * 6.5 ** 2, rel=0.02)
    assert float(disk[1].sum()) == pytest.approx(math.pi * 5.0 ** 2, rel=0.02)
    # 6 px from the centre: on the keypoints' outline, half covered by the plain ramp,
    # inside the drawn one 0.5 px further out (and outside the one 1 px further in).
    plain = coverage(field.sd).detach().view(2, 64, 64)
    assert float(plain[0, 30, 26]) == pytest.approx(0.5, abs=1e-3)
    assert float(disk[0, 30, 26]) == pytest.approx(1.0) and float(disk[1, 30, 26]) == 0.0
    cov[:, 0].sum().backward()
    # d(area)/d(offset): one per pixel on the ramp, about the outline's length 2 pi (r + 0.5).
    ramp = int(((disk[0] > 0) & (disk[0] < 1)).sum())
    assert float(shader.outline.grad[0]) == ramp
    assert ramp == pytest.approx(2 * math.pi * 6.5, rel=0.15)
    assert float(shader.outline.grad[1]) == 0.0
    assert TubeShader(2, 1).outline is None


def test_gradients_reach_every_keypoint():
    kp = tube([[20.0, 10.0, 3.0, 0.0], [24.0, 25.0, 3.5, 2.0], [30.0, 40.0, 4.0, 5.0]])
    field = tube_field(kp, 64)
    # A target disk off the tube: the loss pulls on position and radius of every point.
    target = coverage(tube_field(tube([[26.0, 12.0, 5.0, 0.0]] * 2), 64).sd).detach()
    shade = field.nz * field.depth                                  # normals and depth too
    loss = ((coverage(field.sd) - target) ** 2).sum() + 1e-3 * shade.sum()
    loss.backward()
    g = kp.grad[0, 0]
    assert torch.isfinite(g).all()
    assert (g[:, :3].abs() > 1e-6).all(), g                          # x, y, radius
    assert (g[1:, 3].abs() > 1e-9).all(), g                          # depth (moves off 0)
    # The numbers are gradients of this function: a finite-difference check on one.
    eps = 1e-4
    with torch.no_grad():
        moved = kp.detach().clone()
        moved[0, 0, 1, 0] += eps
        f2 = tube_field(moved, 64)
        l2 = ((coverage(f2.sd) - target) ** 2).sum() + 1e-3 * (f2.nz * f2.depth).sum()
    slope = (float(l2) - float(loss.detach())) / eps
    assert slope == pytest.approx(float(g[1, 0]), rel=0.05, abs=1e-3)


def _all_pairs_field(kp, size):
    """Return (sd, depth) from every pixel x segment pair with gradients: the reference."""
    r = torch.arange(size, dtype=kp.dtype)
    qy, qx = (g.reshape(-1) for g in torch.meshgrid(r, r, indexing='ij'))
    a, b = kp[:, :, :-1, None, :], kp[:, :, 1:, None, :]
    e = b - a
    exy2 = (e[..., 0] ** 2 + e[..., 1] ** 2).clamp_min(1e-6)
    px, py = qx - a[..., 0], qy - a[..., 1]
    s = (px * e[..., 0] + py * e[..., 1]) / exy2
    t = s.clamp(0.0, 1.0)
    dx, dy = px - t * e[..., 0], py - t * e[..., 1]
    d = torch.sqrt(dx * dx + dy * dy + 1e-6)
    sd, k = (d - a[..., 2] - t * e[..., 2]).min(dim=2, keepdim=True)
    depth = torch.gather(a[..., 3] + t * e[..., 3], 2, k).squeeze(2)
    return sd.squeeze(2), depth


def test_the_nearest_segment_render_equals_every_pair_with_gradients():
    # The renderer finds each pixel's nearest segment without autograd and differentiates
    # that segment alone; a minimum's gradient reaches only the segment it picks, so values
    # and gradients equal the all-pairs formulation (float rounding aside).
    gen = torch.Generator().manual_seed(3)
    base = torch.zeros(2, KEYPOINTS, 4, dtype=torch.float64)
    base[..., 0] = 32 + torch.randn(2, KEYPOINTS, generator=gen, dtype=torch.float64).cumsum(1)
    base[..., 1] = torch.linspace(8, 56, KEYPOINTS, dtype=torch.float64)
    base[..., 2], base[..., 3] = 4.0, torch.linspace(0, 6, KEYPOINTS, dtype=torch.float64)
    noise = torch.randn(8, 2, KEYPOINTS, 4, generator=gen, dtype=torch.float64)
    kp = (base + noise * torch.tensor([3.0, 3.0, 0.3, 2.0], dtype=torch.float64))
    weights = torch.randn(2, 8, 2, 64 * 64, generator=gen, dtype=torch.float64)
    grads = []
    for render in (lambda k: tuple(tube_field(k, 64))[::4], lambda k: _all_pairs_field(k, 64)):
        leaf = kp.clone().requires_grad_(True)
        sd, depth = render(leaf)
        (weights[0] * sd + weights[1] * depth).sum().backward()
        grads.append((sd.detach(), depth.detach(), leaf.grad))
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)
    assert (grads[0][2][..., :3].abs() > 0).all()                  # every point moved


def test_the_nearest_segment_is_every_pairs_first_minimum_ties_included():
    # One segment at a time with a running minimum (from LOOP_ROWS rows on), or one pass
    # (fewer): the same pick as the minimum over every pair at once, to the bit, and ties
    # (a repeated keypoint: two segments alike) to the first segment, as ``min`` breaks them.
    from softshape_ros.model.tube_render import LOOP_ROWS
    gen = torch.Generator().manual_seed(5)
    kp = torch.rand(12, 2, KEYPOINTS, 4, generator=gen) * torch.tensor([48.0, 48.0, 3.0, 6.0])
    kp[..., :2] += 8.0
    kp[..., 2] += 1.0
    kp[0:12:2, :, 6] = kp[0:12:2, :, 5]                             # a zero-length segment
    kp[1:12:2, :, 7:9] = kp[1:12:2, :, 5:7].flip(2)                 # a segment walked back
    r = torch.arange(64.0)
    qy, qx = (g.reshape(-1) for g in torch.meshgrid(r, r, indexing='ij'))
    a, e = kp[:, :, :-1, None, :], kp[:, :, 1:, None, :] - kp[:, :, :-1, None, :]
    exy2 = (e[..., 0] ** 2 + e[..., 1] ** 2).clamp_min(1e-6)
    px, py = qx - a[..., 0], qy - a[..., 1]
    t = (px * e[..., 0]).addcmul_(py, e[..., 1]).div_(exy2).clamp_(0.0, 1.0)
    px.addcmul_(t, e[..., 0], value=-1.0)
    py.addcmul_(t, e[..., 1], value=-1.0)
    sd = px.mul_(px).addcmul_(py, py).add_(1e-6).sqrt_()
    sd.sub_(a[..., 2]).addcmul_(t, e[..., 2], value=-1.0)
    want = sd.min(dim=2).indices
    tied = (sd == sd.min(dim=2, keepdim=True).values).sum(2) > 1
    for n in (12, 4):                                   # 24 rows: the loop; 8: one pass
        assert (n * 2 >= LOOP_ROWS) == (n == 12)
        assert torch.equal(nearest_segment(kp[:n], qx, qy), want[:n])
        assert tied[:n].sum() > 100                                  # ties were met


@pytest.fixture(scope='module')
def simulated(tmp_path_factory):
    """240 mono samples of the default contact-rich distribution over 12 scenes (seeded)."""
    plan = make_plan(CFG, 240, 12, seed=5)
    ds, _ = generate(CFG, plan, tmp_path_factory.mktemp('sim') / 'ds', ['main'],
                     workers=2, progress=False)
    return ds


def test_simulate_writes_a_shape_record_that_matches_the_images(simulated):
    ds = load_dataset(simulated.path)
    assert ds.meta['shape']['recorded'] is True
    assert ds.meta['shape']['keypoints'] == SHAPE_KEYPOINTS
    assert ds.shape.keypoints_px.shape == (len(ds), 1, SHAPE_KEYPOINTS, 2)
    kp, free = shape_tensors(ds, np.arange(len(ds)))
    assert kp.shape == (len(ds), 1, SHAPE_KEYPOINTS, 4) and free.shape == (len(ds),)
    # The base stays put, the tip moves; radii positive; depth 0 at the base.
    assert float(kp[:, 0, 0, :2].std(0).max()) < 0.5
    assert float(kp[:, 0, -1, :2].std(0).max()) > 2.0
    assert (kp[..., 2] > 0).all() and float(kp[..., 0, 3].abs().max()) < 1e-3
    # The tube the record describes is the robot in the images (the object hides some).
    tgt = np.asarray(ds.target)
    robot = RobotSilhouette.fit(tgt).mask(tgt)[:, 0]
    drawn = coverage(tube_field(kp, 64).sd).view(len(ds), 64, 64).numpy() > 0.5
    iou = (robot & drawn).sum((1, 2)) / (robot | drawn).sum((1, 2))
    assert np.median(iou) > 0.93, np.median(iou)
    assert iou[~free.numpy()].mean() > 0.9, iou[~free.numpy()].mean()


def test_datasets_without_a_shape_record_load_and_say_why(tmp_path, caplog):
    img = np.zeros((2, 1, 1, 8, 8), np.uint8)
    w = DatasetWriter(tmp_path / 'bags', 2, ['main'], 1, 8, [1.5e5] * 6,
                      contact='unknown: a real rig', shape='unknown: a real rig')
    w.put(slice(None), img, img, np.zeros((2, 6)), np.zeros(2))
    w.close()
    meta = json.loads((tmp_path / 'bags' / 'meta.json').read_text())
    del meta['shape']                      # as written before the record existed
    (tmp_path / 'bags' / 'meta.json').write_text(json.dumps(meta))
    with caplog.at_level('INFO', logger='softshape_ros.data.dataset'):
        ds = load_dataset(tmp_path / 'bags')
    assert ds.shape is None and 'before datasets carried' in ds.meta['shape']['why']
    assert 'no shape record' in caplog.text
    assert shape_tensors(ds, [0, 1]) == (None, None)


def test_bad_shape_records_are_refused_and_lose_nothing(tmp_path, simulated):
    img = np.zeros((1, 1, 1, 8, 8), np.uint8)
    good = (np.full((1, 1, 4, 2), 3.0), np.ones((1, 1, 4)), np.zeros((1, 1, 4)))
    w = DatasetWriter(tmp_path / 'd', 1, ['main'], 1, 8, [1.5e5] * 6, shape=4)
    with pytest.raises(DatasetError, match='records the shape; none given'):
        w.put(0, img, img, np.zeros(6), 0)
    for bad, match in (((good[0], -good[1], good[2]), 'radius_px must be > 0'),
                       ((good[0] * np.nan, good[1], good[2]), 'not finite')):
        with pytest.raises(DatasetError, match=match):
            w.put(0, img, img, np.zeros(6), 0, shape=bad)
    w.put(0, img, img, np.zeros(6), 0, shape=good)
    assert load_dataset(w.close().path).shape.radius_px.shape == (1, 1, 4)
    with pytest.raises(DatasetError, match='keypoints per view'):
        DatasetWriter(tmp_path / 'e', 1, ['main'], 1, 8, [1.5e5] * 6, shape=1)
    # A record file cut short on disk is refused with its name.
    (simulated.path / 'radius_px.npy').rename(tmp_path / 'saved.npy')
    try:
        with pytest.raises(DatasetError, match='missing radius_px'):
            load_dataset(simulated.path)
    finally:
        (tmp_path / 'saved.npy').rename(simulated.path / 'radius_px.npy')


def test_scene_targets_describe_the_recorded_placements(simulated):
    import dataclasses
    from types import SimpleNamespace
    ds = load_dataset(simulated.path)
    t = scene_targets(ds, np.arange(len(ds)))
    assert t.shape == (len(ds), len(SCENE_FEATURES)) and torch.isfinite(t).all()
    scenes = [Scene.from_json(s) for s in ds.meta['scenes']]
    for i in (0, len(ds) // 2, len(ds) - 1):
        sc, row = scenes[int(ds.scene[i])], dict(zip(SCENE_FEATURES, t[i].tolist()))
        assert row[f'is_{sc.object}'] == 5.0
        assert sum(row[f'is_{k}'] for k in OBJECT_DIMS) == 5.0
        assert [row['x_mm'], row['y_mm'], row['z_mm']] == pytest.approx(
            [1000 * v for v in sc.position_m], rel=1e-5)
    # A cylinder's yaw is not in the images, a ring's half turn neither; a quarter turn is.
    cyl = Scene(0, 'cylinder', (0.02, 0.0, 0.03), (0.0, 0.0, 1.0),
                {'radius_m': 0.005, 'height_m': 0.04})
    assert scene_vector(cyl) == scene_vector(dataclasses.replace(cyl, rpy_rad=(0, 0, 2.0)))
    ring = Scene(1, 'ring', (0.02, 0.0, 0.03), (math.pi / 2, 0.0, 0.3),
                 {'major_radius_m': 0.01, 'minor_radius_m': 0.003})
    half = scene_vector(dataclasses.replace(ring, rpy_rad=(math.pi / 2, 0.0, 0.3 + math.pi)))
    quarter = scene_vector(dataclasses.replace(ring, rpy_rad=(math.pi / 2, 0, 0.3 + math.pi / 2)))
    assert half == pytest.approx(scene_vector(ring)) and quarter != pytest.approx(half)
    # Datasets built from bags carry the session's scenes by index.
    bag = SimpleNamespace(meta={'scenes': [{'bag': 'b', 'scene_id': 7, 'index': 1,
                                            'scene': json.loads(ring.to_json())}]},
                          scene=np.array([1, 1]))
    assert scene_targets(bag, [0, 1]).tolist() == [pytest.approx(scene_vector(ring))] * 2
    # Unknown placements: no targets (the model learns from the images alone).
    assert scene_targets(SimpleNamespace(meta={'scenes': 4}, scene=np.zeros(2)), [0]) is None
    assert scene_targets(SimpleNamespace(meta=bag.meta, scene=np.array([2])), [0]) is None
    broken = {'scenes': [{'index': 1, 'scene': {'id': 1, 'object': 'ring'}}]}
    assert scene_targets(SimpleNamespace(meta=broken, scene=np.array([1])), [0]) is None


def test_the_scene_encoder_learns_to_see_the_placement(simulated):
    """A short keypoint training tells the encoder where the object is (the scene term)."""
    ds = load_dataset(simulated.path)
    cfg = TrainConfig(arch='tube', loss='keypoints', batch_size=16, max_steps=150,
                      eval_every=50, patience=100, seed=0, threads=2)
    idx = np.arange(len(ds))
    x = torch.from_numpy(np.array(ds.initial).reshape(len(ds), -1, 64, 64)).float() / 255
    want = scene_targets(ds, idx)
    pos = [SCENE_FEATURES.index(k) for k in ('x_mm', 'y_mm', 'z_mm')]
    spread = float((want[:, pos] - want[:, pos].mean(0)).abs().mean())
    net = train(ds, cfg, progress=False).model
    with torch.no_grad():
        got = net.keypoints.scene(x)[1]
    err = float((got[:, pos] - want[:, pos]).abs().mean())
    assert err < 0.5 * spread, (err, spread)


def test_the_keypoint_phase_validates_without_drawing(simulated, monkeypatch):
    """A keypoint-only objective: validation draws no image, and reports no image error."""
    from softshape_ros.model.tube_net import TubeNet
    ds = load_dataset(simulated.path)
    forward, drawn = TubeNet.forward, []

    def spy(self, image, pressure, truth=None, parts=False):
        if parts != 'keypoints':
            drawn.append(len(image))
        return forward(self, image, pressure, truth, parts)

    monkeypatch.setattr(TubeNet, 'forward', spy)
    cfg = TrainConfig(arch='tube', loss='keypoints', batch_size=16, max_steps=20,
                      eval_every=10, patience=100, seed=0, threads=1, split='scene')
    res = train(ds, cfg, progress=False)
    assert drawn == []
    assert [h['step'] for h in res.history] == [10, 20]
    assert all(h['val_mse'] is None and h['val_loss'] > 0 for h in res.history)
    assert res.best_val_mse is None and res.config['training']['best_val_mse'] is None
    assert res.copy_val_mse > 0
    # The full objective still draws and reports its image error.
    res = train(ds, TrainConfig(arch='tube', batch_size=16, max_steps=2, eval_every=2,
                                seed=0, threads=1, split='scene'), progress=False)
    assert drawn and 0 < res.best_val_mse == res.history[-1]['val_mse']


def test_scene_batches_hold_whole_placements_and_encode_each_once(simulated, monkeypatch):
    """--scene-batch: every batch is whole placements; each one's rest images encoded once."""
    from softshape_ros.model import train as train_mod
    from softshape_ros.model.tube_net import SceneEncoder
    scenes = np.array([3, 3, 1, 1, 1, 7, 3, 9, 9, 1, 7])
    gen = torch.Generator().manual_seed(0)
    batches = train_mod._batches(len(scenes), 2, 1, gen, scenes)
    assert sorted(torch.cat(batches).tolist()) == list(range(len(scenes)))   # once each
    assert [len(set(scenes[b.numpy()])) for b in batches] == [2, 2]
    for b in batches:           # a placement's rows all in one batch
        ids = set(scenes[b.numpy()])
        assert sorted(b.tolist()) == sorted(np.flatnonzero(np.isin(scenes, list(ids))))
    again = train_mod._batches(len(scenes), 2, 1, torch.Generator().manual_seed(0), scenes)
    assert all(torch.equal(a, b) for a, b in zip(batches, again))            # seeded
    # The encoder sees the distinct rest images only, and the keypoints are the same as
    # from one row at a time.
    ds = load_dataset(simulated.path)
    net = build_network('tube', len(ds.views), ds.channels).eval()
    with torch.no_grad():
        for q in net.parameters():
            q.add_(0.05 * torch.randn_like(q))
    rows = np.array([0, 1, 2, 30, 31, 60])
    x = torch.from_numpy(np.asarray(ds.initial)[rows].reshape(len(rows), -1, 64, 64)) / 255.0
    p = torch.rand(len(rows), 6)
    seen = []
    forward = SceneEncoder.forward
    monkeypatch.setattr(SceneEncoder, 'forward',
                        lambda self, image: seen.append(len(image)) or forward(self, image))
    distinct = len(set(np.asarray(ds.scene)[rows].tolist()))
    assert distinct < len(rows)
    kp = net(x, p, parts='keypoints')[0].detach()      # training runs with gradients
    one = torch.cat([net(x[i:i + 1], p[i:i + 1], parts='keypoints')[0].detach()
                     for i in range(len(rows))])
    image = net(x, p)
    assert seen[0] == distinct and torch.allclose(kp, one, atol=1e-5)
    assert seen[-1] == distinct and image.shape == x.shape
    # A keypoint phase in whole placements trains, and the checkpoint records how.
    cfg = TrainConfig(arch='tube', loss='keypoints', scene_batch=4, max_steps=40,
                      eval_every=20, patience=100, seed=0, threads=1, split='scene')
    res = train(ds, cfg, progress=False)
    assert res.config['training']['scene_batch'] == 4
    # It counts the rows it trained on (pretrain's samples/s): replay its seeded batches.
    tr = np.setdiff1d(np.arange(len(ds)), res.config['dataset']['val_rows'])
    gen, sizes = torch.Generator().manual_seed(0), []
    while len(sizes) < 40:
        sizes += [len(b) for b in train_mod._batches(len(tr), 4, 1, gen,
                                                     np.asarray(ds.scene)[tr])]
    assert res.rows_seen == sum(sizes[:40]) and len(set(sizes)) > 1
    assert res.history[-1]['val_loss'] < res.history[0]['val_loss']
    with pytest.raises(ValueError, match='scene_batch'):
        train(ds, TrainConfig(arch='tube', scene_batch=-1), progress=False)


def test_validation_encodes_each_placement_once(simulated, monkeypatch):
    """Validation rows come in placements: each one's scene parts run once, same numbers."""
    from softshape_ros.model import train as train_mod
    from softshape_ros.model.losses import TubeLoss
    from softshape_ros.model.tube_net import SceneEncoder, scenes_shared
    ds = load_dataset(simulated.path)
    net = build_network('tube', len(ds.views), ds.channels, depth_test=True).eval()
    with torch.no_grad():
        for q in net.parameters():
            q.add_(0.05 * torch.randn_like(q))
    rows = np.array([0, 1, 2, 30, 31, 60, 61])
    x8 = torch.from_numpy(np.asarray(ds.initial)[rows].reshape(len(rows), -1, 64, 64))
    t8 = torch.from_numpy(np.asarray(ds.target)[rows].reshape(len(rows), -1, 64, 64))
    scene = scene_targets(ds, rows)
    val, extra = (x8, t8, torch.rand(len(rows), 6)), (None, None, scene, None)
    distinct = len(set(np.asarray(ds.scene)[rows].tolist()))
    assert distinct < len(rows)
    seen = []
    forward = SceneEncoder.forward
    monkeypatch.setattr(SceneEncoder, 'forward',
                        lambda self, image: seen.append(len(image)) or forward(self, image))
    for objective in (TubeLoss(), TubeLoss(scene_only=True)):
        shared = train_mod._validate(net, val, extra, objective)
        assert seen[-1] == distinct
        with torch.no_grad():           # the plain path: every row encoded
            lo, y = objective(net, val[0].float() / 255, val[2], val[1].float() / 255,
                              scene=scene)
        assert seen[-1] == len(rows)
        assert shared[1] == pytest.approx(float(lo) * len(rows), rel=1e-5)
        if y is not None:
            assert shared[0] == pytest.approx(float(((y - t8 / 255.0) ** 2).sum()), rel=1e-5)
    # Outside validation a batch without gradients is one scene's (inference, export).
    with torch.no_grad():
        net(x8.float() / 255, val[2])
    assert seen[-1] == len(rows)
    with torch.no_grad(), scenes_shared():
        net(x8.float() / 255, val[2])
    assert seen[-1] == distinct


# The short training _in_training_steps_alone runs: its batch and threads.
STEPS_ALONE_BATCH, STEPS_ALONE_THREADS = 16, 1


def _in_training_steps_alone(simulated, monkeypatch, owner, name: str, context, flag: str,
                             **config) -> None:
    """
    Spy on ``owner.name``, train with ``flag`` on, then off: ``context`` on in steps alone.

    Every call with gradients (a training step) runs within the flag's context, every call
    without (validation) outside it; the weights stay float32; ``ours`` refuses the flag.
    """
    seen, inner = [], getattr(owner, name)

    def spy(*args, **kw):
        seen.append((torch.is_grad_enabled(), context.get()))
        return inner(*args, **kw)

    monkeypatch.setattr(owner, name, spy)
    ds = load_dataset(simulated.path)
    cfg = TrainConfig(arch='tube', max_steps=4, eval_every=2, patience=100, seed=0,
                      threads=STEPS_ALONE_THREADS, split='scene', batch_size=STEPS_ALONE_BATCH,
                      **{flag: True}, **config)
    res = train(ds, cfg, progress=False)
    assert {on for grad, on in seen if grad} == {True}         # every step within it
    assert {on for grad, on in seen if not grad} == {False}    # every validation not
    assert all(p.dtype == torch.float32 for p in res.model.parameters())
    assert res.config['training'][flag] is True
    seen.clear()
    train(ds, replace(cfg, **{flag: False}), progress=False)
    assert {on for _, on in seen} == {False}
    with pytest.raises(ValueError, match=f"{flag}.*'ours' has none"):
        train(ds, TrainConfig(arch='ours', max_steps=2, **{flag: True}), progress=False)


def test_the_encoder_runs_in_bf16_only_where_training_asks(simulated, monkeypatch):
    """encoder_bf16: the training steps' convolutions in bfloat16; validation and use float32."""
    from softshape_ros.model import tube_net
    from softshape_ros.model.tube_net import SceneEncoder, encoder_bf16
    torch.manual_seed(0)
    enc = SceneEncoder(2, 64).eval()
    image = torch.rand(4, 2, 64, 64)
    with torch.no_grad():
        plain = enc(image)
        with encoder_bf16():
            low = enc(image)
        again = enc(image)
    assert all(torch.equal(a, b) for a, b in zip(plain, again))   # the context leaves nothing
    assert all(t.dtype == torch.float32 for t in low)              # what it feeds stays float32
    assert not torch.equal(plain[0], low[0])                        # computed in bfloat16 ...
    torch.testing.assert_close(low[0], plain[0], atol=0.05, rtol=0.05)   # ... to its precision
    # In training, the steps run within the context, validation outside it.
    _in_training_steps_alone(simulated, monkeypatch, SceneEncoder, 'forward', tube_net._BF16,
                             'encoder_bf16', loss='scene')


def test_the_scene_nets_run_in_bf16_only_where_training_asks(simulated, monkeypatch):
    """scene_nets_bf16: ObjectNet's and BackgroundNet's convolutions in bf16, not their heads."""
    from softshape_ros.model import tube_net
    from softshape_ros.model.tube_net import ObjectNet, TubeNet, scene_nets_bf16
    torch.manual_seed(0)
    net = TubeNet(2, 1, depth_test=True).eval()
    for head in (net.objects.head, net.background.head):      # zero at first: give them a say
        torch.nn.init.normal_(head.weight, std=0.05)
    dtypes = {}
    for name, layer in (('obj conv', net.objects.inp[0]), ('obj head', net.objects.head),
                        ('bg conv', net.background.down[0][0]), ('bg head', net.background.head)):
        layer.register_forward_hook(lambda m, i, o, name=name: dtypes.__setitem__(name, o.dtype))
    image, code, rest = torch.rand(4, 2, 64, 64), torch.randn(4, 64), net.keypoints.rest()

    def both():
        return (*net.objects(image, code), net.background(image, rest))

    with torch.no_grad():
        plain = both()
        assert set(dtypes.values()) == {torch.float32}
        with scene_nets_bf16():
            low = both()
        assert dtypes == {'obj conv': torch.bfloat16, 'obj head': torch.float32,
                          'bg conv': torch.bfloat16, 'bg head': torch.float32}
        again = both()
    assert all(torch.equal(a, b) for a, b in zip(plain, again))   # the context leaves nothing
    assert all(t.dtype == torch.float32 for t in low)              # what they feed: float32
    for a, b in zip(plain, low):    # occupancy logits, depth (px), backgrounds
        assert not torch.equal(a, b)                                # computed in bfloat16 ...
        assert (b - a).abs().max() <= 0.02 * a.abs().max()         # ... to its precision
    # In training, the full loss's steps run within the context, validation outside it.
    _in_training_steps_alone(simulated, monkeypatch, ObjectNet, 'forward', tube_net._BF16_NETS,
                             'scene_nets_bf16', arch_params={'depth_test': True})


def test_the_compiled_renderer_draws_the_same_field_in_steps_alone(simulated, monkeypatch):
    """compile_renderer: torch.compile's renderer field in training steps, the same field."""
    from softshape_ros.model import tube_net
    from softshape_ros.model.tube_net import compiled_renderer, draw_field
    gen = torch.Generator().manual_seed(7)
    # The batch and views the training below draws (one compilation for both)
    b, v = STEPS_ALONE_BATCH, len(load_dataset(simulated.path).views)
    kp = torch.rand(b, v, KEYPOINTS, 4, generator=gen) * torch.tensor([40.0, 40.0, 3.0, 6.0])
    kp += torch.tensor([12.0, 12.0, 2.0, 0.0])
    weights = torch.randn(6, b, v, 64 * 64, generator=gen)
    built, compiled_field = [], tube_net._compiled_field

    def spy():
        built.append(True)
        return compiled_field()

    monkeypatch.setattr(tube_net, '_compiled_field', spy)

    def drawn(compiled: bool):
        leaf = kp.clone().requires_grad_(True)
        with compiled_renderer(compiled):
            field = draw_field(leaf, 64)
        sum((w * f).sum() for w, f in zip(weights, field)).backward()
        return [f.detach() for f in field] + [leaf.grad]

    plain = drawn(False)
    assert not built
    threads = torch.get_num_threads()
    torch.set_num_threads(STEPS_ALONE_THREADS)  # as training below: it reuses this compilation
    try:
        fused = drawn(True)
    finally:
        torch.set_num_threads(threads)
    assert built                                                # the compiled path drew it
    for a, b in zip(plain, fused):                              # six maps, the gradient
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-4)
    with torch.no_grad(), compiled_renderer():                  # no gradients: plain
        built.clear()
        draw_field(kp, 64)
    assert not built
    # In training, the full loss's steps draw within the context, validation outside it.
    _in_training_steps_alone(simulated, monkeypatch, tube_net, 'draw_field', tube_net._COMPILED,
                             'compile_renderer', arch_params={'depth_test': True})


def test_a_renderer_that_cannot_compile_is_refused_before_training(simulated, monkeypatch,
                                                                   tmp_path):
    """Without a working C++ compiler: a clear error up front, naming the way out."""
    from softshape_ros.model import tube_net

    def no_compiler(fn, **kw):
        def fail(*a, **k):
            raise RuntimeError('InvalidCxxCompiler: No working C++ compiler found\nmore')
        return fail

    monkeypatch.setattr(torch, 'compile', no_compiler)
    tube_net.check_renderer_compiles.cache_clear()
    try:
        ds = load_dataset(simulated.path)
        cfg = TrainConfig(arch='tube', max_steps=2, seed=0, threads=1, split='scene',
                          batch_size=16, compile_renderer=True)
        with pytest.raises(ValueError, match=r'compile_renderer: torch.compile could not build '
                           r'the renderer here \(RuntimeError: InvalidCxxCompiler: No working '
                           r'C\+\+ compiler found\); it needs a working C\+\+ compiler\. '
                           r'.*--no-compile-renderer'):
            train(ds, cfg, out=tmp_path / 'ck', progress=False)
        assert not (tmp_path / 'ck').exists()
        # The keypoint phases draw nothing: the flag is no concern of theirs.
        res = train(ds, replace(cfg, loss='keypoints'), progress=False)
        assert res.steps == 2
    finally:
        tube_net.check_renderer_compiles.cache_clear()


def test_bf16_instructions_are_read_from_the_cpu_flags(tmp_path):
    """cpu_bf16_native: the bfloat16 instructions, not just AVX-512 (which torch's check reads)."""
    from softshape_ros.model.tube_net import cpu_bf16_native
    info = tmp_path / 'cpuinfo'
    info.write_text('flags\t\t: fpu sse avx2 avx512f avx512bw avx512vl avx512dq\n')
    assert cpu_bf16_native(info) is False
    info.write_text('flags\t\t: fpu avx512bw avx512_bf16 avx512_vnni\n')
    assert cpu_bf16_native(info) is True
    info.write_text('Features\t: fp asimd sve bf16 i8mm\n')           # aarch64
    assert cpu_bf16_native(info) is True
    assert isinstance(cpu_bf16_native(tmp_path / 'missing'), bool)   # not Linux: torch's answer


def test_the_rate_warms_up_then_follows_its_cosine(simulated):
    """TrainConfig.warmup: a linear rise from 1/25, then the cosine; 0 is the plain cosine."""
    from softshape_ros.model.train import _rate
    cfg = TrainConfig(max_steps=100, warmup=0.3)
    assert _rate(0, cfg) == pytest.approx(0.04) and _rate(15, cfg) == pytest.approx(0.52)
    assert _rate(30, cfg) == 1.0 and _rate(65, cfg) == pytest.approx(0.5)
    assert _rate(100, cfg) == pytest.approx(0.0, abs=1e-12)
    plain = TrainConfig(max_steps=100)
    assert [_rate(s, plain) for s in (0, 50, 100)] == pytest.approx([1.0, 0.5, 0.0])
    with pytest.raises(ValueError, match='warmup'):
        train(load_dataset(simulated.path), TrainConfig(arch='tube', warmup=1.0),
              progress=False)


def test_a_reader_phase_then_the_heads_on_frozen_codes(simulated, tmp_path, monkeypatch):
    """The scene loss trains the encoder alone; freeze_scene then trains the heads alone."""
    from softshape_ros.model.losses import TubeLoss
    from softshape_ros.model.tube_net import SceneEncoder
    ds = load_dataset(simulated.path)
    # Rows held out at random: on held-out scenes of 12 placements the validation loss of
    # either phase rose on seeds 1 and 4; this way it falls on seeds 0-4.
    base = dict(arch='tube', max_steps=30, eval_every=15, patience=100, seed=0, threads=2,
                split='random', batch_size=16)
    start = build_network('tube', 1, 1)

    def parts(net):
        kn = net.keypoints
        return ({k: v.clone() for k, v in kn.scene.state_dict().items()},
                {k: v.clone() for k, v in [*kn.free.state_dict().items(),
                                           *kn.correct.state_dict().items()]})

    def same(a, b):
        return all(torch.equal(a[k], b[k]) for k in a)

    reader = train(ds, TrainConfig(loss='scene', **base), out=tmp_path / 'reader',
                   progress=False)
    assert reader.best_val_mse is None                       # nothing drawn
    assert reader.history[-1]['val_loss'] < reader.history[0]['val_loss']
    enc, heads = parts(reader.model)
    torch.manual_seed(0)
    _, heads0 = parts(build_network('tube', 1, 1))
    assert same(heads, heads0) and not same(enc, parts(start)[0])   # only the encoder moved
    # The heads on frozen codes: every distinct rest image encoded once, before the steps
    # (the training rows' and the validation rows').
    seen = []
    forward = SceneEncoder.forward
    monkeypatch.setattr(SceneEncoder, 'forward',
                        lambda self, image: seen.append(len(image)) or forward(self, image))
    res = train(ds, TrainConfig(loss='keypoints', freeze_scene=True, init=str(tmp_path / 'reader'),
                                **base), progress=False)
    val = np.zeros(len(ds), bool)
    val[res.config['dataset']['val_rows']] = True
    rest = np.asarray(ds.initial).reshape(len(ds), -1)
    assert seen == [len(np.unique(rest[~val], axis=0)), len(np.unique(rest[val], axis=0))]
    enc2, heads2 = parts(res.model)
    assert same(enc2, enc) and not same(heads2, heads)               # only the heads moved
    assert res.history[-1]['val_loss'] < res.history[0]['val_loss']
    assert res.config['training']['freeze_scene'] is True
    with pytest.raises(ValueError, match='freeze_scene'):
        train(ds, TrainConfig(loss='tube', freeze_scene=True, **base), progress=False)
    with pytest.raises(ValueError, match='placements recorded'):
        x = torch.zeros(2, 1, 64, 64)
        TubeLoss(scene_only=True)(start, x, torch.zeros(2, 6), x)


def test_short_tube_training_beats_copy_on_touching_samples(simulated, tmp_path):
    from softshape_ros.model.evaluate import predict_rows
    from softshape_ros.model.metrics import evaluate_arrays
    from softshape_ros.model.train import train_in_phases
    ds = load_dataset(simulated.path)
    # The recipe's order, short: keypoints first (nothing drawn: fast), then the full loss.
    # Rows held out at random, their placements seen in other rows: 12 placements are too
    # few to learn to see unseen ones, and on held-out scenes 200 full steps beat copying's
    # touching RMSE on seed 0 and lost on seed 2. This way seeds 0-4 all pass, the worst at
    # RMSE 0.83, changed-region RMSE 0.65 and tip 0.59 of copying's, IoU 0.015 above it.
    cfg = TrainConfig(arch='tube', batch_size=16, max_steps=60, eval_every=30, patience=100,
                      seed=0, threads=2, split='random', arch_params={'outline': True})
    _, res = train_in_phases(ds, cfg, keypoint_steps=150, first=tmp_path / 'keypoints',
                             out=tmp_path / 'ck', progress=False)
    val = np.asarray(res.config['dataset']['val_rows'])
    touching = np.asarray(ds.contact.touching)
    assert touching[val].sum() >= 10, touching[val].sum()
    model, cfg_loaded = load_checkpoint(tmp_path / 'ck')
    assert cfg_loaded['arch'] == 'tube' and cfg_loaded['dataset']['shape_record'] is True
    # Training builds the visibility that reads the scene code, and the checkpoint says so.
    assert cfg_loaded['arch_params']['scene_visibility'] is True and model.scene_visibility
    # The learned outline asked for (softshape train --outline), moved from its zero start
    # by the image terms; a fine-tune that asks for another architecture is refused.
    assert cfg_loaded['arch_params']['outline'] is True
    assert float(model.shader.outline.detach().abs().min()) > 1e-3, model.shader.outline
    with pytest.raises(CheckpointError, match='outline'):
        train(ds, TrainConfig(arch='tube', init=str(tmp_path / 'ck'), max_steps=1,
                              arch_params={'outline': False}), progress=False)
    pred = predict_rows(Predictor.from_checkpoint(tmp_path / 'ck'), ds, val)
    m = evaluate_arrays(np.asarray(ds.initial)[val], np.asarray(ds.target)[val], pred,
                        RobotSilhouette.fit(np.asarray(ds.initial)), touching[val])
    touch = m['touching']
    # The drawn robot is where it moved to: on touching samples its tip and the pixels that
    # changed are far better than copying's, and so is its silhouette.
    assert touch['model']['rmse'] < touch['copy']['rmse'], touch
    assert touch['model']['rmse_changed'] < 0.75 * touch['copy']['rmse_changed'], touch
    assert touch['model']['tip_error_px'] < 0.75 * touch['copy']['tip_error_px'], touch
    assert touch['model']['silhouette_iou'] > touch['copy']['silhouette_iou'], touch
    assert m['free']['model']['silhouette_iou'] > m['free']['copy']['silhouette_iou'], m


def test_tube_network_shapes_and_seeded_start():
    for views, channels in ((1, 1), (2, 3)):
        net = build_network('tube', views, channels)
        x = torch.rand(2, views * channels, 64, 64)
        y = net(x, torch.rand(2, 6))
        assert y.shape == x.shape and torch.isfinite(y).all()
        assert float(y.detach().min()) >= 0.0 and float(y.detach().max()) <= 1.0
    # Inference caches the scene: one rest image repeated over a batch of actuations (a
    # planner's candidates) is worked out once, and gives what the uncached model gives.
    net = build_network('tube', 2, 1).eval()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
        x, p = torch.rand(1, 2, 64, 64).expand(5, -1, -1, -1), torch.rand(5, 6)
        plain = net(x, p)
        net.cache = True
        assert torch.allclose(net(x, p), plain, atol=1e-5)
        assert net._cached[1].code.stride(0) == 0          # one code, expanded
        assert torch.allclose(net(x, p), plain, atol=1e-5)  # and from the cache
    torch.manual_seed(3)
    a = build_network('tube', 1, 1).state_dict()
    torch.manual_seed(3)
    b = build_network('tube', 1, 1).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_the_visibility_reads_the_scene_code_and_older_checkpoints_still_load(tmp_path):
    # Which of robot and object is in front depends on where the object stands in 3-D: the
    # visibility's logits must change with the scene code alone (same pixels, same
    # pressures).
    torch.manual_seed(0)
    net = build_network('tube', 2, 1, scene_visibility=True)
    vis = net.visibility
    with torch.no_grad():
        for p in vis.parameters():
            p.add_(0.1 * torch.randn_like(p))
    x, cond = torch.rand(1, vis.inp[0].in_channels, 64, 64), torch.rand(1, 64)
    x = x.expand(2, -1, -1, -1)
    code = torch.randn(2, vis.code)
    same = vis(x, torch.cat([cond, code[:1]], 1).expand(2, -1))
    assert torch.equal(same[0], same[1])
    other = vis(x, torch.cat([cond.expand(2, -1), code], 1))
    assert float((other[0] - other[1]).detach().abs().max()) > 1e-3
    assert vis.fine is not None and other.shape == (2, 2, 64, 64)
    # The shipped checkpoint hides the robot by its depth test instead (pretrain's recipe;
    # docs/model.md, "A depth test"); its config still records the visibility training
    # builds without it.
    shipped, cfg = load_checkpoint(PRETRAINED)
    assert shipped.depth_test and cfg['arch_params']['depth_test'] is True
    assert shipped.visibility is None and cfg['arch_params']['scene_visibility'] is True
    # ... and comes from the recipe with the reader phases: its full loss started from the
    # heads phase (docs/model.md, "A reader first, with the depth test").
    assert cfg['training']['init_from'].endswith('tube_keypoints_heads')
    assert cfg['training']['encoder_bf16'] is True     # "The encoder in bfloat16": shipped
    assert cfg['training']['steps'] == 2400             # "A longer full phase": shipped
    # "The full phase on more placements": shipped (5 % of them held out, 1000 rows).
    assert cfg['training']['val_fraction'] == 0.05 and cfg['dataset']['val'] == 1000
    # "Trainings averaged": shipped, the recipe's seeds 0 and 1 (seed 0's renderer).
    assert cfg['arch_params']['members'] == 2 and len(shipped.members) == 1
    assert [m['seed'] for m in cfg['ensemble']] == [0, 1]
    assert cfg['training']['fused_adam'] and cfg['training']['compile_renderer']
    # A checkpoint made before (no scene_visibility in its arch_params) gets the
    # pressure-only visibility it was trained with, and predicts as it did.
    legacy = build_network('tube', 2, 1).eval()
    assert not legacy.scene_visibility and legacy.visibility.fine is None
    assert legacy.visibility.film.in_features == 64
    old = dict(cfg, arch_params={'keypoints': KEYPOINTS})
    save_checkpoint(tmp_path / 'old', legacy, old)
    img = np.random.default_rng(0).integers(0, 256, (2, 1, 64, 64), dtype=np.uint8)
    want = Predictor(legacy, old).predict(img, [0.0] * 6)
    got = Predictor.from_checkpoint(tmp_path / 'old').predict(img, [0.0] * 6)
    assert np.array_equal(got, want)
    # The old weights under a config that says otherwise: refused, the mismatch named.
    save_checkpoint(tmp_path / 'mixed', legacy, dict(old, arch_params={
        'keypoints': KEYPOINTS, 'scene_visibility': True}))
    with pytest.raises(CheckpointError, match='visibility'):
        load_checkpoint(tmp_path / 'mixed')
    # Nor does it draw the learned outline (the plain ramp it was trained with), and its
    # weights under a config that claims one are refused by name too.
    assert legacy.shader.outline is None and not legacy.outline
    assert shipped.shader.outline is None           # the shipped recipe draws it plainly
    save_checkpoint(tmp_path / 'no_outline', legacy, dict(old, arch_params={
        'keypoints': KEYPOINTS, 'outline': True}))
    with pytest.raises(CheckpointError, match='outline'):
        load_checkpoint(tmp_path / 'no_outline')


def test_tube_trains_under_torchrun_with_two_processes(simulated, tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path
    bin_dir = Path(sys.executable).parent
    proc = subprocess.run(
        [str(bin_dir / 'torchrun'), '--standalone', '--nnodes', '1', '--nproc_per_node', '2',
         str(bin_dir / 'softshape'), 'train', '--dataset', str(simulated.path), '--arch',
         'tube', '--out', str(tmp_path / 'ck'), '--max-steps', '4', '--eval-every', '2',
         '--batch-size', '8', '--threads', '1', '--quiet', '--rows', '60'],
        env=dict(os.environ, OMP_NUM_THREADS='1'), capture_output=True, text=True,
        timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith('{')]
    assert len(lines) == 1 and json.loads(lines[0])['steps'] == 4
    _, cfg = load_checkpoint(tmp_path / 'ck')
    assert cfg['training']['world_size'] == 2 and cfg['training']['loss'] == 'tube'


def test_reproduce_trains_tube_in_its_two_phases_beside_paper_and_ours(tmp_path):
    from softshape_ros.experiments.object_depths import object_depths
    from softshape_ros.model.reproduce import ReproConfig, reproduce
    ds, _ = generate(CFG, make_plan(CFG, 60, 6, seed=7), tmp_path / 'ds', ['main', 'side'],
                     workers=1, progress=False)
    cfg = ReproConfig(sizes=[24], max_steps=2, eval_every=1, patience=5, threads=1,
                      tube_keypoint_steps=3, tube_eval_every=1)
    out, work = tmp_path / 'repro', tmp_path / 'work'
    cast = []

    def counted(ds, idx, **kw):
        cast.append(len(idx))
        return object_depths(ds, idx, **kw)

    with pytest.raises(ValueError, match='unknown architecture tub'):
        reproduce(ds.path, out, cfg, work=work, archs=['tub'])
    table = reproduce(ds.path, out, cfg, work=work, splits=['scene'], views=['stereo'],
                      archs=['paper', 'ours', 'tube'], object_depths=counted)
    run = json.loads((out / 'runs' / 'scene_stereo_tube_24.json').read_text())
    assert run['keypoint_steps'] == 3 and run['steps'] == 2 and run['test_rows'] == 10
    first, _ = load_checkpoint(work / 'scene_stereo_tube_24_keypoints')
    second, cfg_loaded = load_checkpoint(work / 'scene_stereo_tube_24')
    # The grid's tube composes as the shipped recipe's does: the depth test, its object
    # maps cast once for the full phase's training + validation rows.
    assert cfg_loaded['arch_params']['depth_test'] and second.objects is not None
    assert cast == [24]
    # The second phase started from the first, at the tube's own batch size.
    assert cfg_loaded['training']['init_from'] == str(work / 'scene_stereo_tube_24_keypoints')
    assert cfg_loaded['training']['batch_size'] == 64 and cfg_loaded['training']['loss'] == 'tube'
    tube_part = table.split('`tube` on the same test rows (scene split)')[1]
    assert '| 24 | stereo |' in tube_part and 'missing run' not in tube_part
    row = next(r for r in tube_part.splitlines() if r.startswith('| 24 | stereo |'))
    cells = [c.strip() for c in row.strip('|').split('|')]
    assert float(cells[4]) == pytest.approx(run['model']['rmse'], abs=0.01)
    assert (out / 'panels_stereo.png').stat().st_size > 100


def test_the_depth_test_hides_the_robot_only_where_the_object_is_nearer():
    """Known answer: an object over the tube's left half, in front above row 32, behind below."""
    from softshape_ros.model.tube_net import TubeNet
    net = TubeNet(1, 1, depth_test=True).double()
    assert net.visibility is None and net.objects is not None
    kp = torch.zeros(1, 1, KEYPOINTS, 4, dtype=torch.float64)
    kp[..., 0], kp[..., 1], kp[..., 2] = 20.0, torch.linspace(8, 56, KEYPOINTS), 4.0
    occupancy = torch.full((1, 1, 64, 64), -30.0, dtype=torch.float64)
    occupancy[..., 17:21] = 30.0                                  # the object: columns 17-20
    depth = torch.full((1, 1, 64, 64), 30.0, dtype=torch.float64)  # behind the tube ...
    depth[..., :32, :] = -30.0                                    # ... but in front above
    image = torch.full((1, 1, 64, 64), 0.9, dtype=torch.float64)
    _, alpha, cov, logit = net.render(kp, image, image, None, torch.cat([occupancy, depth], 1))
    hidden = torch.zeros(64, 64, dtype=torch.bool)
    hidden[:32, 17:21] = True
    a, c = alpha[0, 0], cov[0, 0]
    assert float(c[8:32, 17:21].min()) > 0.99                     # the tube is there ...
    assert float(a[hidden].max()) < 1e-6                          # ... and hidden
    assert torch.allclose(a[~hidden], c[~hidden], atol=1e-4)      # elsewhere as drawn
    assert float(logit[0, 0][hidden].max()) < -10 and float(logit[0, 0][~hidden].min()) > 8
    # Its scene parts carry the object's two maps; the prediction draws through them.
    x = torch.rand(2, 1, 64, 64, dtype=torch.float64)
    out = net(x, torch.rand(2, 6, dtype=torch.float64), parts=True)
    assert out.occupancy.shape == out.object_depth.shape == (2, 1, 64, 64)
    assert float(torch.sigmoid(out.occupancy.detach()).max()) < 0.05  # sees no object yet


def test_object_depths_come_from_the_recorded_placements(simulated):
    """Per row, its placement's object depth: finite over the object's pixels, inf elsewhere."""
    from types import SimpleNamespace
    from softshape_ros.experiments.object_depths import object_depths
    from softshape_ros.model.losses import object_loss
    ds = load_dataset(simulated.path)
    idx = np.arange(len(ds))
    od = object_depths(ds, idx)
    assert len(od) == len(ds) and len(od.maps) == len(np.unique(ds.scene))
    maps = od[idx]
    assert maps.shape == (len(ds), 1, 64, 64) and maps.dtype == torch.float32
    hit = torch.isfinite(maps)
    # What the rest images show of the object lies where the rays hit it (the robot hides
    # the rest of it at rest); the object stands within reach, so about the robot's depth.
    seen = torch.from_numpy(RobotSilhouette.fit(np.asarray(ds.initial)).object_mask(
        np.asarray(ds.initial)))
    # (A quarter-covered edge pixel counts as seen, a ray through its centre misses: 6 %
    # of the seen pixels; the maps shifted by one column miss 12 %.)
    assert int(seen.sum()) > 1000
    assert int((seen & ~hit).sum()) < 0.08 * int(seen.sum())
    assert float(maps[hit].abs().max()) < 60
    assert torch.equal(od.rows(slice(3, 7))[np.arange(4)], maps[3:7])
    # Unknown placements (bags without a session YAML): none.
    assert object_depths(SimpleNamespace(meta={}, scene=np.zeros(2)), [0, 1]) is None
    # The object term: low for the truth, higher for a wrong depth or no object seen.
    t = maps[:8]
    right = object_loss(torch.where(torch.isfinite(t), 20.0, -20.0), t.nan_to_num(0, 0, 0), t)
    far = object_loss(torch.where(torch.isfinite(t), 20.0, -20.0), t.nan_to_num(0, 0, 0) + 5, t)
    blind = object_loss(torch.full_like(t, -20.0), t.nan_to_num(0, 0, 0), t)
    share = float(torch.isfinite(t).float().mean())               # the object's pixels
    assert float(right) < 1e-6 and float(blind) > 10 * share
    assert float(far) == pytest.approx(0.1 * 4.5 * share, rel=1e-4)  # smooth L1 of 5 px


def test_a_depth_test_model_learns_where_the_object_is(simulated, tmp_path):
    """A short training: ObjectNet finds the objects; the checkpoint loads and predicts."""
    from softshape_ros.experiments.object_depths import object_depths
    ds = load_dataset(simulated.path)
    # Rows held out at random: on 12 placements, held-out scenes left it to the seed (IoU
    # 0.82, 0.28, 0.50 and 0.0 on seeds 0-3); this way seeds 0-4 give 0.77-0.85.
    cfg = TrainConfig(arch='tube', batch_size=16, max_steps=120, eval_every=40, patience=100,
                      seed=0, threads=2, split='random', arch_params={'depth_test': True})
    res = train(ds, cfg, out=tmp_path / 'ck', progress=False, object_depths=object_depths)
    model, saved = load_checkpoint(tmp_path / 'ck')
    assert saved['arch_params']['depth_test'] is True and model.depth_test
    assert model.visibility is None
    val = np.asarray(saved['dataset']['val_rows'])
    x = torch.from_numpy(np.asarray(ds.initial)[val]).float().flatten(1, 2) / 255
    want = torch.isfinite(object_depths(ds, val)[np.arange(len(val))])
    with torch.no_grad():
        occupancy = model.scene_parts(x).objects[:, :1] > 0
    iou = float((occupancy & want).sum() / (occupancy | want).sum())
    assert iou > 0.5, iou
    assert res.history[-1]['val_loss'] < res.history[0]['val_loss']
    img = np.asarray(ds.initial)[val[0]]
    pred = Predictor.from_checkpoint(tmp_path / 'ck').predict(img, ds.pressure[val[0]])
    assert pred.shape == img.shape and pred.dtype == np.uint8
    with pytest.raises(CheckpointError, match='depth_test'):
        train(ds, TrainConfig(arch='tube', init=str(tmp_path / 'ck'), max_steps=1,
                              arch_params={'depth_test': False}), progress=False)


def _tube_checkpoint(path, seed: int, config: dict, views: int = 2):
    """Save a tube network of the shipped recipe's build, moved off its seeded start."""
    torch.manual_seed(seed)
    net = build_network('tube', views, 1, **config['arch_params'])
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return save_checkpoint(path, net, config), net.eval()


def test_trainings_averaged_draw_their_mean_keypoints_with_the_first_renderer(
        simulated, tmp_path, capsys):
    from softshape_ros.model.ensemble import ensemble
    shipped = load_checkpoint(PRETRAINED)[1]        # itself an ensemble: one training's build
    cfg = {k: v for k, v in shipped.items() if k != 'ensemble'}
    cfg['arch_params'] = {k: v for k, v in shipped['arch_params'].items() if k != 'members'}
    (a_ck, a), (b_ck, b) = (_tube_checkpoint(tmp_path / f'm{s}', s, cfg) for s in (1, 2))
    out = ensemble([a_ck, b_ck], tmp_path / 'both')
    model, saved = load_checkpoint(out)
    assert saved['arch_params'] == dict(cfg['arch_params'], members=2)
    assert [m['checkpoint'] for m in saved['ensemble']] == [str(a_ck), str(b_ck)]
    x, p = torch.rand(3, 2, 64, 64), torch.rand(3, 6)
    with torch.no_grad():
        got, one, two = (n(x, p, parts=True) for n in (model, a, b))
        mean = (one.keypoints + two.keypoints) / 2
        assert not torch.allclose(one.keypoints, two.keypoints, atol=1e-2)   # two trainings
        assert torch.allclose(got.keypoints, mean, atol=1e-5)
        assert torch.allclose(got.free_keypoints, (one.free_keypoints + two.free_keypoints)
                              / 2, atol=1e-5)
        assert torch.allclose(model(x, p, parts='keypoints')[0], mean, atol=1e-5)
        # Drawn by the first one: its scene parts, shading and depth test, the mean shape.
        scene = a.scene_parts(x)
        cond = torch.cat([a.keypoints(scene.code, p)[2], scene.code], 1)
        want = a.render(mean, x, scene.background, cond, scene.objects)[0]
        assert torch.allclose(got.image, want, atol=1e-5)
        assert not torch.allclose(got.image, one.image, atol=1e-3)
    # Its first training alone is the first checkpoint again (what the bench's steps train).
    from softshape_ros.model.ensemble import first_training
    alone, alone_cfg = first_training(out)
    assert 'members' not in alone_cfg['arch_params'] and 'ensemble' not in alone_cfg
    with torch.no_grad():
        assert torch.equal(alone(x, p), a(x, p))
    assert first_training(a_ck)[1] == load_checkpoint(a_ck)[1]
    # It predicts as any checkpoint does, one scene's actuations from its cached parts.
    pred = Predictor.from_checkpoint(out)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (2, 1, 64, 64), dtype=np.uint8)
    pressures = rng.uniform(0, 4e4, (4, 6))
    many = pred.predict_batch(np.repeat(img[None], 4, 0), list(pressures))
    assert np.array_equal(many[2], Predictor.from_checkpoint(out).predict(img, pressures[2]))
    # Refused, the reason named: one member, an ensemble as a member, other views or
    # another architecture; training an ensemble further.
    with pytest.raises(CheckpointError, match='two checkpoints or more'):
        ensemble([a_ck], tmp_path / 'x')
    with pytest.raises(CheckpointError, match='already an ensemble of 2'):
        ensemble([out, a_ck], tmp_path / 'x')
    mono, _ = _tube_checkpoint(tmp_path / 'mono', 3, dict(cfg, views=['main']), views=1)
    with pytest.raises(CheckpointError, match=r"views \['main'\] \(first: \['main', 'side'\]"):
        ensemble([a_ck, mono], tmp_path / 'x')
    ours = save_checkpoint(tmp_path / 'ours', build_network('ours', 2, 1),
                           dict(cfg, arch='ours', arch_params={}))
    with pytest.raises(CheckpointError, match="architecture 'ours'; ensembles average"):
        ensemble([a_ck, ours], tmp_path / 'x')
    assert not (tmp_path / 'x').exists()
    # The command: the same checkpoint, and a refusal as a message and an exit code.
    from softshape_ros.cli import main as cli
    assert cli(['ensemble', str(a_ck), str(b_ck), '--out', str(tmp_path / 'cli')]) == 0
    assert json.loads(capsys.readouterr().out)['members'] == 2
    assert (tmp_path / 'cli' / 'model.safetensors').read_bytes() == (
        out / 'model.safetensors').read_bytes()
    assert cli(['ensemble', str(a_ck), '--out', str(tmp_path / 'x')]) != 0
    assert 'two checkpoints or more' in capsys.readouterr().err
    ds = load_dataset(simulated.path)
    # Fine-tuned whole (the demo's fine-tune on a bag): the members train through their
    # mean, and it stays an ensemble (main view alone, as this dataset).
    other, _ = _tube_checkpoint(tmp_path / 'mono2', 4, dict(cfg, views=['main']), views=1)
    monos = ensemble([mono, other], tmp_path / 'monos')
    with pytest.raises(CheckpointError, match='an ensemble of 2 trainings: each member'):
        train(ds, TrainConfig(arch='tube', init=str(monos), max_steps=1, loss='keypoints',
                              freeze_scene=True), progress=False)
    train(ds, TrainConfig(arch='tube', init=str(monos), max_steps=2, batch_size=8,
                          eval_every=2, threads=1, split='scene'),
          out=tmp_path / 'tuned', progress=False)
    tuned, tuned_cfg = load_checkpoint(tmp_path / 'tuned')
    assert tuned_cfg['arch_params']['members'] == 2 and len(tuned.members) == 1
    before = load_checkpoint(monos)[0].state_dict()
    moved = {k for k, v in tuned.state_dict().items() if not torch.equal(v, before[k])}
    assert any(k.startswith('members.0.correct') for k in moved)
    assert any(k.startswith('keypoints.correct') for k in moved)
    with pytest.raises(ValueError, match='members 2: an ensemble is made of trained'):
        train(ds, TrainConfig(arch='tube', max_steps=1, arch_params={'members': 2}),
              progress=False)
