"""The rig's turn-and-mirror symmetry (sim/symmetry.py), checked on the simulator itself."""

import dataclasses
import math

import numpy as np
import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.sim.generate import make_plan
from softshape_ros.sim.rig import SimRig
from softshape_ros.sim.symmetry import RigSymmetry, SymmetryError

CFG = load_rig_config(None)
SYM = RigSymmetry.from_config(CFG)


def test_the_stiff_flop_rig_turns_by_a_third_and_mirrors_about_a_chamber():
    assert SYM.order == 3 and SYM.size == 6
    # One turn hands every chamber's role on within its segment, never across segments.
    for perm in (SYM.turn_perm, SYM.mirror_perm):
        assert sorted(perm) == list(range(6))
        assert all(CFG.chambers[i].segment == CFG.chambers[j].segment for i, j in enumerate(perm))
    assert list(SYM.turn_perm) != list(range(6))
    assert sum(int(i == j) for i, j in enumerate(SYM.mirror_perm)) == 2     # one per segment


def test_turned_and_mirrored_placements_give_the_turned_equilibrium():
    plan = make_plan(CFG, 12, 3, seed=11)          # a cylinder, a ring and a prism
    rig = SimRig(CFG)
    worst, moved = 0.0, 0.0
    for row in (2, 4, 8):                           # each pressed against its object
        scene, p = plan.scenes[plan.sample_scene[row]], plan.pressures[row]
        rig.set_scene(scene)
        state = rig.solve(p)
        assert state.contacts, f'row {row} ({scene.object}) should touch'
        ref = np.array(state.backbone_m)
        for turns in range(3):
            for mirrored in (False, True):
                fold = SYM.element(turns, mirrored)
                rig.set_scene(fold.scene(scene))
                got = np.array(rig.solve(fold.pressures(p)).backbone_m)
                worst = max(worst, float(np.abs(fold.points(ref) - got).max()))
                moved = max(moved, float(np.abs(ref - got).max()))
                np.testing.assert_allclose(fold.unfold_points(fold.points(ref)), ref, atol=1e-12)
    assert worst < 1e-6, f'the folded equilibrium is {worst * 1e3:.4f} mm off the turned one'
    assert moved > 5e-3                 # the folds do move the robot (a check that can fail)


def test_every_azimuth_folds_into_one_sixty_degree_sector():
    for az in np.linspace(-math.pi, math.pi, 721):
        point = SYM.base + [math.cos(az), math.sin(az), -0.02]
        fold = SYM.fold_of(point)
        rel = (SYM.azimuth(fold.points(point)) - SYM.mirror_angle) % (2 * math.pi)
        assert rel <= math.pi / 3 + 1e-9 or rel > 2 * math.pi - 1e-9, (az, rel)


@pytest.mark.parametrize('change, match', [
    (lambda c: dataclasses.replace(c, chambers=(
        dataclasses.replace(c.chambers[0], angle_deg=10.0), *c.chambers[1:])), 'seg1_ch1'),
    (lambda c: dataclasses.replace(c, chambers=(
        *c.chambers[:4], dataclasses.replace(c.chambers[4], max_pressure_pa=1e5),
        c.chambers[5])), 'seg2_ch'),
    (lambda c: dataclasses.replace(c, robot=dataclasses.replace(
        c.robot, gravity_m_s2=(1.0, 0.0, -9.81))), 'gravity'),
])
def test_a_rig_without_the_symmetry_is_refused_with_the_reason(change, match):
    with pytest.raises(SymmetryError, match=match):
        RigSymmetry.from_config(change(CFG))
