"""
Renderer benchmark: stereo frames at 640x480 and 1920x1080, and the two 64x64 network inputs.

The inputs at render_inputs's default supersample of 4, and at the 3 `softshape simulate` uses.

Reports (never asserts) median wall and CPU times on one core (the process is pinned to one
CPU) over the seven reference scenes of test/data/render_reference (robot alone, each
object, occlusion both ways, the plane), and how far the images are from the reference
ray caster's (mean absolute gray difference). With RENDER_BENCH_BASELINE=<checkout> the
same measurement also runs on that checkout's code (a subprocess with it first on the
path, one frame per scene), side by side in one run. RENDER_BENCH_REPEAT sets the frames
per scene (default 5). Figure: bench_out/render_side_by_side.png (reference
and compiled renderer, with their difference x20).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
import statistics
import subprocess
import sys
import time

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
REF = ROOT / 'test' / 'data' / 'render_reference'
FIG = ROOT / 'bench_out' / 'render_side_by_side.png'


def _pin_one_core() -> int:
    cpu = sorted(os.sched_getaffinity(0))[0]
    os.sched_setaffinity(0, {cpu})
    return cpu


def _hd_config(cfg):
    """Return the rig config with 1920x1080 cameras of the same vertical field of view."""
    s = 1080 / 480
    cams = {n: dataclasses.replace(c, width=1920, height=1080, fx=c.fx * s, fy=c.fy * s,
                                   cx=960.0, cy=540.0,
                                   crop_px=[int(v * s) for v in c.crop_px])
            for n, c in cfg.cameras.items()}
    for n, c in cams.items():
        x, y, w, h = c.crop_px
        cams[n] = dataclasses.replace(c, crop_px=[(1920 - w) // 2, y, w, h])
    return dataclasses.replace(cfg, cameras=cams)


def measure(repeat: int) -> dict:
    """Time this interpreter's SimRig.render / render_inputs on the reference scenes."""
    from softshape_ros.config import load_rig_config
    from softshape_ros.scene import Scene
    from softshape_ros.sim import SimRig, SimState
    from softshape_ros.vision.preprocess import to_gray
    import cv2

    cfg = load_rig_config()
    cases = json.loads((REF / 'cases.json').read_text())

    def state(c):
        b = np.asarray(c['backbone_m'])
        return SimState(q=np.zeros(1), pressures_pa=np.zeros(6), s_m=np.zeros(len(b)),
                        backbone_m=b, radii_m=np.asarray(c['radii_m']), tip_pose=np.eye(4),
                        residual=0.0, iterations=0)

    def rig_for(config, c):
        rig = SimRig(config)
        rig.set_scene(Scene.from_dict(c['scene']) if c['scene'] else None)
        return rig

    def timed(fn):
        wall, cpu = [], []
        for c in cases:
            rig, st = rig_for(*fn.args(c)), state(c)
            fn(rig, st)                            # compile / warm caches, not timed
            for _ in range(repeat):
                t0, c0 = time.perf_counter(), time.thread_time()
                fn(rig, st)
                wall.append(time.perf_counter() - t0)
                cpu.append(time.thread_time() - c0)
        return {'median_ms': round(1e3 * statistics.median(wall), 2),
                'p90_ms': round(1e3 * float(np.percentile(wall, 90)), 2),
                'cpu_median_ms': round(1e3 * statistics.median(cpu), 2), 'frames': len(wall)}

    def stereo(rig, st):
        return rig.render(st)
    stereo.args = lambda c: (cfg, c)

    def inputs(rig, st):
        return rig.render_inputs(st)
    inputs.args = lambda c: (cfg, c)

    def inputs_ss3(rig, st):                       # what `softshape simulate` renders
        return rig.render_inputs(st, supersample=3)
    inputs_ss3.args = lambda c: (cfg, c)

    hd_cfg = _hd_config(cfg)

    def stereo_hd(rig, st):
        return rig.render(st)
    stereo_hd.args = lambda c: (hd_cfg, c)

    t0 = time.perf_counter()
    rig_for(cfg, cases[0]).render(state(cases[0]))
    first = time.perf_counter() - t0
    out = {'first_render_s': round(first, 2),       # includes numba's compile or cache load
           'stereo_640x480': timed(stereo),
           'inputs_2x64x64': timed(inputs),
           'inputs_2x64x64_supersample_3': timed(inputs_ss3),
           'stereo_1920x1080': timed(stereo_hd)}
    diffs, panels = [], []
    for c in cases:
        images = rig_for(cfg, c).render(state(c))
        for cam, img in images.items():
            ref = cv2.imread(str(REF / f'{c["name"]}_{cam}.png'), cv2.IMREAD_GRAYSCALE)
            g = to_gray(img)
            diffs.append(float(np.abs(g.astype(int) - ref).mean()))
            if cam == 'main':
                panels.append((ref, g))
    out['mean_abs_gray_diff_to_reference'] = {'mean': round(statistics.mean(diffs), 3),
                                              'max': round(max(diffs), 3)}
    out['_panels'] = panels
    return out


def _figure(panels) -> str:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    FIG.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(len(panels), 3, figsize=(9, 2.4 * len(panels)))
    for row, (ref, new) in zip(axes, panels):
        d = np.abs(ref.astype(int) - new)
        for ax, img, title in zip(row, (ref, new, np.clip(20 * d, 0, 255)),
                                  ('reference ray caster', 'compiled renderer',
                                   f'|difference| x20 (mean {d.mean():.2f})')):
            ax.imshow(img, cmap='gray', vmin=0, vmax=255)
            ax.set_title(title, fontsize=8)
            ax.axis('off')
    fig.tight_layout()
    fig.savefig(FIG, dpi=80)
    plt.close(fig)
    return str(FIG)


def _baseline(path: str, repeat: int) -> dict:
    # This file, loaded by path, measures the other checkout's softshape_ros (first on the path).
    code = ('import importlib.util, json, sys; sys.path.insert(0, sys.argv[1]); '
            'spec = importlib.util.spec_from_file_location("bench_render", sys.argv[2]); '
            'b = importlib.util.module_from_spec(spec); spec.loader.exec_module(b); '
            'b._pin_one_core(); r = b.measure(int(sys.argv[3])); r.pop("_panels"); '
            'import softshape_ros; r["code"] = softshape_ros.__file__; print(json.dumps(r))')
    env = dict(os.environ, OMP_NUM_THREADS='1', OPENBLAS_NUM_THREADS='1')
    env.pop('PYTHONPATH', None)
    res = subprocess.run([sys.executable, '-c', code, path, __file__, str(repeat)],
                         capture_output=True, text=True, env=env, cwd=path)
    if res.returncode != 0:
        return {'error': res.stderr[-2000:]}
    return json.loads(res.stdout.strip().splitlines()[-1])


def run() -> dict:
    repeat = int(os.environ.get('RENDER_BENCH_REPEAT', '5'))
    cpu = _pin_one_core()
    out = {'cpu': cpu, 'load_average': os.getloadavg()}
    new = measure(repeat)
    out['figure'] = _figure(new.pop('_panels'))
    import softshape_ros
    new['code'] = softshape_ros.__file__
    out['compiled'] = new
    base = os.environ.get('RENDER_BENCH_BASELINE')
    if base:
        out['baseline'] = _baseline(base, 1)
        b, n = out['baseline'], out['compiled']
        if 'error' not in b:
            out['speedup_median'] = {k: round(b[k]['median_ms'] / v['median_ms'], 1)
                                     for k, v in n.items()
                                     if isinstance(v, dict) and 'median_ms' in v and k in b}
    out['load_average_after'] = os.getloadavg()
    return out
