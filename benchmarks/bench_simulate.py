"""
``softshape simulate`` at scale: samples/s, peak memory of all its processes, failures.

Runs the CLI as a subprocess (all cores by default) and samples the memory of the whole
process tree (parent, forkserver, workers) every 0.1 s: the sum of RSS and of PSS (shared
pages split between the processes that map them). ``SIMULATE_BENCH_BASE`` names other
source trees (``:``-separated, e.g. ``git worktree add /tmp/base <commit>``) run the same
way in the same call, side by side. It also times, in this process on one core, what a
sample costs in ``SimRig.solve`` and ``render_inputs`` and what ``generate`` adds around
them (planning, the contact record, writing, the worker machinery), and how fast the write
path alone (worker processes, chunks, memory-mapped rows) takes 100 000 samples, and the
peak memory of ``DatasetWriter`` writing them in one process, per tree.

Sizes via environment variables: SIMULATE_BENCH_N (samples, default 2000),
SIMULATE_BENCH_SCENES (default 12), SIMULATE_BENCH_WORKERS (default 0: all cores),
SIMULATE_BENCH_OVERHEAD_N (default 200; 0 skips it), SIMULATE_BENCH_IO_N (default 100000,
the write path alone; 0 skips it), SIMULATE_BENCH_DIR (scratch folder, default a temporary
one; the datasets are deleted afterwards).
"""

from __future__ import annotations

import inspect
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


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


class PeakMemory:
    """Sample the memory of a process tree every 0.1 s in a thread, keep the peaks."""

    def __init__(self, pid: int):
        self.pid, self.rss, self.pss, self.procs = pid, 0, 0, 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def _watch(self):
        while not self._done.is_set():
            pids = _tree(self.pid)
            rss, pss = _memory(pids)
            self.rss, self.pss = max(self.rss, rss), max(self.pss, pss)
            self.procs = max(self.procs, len(pids))
            self._done.wait(0.1)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._done.set()
        self._thread.join()

    def report(self) -> dict:
        return {'peak_rss_mib': round(self.rss / 2 ** 20, 1),
                'peak_pss_mib': round(self.pss / 2 ** 20, 1), 'processes': self.procs}


def run_cli(tree: Path, args: list[str]) -> dict:
    """Run ``softshape <args>`` from source ``tree``; return its JSON, wall time, memory."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, '-c', RUN_CLI, *args], cwd=tree,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with PeakMemory(proc.pid) as peak:
        out, err = proc.communicate()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f'{tree}: softshape {" ".join(args)} exited {proc.returncode}: '
                           f'{err.strip().splitlines()[-1] if err.strip() else ""}')
    summary = json.loads(out.strip().splitlines()[-1])
    return {'summary': summary, 'wall_s': round(wall, 2), **peak.report()}


_IO = {}


def _io_init(rows, shape):
    rng = np.random.default_rng(0)
    _IO.update(rows=rows, img=rng.integers(0, 255, shape, dtype=np.uint8))


def _io_chunk(span):
    a, b = span
    k = b - a
    t = np.arange(k) % 3 > 0
    _IO['rows'].put(slice(a, b), _IO['img'][:1], _IO['img'][:k], np.zeros((k, 6)), 0,
                    (t, np.where(t, 1e-3, 0.0), np.where(t, 0.5, 0.0), np.where(t, 1e-5, 0.0)))
    return k


def io_ceiling(n: int, folder: Path, workers: int) -> dict:
    """
    Write ``n`` stereo 64x64 samples (fixed images) the way ``generate`` does, no simulator.

    Worker processes (forkserver) write chunks of 50 rows through ``DatasetRows.put``: the
    samples/s the machinery allows, and its memory, at any size.
    """
    from concurrent.futures import ProcessPoolExecutor

    from softshape_ros.data.dataset import DatasetWriter
    from softshape_ros.sim.generate import CHUNK, _context
    t0 = time.perf_counter()
    w = DatasetWriter(folder / 'io', n, ['main', 'side'], 1, 64, [1.5e5] * 6, overwrite=True,
                      contact=True)
    spans = [(a, min(a + CHUNK, n)) for a in range(0, n, CHUNK)]
    with PeakMemory(os.getpid()) as peak:
        with ProcessPoolExecutor(workers, mp_context=_context(), initializer=_io_init,
                                 initargs=(w.rows, (CHUNK, 2, 1, 64, 64))) as pool:
            done = sum(pool.map(_io_chunk, spans, chunksize=8))
        ds = w.close()
    wall = time.perf_counter() - t0
    ok = done == n and bool(ds.contact.touching[1]) and not ds.contact.touching[0]
    shutil.rmtree(folder / 'io', ignore_errors=True)
    return {'samples': n, 'wall_s': round(wall, 2), 'samples_per_s': round(n / wall),
            'read_back_ok': ok, **peak.report()}


def overhead(n: int) -> dict:
    """
    Per-sample ms on one core: solve, render, contact record, and generate's total.

    Self-contained (it runs as source in a subprocess of each tree; code without a contact
    record times none). CPU time of this process, not wall time: it holds up better on a
    loaded machine. A failed solve is counted (its time in ``solve_ms``) and skipped.
    """
    import tempfile
    import time
    from pathlib import Path

    from softshape_ros.config import load_rig_config
    from softshape_ros.sim import SimRig
    from softshape_ros.sim.generate import generate, make_plan
    from softshape_ros.sim.statics import SolverError
    try:
        from softshape_ros.sim.generate import measure_contact
    except ImportError:
        def measure_contact(state, obstacles):
            return None
    cfg = load_rig_config()
    views = list(cfg.cameras)[:2]
    plan = make_plan(cfg, n, max(1, n // 50), seed=1)
    rig = SimRig(cfg)
    solve = render = record = 0.0
    last, failed = None, 0
    for i, p in enumerate(plan.pressures):
        si = int(plan.sample_scene[i])
        if si != last:
            rig.set_scene(plan.scenes[si])
            rig.solve([0.0] * 6)
            last = si
        t0 = time.process_time()
        try:
            st = rig.solve(p)
        except SolverError:
            failed += 1
            solve += time.process_time() - t0
            rig.set_scene(plan.scenes[si])
            continue
        t1 = time.process_time()
        rig.render_inputs(st, 64, True, 3, views)
        t2 = time.process_time()
        measure_contact(st, rig.obstacles)
        t3 = time.process_time()
        solve, render, record = solve + t1 - t0, render + t2 - t1, record + t3 - t2
    with tempfile.TemporaryDirectory() as d:
        t0 = time.process_time()
        generate(cfg, plan, Path(d) / 'ds', views, workers=1, progress=False)
        total = time.process_time() - t0
    ms = 1e3 / n
    out = {'samples': n, 'failed_solves': failed, 'solve_ms': solve * ms, 'render_ms': render * ms,
           'contact_record_ms': record * ms, 'generate_ms': total * ms}
    out['overhead_ms'] = out['generate_ms'] - out['solve_ms'] - out['render_ms']
    out['overhead_share'] = out['overhead_ms'] / out['generate_ms']
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()}


def writer_memory(n: int) -> dict:
    """
    Write ``n`` stereo 64x64 samples in blocks of 50 through ``DatasetWriter.put``, in one process.

    Self-contained (it runs as source in a subprocess of each tree): the writer's own peak
    RSS, which grows with the dataset where the writer keeps the written pages mapped.
    """
    import resource
    import shutil
    import tempfile
    import time
    from pathlib import Path

    import numpy as np

    from softshape_ros.data.dataset import DatasetWriter
    b = 50
    img = np.random.default_rng(0).integers(0, 255, (b, 2, 1, 64, 64), dtype=np.uint8)
    has_contact = 'contact' in DatasetWriter.__init__.__code__.co_varnames
    folder = Path(tempfile.mkdtemp(prefix='writer_memory'))
    t0 = time.perf_counter()
    w = DatasetWriter(folder / 'ds', n, ['main', 'side'], 1, 64, [1.5e5] * 6,
                      **({'contact': True} if has_contact else {}))
    free = np.zeros(b, bool)
    record = ((free, np.zeros(b), np.zeros(b), np.zeros(b)),) if has_contact else ()
    for a in range(0, n, b):
        w.put(slice(a, a + b), img[:1], img, np.zeros((b, 6)), 0, *record)
    w.close()
    wall = time.perf_counter() - t0
    shutil.rmtree(folder)
    return {'samples': n, 'wall_s': round(wall, 2),
            'peak_rss_mib': round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def _in_tree(fn, tree: Path, arg: int) -> dict:
    """Run the self-contained ``fn(arg)`` in a subprocess of source ``tree``; its JSON."""
    code = f'{inspect.getsource(fn)}\nimport json\nprint(json.dumps({fn.__name__}({arg})))'
    proc = subprocess.run([sys.executable, '-c', code], cwd=tree, capture_output=True,
                          text=True, env=dict(os.environ, OMP_NUM_THREADS='1'))
    if proc.returncode != 0:
        raise RuntimeError(f'{tree}: {fn.__name__} failed: {proc.stderr[-500:]}')
    return json.loads(proc.stdout.strip().splitlines()[-1])


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
                     cpu_ms_per_sample=s.get('cpu_ms_per_sample'),
                     dataset_mib=round(sum(f.stat().st_size for f in out.iterdir()) / 2 ** 20,
                                       1))
            result['runs'][name] = r
            shutil.rmtree(out, ignore_errors=True)
        io_n = int(os.environ.get('SIMULATE_BENCH_IO_N', '100000'))
        if io_n:
            result['io_ceiling'] = io_ceiling(io_n, scratch, workers or os.cpu_count() or 1)
        m = int(os.environ.get('SIMULATE_BENCH_OVERHEAD_N', '200'))
        for name, tree in trees:
            if m:
                result['runs'][name]['one_core_per_sample'] = _in_tree(overhead, tree, m)
            if io_n:
                result['runs'][name]['writer_one_process'] = _in_tree(writer_memory, tree, io_n)
    finally:
        if not os.environ.get('SIMULATE_BENCH_DIR'):
            shutil.rmtree(scratch, ignore_errors=True)
    with open('/proc/loadavg') as fh:
        result['load_average_at_end'] = [float(v) for v in fh.read().split()[:3]]
    return result


if __name__ == '__main__':
    print(json.dumps(run(), indent=2))
