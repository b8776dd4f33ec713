"""Simulated training data: the contact-rich distribution, the contact record, datasets."""

import json
import math
import os

import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.data import ContactRecord, DatasetError, DatasetWriter, load_dataset
from softshape_ros.data.dataset import write_dataset
from softshape_ros.model.reproduce import select_views
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig
from softshape_ros.sim.generate import (
    CHUNK, CONTACT_GAP_M, FAR_GAP_M, MAX_GAP_M, SPARSE_SHARE, TOWARD_WINDOW_RAD, ContactSample,
    bend_directions, generate, make_plan, measure_contact, scene_supersample, sparse_pressures,
    toward_pressures)

CFG = load_rig_config()
VIEWS = ['main', 'side']


@pytest.fixture(scope='module')
def small(tmp_path_factory):
    """60 samples of the default distribution over 12 scenes (seeded), and its plan."""
    plan = make_plan(CFG, 60, 12, seed=0)
    ds, summary = generate(CFG, plan, tmp_path_factory.mktemp('sim') / 'ds', VIEWS,
                           workers=2, progress=False)
    return plan, ds, summary


def changed_pixels(a, b):
    return int((np.abs(a.astype(int) - b.astype(int)) > 10).sum())


def test_default_distribution_touches_in_most_samples(small):
    plan, ds, summary = small
    c = ds.contact
    assert isinstance(c, ContactRecord) and len(c) == len(ds) == 60
    share = float(c.touching.mean())
    assert 0.5 <= share < 1.0, share                      # free samples still present
    assert ds.meta['touching_share'] == pytest.approx(share) == summary['touching_share']
    assert ds.meta['contact']['recorded'] is True
    assert ds.meta['simulator']['sparse_share'] == pytest.approx(plan.sparse.mean())
    kinds = [plan.scenes[i].object for i in plan.sample_scene]
    for kind in ('cylinder', 'ring', 'prism'):
        touched = c.touching[np.array(kinds) == kind]
        assert touched.any(), kind                         # every shape gets touched
    # Several distances: object surfaces from a fraction of a mm to several mm away.
    gaps = list(rest_gaps(plan.scenes))
    assert min(gaps) >= -1e-9 and max(gaps) - min(gaps) > 0.3 * MAX_GAP_M, gaps


def rest_gaps(scenes):
    """Each scene's object surface to the robot's at rest (m)."""
    rig = SimRig(CFG)
    out = []
    for sc in scenes:
        rig.set_scene(sc)
        st = rig.solve([0.0] * 6)
        out.append(min(float(o.sdf(st.backbone_m)[0].min() - st.radii_m.max())
                       for o in rig.obstacles))
    return np.array(out)


def test_a_far_share_places_scenes_beyond_reach_and_keeps_the_rest(tmp_path):
    near = make_plan(CFG, 18, 18, seed=4)
    mixed = make_plan(CFG, 18, 18, seed=4, far_share=0.5)
    far = [a != b for a, b in zip(near.scenes, mixed.scenes)]
    assert 3 <= sum(far) <= 15                              # about half, drawn per scene
    assert np.array_equal(near.pressures, mixed.pressures)  # the actuations are kept
    gaps = rest_gaps([s for s, f in zip(mixed.scenes, far) if f])
    # The surface gap is measured on the object's mesh, within a mm of the drawn one.
    assert gaps.min() > MAX_GAP_M - 1e-3 and gaps.max() < FAR_GAP_M + 1e-3, gaps
    ds, summary = generate(CFG, mixed, tmp_path / 'ds', VIEWS, workers=1, progress=False)
    assert ds.meta['scene_distribution']['far_share'] == 0.5
    assert ds.meta['scene_distribution']['far_gap_m'] == FAR_GAP_M
    with pytest.raises(ValueError, match='far-share'):
        make_plan(CFG, 18, 18, seed=4, far_share=1.5)


def test_contact_record_agrees_with_the_images(small):
    """Free samples are the contact-off shape; pressed ones differ from it visibly."""
    plan, ds, _ = small
    c = ds.contact
    assert np.all(c.arc_m[c.touching] > 0) and np.all(c.force_n[c.touching] > 0)
    assert np.all(c.arc_m[~c.touching] == 0) and np.all(c.penetration_m[~c.touching] == 0)
    assert np.all(c.arc_m < CFG.robot.total_length_m) and np.all(c.penetration_m < 1e-3)
    free_rig = SimRig(CFG, contact=False)     # objects drawn, never pushing
    pressed = []
    for i in range(0, len(ds), 2):
        free_rig.set_scene(plan.scenes[int(plan.sample_scene[i])])
        img = free_rig.render_inputs(free_rig.solve(ds.pressure[i]), 64, True, 3, VIEWS)
        diff = changed_pixels(np.stack([img[v] for v in VIEWS]), ds.target[i])
        if not c.touching[i]:
            assert diff <= 10, (i, diff, float(c.force_n[i]))
            assert c.force_n[i] < 0.01              # within the penalty's reach, a few mN
        elif c.force_n[i] > 0.1:
            assert diff > 10, (i, diff, float(c.force_n[i]))
            pressed.append(diff)
    assert len(pressed) >= 5 and np.median(pressed) > 100


def test_measure_contact_on_a_known_press():
    rig = SimRig(CFG)
    rig.set_scene(Scene(id=0, object='cylinder', position_m=(0.0, -0.026, 0.02),
                        dims={'radius_m': 0.008, 'height_m': 0.05}))
    # Chamber 1 of each segment bends the robot towards -y (bend_directions), into it.
    st = rig.solve([1.2e5, 0, 0, 1.2e5, 0, 0])
    c = measure_contact(st, rig.obstacles)
    assert c.touching and 1e-4 < c.arc_m < 0.02
    net = np.sum([k.force_n for k in st.contacts], axis=0)
    assert c.force_n == pytest.approx(float(np.linalg.norm(net))) and c.force_n > 0.1
    assert c.penetration_m == pytest.approx(st.max_penetration_m)
    # The arc against the exact backbone every 10 um (the record interpolates the samples).
    X = np.linspace(0.0, rig.rod.length, 4601)
    g, _ = rig.rod.at(rig.rod.forward(st.q, jac=False), X, jac=False)
    gap = rig.obstacles[0].sdf(g[:, :3, 3])[0] - rig.rod.radii[rig.rod.locate(X)[0]]
    inside = gap <= CONTACT_GAP_M
    assert inside.any() and c.arc_m == pytest.approx(inside.sum() * (X[1] - X[0]), abs=2e-5)
    away = rig.solve([0, 1.2e5, 1.2e5, 0, 1.2e5, 1.2e5])
    assert measure_contact(away, rig.obstacles) == ContactSample(False, 0.0, 0.0, 0.0)


def test_bend_directions_match_the_simulator():
    rig = SimRig(CFG)
    dirs = bend_directions(CFG)
    for i in range(6):
        p = np.zeros(6)
        p[i] = 0.5 * CFG.max_pressures_pa[i]
        tip = rig.solve(p).tip_pose[:2, 3] - np.asarray(CFG.robot.base_position_m[:2])
        cosang = tip @ dirs[i] / np.linalg.norm(tip) / np.linalg.norm(dirs[i])
        assert cosang > math.cos(math.radians(2)), (i, tip, dirs[i])


def test_toward_actuations_stay_in_limits_and_point_at_the_object():
    rng = np.random.default_rng(1)
    p = toward_pressures(rng, 500, 1.0, CFG)
    lim = np.asarray(CFG.max_pressures_pa)
    assert p.shape == (500, 6) and (p >= 0).all() and (p <= lim).all()
    b = (p / lim) @ bend_directions(CFG)
    ang = np.abs(np.angle(np.exp(1j * (np.arctan2(b[:, 1], b[:, 0]) - 1.0))))
    assert ang.max() <= TOWARD_WINDOW_RAD + 1e-9
    plan = make_plan(CFG, 200, 4, seed=2)
    assert 0.5 < plan.toward.mean() < 0.9
    uniform = make_plan(CFG, 200, 4, seed=2, toward_share=0.0)
    assert not uniform.toward.any() and (uniform.pressures <= lim).all()
    with pytest.raises(ValueError, match='toward-share'):
        make_plan(CFG, 10, 2, seed=0, toward_share=1.5)
    # Scenes without an object beside the robot get uniform actuations only.
    none = make_plan(CFG, 20, [Scene(id=0)], seed=0)
    assert not none.toward.any()


def test_a_share_of_the_plan_is_sparse_and_the_rest_is_unchanged():
    """Sparse rows: one chamber, or one per segment; the other rows as with no sparse share."""
    lim = np.asarray(CFG.max_pressures_pa)
    segment = np.array([c.segment for c in CFG.chambers])
    plan = make_plan(CFG, 2000, 20, seed=3)
    share = float(plan.sparse.mean())
    assert abs(share - SPARSE_SHARE) < 0.03, share
    on = plan.pressures > 0
    count = on.sum(1)
    assert set(count[plan.sparse]) == {1, 2} and (count[~plan.sparse] == 6).all()
    pairs = on[plan.sparse & (count == 2)]
    assert len(pairs) > 100 and all(sorted(segment[r]) == [0, 1] for r in pairs)
    # The aligned pairs (the sweep's kind of actuation) are among them.
    assert any((segment[r] == [0, 1]).all() and np.nonzero(r)[0][1] - np.nonzero(r)[0][0] == 3
               for r in pairs)
    assert (plan.pressures >= 0).all() and (plan.pressures <= lim).all()
    # Sparse rows keep their toward flag: those bend at the object too.
    assert (plan.sparse & plan.toward).sum() > 0.5 * plan.sparse.sum()
    none = make_plan(CFG, 2000, 20, seed=3, sparse_share=0.0)
    assert not none.sparse.any()
    keep = ~plan.sparse
    assert np.array_equal(none.pressures[keep], plan.pressures[keep])
    assert np.array_equal(none.toward, plan.toward)
    with pytest.raises(ValueError, match='sparse-share'):
        make_plan(CFG, 10, 2, seed=0, sparse_share=-0.1)


def test_sparse_actuations_toward_the_object_point_at_it():
    rng = np.random.default_rng(5)
    for azimuth in (0.0, 1.0, math.pi / 2, -2.5):      # between and on the chambers' ways
        p = sparse_pressures(rng, 300, CFG, azimuth)
        assert set((p > 0).sum(1)) <= {1, 2}
        b = (p / np.asarray(CFG.max_pressures_pa)) @ bend_directions(CFG)
        ang = np.abs(np.angle(np.exp(1j * (np.arctan2(b[:, 1], b[:, 0]) - azimuth))))
        assert ang.max() <= TOWARD_WINDOW_RAD + 1e-9


def test_chunks_split_scenes_and_keep_the_bytes_for_any_worker_count(tmp_path):
    plan = make_plan(CFG, 9, 2, seed=4)
    chunks = plan.chunks(3)
    assert [(c.scene_index, c.start, c.stop) for c in chunks] == \
        [(0, 0, 2), (0, 2, 5), (1, 5, 7), (1, 7, 9)]
    kw = dict(progress=False, chunk=3, noise=(2.0, 500.0))
    a, _ = generate(CFG, plan, tmp_path / 'a', VIEWS, workers=1, **kw)
    b, _ = generate(CFG, plan, tmp_path / 'b', VIEWS, workers=2, **kw)
    files = sorted(p.name for p in (tmp_path / 'a').iterdir())
    assert 'touching.npy' in files and 'meta.json' in files
    for name in files:
        assert (tmp_path / 'a' / name).read_bytes() == (tmp_path / 'b' / name).read_bytes(), name
    # With image noise, a scene's rest images are still one set for all its chunks.
    assert all(np.array_equal(a.initial[0], a.initial[k]) for k in range(1, 5))


def old_format(path, n=4):
    """Write a dataset exactly as format version 1 did (no contact arrays, no note)."""
    path.mkdir()
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (n, 2, 1, 8, 8), dtype=np.uint8)
    for name, arr in (('initial', img), ('target', img[::-1].copy()),
                      ('pressure', np.full((n, 6), 1e4, np.float32)),
                      ('scene', np.zeros(n, np.int64))):
        np.save(path / f'{name}.npy', arr)
    meta = {'format': 'softshape-dataset', 'version': 1, 'views': VIEWS, 'channels': 1,
            'image_size': 8, 'max_pressure_pa': [1.5e5] * 6, 'count': n}
    (path / 'meta.json').write_text(json.dumps(meta))
    return path


def test_datasets_without_a_record_load_and_say_why(tmp_path, caplog):
    with caplog.at_level('INFO', logger='softshape_ros.data.dataset'):
        ds = load_dataset(old_format(tmp_path / 'v1'))
    assert ds.contact is None and len(ds) == 4
    assert ds.meta['contact']['recorded'] is False
    assert 'before datasets carried' in ds.meta['contact']['why']
    assert 'no contact record' in caplog.text
    # A writer without contact (the bag builder) stores its reason.
    w = DatasetWriter(tmp_path / 'bags', 1, VIEWS, 1, 8, [1.5e5] * 6,
                      contact='unknown: a real rig')
    w.put(0, ds.initial[0], ds.target[0], ds.pressure[0], 0)
    bags = w.close()
    assert bags.contact is None and bags.meta['contact']['why'] == 'unknown: a real rig'
    assert 'touching_share' not in bags.meta
    with pytest.raises(DatasetError, match='say why'):
        DatasetWriter(tmp_path / 'x', 1, VIEWS, 1, 8, [1.5e5] * 6, contact=False)


def record(n, touching=None, arc=None, force=None, pen=None):
    t = np.array([True, False] * (n // 2)) if touching is None else np.asarray(touching)
    return (t, np.where(t, 0.002, 0.0) if arc is None else np.asarray(arc),
            np.where(t, 0.5, 0.001) if force is None else np.asarray(force),
            np.where(t, 1e-5, 0.0) if pen is None else np.asarray(pen))


def test_contact_record_round_trips_and_follows_subsets(tmp_path):
    img = np.zeros((4, 2, 1, 8, 8), np.uint8)
    ds = write_dataset(tmp_path / 'd', img, img, np.zeros((4, 6)), np.arange(4), [1.5e5] * 6,
                       VIEWS, contact=record(4))
    c = ds.contact
    assert c.touching.dtype == bool and c.arc_m.dtype == np.float32
    assert isinstance(c.touching, np.memmap) and ds.meta['touching_share'] == 0.5
    assert list(c.touching) == [True, False, True, False]
    sub = c[np.array([0, 1])]
    assert list(sub.touching) == [True, False] and sub.force_n[1] == np.float32(0.001)
    mono = select_views(ds, 1)
    assert mono.contact is ds.contact and mono.initial.shape[1] == 1


@pytest.mark.parametrize('bad, match', [
    (dict(arc=[-1e-3, 0, 1e-3, 0]), 'contact_arc_m must be >= 0'),
    (dict(force=[np.nan, 0, 1, 0]), 'contact_force_n is not finite'),
    (dict(touching=[2, 0, 1, 0]), 'touching must be true/false'),
    (dict(arc=[1e-3, 1e-3, 1e-3, 0]), 'must be 0 where the robot does not touch'),
    (dict(pen=[0, 1e-5, 0, 0]), 'must be 0 where the robot does not touch'),
    (dict(arc=[0, 0, 1e-3, 0]), 'must be > 0 where the robot touches'),
    (dict(arc=[1e-3, 0]), 'shape'),
])
def test_bad_contact_values_are_refused_and_lose_nothing(tmp_path, bad, match):
    img = np.full((4, 2, 1, 8, 8), 7, np.uint8)
    w = DatasetWriter(tmp_path / 'd', 8, VIEWS, 1, 8, [1.5e5] * 6, contact=True)
    w.put(slice(0, 4), img, img, np.zeros((4, 6)), 0, record(4))
    with pytest.raises(DatasetError, match=match):
        w.put(slice(4, 8), img + 1, img + 1, np.ones((4, 6)), 1, record(4, **bad))
    with pytest.raises(DatasetError, match='records contact; none given'):
        w.put(slice(4, 8), img, img, np.zeros((4, 6)), 1)
    w.put(slice(4, 8), img, img, np.zeros((4, 6)), 1, record(4))
    ds = w.close()
    assert (ds.target[:4] == 7).all() and list(ds.scene) == [0] * 4 + [1] * 4


def test_corrupt_or_incomplete_records_on_disk_are_refused(tmp_path):
    img = np.zeros((2, 2, 1, 8, 8), np.uint8)
    write_dataset(tmp_path / 'd', img, img, np.zeros((2, 6)), np.arange(2), [1.5e5] * 6,
                  VIEWS, contact=record(2))
    np.save(tmp_path / 'd' / 'contact_force_n.npy', np.array([-1.0, 0.0], np.float32))
    with pytest.raises(DatasetError, match='contact_force_n must be >= 0'):
        load_dataset(tmp_path / 'd')
    np.save(tmp_path / 'd' / 'contact_force_n.npy', np.array([1.0, 0.0]))     # float64
    with pytest.raises(DatasetError, match='expected float32'):
        load_dataset(tmp_path / 'd')
    (tmp_path / 'd' / 'contact_force_n.npy').unlink()
    with pytest.raises(DatasetError, match='incomplete, missing contact_force_n'):
        load_dataset(tmp_path / 'd')
    meta = json.loads((tmp_path / 'd' / 'meta.json').read_text())
    (tmp_path / 'd' / 'meta.json').write_text(json.dumps(dict(meta, version=9)))
    with pytest.raises(DatasetError, match='format version 9'):
        load_dataset(tmp_path / 'd')


def test_a_failing_worker_stops_the_run_and_leaves_nothing(tmp_path):
    plan = make_plan(CFG, 6, 2, seed=0)
    plan.pressures[4, 2] = np.nan                   # refused by the rig in the second scene
    with pytest.raises(ValueError, match='non-finite'):
        generate(CFG, plan, tmp_path / 'ds', VIEWS, workers=2, progress=False, chunk=2)
    assert list(tmp_path.iterdir()) == []           # no dataset, no .partial folder


def test_a_mix_of_renderings_draws_one_per_placement(tmp_path):
    # Each placement's rest and actuated images are those of one rendering, the same as
    # rendering the whole plan that way; both renderings are drawn; meta.json says which.
    plan = make_plan(CFG, 24, 8, seed=3)
    mix, _ = generate(CFG, plan, tmp_path / 'mix', VIEWS, workers=1, progress=False,
                      supersample=(0, 3))
    pure = {s: generate(CFG, plan, tmp_path / f'ss{s}', VIEWS, workers=1, progress=False,
                        supersample=s)[0] for s in (0, 3)}
    drawn = set()
    for c in plan.chunks(CHUNK):
        rows = slice(c.start, c.stop)
        s = scene_supersample((0, 3), plan.seed, c.scene_index)
        drawn.add(s)
        assert np.array_equal(mix.initial[rows], pure[s].initial[rows])
        assert np.array_equal(mix.target[rows], pure[s].target[rows])
        assert not np.array_equal(mix.initial[rows], pure[3 - s].initial[rows])
    assert drawn == {0, 3}
    assert mix.meta['rendering'] == {'supersample': [0, 3], 'per': 'placement'}
    assert pure[3].meta['rendering']['supersample'] == [3]


def test_simulate_cli_parses_and_refuses_supersample_mixes(tmp_path, capsys):
    from softshape_ros.commands.sim import supersample_arg
    assert supersample_arg('3') == 3 and supersample_arg('0,3') == (0, 3)
    from softshape_ros.cli import main
    base = ['simulate', '--samples', '2', '--scenes', '1', '--out', str(tmp_path / 'x')]
    for bad in ('0,x', '-1', '3,'):
        with pytest.raises(SystemExit):
            main(base + ['--supersample', bad])
        assert 'comma-separated' in capsys.readouterr().err
    assert not (tmp_path / 'x').exists()


def test_simulate_cli_refuses_bad_worker_counts_and_shares(tmp_path, capsys):
    from softshape_ros.cli import main
    base = ['simulate', '--samples', '2', '--scenes', '1', '--out', str(tmp_path / 'x')]
    assert main(base + ['--workers', '-1']) == 2
    assert '--workers must be >= 0' in capsys.readouterr().err
    assert main(base + ['--toward-share', '2']) == 2
    assert 'toward-share' in capsys.readouterr().err
    assert not (tmp_path / 'x').exists()


@pytest.mark.parametrize('kw, match', [
    (dict(views=['main', 'top']), 'views must be cameras'),
    (dict(size=0), 'size must be an integer >= 1'),
    (dict(supersample=1.5), 'supersample must be an integer'),
    (dict(supersample=(0, -1)), 'supersample must be an integer >= 0'),
    (dict(supersample=()), 'supersample must name at least one'),
    (dict(noise=(-1.0, 0.0)), 'noise'),
    (dict(noise=(0.0, float('nan'))), 'noise'),
    (dict(chunk=0), 'chunk must be'),
])
def test_generate_refuses_bad_settings_before_starting(tmp_path, kw, match):
    plan = make_plan(CFG, 2, 1, seed=0)
    args = dict(views=VIEWS, workers=2, progress=False)
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        generate(CFG, plan, tmp_path / 'ds', **args)
    assert list(tmp_path.iterdir()) == []


class _DiesInTheWorker(int):
    """A seed that ends the process unpickling it: a worker killed mid-run."""

    def __reduce__(self):
        return (os._exit, (3,))


def test_a_dead_worker_is_an_error_not_a_hang(tmp_path):
    plan = make_plan(CFG, 4, 2, seed=0)
    plan.seed = _DiesInTheWorker(0)
    with pytest.raises(RuntimeError, match='worker process died'):
        generate(CFG, plan, tmp_path / 'ds', VIEWS, workers=2, progress=False, chunk=2)
    assert list(tmp_path.iterdir()) == []
