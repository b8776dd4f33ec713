"""Exact answers for the Cosserat-rod statics (issue #3): each with the tolerance it deserves."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from softshape_ros.sim.rod import Rod, RodSpec
from softshape_ros.sim.statics import Actuator, PointLoad, SolverError, Statics

E, R_TUBE, L = 6.0e4, 0.0125, 0.046
EI = E * np.pi * R_TUBE ** 4 / 4
OFFSET = 0.0075


def rod(n_seg=1, **kw):
    seg_l = L / n_seg
    spec = RodSpec(lengths=(seg_l,) * n_seg, radii=(R_TUBE,) * n_seg, youngs_modulus=E, **kw)
    return Rod(spec)


def tendons(n_seg):
    return [Actuator('tendon', s, np.deg2rad(a), OFFSET) for s in range(n_seg)
            for a in (0.0, 120.0, 240.0)]


def curvature(r, q, X):
    return r.strain(q, X)[:, :3]


def test_tendon_gives_constant_curvature_F_r_over_EI():
    r = rod(1)
    st = Statics(r, tendons(1), gravity_on=False)
    F = 0.4
    q, asm, _ = st.solve([F, 0.0, 0.0])
    k = curvature(r, q, np.linspace(0, L, 9))
    # Tendon at angle 0 sits on body +y: it pulls the rod towards +y, i.e. +k3.
    assert np.allclose(k[:, 2], F * OFFSET / EI, rtol=1e-9, atol=0)
    assert np.abs(k[:, :2]).max() < 1e-9 * F * OFFSET / EI


def test_pure_tip_moment_gives_constant_curvature():
    r = rod(1, order=6)
    st = Statics(r, [], gravity_on=False)
    M = 2e-3
    q, _, _ = st.solve([], [PointLoad(L, moment_nm=(0.0, 0.0, M))])
    k = curvature(r, q, np.linspace(0, L, 9))
    assert np.allclose(k[:, 2], M / EI, rtol=1e-9, atol=0)


def test_chamber_pressure_bends_away_with_p_A_r_over_EI():
    r = rod(1)
    ch = [Actuator('chamber', 0, 0.0, OFFSET, 4e-5)]
    q, _, _ = Statics(r, ch, gravity_on=False).solve([1.0e5])
    k = curvature(r, q, np.linspace(0, L, 5))
    assert np.allclose(k[:, 2], -1.0e5 * 4e-5 * OFFSET / EI, rtol=1e-9, atol=0)


def test_distal_tendon_bends_both_segments_equally():
    r = rod(2)
    st = Statics(r, tendons(2), gravity_on=False)
    q, _, _ = st.solve([0, 0, 0, 0.0, 0.3, 0])
    k = curvature(r, q, np.linspace(0, L, 11))
    assert np.allclose(k, k[0], rtol=0, atol=1e-9 * np.abs(k).max())
    assert np.linalg.norm(k[0]) == pytest.approx(0.3 * OFFSET / EI, rel=1e-9)
    # A proximal tendon bends the proximal segment only.
    q, _, _ = st.solve([0.3, 0, 0, 0, 0, 0])
    k = curvature(r, q, np.array([0.25 * L, 0.75 * L]))
    assert abs(k[0, 2]) > 0 and abs(k[1]).max() < 1e-9 * abs(k[0, 2])


def test_equal_tension_in_three_tendons_gives_no_bending_and_slack_pulls_nothing():
    r = rod(2)
    st = Statics(r, tendons(2), gravity_on=False)
    q, _, _ = st.solve([0.5, 0.5, 0.5, 0.2, 0.2, 0.2])
    assert np.abs(q).max() < 1e-12
    q, _, _ = st.solve([-3.0, 0, 0, 0, -1.0, 0])       # slack: negative tension
    assert np.abs(q).max() == 0.0


def test_tip_moment_2_pi_EI_over_L_closes_a_circle():
    r = rod(2)
    st = Statics(r, [], gravity_on=False)
    q, _, _ = st.solve([], [PointLoad(L, moment_nm=(0.0, 0.0, 2 * np.pi * EI / L))],
                       tol=1e-13)
    tip = r.forward(q).g[-1]
    assert np.linalg.norm(tip[:3, 3]) < 1e-6 * L
    assert np.allclose(tip[:3, :3], np.eye(3), atol=1e-6)


def elastica_tip(a):
    """Cantilever, unit length, dead tip load perpendicular to it: P L^2 / EI = a (shooting)."""
    def rhs(s, y):
        return [y[1], -a * np.cos(y[0]), np.cos(y[0]), np.sin(y[0])]

    def end_moment(k0):
        return solve_ivp(rhs, [0, 1], [0, k0, 0, 0], rtol=1e-12, atol=1e-12).y[1, -1]

    k0 = brentq(end_moment, 0.0, a, xtol=1e-14)
    y = solve_ivp(rhs, [0, 1], [0, k0, 0, 0], rtol=1e-12, atol=1e-12).y[:, -1]
    return np.array([y[2], y[3]])


@pytest.mark.parametrize('a', [1.0, 2.0])
def test_large_deflection_cantilever_matches_elastica(a):
    exact = elastica_tip(a)
    r = rod(1, order=6)
    q, _, it = Statics(r, [], gravity_on=False).solve(
        [], [PointLoad(L, force_n=(0.0, a * EI / L ** 2, 0.0))])
    tip = r.forward(q).g[-1][:2, 3] / L
    assert np.linalg.norm(tip - exact) < 1e-4
    assert it > 1    # really nonlinear: Newton needed more than one step


def test_refining_basis_order_converges():
    exact = elastica_tip(2.0)
    errs = []
    for order in (1, 2, 4, 8):
        r = rod(1, order=order)
        q, _, _ = Statics(r, [], gravity_on=False).solve(
            [], [PointLoad(L, force_n=(0.0, 2.0 * EI / L ** 2, 0.0))])
        errs.append(np.linalg.norm(r.forward(q).g[-1][:2, 3] / L - exact))
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    assert errs[-1] < 5e-6


def test_linear_timoshenko_deflection_with_shear():
    G, A = E / 3.0, np.pi * R_TUBE ** 2
    P = 1e-5 * EI / L ** 2
    out = {}
    for shear in (False, True):
        r = rod(1, shear=shear)
        q, _, _ = Statics(r, [], gravity_on=False).solve([], [PointLoad(L, force_n=(0, P, 0))])
        out[shear] = r.forward(q).g[-1][1, 3]
    assert out[False] == pytest.approx(P * L ** 3 / (3 * EI), rel=1e-4)
    assert out[True] == pytest.approx(P * L ** 3 / (3 * EI) + P * L / (G * A), rel=1e-4)
    # This short, thick robot: shear adds a double-digit percentage to the tip deflection.
    assert out[True] / out[False] - 1 > 0.10


def test_tangent_matches_finite_differences_with_gravity_tendons_and_loads():
    r = rod(2, shear=True, stretch=True, density=1070.0, gravity=(-9.81, 0.0, 3.0))
    st = Statics(r, tendons(2))
    rng = np.random.default_rng(0)
    q = rng.normal(size=r.n) * 5
    u = np.array([0.3, 0.0, 0.1, 0.0, 0.2, 0.0])
    loads = [PointLoad(0.031, force_n=(0.05, 0.1, -0.02))]
    a = st.assemble(q, u, loads)
    fd = np.zeros_like(a.tangent)
    for i in range(r.n):
        dq = np.zeros(r.n)
        dq[i] = 1e-7
        fd[:, i] = (st.assemble(q + dq, u, loads).residual
                    - st.assemble(q - dq, u, loads).residual) / 2e-7
    assert np.abs(fd - a.tangent).max() < 1e-3 * np.abs(fd).max()
    # And the residual is the gradient of the potential (tendons, gravity, dead force).
    g = np.zeros(r.n)
    for i in range(r.n):
        dq = np.zeros(r.n)
        dq[i] = 1e-7
        g[i] = (st.assemble(q + dq, u, loads).energy - st.assemble(q - dq, u, loads).energy) / 2e-7
    assert np.abs(g - a.residual).max() < 1e-5 * np.abs(a.residual).max()


def test_non_convergence_raises_solver_error_not_a_shape():
    r = rod(1)
    st = Statics(r, tendons(1), gravity_on=False)
    with pytest.raises(SolverError, match='did not converge'):
        st.solve([50.0, 0, 0], max_iter=1, max_depth=0)
    with pytest.raises(ValueError):
        st.solve([float('nan'), 0, 0])
