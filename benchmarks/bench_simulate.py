"""
``softshape simulate`` at scale: samples/s, peak memory of all its processes, failures.

Runs the CLI as a subprocess (all cores by default) and samples the memory of the whole
process tree (parent, forkserver, workers) every 0.1 s: the sum of RSS and of PSS (shared
pages split between the processes that map them). ``SIMULATE_BENCH_BASE`` names other
source trees (``:``-separated, e.g. ``git worktree add /tmp/base <commit>``) run the same
way in the same call, side by side. It also times, in this process on one core, what a
sample costs in ``SimRig.solve`` and ``render_inputs`` and what ``generate`` adds around
them (planning, the contact record, writing, the worker machinery).

Sizes via environment variables: SIMULATE_BENCH_N (samples, default 2000),
SIMULATE_BENCH_SCENES (default 12), SIMULATE_BENCH_WORKERS (default 0: all cores),
SIMULATE_BENCH_OVERHEAD_N (default 200; 0 skips it), SIMULATE_BENCH_DIR (scratch folder,
default a temporary one; the datasets are deleted afterwards).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parent.parent
RUN_CLI = 'import sys; from softshape_ros.cli import main; sys.exit(main(sys.argv[1:]))'


def _tree(root: int) -> list[int]:
    """Return ``root`` and all its descendants (from /proc)."""
    children = {}
    for d in os.listdir('/proc'):
        if not d.isdigit():
            continue
        try:
            with open(f'/proc/{d}/stat') as fh:
                ppid = int(fh.read().rsplit(')', 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(d))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def _memory(pids) -> tuple[int, int]:
    """Return (sum of RSS, sum of PSS) in bytes over ``pids``."""
    rss = pss = 0
    for p in pids:
        try:
            with open(f'/proc/{p}/smaps_rollup') as fh:
                for line in fh:
                    if line.startswith('Rss:'):
                        rss += int(line.split()[1]) * 1024
                    elif line.startswith('Pss:'):
                        pss += int(line.split()[1]) * 1024
        except OSError:
            continue
    return rss, pss


def run_cli(tree: Path, args: list[str]) -> dict:
    """Run ``softshape <args>`` from source ``tree``; return its JSON, wall time, memory."""
    peak = {'rss': 0, 'pss': 0, 'procs': 0}
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, '-c', RUN_CLI, *args], cwd=tree,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    done = threading.Event()

    def watch():
        while not done.is_set():
            pids = _tree(proc.pid)
            rss, pss = _memory(pids)
            peak['rss'], peak['pss'] = max(peak['rss'], rss), max(peak['pss'], pss)
            peak['procs'] = max(peak['procs'], len(pids))
            done.wait(0.1)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    done.set()
    th.join()
    if proc.returncode != 0:
        raise RuntimeError(f'{tree}: softshape {" ".join(args)} exited {proc.returncode}: '
                           f'{err.strip().splitlines()[-1] if err.strip() else ""}')
    summary = json.loads(out.strip().splitlines()[-1])
    return {'summary': summary, 'wall_s': round(wall, 2),
            'peak_rss_mib': round(peak['rss'] / 2 ** 20, 1),
            'peak_pss_mib': round(peak['pss'] / 2 ** 20, 1), 'processes': peak['procs']}


def overhead(n: int) -> dict:
    """Per-sample ms on one core: solve, render, contact record, and generate's total."""
    from softshape_ros.config import load_rig_config
    from softshape_ros.sim import SimRig
    from softshape_ros.sim.generate import generate, make_plan, measure_contact
    cfg = load_rig_config()
    views = list(cfg.cameras)[:2]
    plan = make_plan(cfg, n, max(1, n // 50), seed=1)
    rig = SimRig(cfg)
    solve = render = record = 0.0
    last = None
    for i, p in enumerate(plan.pressures):
        si = int(plan.sample_scene[i])
        if si != last:
            rig.set_scene(plan.scenes[si])
            rig.solve([0.0] * 6)
            last = si
        t0 = time.perf_counter()
        st = rig.solve(p)
        t1 = time.perf_counter()
        rig.render_inputs(st, 64, True, 3, views)
        t2 = time.perf_counter()
        measure_contact(st, rig.obstacles)
        t3 = time.perf_counter()
        solve, render, record = solve + t1 - t0, render + t2 - t1, record + t3 - t2
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        generate(cfg, plan, Path(d) / 'ds', views, workers=1, progress=False)
        total = time.perf_counter() - t0
    ms = 1e3 / n
    out = {'samples': n, 'solve_ms': solve * ms, 'render_ms': render * ms,
           'contact_record_ms': record * ms, 'generate_ms': total * ms}
    out['overhead_ms'] = out['generate_ms'] - out['solve_ms'] - out['render_ms']
    out['overhead_share'] = out['overhead_ms'] / out['generate_ms']
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()}


def run() -> dict:
    n = int(os.environ.get('SIMULATE_BENCH_N', '2000'))
    scenes = int(os.environ.get('SIMULATE_BENCH_SCENES', '12'))
    workers = int(os.environ.get('SIMULATE_BENCH_WORKERS', '0'))
    trees = [('this', ROOT)] + [(str(Path(t)), Path(t)) for t in
                                os.environ.get('SIMULATE_BENCH_BASE', '').split(':') if t]
    scratch = Path(os.environ.get('SIMULATE_BENCH_DIR') or tempfile.mkdtemp(prefix='simbench'))
    scratch.mkdir(parents=True, exist_ok=True)
    with open('/proc/loadavg') as fh:
        load = fh.read().split()[:3]
    result = {'samples': n, 'scenes': scenes, 'cores': os.cpu_count(),
              'load_average_at_start': [float(v) for v in load], 'runs': {}}
    try:
        for name, tree in trees:
            out = scratch / f'ds_{len(result["runs"])}'
            args = ['simulate', '--samples', str(n), '--scenes', str(scenes), '--views',
                    'stereo', '--out', str(out), '--seed', '0', '--overwrite']
            if workers:
                args += ['--workers', str(workers)]
            r = run_cli(tree, args)
            s = r.pop('summary')
            r.update(samples_per_s=round(n / r['wall_s'], 1),
                     touching_share=s.get('touching_share', s.get('contact_share')),
                     replaced_failed_solves=s.get('replaced_failed_solves'),
                     generate_samples_per_s=s.get('samples_per_s'),
                     dataset_mib=round(sum(f.stat().st_size for f in out.iterdir()) / 2 ** 20,
                                       1))
            result['runs'][name] = r
            shutil.rmtree(out, ignore_errors=True)
        m = int(os.environ.get('SIMULATE_BENCH_OVERHEAD_N', '200'))
        if m:
            result['one_core_per_sample'] = overhead(m)
    finally:
        if not os.environ.get('SIMULATE_BENCH_DIR'):
            shutil.rmtree(scratch, ignore_errors=True)
    with open('/proc/loadavg') as fh:
        result['load_average_at_end'] = [float(v) for v in fh.read().split()[:3]]
    return result


if __name__ == '__main__':
    print(json.dumps(run(), indent=2))
