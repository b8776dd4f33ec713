"""
The demo's control stage: reach goal shapes through the trained model, closed loop.

Two parts. ``softshape control-eval`` on the simulated rig (the planner through the model
against random search with the same budget and against the planner through the simulator,
the oracle), and the same loop live over DDS: ``mock_hardware`` and ``shape_controller`` as
separate processes, goal images published the way a user would, the results read from
``/softshape/goal/result``. Kept apart from ``pipeline.py`` so that it and ``report.py``
only call :func:`run_stage` and :func:`append_report` (a line each).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np

from softshape_ros.demo.participant import Participant

#: DemoSettings fields this stage depends on (its reuse key).
KEYS = ('control_goals', 'control_live', 'control_bank', 'seed')


def run_stage(settings, cfg, root: Path, run_tool, redo: bool) -> dict:
    """
    Run the stage after the pipeline's own, or reuse it (same settings, model unchanged).

    ``redo``: an earlier stage was redone (then so is this one). The marker is
    ``.control.done.json``, like the pipeline's stages.
    """
    key = dict(settings.stage_key('live'), **{k: getattr(settings, k) for k in KEYS})
    marker = root / '.control.done.json'
    if not redo and marker.is_file():
        try:
            done = json.loads(marker.read_text())
            if done.get('key') == key:
                print(f'\n=== control: reusing {root} (same settings; --fresh to redo) ===')
                return done['result']
        except (OSError, json.JSONDecodeError):
            pass
    print('\n=== control ===', flush=True)
    t0 = time.monotonic()
    res = run(settings, root, cfg, root / 'model', run_tool)
    res['seconds'] = round(time.monotonic() - t0, 1)
    marker.write_text(json.dumps({'key': key, 'result': res}, indent=2))
    return res


def run(settings, root: Path, cfg, checkpoint: Path, run_tool) -> dict:
    """Run both parts; return the numbers (and figure paths) for the report."""
    out = root / 'control'
    run_tool(['control-eval', '--model', str(checkpoint), '--goals',
              str(settings.control_goals), '--seed', str(settings.seed + 3000), '--out',
              str(out), '--threads', '1', '--bank-size', str(settings.control_bank)],
             root / 'logs' / 'control_eval.txt')
    summary = json.loads((out / 'control.json').read_text())['summary']
    live = live_loop(settings, root, cfg, checkpoint) if settings.control_live else None
    return {'eval': summary, 'eval_figure': str(out / 'control.png'), 'live': live}


def live_loop(settings, root: Path, cfg, checkpoint: Path) -> dict:
    """Close the loop over DDS on a few goals in unseen placements; figure goal/plan/reached."""
    from tqdm import tqdm

    from softshape_ros.control.evaluate import make_goals
    from softshape_ros.model import Predictor
    from softshape_ros.processes import NodeProcess
    from softshape_ros.sim import SimRig
    logs = root / 'logs' / 'control'
    views = list(cfg.camera_names)
    goals = make_goals(cfg, settings.control_live, settings.seed + 4000, views, progress=False)
    rows = []
    with ControlClient(cfg) as client:
        mock = NodeProcess('mock_hardware', {'seed': settings.seed + 2}, log_dir=logs).start()
        ctl = NodeProcess('shape_controller', {'model': str(checkpoint), 'threads': 1,
                                               'bank_size': settings.control_bank},
                          log_dir=logs).start()
        procs = [mock, ctl]
        try:
            client.wait_ready(procs)
            scene_id = None
            for g in tqdm(goals, desc='closed loop over DDS', unit='goal'):
                if g.scene.id != scene_id:
                    client.set_scene(g.scene, procs)
                    scene_id = g.scene.id
                rig = SimRig(cfg)
                rig.set_scene(g.scene)
                frames = rig.snap(g.pressures_pa)
                t0 = time.monotonic()
                res = client.send_goal(frames, procs)
                res['seconds'] = round(time.monotonic() - t0, 2)
                res['touching_goal'] = g.touching
                rows.append((frames, res, client.frames_at(res.get('rest_stamp_ns')),
                             client.frames_at(_best_stamp(res))))
        finally:
            codes = {p.name: p.stop() for p in reversed(procs)}
    pred = Predictor.from_checkpoint(checkpoint)
    fig = _figure(rows, views, pred, cfg, root / 'control_live.png')
    results = [r for _, r, _, _ in rows]
    reached = [r.get('state') == 'reached' for r in results]
    return {'goals': len(rows), 'reached': int(sum(reached)),
            'results': [{k: r.get(k) for k in ('state', 'iterations', 'tip_error_px', 'iou',
                                               'touching_goal', 'seconds', 'reason')}
                        | {'plan_ms': [s['plan_ms'] for s in r.get('steps', [])]}
                        for r in results],
            'figure': str(fig), 'exit_codes': codes}


def _best_stamp(res: dict):
    steps = res.get('steps') or []
    if not steps:
        return None
    return steps[res.get('best_iteration', len(steps)) - 1].get('trigger_stamp_ns')


def _network(cfg, frames: dict | None, views):
    from softshape_ros.vision.preprocess import preprocess
    if not frames or any(v not in frames for v in views):
        return None
    return np.stack([preprocess(frames[v], cfg.cameras[v].crop_px, cfg.dataset.image_size,
                                cfg.dataset.gray) for v in views])


def _figure(rows, views, pred, cfg, path: Path) -> Path:
    """Per goal and view: goal | the model's plan | what the camera saw (the best step)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n = max(1, len(rows))
    fig, axes = plt.subplots(n, 3 * len(views), figsize=(1.6 * 3 * len(views), 1.7 * n + 0.5),
                             squeeze=False)
    for i, (frames, res, rest, best) in enumerate(rows):
        goal = _network(cfg, frames, views)
        rest_n, seen = _network(cfg, rest, views), _network(cfg, best, views)
        plan = None
        if rest_n is not None and res.get('pressures_pa'):
            plan = pred.predict(rest_n, res['pressures_pa'])
        for j, v in enumerate(views):
            for k, (img, label) in enumerate(((goal, 'goal'), (plan, 'plan (model)'),
                                              (seen, 'reached (camera)'))):
                ax = axes[i, 3 * j + k]
                if img is not None:
                    ax.imshow(img[j, 0], cmap='gray', vmin=0, vmax=255, interpolation='nearest')
                ax.set_xticks([])
                ax.set_yticks([])
                if i == 0:
                    ax.set_title(f'{v}: {label}', fontsize=7)
            tips = res.get('tip_error_px') or []
            axes[i, 0].set_ylabel(f'{res.get("state")} it {res.get("iterations")}\n'
                                  f'tip {max(tips) if tips else float("nan"):.1f} px', fontsize=6)
    fig.suptitle('shape_controller over DDS against mock_hardware (unseen placements)',
                 fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


class ControlClient(Participant):
    """The user's side over DDS: scene, goal images, results, camera frames (by stamp)."""

    node_name = 'softshape_demo_control'

    def __init__(self, cfg):
        self.cfg = cfg
        self.lock = threading.Lock()
        self.results: list = []
        self.frames: dict = {v: {} for v in cfg.camera_names}
        self.diag: dict = {}

    def connect(self, n) -> None:
        """Publish the scene and goal images; watch results, diagnostics and frames."""
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import Image
        from std_msgs.msg import String

        from softshape_ros.nodes.common import IMAGE_QOS, LATCHED_QOS, RELIABLE_QOS
        t = self.cfg.topics
        self.String = String
        self.pub_scene = n.create_publisher(String, t.scene, LATCHED_QOS)
        self.pub_goal = {v: n.create_publisher(Image, t.camera('goal_image', v), IMAGE_QOS)
                         for v in self.cfg.camera_names}
        n.create_subscription(String, t.goal_result, self._on_result, RELIABLE_QOS)
        n.create_subscription(DiagnosticArray, t.diagnostics, self._on_diag, RELIABLE_QOS)
        for v in self.cfg.camera_names:
            n.create_subscription(Image, t.camera('camera_image', v),
                                  lambda m, v=v: self._on_frame(v, m), IMAGE_QOS)

    def _on_result(self, msg):
        with self.lock:
            self.results.append(json.loads(msg.data))

    def _on_diag(self, msg):
        with self.lock:
            for st in msg.status:
                self.diag[st.name] = {kv.key: kv.value for kv in st.values}

    def _on_frame(self, view, msg):
        from softshape_ros.nodes.common import image_to_numpy, stamp_to_ns
        with self.lock:
            store = self.frames[view]
            store[stamp_to_ns(msg.header.stamp)] = image_to_numpy(msg)
            while len(store) > 12:
                store.pop(next(iter(store)))

    def frames_at(self, stamp):
        with self.lock:
            if stamp is None or any(stamp not in f for f in self.frames.values()):
                return None
            return {v: f[stamp] for v, f in self.frames.items()}

    def wait_ready(self, procs, timeout: float = 60.0) -> None:
        from softshape_ros.processes import wait_until
        t = self.cfg.topics
        wait_until(lambda: {'mock_hardware', 'shape_controller'} <= set(
            self.node.get_node_names()), timeout, what='mock_hardware and shape_controller',
            processes=procs)
        wait_until(lambda: self.node.count_subscribers(t.camera('goal_image', 'main')) >= 1
                   and self.node.count_subscribers(t.trigger) >= 1
                   and 'shape_controller: loop' in self.diag, timeout,
                   what='the controller and the mock rig connected', processes=procs)

    def set_scene(self, scene, procs, timeout: float = 30.0) -> None:
        """Publish a placement; wait until the mock has it and the controller dropped its rest."""
        from softshape_ros.processes import wait_until
        self.pub_scene.publish(self.String(data=scene.to_json()))

        def applied():
            with self.lock:
                cams = self.diag.get('mock_hardware: cameras', {})
                loop = self.diag.get('shape_controller: loop', {})
                return cams.get('scene') == str(scene.id) and loop.get('scene_ready') == 'False'
        wait_until(applied, timeout, what=f'scene {scene.id} applied', processes=procs)

    def send_goal(self, frames: dict, procs, timeout: float = 180.0) -> dict:
        """Publish goal frames (one stamp for all views); return the controller's result."""
        from softshape_ros.nodes.common import ns_to_stamp, numpy_to_image
        from softshape_ros.processes import wait_until
        with self.lock:
            before = len(self.results)
        stamp = ns_to_stamp(time.time_ns())
        for v, img in frames.items():
            self.pub_goal[v].publish(numpy_to_image(img, stamp, self.cfg.cameras[v].frame_id))
        wait_until(lambda: len(self.results) > before, timeout, what='the goal result',
                   processes=procs)
        with self.lock:
            return self.results[before]


def append_report(path: Path, res: dict | None) -> None:
    """Append the stage's section to ``report.md``."""
    lines = report_lines(res)
    if lines:
        with open(path, 'a') as f:
            f.write('\n' + '\n'.join(lines) + '\n')


def report_lines(res: dict | None) -> list[str]:
    """Markdown for ``report.md``: the evaluation table, the live loop, both figures."""
    if not res:
        return []
    ev = res['eval']
    lines = ['## Control: reaching goal shapes through the model (closed loop)', '',
             f'{res.get("seconds")} s (0 = reused).', '',
             f'`softshape control-eval`: {ev.get("goals")} goals (images of random actuations '
             'in placements not seen in training, half pressed against the object), at most '
             f'{ev["max_iterations"]} closed-loop iterations; reached = tip within '
             f'{ev["tolerance"]["tip_px"]} px in every view and silhouette IoU >= '
             f'{ev["tolerance"]["iou"]}. Random search gets the same number of model calls; '
             'the oracle plans through the simulator itself.', '',
             '| | model | random search | oracle (simulator) |', '|---|---|---|---|']
    rows = (('success rate', 'success_rate', '{:.0%}'),
            ('touching goals', 'success_rate_touching', '{:.0%}'),
            ('free goals', 'success_rate_free', '{:.0%}'),
            ('within 1 / 2 / 3 iterations', 'success_within_iterations', None),
            ('iterations (median)', 'iterations_median', '{:.1f}'),
            ('planning ms per step (median, 1 thread)', 'plan_ms_median', '{:.0f}'),
            ('tip error px (median, best step)', 'final_tip_error_px_median', '{:.2f}'),
            ('silhouette IoU (median, best step)', 'final_iou_median', '{:.3f}'),
            ('pressure error kPa RMS (median)', 'final_pressure_error_kpa_median', '{:.1f}'),
            ('... less each segment\'s common mode',
             'final_differential_pressure_error_kpa_median', '{:.1f}'))
    for label, key, fmt in rows:
        cells = []
        for m in ('model', 'random', 'oracle'):
            v = ev.get(m, {}).get(key)
            if v is None:
                cells.append('-')
            elif fmt is None:
                cells.append(' / '.join(f'{x:.0%}' for x in v))
            else:
                cells.append(fmt.format(v))
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    if 'gap_to_oracle_points' in ev:
        lines += ['', f'Gap to the oracle: {ev["gap_to_oracle_points"]:.0f} points.']
    lines += ['', '![goal / plan / reached](control/control.png)', '']
    live = res.get('live')
    if live:
        lines += ['### The same loop live: shape_controller over DDS against mock_hardware', '',
                  f'{live["reached"]} of {live["goals"]} goals reached.', '',
                  '| goal | touching | state | iterations | tip error px | IoU | plan ms |',
                  '|---|---|---|---|---|---|---|']
        for i, r in enumerate(live['results']):
            tips = r.get('tip_error_px') or []
            iou = r.get('iou')
            lines.append(f'| {i} | {r.get("touching_goal")} | {r.get("state")} | '
                         f'{r.get("iterations")} | '
                         f'{" / ".join(f"{t:.1f}" for t in tips) or "-"} | '
                         f'{"-" if iou is None else f"{iou:.3f}"} | '
                         f'{" / ".join(f"{m:.0f}" for m in r.get("plan_ms", [])) or "-"} |')
        lines += ['', '![live: goal / plan / reached](control_live.png)', '']
    return lines
