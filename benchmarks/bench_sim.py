"""
Simulator benchmark: equilibrium times, dataset throughput, contact robustness, PyElastica.

Reports (never asserts) the wall and CPU time of one equilibrium without and with contact
(one process, one thread; median and p90), the convergence failures over random actuations
next to each object, the first-call cost of the compiled kernels (cold: compiling them into
an empty cache; warm: loading them), stereo samples per second of ``softshape simulate`` at
64x64 on all cores and, side by side in the same run, PyElastica (``pip install -r
requirements-bench.txt``) bringing the same dead-load cantilevers to rest by damped
dynamics: a slender one (L/d = 40, where the elastica is exact) and the robot-sized one with
shear on. ``SIM_BENCH_REFERENCE=/path/to/another/checkout`` times that checkout's simulator
on the same actuations right after this one's (e.g. the code before a change). Sizes via
environment variables: SIM_BENCH_FREE_N (default 200), SIM_BENCH_CONTACT_N (actuations per
object, default 1000), SIM_BENCH_DATASET_N (default 1000), SIM_BENCH_COLD=0 skips the cold
compile (~30 s of CPU). Figure: bench_out/sim_samples.png, rest and actuated images of the
first samples per view.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from softshape_ros.config import load_rig_config
from softshape_ros.sim.rod import Rod, RodSpec
from softshape_ros.sim.statics import PointLoad, Statics

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
FIG = REPO / 'bench_out' / 'sim_samples.png'
ONE_THREAD = {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1',
              'NUMBA_NUM_THREADS': '1'}


def _elastica_tip(a: float) -> np.ndarray:
    """Exact tip of a unit cantilever under a dead perpendicular load, P L^2 / EI = a."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import brentq

    def rhs(s, y):
        return [y[1], -a * np.cos(y[0]), np.cos(y[0]), np.sin(y[0])]

    def end(k0):
        return solve_ivp(rhs, [0, 1], [0, k0, 0, 0], rtol=1e-12, atol=1e-12).y[1, -1]

    k0 = brentq(end, 0.0, a, xtol=1e-14)
    y = solve_ivp(rhs, [0, 1], [0, k0, 0, 0], rtol=1e-12, atol=1e-12).y[:, -1]
    return np.array([y[2], y[3]])


def _timed(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


# -- case definitions shared by both simulators -----------------------------------------
CASES = {
    # name: (length, radius, E, density, P L^2 / EI, shear)
    'slender': (0.2, 0.0025, 1.0e6, 1000.0, 1.0, False),
    'robot_shear': (0.046, 0.0125, 6.0e4, 1070.0, 1.0, True),
}


def _ours(case):
    L, r, E, rho, a, shear = CASES[case]
    EI = E * np.pi * r ** 4 / 4
    rod = Rod(RodSpec(lengths=(L,), radii=(r,), youngs_modulus=E, density=rho, order=6,
                      shear=shear, stretch=shear))
    st = Statics(rod, [], gravity_on=False)
    load = [PointLoad(L, force_n=(0.0, a * EI / L ** 2, 0.0))]

    def solve():
        q, _, _ = st.solve([], load)
        return rod.forward(q).g[-1][:2, 3]

    t, tip = _timed(solve, 20)
    return t, tip


def _pyelastica(case, max_time_s=60.0):
    """Bring the cantilever to rest by damped dynamics; return (wall s, tip, sim s, steps)."""
    import elastica as ea
    L, r, E, rho, a, shear = CASES[case]
    EI = E * np.pi * r ** 4 / 4
    G = E / 3.0
    n = 50

    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.Damping):
        pass

    sim = Sim()
    # PyElastica scales GA by 27/28: give it G * 28/27 so its GA equals ours.
    rod = ea.CosseratRod.straight_rod(n, np.zeros(3), np.array([1.0, 0, 0]),
                                      np.array([0, 0, 1.0]), L, r, rho, youngs_modulus=E,
                                      shear_modulus=G * 28.0 / 27.0)
    sim.append(rod)
    sim.constrain(rod).using(ea.OneEndFixedBC, constrained_position_idx=(0,),
                             constrained_director_idx=(0,))
    P = a * EI / L ** 2
    omega1 = 1.875 ** 2 * np.sqrt(EI / (rho * np.pi * r * r * L ** 4))
    dx = L / n
    c = np.sqrt(E / rho)
    dt = 0.05 * dx / c
    sim.add_forcing_to(rod).using(ea.EndpointForces, np.zeros(3), np.array([0.0, P, 0.0]),
                                  ramp_up_time=2.0 / omega1)
    # Damping near critical for the first bending mode (fastest rest).
    sim.dampen(rod).using(ea.AnalyticalLinearDamper, uniform_damping_constant=1.5 * omega1,
                          time_step=dt)
    sim.finalize()
    stepper = ea.PositionVerlet()
    t_sim, steps, last = 0.0, 0, None
    chunk = max(int(0.25 / omega1 / dt), 1)
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < max_time_s:
        for _ in range(chunk):
            t_sim = stepper.step(sim, t_sim, dt)
        steps += chunk
        tip = rod.position_collection[:2, -1].copy()
        vel = float(np.linalg.norm(rod.velocity_collection[:, -1]))
        if last is not None and np.linalg.norm(tip - last) < 1e-7 * L and vel < 1e-6 * L * omega1 \
                and t_sim > 4.0 / omega1:
            break
        last = tip
    return time.perf_counter() - t0, tip, t_sim, steps


def bench_pyelastica() -> dict:
    out = {}
    try:
        import elastica  # noqa: F401
    except ImportError:
        return {'pyelastica': 'MISSING: pip install -r requirements-bench.txt to compare'}
    _pyelastica('robot_shear', max_time_s=5.0)        # numba JIT warm-up, not timed
    for case in CASES:
        L = CASES[case][0]
        t_ours, tip_ours = _ours(case)
        t_pe, tip_pe, t_sim, steps = _pyelastica(case)
        row = {'ours_median_s': t_ours, 'pyelastica_s': t_pe, 'pyelastica_sim_time_s': t_sim,
               'pyelastica_steps': steps, 'speedup': t_pe / t_ours,
               'ours_tip_over_L': (tip_ours / L).tolist(),
               'pyelastica_tip_over_L': (tip_pe / L).tolist()}
        if case == 'slender':
            exact = _elastica_tip(CASES[case][4])
            row['exact_tip_over_L'] = exact.tolist()
            row['ours_tip_error_over_L'] = float(np.linalg.norm(tip_ours / L - exact))
            row['pyelastica_tip_error_over_L'] = float(np.linalg.norm(tip_pe / L - exact))
        else:
            row['tip_distance_between_simulators_over_L'] = float(
                np.linalg.norm(tip_ours - tip_pe) / L)
        out[case] = row
    return out


def _run_python(args, root: Path, extra_env=None, timeout=3600) -> str:
    """Run ``python args`` in a fresh one-thread process importing softshape_ros from root."""
    env = dict(os.environ, **ONE_THREAD, **(extra_env or {}))
    paths = [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p]
    env['PYTHONPATH'] = os.pathsep.join([str(root)] + paths)
    out = subprocess.run([sys.executable, *args], env=env, cwd=str(root), capture_output=True,
                         text=True, timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f'{args[0]} under {root} failed: {out.stderr[-2000:]}')
    return out.stdout


def bench_equilibria(n_free: int, n_contact: int, root: Path = REPO) -> dict:
    """Equilibrium wall/CPU times (free, touching) and failures per object, one process."""
    out = _run_python([str(HERE / 'sim_equilibria.py'), str(n_free), str(n_contact)], root)
    return json.loads(out.strip().splitlines()[-1])


FIRST_CALL = (
    'import time; t0, c0 = time.perf_counter(), time.process_time(); '
    'from softshape_ros.sim.warmup import compile_kernels; compile_kernels(); '
    'print(time.perf_counter() - t0, time.process_time() - c0)')


def bench_first_call(cold: bool) -> dict:
    """Import and first solves of every kind: from the kernel cache, and compiled afresh."""
    out = {}
    runs = [('cached', None)] + ([('cold_compile', 'cold')] if cold else [])
    for name, mode in runs:
        with tempfile.TemporaryDirectory() as d:
            env = {'NUMBA_CACHE_DIR': d} if mode == 'cold' else None
            wall, cpu = map(float, _run_python(['-c', FIRST_CALL], REPO, env).split())
        out[name] = {'wall_s': wall, 'cpu_s': cpu}
    return out


def _figure(ds, rows: int = 6) -> None:
    """Save rest | actuated images (main, side) of samples from different scenes."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    picks = [int(np.nonzero(ds.scene == s)[0][1]) for s in np.unique(ds.scene)[:rows]]
    fig, axes = plt.subplots(len(picks), 4, figsize=(6, 1.6 * len(picks)))
    for r, i in enumerate(picks):
        for c, (arr, v, name) in enumerate([(ds.initial, 0, 'rest main'),
                                            (ds.target, 0, 'actuated main'),
                                            (ds.initial, 1, 'rest side'),
                                            (ds.target, 1, 'actuated side')]):
            ax = axes[r, c]
            ax.imshow(arr[i, v, 0], cmap='gray', vmin=0, vmax=255)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(name, fontsize=7)
        axes[r, 0].set_ylabel(f'scene {int(ds.scene[i])}', fontsize=7)
    fig.tight_layout()
    FIG.parent.mkdir(exist_ok=True)
    fig.savefig(FIG, dpi=120)
    plt.close(fig)


def bench_dataset(cfg, n: int) -> dict:
    from softshape_ros.sim.generate import generate, make_plan
    plan = make_plan(cfg, n, 12, seed=0)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        ds, summary = generate(cfg, plan, os.path.join(d, 'ds'), ['main', 'side'],
                               progress=False)
        wall = time.perf_counter() - t0
        _figure(ds)
    return {'samples': n, 'wall_s': wall, 'stereo_samples_per_s': n / wall,
            'cores': os.cpu_count(), 'figure': str(FIG), **summary}


def run() -> dict:
    cfg = load_rig_config()
    n_free = int(os.environ.get('SIM_BENCH_FREE_N', '200'))
    n_contact = int(os.environ.get('SIM_BENCH_CONTACT_N', '1000'))
    n_data = int(os.environ.get('SIM_BENCH_DATASET_N', '1000'))
    out = {'load_average_1min': os.getloadavg()[0],
           'first_call': bench_first_call(os.environ.get('SIM_BENCH_COLD', '1') != '0'),
           'equilibrium': bench_equilibria(n_free, n_contact)}
    ref = os.environ.get('SIM_BENCH_REFERENCE')
    if ref:
        out['equilibrium_reference'] = {'checkout': ref,
                                        **bench_equilibria(n_free, n_contact, Path(ref))}
    out['load_average_1min_after'] = os.getloadavg()[0]
    out['dataset_64x64_stereo'] = bench_dataset(cfg, n_data)
    out['vs_pyelastica'] = bench_pyelastica()
    return out


if __name__ == '__main__':
    print(json.dumps(run(), indent=2))
