"""
Simulated training data like the paper's (IV-B): objects next to the robot, random actuations.

On the paper's rig the object stands where the robot's bending reaches it, so most samples
show an interaction. Here scenes cycle through cylinder, ring and oblique prism placed
around the hanging robot at a random azimuth and height, their surface 1-10 mm from the
robot's at rest (small gaps more often); actuations are uniform within the chamber limits,
and a share of them (``toward_share``) is drawn uniform *given* that the bending points at
the object (within 30 degrees), as an operator steering the robot at it would. A further
share (``sparse_share``) is sparse: one chamber on, or one per segment, the rest at zero,
pointed at the object as often as the others (``sparse_pressures``). About two samples in
three touch (``meta.json`` ``touching_share``); the rest are free.

Every sample is drawn up front from one seed. The work is cut into chunks of at most
``CHUNK`` samples of one scene, fixed by the plan; each chunk is simulated from its own
seeds (rest images from the scene's), so a dataset has the same bytes whatever the number
of processes. Worker processes write their rows straight into the dataset's memory-mapped
arrays (only those rows are mapped), so memory stays flat however large the dataset.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from dataclasses import dataclass

import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.scene import Scene
from softshape_ros.sim import kernels
from softshape_ros.sim.lie import rpy_matrix
from softshape_ros.sim.objects import ObstacleSet
from softshape_ros.sim.statics import SolverError

OBJECT_CYCLE = ('cylinder', 'ring', 'prism')
MIN_GAP_M = 0.001           # object surface to robot surface at rest: clear of the robot,
MAX_GAP_M = 0.010           # ... within reach of its bending,
GAP_POWER = 2.0             # ... near placements more often: gap = MIN + (MAX - MIN) u^2
FAR_GAP_M = 0.025           # far placements (make_plan's far_share): gap MAX..FAR, uniform
TOWARD_SHARE = 0.7          # actuations drawn to bend towards the object
TOWARD_WINDOW_RAD = math.radians(30.0)
# Sparse actuations, one chamber on or one per segment and the rest at zero, are corners of
# the pressure cube that uniform draws hardly visit; an operator uses them all the time,
# and so does the Fig. 4(c) sweep (two chambers at 80 %, four at zero), where a model
# trained on uniform draws alone drew even the free robot badly (IoU 0.87 against 0.97).
SPARSE_SHARE = 0.2          # actuations drawn sparse (replacing uniform or toward ones)
SPARSE_PAIR_SHARE = 2 / 3   # ... of them one chamber per segment, else a single chamber
CHUNK = 50                  # samples per work item (a scene with more is split)
MAX_RETRIES = 5             # a failed solve is redrawn (counted) this often at most
ARC_STEP_M = 1e-4           # backbone sampling of the contact arc length
CONTACT_GAP_M = 1e-4        # in contact: the tube's surface within this of the object
NEAR_BAND_M = 5e-4          # ... and its knot intervals sampled where within this of that
SHAPE_KEYPOINTS = 16        # backbone points per view in the shape record
_THREAD_VARS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')


def random_scene(scene_id: int, kind: str, rng: np.random.Generator, cfg: RigConfig,
                 far: bool = False) -> Scene:
    """
    Place one object of ``kind`` next to the robot at a random azimuth, gap and height.

    ``far``: the gap drawn beyond the robot's reach instead (MAX_GAP_M..FAR_GAP_M, uniform),
    from the same draws of ``rng``.
    """
    r_robot = max(s.radius_m for s in cfg.robot.segments)
    base = np.asarray(cfg.robot.base_position_m, dtype=float)
    length = cfg.robot.total_length_m
    az = rng.uniform(0.0, 2 * math.pi)
    u = rng.uniform()
    gap = (MAX_GAP_M + (FAR_GAP_M - MAX_GAP_M) * u if far
           else MIN_GAP_M + (MAX_GAP_M - MIN_GAP_M) * u ** GAP_POWER)
    radial = np.array([math.cos(az), math.sin(az), 0.0])
    z = base[2] - length * rng.uniform(0.35, 0.85)
    if kind == 'cylinder':
        radius = rng.uniform(0.005, 0.010)
        dist = r_robot + gap + radius
        dims = {'radius_m': radius, 'height_m': rng.uniform(0.035, 0.055)}
        rpy = (0.0, 0.0, 0.0)
        z = base[2] - length * rng.uniform(0.5, 1.0)
    elif kind == 'ring':
        major, minor = rng.uniform(0.009, 0.014), rng.uniform(0.0025, 0.004)
        dist = r_robot + gap + major + minor
        dims = {'major_radius_m': major, 'minor_radius_m': minor}
        # The ring stands upright in the plane through the robot axis (rim towards it).
        rpy = (math.pi / 2, 0.0, az + math.pi)
        z = base[2] - length * rng.uniform(0.45, 0.8)
    elif kind == 'prism':
        w, d = rng.uniform(0.008, 0.014), rng.uniform(0.008, 0.014)
        h, skew = rng.uniform(0.035, 0.055), rng.uniform(-0.35, 0.35)
        # The slanted faces lean by h/2 tan(skew) at the ends: keep those clear at rest.
        dist = r_robot + gap + w / 2 + h / 2 * abs(math.tan(skew))
        dims = {'width_m': w, 'depth_m': d, 'height_m': h, 'skew_rad': skew}
        rpy = (0.0, 0.0, az)
        z = base[2] - length * rng.uniform(0.5, 1.0)
    else:
        raise ValueError(f'random scenes are cylinder, ring or prism, not {kind!r}')
    pos = base[:2] + dist * radial[:2]
    return Scene(id=scene_id, object=kind, position_m=(float(pos[0]), float(pos[1]), float(z)),
                 rpy_rad=rpy, dims=dims, label=f'random {kind}')


def bend_directions(cfg: RigConfig) -> np.ndarray:
    """
    Return (6, 2): the horizontal way each chamber at full pressure swings the tip.

    A chamber bends its segment away from itself; the weight is the segment's lever on
    the tip (its length times the distance from its middle to the tip), so the sum over
    chambers of ``p / p_max`` times these points where the actuation bends the robot.
    """
    R = rpy_matrix(cfg.robot.base_rpy_rad)
    lengths = [s.length_m for s in cfg.robot.segments]
    out = np.zeros((len(cfg.chambers), 2))
    for i, c in enumerate(cfg.chambers):
        th = math.radians(c.angle_deg)
        away = -(R @ np.array([0.0, math.cos(th), math.sin(th)]))[:2]
        j = c.segment
        lever = lengths[j] * (lengths[j] / 2 + sum(lengths[j + 1:]))
        out[i] = lever * away / np.linalg.norm(away)
    return out


def toward_pressures(rng: np.random.Generator, n: int, azimuth: float, cfg: RigConfig,
                     window: float = TOWARD_WINDOW_RAD) -> np.ndarray:
    """Return (n, 6) Pa: uniform within the limits, given a bend within ``window`` of azimuth."""
    limits = np.asarray(cfg.max_pressures_pa, dtype=float)
    dirs = bend_directions(cfg)
    aim = np.array([math.cos(azimuth), math.sin(azimuth)])
    out = np.empty((n, 6))
    todo = np.arange(n)
    while len(todo):
        u = rng.uniform(0.0, 1.0, (len(todo), 6))
        b = u @ dirs
        ok = b @ aim >= math.cos(window) * np.linalg.norm(b, axis=1)
        out[todo[ok]] = u[ok]
        todo = todo[~ok]
    return out * limits


def sparse_pressures(rng: np.random.Generator, n: int, cfg: RigConfig,
                     azimuth: float | None = None,
                     window: float = TOWARD_WINDOW_RAD) -> np.ndarray:
    """
    Return (n, 6) Pa: sparse actuations, each chamber on at a uniform level, the rest zero.

    A share ``SPARSE_PAIR_SHARE`` has one chamber of each segment on (any pair, the aligned
    ones included), the others a single chamber. Given ``azimuth``, drawn given a bend
    within ``window`` of it (rejection, as ``toward_pressures``); the pairs cover every
    direction, so the draw always ends.
    """
    limits = np.asarray(cfg.max_pressures_pa, dtype=float)
    segment = np.array([c.segment for c in cfg.chambers])
    seg_cols = [np.nonzero(segment == seg)[0] for seg in np.unique(segment)]
    dirs = bend_directions(cfg)
    if azimuth is not None:
        aim = np.array([math.cos(azimuth), math.sin(azimuth)])
    out = np.zeros((n, len(segment)))
    todo = np.arange(n)
    # Everything that does not draw stays out of the loop: a toward draw of single chambers
    # is mostly rejected, so the loop runs many times for a few rows (make_plan's cost).
    while len(todo):
        m = len(todo)
        pair = rng.uniform(0.0, 1.0, m) < SPARSE_PAIR_SHARE
        level = rng.uniform(0.0, 1.0, (m, len(segment)))
        on = np.zeros((m, len(segment)), bool)
        single = rng.integers(0, len(segment), m)
        rows = np.arange(m)
        on[rows[~pair], single[~pair]] = True
        for cols in seg_cols:
            pick = cols[rng.integers(0, len(cols), m)]
            on[rows[pair], pick[pair]] = True
        u = np.where(on, level, 0.0)
        if azimuth is None:
            out[todo] = u
            break
        b = u @ dirs
        ok = b @ aim >= math.cos(window) * np.linalg.norm(b, axis=1)
        out[todo[ok]] = u[ok]
        todo = todo[~ok]
    return out * limits


def _azimuth(scene: Scene, cfg: RigConfig) -> float | None:
    """Return the object's azimuth about the robot axis (None: no object beside it)."""
    if scene.object in ('none', 'plane'):
        return None
    d = np.asarray(scene.position_m[:2]) - np.asarray(cfg.robot.base_position_m[:2])
    return math.atan2(d[1], d[0]) if np.hypot(*d) > 1e-3 else None


@dataclass(frozen=True)
class Chunk:
    """One work item: rows ``start:stop`` (consecutive), all of scene ``scene_index``."""

    scene_index: int
    start: int
    stop: int


@dataclass
class Plan:
    """Everything a dataset needs, drawn up front from the seed."""

    scenes: list
    sample_scene: np.ndarray        # (N,) index into scenes, non-decreasing
    pressures: np.ndarray           # (N, 6) Pa
    seed: int
    toward: np.ndarray | None = None    # (N,) bool: drawn to bend towards the object
    sparse: np.ndarray | None = None    # (N,) bool: sparse (sparse_pressures)
    far_share: float = 0.0              # share of random scenes beyond reach (0: given ones)

    def chunks(self, size: int = CHUNK) -> list[Chunk]:
        """Cut each scene's rows into near-equal chunks of at most ``size`` samples."""
        out = []
        for si in range(len(self.scenes)):
            idx = np.nonzero(self.sample_scene == si)[0]
            if not len(idx):
                continue
            a, b = int(idx[0]), int(idx[-1]) + 1
            if b - a != len(idx):
                raise ValueError(f'scene {si}: its samples are not consecutive')
            parts = -(-(b - a) // size)
            cuts = a + (np.arange(parts + 1) * (b - a)) // parts
            out += [Chunk(si, int(s), int(e)) for s, e in zip(cuts[:-1], cuts[1:])]
        return out


def make_plan(cfg: RigConfig, samples: int, scenes, seed: int,
              toward_share: float = TOWARD_SHARE, sparse_share: float = SPARSE_SHARE,
              far_share: float = 0.0) -> Plan:
    """
    Draw scenes (an int: how many random ones; or a list of Scene) and actuations.

    The sparse rows are drawn last and replace their rows' actuations (a toward row stays
    one, now sparse), so every other row is what ``sparse_share=0`` draws. A share
    ``far_share`` of random scenes is placed beyond reach (``random_scene(far=True)``),
    chosen from a stream of its own: the other scenes and all actuations are those of
    ``far_share=0``.
    """
    if samples < 1:
        raise ValueError(f'--samples must be >= 1, got {samples}')
    for name, share in (('toward', toward_share), ('sparse', sparse_share),
                        ('far', far_share)):
        if not 0.0 <= share <= 1.0:
            raise ValueError(f'--{name}-share must be within [0, 1], got {share}')
    rng = np.random.default_rng(seed)
    if isinstance(scenes, int):
        if scenes < 1:
            raise ValueError(f'--scenes must be >= 1, got {scenes}')
        far = np.random.default_rng([seed, 5]).uniform(0.0, 1.0, scenes) < far_share
        scene_list = [random_scene(i, OBJECT_CYCLE[i % 3], rng, cfg, bool(far[i]))
                      for i in range(scenes)]
    else:
        scene_list = list(scenes)
        if not scene_list:
            raise ValueError('no scenes given')
    s = len(scene_list)
    sample_scene = np.sort(np.arange(samples) % s)
    limits = np.asarray(cfg.max_pressures_pa, dtype=float)
    pressures = rng.uniform(0.0, 1.0, (samples, 6)) * limits
    toward = rng.uniform(0.0, 1.0, samples) < toward_share
    for si, scene in enumerate(scene_list):
        az = _azimuth(scene, cfg)
        rows = np.nonzero(toward & (sample_scene == si))[0]
        if az is None:
            toward[sample_scene == si] = False
        elif len(rows):
            pressures[rows] = toward_pressures(rng, len(rows), az, cfg)
    sparse = rng.uniform(0.0, 1.0, samples) < sparse_share
    rows = np.nonzero(sparse & ~toward)[0]
    pressures[rows] = sparse_pressures(rng, len(rows), cfg)
    for si, scene in enumerate(scene_list):
        rows = np.nonzero(sparse & toward & (sample_scene == si))[0]
        if len(rows):
            pressures[rows] = sparse_pressures(rng, len(rows), cfg, _azimuth(scene, cfg))
    return Plan(scene_list, sample_scene, pressures, seed, toward, sparse,
                far_share if isinstance(scenes, int) else 0.0)


# -- the contact record of one equilibrium ------------------------------------------------
@dataclass(frozen=True)
class ContactSample:
    """How one equilibrium touches: flag, arc length (m), net force (N), penetration (m)."""

    touching: bool
    arc_m: float
    force_n: float
    penetration_m: float


def measure_contact(state, obstacles, step: float = ARC_STEP_M,
                    band: float = CONTACT_GAP_M) -> ContactSample:
    """
    Return the contact record of a :class:`~softshape_ros.sim.rig.SimState`.

    In contact means the tube's surface within ``band`` (0.1 mm) of the object or inside
    it: the robot is soft (a few tenths of a newton bend its tip by millimetres), so the
    smooth penalty often holds it back while its surface is still a few hundredths of a
    millimetre out. Touching: a gap minimum (not a ridge) in contact. Arc: the backbone
    length in contact; the backbone is interpolated (cubic Hermite through the samples and
    the contact points) every ``step`` m where the samples come within 0.5 mm of contact,
    crossings linear (``kernels.contact_arc``). Force: the magnitude of the sum of all
    contact forces (ridges subtract), what a force sensor under the object reads.
    Penetration: how deep the surface is inside the object at most (0 if nowhere).
    """
    cs = list(state.contacts)
    force = float(np.linalg.norm(np.sum([c.force_n for c in cs], axis=0))) if cs else 0.0
    near = [c for c in cs if not c.ridge and c.gap_m <= band]
    if not near:
        return ContactSample(False, 0.0, force, 0.0)
    ob = obstacles if isinstance(obstacles, ObstacleSet) else ObstacleSet.of(obstacles)
    arc = kernels.contact_arc(
        np.ascontiguousarray(state.s_m, dtype=float),
        np.ascontiguousarray(state.backbone_m, dtype=float),
        np.ascontiguousarray(state.radii_m, dtype=float),
        np.array([c.s_m for c in near]), np.array([c.backbone_m for c in near]),
        np.array([c.gap_m for c in near]), ob.kinds, ob.rows, ob.poses, float(step),
        float(band), NEAR_BAND_M)
    return ContactSample(True, float(arc), force, float(state.max_penetration_m))


# -- the shape record of one equilibrium ---------------------------------------------------
def measure_shape(state, cameras, size: int, k: int = SHAPE_KEYPOINTS):
    """
    Return the robot in each camera's input image: points (V, k, 2), radii, depths (V, k).

    ``k`` points equally spaced in arc length from base to tip, projected through each
    :class:`~softshape_ros.sim.camera.PinholeCamera` and mapped from its crop to the
    ``size`` x ``size`` image exactly as ``render_inputs`` samples it (pixel centres at
    integer coordinates; x = column, y = row). Radius: the tube's apparent radius, focal
    length x radius / depth. Depth: how much further from the camera than the base, in the
    same pixels at the base's depth (focal length x (depth / base depth - 1)).
    """
    s = np.asarray(state.s_m, dtype=float)
    sk = np.linspace(s[0], s[-1], k)
    pts = np.column_stack([np.interp(sk, s, state.backbone_m[:, i]) for i in range(3)])
    rad = np.interp(sk, s, state.radii_m)
    rec = np.stack([cam.input_keypoints(pts, rad, cam.project(pts[:1])[0, 2], size)
                    for cam in cameras]).astype(np.float32)              # V x k x 4
    return rec[..., :2], rec[..., 2], rec[..., 3]


# -- worker side ------------------------------------------------------------------------
_WORKER = {}


def _init_worker(cfg, rows, size, gray, views, supersample, noise):
    from softshape_ros.sim.rig import SimRig
    rig = SimRig(cfg, image_noise_std=noise[0], pressure_noise_pa=noise[1])
    _WORKER.clear()
    _WORKER.update(cfg=cfg, rows=rows, size=size, gray=gray, views=list(views),
                   supersample=supersamples(supersample), rig=rig, rest=None)


def supersamples(supersample) -> tuple:
    """Return ``supersample`` (an int, or several: a mix) as a tuple of ints."""
    return tuple(supersample) if isinstance(supersample, (tuple, list)) else (supersample,)


def scene_supersample(supersample, seed: int, scene_index: int) -> int:
    """
    Return the samples per pixel a side a placement is rendered with.

    One of ``supersample`` (a mix), drawn per placement from the plan's seed, so the rest
    and actuated images of a placement are rendered alike, as one camera films them,
    whichever process renders them.
    """
    choices = supersamples(supersample)
    if len(choices) == 1:
        return int(choices[0])
    return int(choices[np.random.default_rng([seed, scene_index, 2]).integers(len(choices))])


CPU_PARTS = ('solve', 'render', 'contact_record', 'rest_images', 'write', 'other')


def simulate_chunk(job):
    """
    Simulate and write one chunk: the scene's rest images, then each actuation.

    Runs in a worker process; returns (rows, stats). The rig starts from the scene's rest
    equilibrium, with the scene's seed for the rest and the chunk's for the actuations,
    whichever process runs it and whatever it ran before. ``stats['cpu_s']``: this
    process's CPU time per part (``CPU_PARTS``), what ``generate`` reports per sample.
    """
    cpu = time.process_time
    c_start = cpu()
    w = _WORKER
    rig, views = w['rig'], w['views']
    chunk, scene, pressures, seed = job
    si = chunk.scene_index
    spent = dict.fromkeys(CPU_PARTS, 0.0)

    supersample = scene_supersample(w['supersample'], seed, si)

    def inputs(state):
        img = rig.render_inputs(state, w['size'], w['gray'], supersample, views)
        return np.stack([img[v] for v in views])

    c0 = cpu()
    rig.set_scene(scene)
    rig.rng = np.random.default_rng([seed, si])
    rest = rig.solve([0.0] * 6)
    if w['rest'] is None or w['rest'][0] != si:
        w['rest'] = (si, inputs(rest))
    initial = w['rest'][1]
    spent['rest_images'] += cpu() - c0
    rig.rng = np.random.default_rng([seed, si, chunk.start, 0])
    redraw = np.random.default_rng([seed, si, chunk.start, 1])
    limits = np.asarray(w['cfg'].max_pressures_pa, dtype=float)
    n = chunk.stop - chunk.start
    target = np.empty((n, *initial.shape), np.uint8)
    pressure = np.empty((n, 6), np.float32)
    record = np.zeros((4, n))
    cams = [rig.cameras[v] for v in views]
    keypoints = np.empty((n, len(views), SHAPE_KEYPOINTS, 2), np.float32)
    radii = np.empty((n, len(views), SHAPE_KEYPOINTS), np.float32)
    depths = np.empty((n, len(views), SHAPE_KEYPOINTS), np.float32)
    stats = {'replaced': 0, 'crease': 0, 'iterations': np.empty(n, np.int32), 'failed': []}
    for k, p in enumerate(pressures):
        c0 = cpu()
        st = _solve_or_redraw(rig, scene, p, lambda: redraw.uniform(0.0, 1.0, 6) * limits,
                              stats, chunk.start + k)
        c1 = cpu()
        target[k] = inputs(st)
        c2 = cpu()
        pressure[k] = st.pressures_pa
        c = measure_contact(st, rig.obstacles)
        record[:, k] = (c.touching, c.arc_m, c.force_n, c.penetration_m)
        keypoints[k], radii[k], depths[k] = measure_shape(st, cams, w['size'])
        stats['iterations'][k] = st.iterations
        stats['crease'] += st.crease
        c3 = cpu()
        spent['solve'] += c1 - c0
        spent['render'] += c2 - c1
        spent['contact_record'] += c3 - c2
    contact = (record[0].astype(bool), record[1].astype(np.float32),
               record[2].astype(np.float32), record[3].astype(np.float32))
    c0 = cpu()
    w['rows'].put(slice(chunk.start, chunk.stop), initial, target, pressure, scene.id, contact,
                  (keypoints, radii, depths))
    spent['write'] += cpu() - c0
    stats['touching'] = int(contact[0].sum())
    stats['max_penetration_m'] = float(record[3].max())
    spent['other'] = cpu() - c_start - sum(spent.values())
    stats['cpu_s'] = spent
    return chunk, stats


def _solve_or_redraw(rig, scene, p, draw, stats: dict, row: int):
    """
    Return the equilibrium at ``p``, or at a redrawn ``draw()`` if it fails (counted).

    A failed solve is recorded in ``stats['failed']`` (row, scene, pressures, error) and
    redrawn at most ``MAX_RETRIES`` times; the rig restarts from the scene's rest.
    """
    for attempt in range(MAX_RETRIES + 1):
        try:
            return rig.solve(p)
        except SolverError as exc:
            if attempt == MAX_RETRIES:
                raise
            stats['replaced'] += 1
            stats['failed'].append({'row': row, 'scene': scene.id,
                                    'pressures_pa': [float(v) for v in p],
                                    'error': str(exc)[:200]})
            p = draw()
            rig.set_scene(scene)


def _context():
    """Return a start method safe with threads in the parent (3.12 warns on fork)."""
    methods = mp.get_all_start_methods()
    ctx = mp.get_context('forkserver' if 'forkserver' in methods else 'spawn')
    if ctx.get_start_method() == 'forkserver':
        ctx.set_forkserver_preload(['softshape_ros.sim.preload'])
    return ctx


def _check_args(cfg: RigConfig, views, size, supersample, noise, chunk) -> None:
    """Refuse bad settings here, with their name, before any process starts."""
    unknown = [v for v in views if v not in cfg.cameras]
    if not list(views) or unknown:
        raise ValueError(f'views must be cameras of the config {list(cfg.cameras)}, got '
                         f'{list(views)}')
    if not supersamples(supersample):
        raise ValueError('supersample must name at least one setting, got none')
    for name, v, least in (('size', size, 1), *(('supersample', s, 0)
                                                for s in supersamples(supersample)),
                           ('chunk', chunk, 1)):
        if not isinstance(v, (int, np.integer, float)) or int(v) != v or v < least:
            raise ValueError(f'{name} must be an integer >= {least}, got {v!r}')
    if len(noise) != 2 or not all(math.isfinite(v) and v >= 0 for v in noise):
        raise ValueError(f'noise (image gray levels, pressure Pa) must be >= 0, got {noise}')


def _pool(workers: int, init, jobs):
    """
    Start the worker processes and hand them the jobs: return (pool, futures).

    The start method is thread-safe (forkserver, else spawn), and the processes start
    while the environment says one BLAS thread each (they are forked from the forkserver
    as it was when it started, or spawned as the jobs are submitted).
    """
    from concurrent.futures import ProcessPoolExecutor
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: '1' for k in _THREAD_VARS})
    try:
        pool = ProcessPoolExecutor(workers, mp_context=_context(), initializer=_init_worker,
                                   initargs=init)
        return pool, [pool.submit(simulate_chunk, j) for j in jobs]
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def generate(cfg: RigConfig, plan: Plan, out, views, size: int = 64, gray: bool = True,
             workers: int = 0, supersample=3, noise=(0.0, 0.0), overwrite=False,
             progress: bool = True, source: str = '', chunk: int = CHUNK):
    """
    Write the plan as a dataset at ``out``: chunks over processes, tqdm progress.

    ``supersample``: samples per pixel a side (0: the camera's own pixels), or several, a
    mix: each placement rendered with one of them (:func:`scene_supersample`).

    ``workers``: processes (0: all cores; 1: this process). A worker that dies (killed,
    out of memory) stops the run with a RuntimeError instead of hanging it; any failure
    leaves no folder behind. Returns (Dataset, summary).
    """
    from concurrent.futures import as_completed
    from concurrent.futures.process import BrokenProcessPool

    from tqdm import tqdm

    from softshape_ros.data.dataset import DatasetWriter
    t0, cpu0 = time.perf_counter(), time.process_time()
    _check_args(cfg, views, size, supersample, noise, chunk)
    n = len(plan.pressures)
    channels = 1 if gray else 3
    writer = DatasetWriter(out, n, list(views), channels, size, cfg.max_pressures_pa,
                           overwrite=overwrite, contact=True, shape=SHAPE_KEYPOINTS)
    jobs = [(c, plan.scenes[c.scene_index], plan.pressures[c.start:c.stop], plan.seed)
            for c in plan.chunks(chunk)]
    workers = max(1, min(len(jobs), workers or os.cpu_count() or 1))
    init = (cfg, writer.rows, size, gray, list(views), supersample, noise)
    tally = _Tally(n)
    bar = tqdm(total=n, desc='simulate', unit='sample', disable=not progress)
    pool = None
    try:
        if workers == 1:
            _init_worker(*init)
            results = map(simulate_chunk, jobs)
        else:
            pool, futures = _pool(workers, init, jobs)
            results = (f.result() for f in as_completed(futures))
        for c, stats in results:
            tally.add(c, stats)
            bar.update(c.stop - c.start)
    except BrokenProcessPool as exc:
        writer.abort()
        raise RuntimeError(f'simulate: a worker process died ({exc}); killed or out of '
                           'memory? Nothing was written.') from None
    except BaseException:
        writer.abort()
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        bar.close()
    toward = plan.toward if plan.toward is not None else np.zeros(n, bool)
    sparse = plan.sparse if plan.sparse is not None else np.zeros(n, bool)
    summary = dict(tally.summary(), toward_share=float(np.mean(toward)),
                   sparse_share=float(np.mean(sparse)))
    distribution = {'min_gap_m': MIN_GAP_M, 'max_gap_m': MAX_GAP_M, 'gap_power': GAP_POWER,
                    'far_gap_m': FAR_GAP_M, 'far_share': plan.far_share,
                    'toward_window_deg': math.degrees(TOWARD_WINDOW_RAD), 'chunk': chunk,
                    'sparse_pair_share': SPARSE_PAIR_SHARE}
    ds = writer.close(
        source=source or 'softshape simulate', seed=plan.seed, cameras=list(views),
        config=cfg.source, scenes=[s.to_json() for s in plan.scenes],
        normalisation='pressure / max_pressure_pa', simulator=summary,
        scene_distribution=distribution,
        rendering={'supersample': [int(v) for v in supersamples(supersample)],
                   'per': 'placement'},
        dropped={'count': 0, 'why': 'failed solves are redrawn, counted in '
                 'simulator.replaced_failed_solves'})
    wall = time.perf_counter() - t0
    ms = tally.cpu_ms_per_sample(time.process_time() - cpu0, in_process=workers == 1)
    return ds, dict(summary, workers=workers, wall_s=round(wall, 3),
                    samples_per_s=round(n / wall, 1), cpu_ms_per_sample=ms)


class _Tally:
    """What the chunks report, summed as they come back (in any order)."""

    def __init__(self, n: int):
        self.n, self.touching, self.replaced, self.crease = n, 0, 0, 0
        self.penetration_m, self.failed = 0.0, []
        self.spent = dict.fromkeys(CPU_PARTS, 0.0)
        self.iterations = np.zeros(n, np.int32)

    def add(self, c, stats: dict) -> None:
        self.touching += stats['touching']
        self.replaced += stats['replaced']
        self.crease += stats['crease']
        self.failed += stats['failed']
        self.iterations[c.start:c.stop] = stats['iterations']
        self.penetration_m = max(self.penetration_m, stats['max_penetration_m'])
        for part, v in stats['cpu_s'].items():
            self.spent[part] += v

    def summary(self) -> dict:
        """Return the simulator section of ``meta.json`` (at most 100 failures listed)."""
        return {'samples': self.n, 'touching_share': self.touching / self.n,
                'replaced_failed_solves': self.replaced,
                'failed_solves': sorted(self.failed, key=lambda f: f['row'])[:100],
                'crease_solves': self.crease,
                'median_newton_iterations': float(np.median(self.iterations)),
                'max_penetration_m': self.penetration_m}

    def cpu_ms_per_sample(self, parent_cpu_s: float, in_process: bool) -> dict:
        """
        Return CPU ms per sample: the workers' parts, and this process's own.

        The parent plans the jobs, draws the progress bar, collects results and closes the
        dataset; with one worker the chunks ran here too, so their CPU is taken out.
        """
        n = self.n
        ms = {part: round(v * 1e3 / n, 3) for part, v in self.spent.items()}
        ms['parent'] = round(parent_cpu_s * 1e3 / n, 3)
        if in_process:
            ms['parent'] = round(max(0.0, ms['parent'] - sum(self.spent.values()) * 1e3 / n),
                                 3)
        ms['beyond_solve_render'] = round(sum(v for k, v in ms.items()
                                              if k not in ('solve', 'render')), 3)
        return ms
