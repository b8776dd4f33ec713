"""``softshape sim-solve`` JSON and ``softshape simulate`` datasets (small sizes)."""

import json

import numpy as np
import pytest

from softshape_ros.cli import main
from softshape_ros.config import load_rig_config
from softshape_ros.data import load_dataset
from softshape_ros.scene import Scene
from softshape_ros.sim import SimRig
from softshape_ros.sim.generate import make_plan, random_scene

CFG = load_rig_config()


def run_json(capsys, argv):
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_sim_solve_prints_equilibrium_json(capsys):
    out = run_json(capsys, ['sim-solve', '--pressures', '0', '0', '1.2e5', '0', '0', '0',
                            '--compact', '--samples', '5'])
    assert len(out['q']) == out['dof'] == 20
    assert len(out['backbone_m']) == 5 and out['residual'] < 1e-9 and out['iterations'] >= 1
    # Same answer as the SimRig path.
    st = SimRig(CFG).solve([0, 0, 1.2e5, 0, 0, 0])
    assert np.allclose(out['tip_position_m'], st.tip_pose[:3, 3], atol=1e-9)


def test_sim_solve_overrides_tendons_loads_shear_and_object(capsys):
    base = run_json(capsys, ['sim-solve', '--tensions', '0.3', '0', '0', '0', '0', '0',
                             '--gravity', 'off'])
    shear = run_json(capsys, ['sim-solve', '--tensions', '0.3', '0', '0', '0', '0', '0',
                              '--gravity', 'off', '--shear', 'on', '--order', '2'])
    assert base['actuation'] == 'tendons' and shear['shear'] and shear['order'] == 2
    assert shear['dof'] == 2 * 4 * 3
    loaded = run_json(capsys, ['sim-solve', '--tip-force', '0.1', '0', '0'])
    assert loaded['tip_position_m'][0] > 0.001
    obj = json.dumps({'id': 0, 'object': 'sphere', 'position_m': [0.008, -0.03, 0.03],
                      'dims': {'radius_m': 0.008}})
    touched = run_json(capsys, ['sim-solve', '--pressures', '1.5e5', '0', '0', '1.5e5', '0',
                                '0', '--object', obj])
    assert touched['contacts'] and touched['max_penetration_m'] < 5e-4


def test_sim_solve_bad_input_is_one_clear_error(capsys):
    assert main(['sim-solve', '--gravity', 'maybe']) == 2
    assert 'expected on or off' in capsys.readouterr().err
    assert main(['sim-solve', '--pressures', 'nan', '0', '0', '0', '0', '0']) == 2
    assert 'non-finite' in capsys.readouterr().err


def test_random_scenes_clear_the_robot_at_rest():
    rng = np.random.default_rng(5)
    rig = SimRig(CFG)
    for i in range(9):
        sc = random_scene(i, ('cylinder', 'ring', 'prism')[i % 3], rng, CFG)
        assert isinstance(sc, Scene)
        rig.set_scene(sc)
        st = rig.solve([0.0] * 6)
        assert st.max_penetration_m == 0.0, sc
        assert np.allclose(st.tip_pose[:2, 3], 0.0, atol=1e-6), sc


def test_plan_is_seeded_and_within_limits():
    a = make_plan(CFG, 30, 4, seed=7)
    b = make_plan(CFG, 30, 4, seed=7)
    assert np.array_equal(a.pressures, b.pressures) and a.scenes == b.scenes
    assert (a.pressures >= 0).all() and (a.pressures <= np.array(CFG.max_pressures_pa)).all()
    assert sorted(set(a.sample_scene)) == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        make_plan(CFG, 0, 4, seed=0)


def test_simulate_writes_a_loadable_dataset_same_for_any_worker_count(tmp_path, capsys):
    args = ['simulate', '--samples', '6', '--scenes', '2', '--views', 'stereo', '--seed', '3']
    out1 = run_json(capsys, args + ['--out', str(tmp_path / 'a'), '--workers', '1'])
    run_json(capsys, args + ['--out', str(tmp_path / 'b'), '--workers', '2'])
    a, b = load_dataset(tmp_path / 'a'), load_dataset(tmp_path / 'b')
    assert len(a) == 6 and a.initial.shape == (6, 2, 1, 64, 64) and a.views == ['main', 'side']
    assert np.array_equal(a.target, b.target) and np.array_equal(a.pressure, b.pressure)
    assert np.array_equal(a.initial[0], a.initial[1]) and list(a.scene) == [0, 0, 0, 1, 1, 1]
    assert a.meta['simulator']['samples'] == 6 and 'touching_share' in out1
    # Targets differ from the rest images (the robot moved) and images are not blank.
    assert (a.target.astype(int) - a.initial).any() and a.target.std() > 10
    mono = run_json(capsys, ['simulate', '--samples', '2', '--scenes', '1', '--views', 'mono',
                             '--out', str(tmp_path / 'm'), '--workers', '1'])
    assert load_dataset(mono['out']).initial.shape == (2, 1, 1, 64, 64)
