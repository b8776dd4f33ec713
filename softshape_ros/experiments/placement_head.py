"""
The placement head: a known placement and six pressures -> the robot's shape, in the fold.

The shipped tube model reads the placement from the rest images and predicts keypoints
from its own reading; its touching samples stay 0.02 IoU below the free ones at 20 000
samples, and a learned reader reads placements 3-9x coarser than the images hold them
(docs/model.md). This head takes the placement as numbers instead (read by
``sim/placement_fit.py`` or known) and learns the 3D backbone in one fold of the rig's
symmetry (``sim/symmetry.py``): every placement is turned and mirrored into a 60-degree
sector, its pressures handed on with it, so 10 000 placements fill the sector as 60 000
would fill the turn. The backbone is unfolded and projected through the rig's cameras into
the shape record's keypoints (x, y, radius, depth per view), which the tube model draws.

Saved as ``head.safetensors`` + ``head.json`` (never pickled).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save
from torch import nn
from tqdm import tqdm

from softshape_ros.config import RigConfig
from softshape_ros.model.data import placements, scene_vector, shape_tensors
from softshape_ros.scene import Scene
from softshape_ros.sim.camera import PinholeCamera
from softshape_ros.sim.placement_fit import twin
from softshape_ros.sim.symmetry import RigSymmetry

FORMAT = 'softshape-placement-head'
WEIGHTS = 'head.safetensors'
CONFIG = 'head.json'


class PlacementHeadError(ValueError):
    """A placement head is missing, corrupt, or made for other cameras or chambers."""


class ShapeProjection:
    """The shape record's keypoints <-> 3D backbone points, through the rig's cameras."""

    def __init__(self, cfg: RigConfig, views, size: int):
        self.views, self.size = list(views), int(size)
        self.cameras = [PinholeCamera.from_config(v, cfg.cameras[v]) for v in self.views]
        base = np.asarray(cfg.robot.base_position_m, dtype=float)
        self.z_base = [float(c.project(base)[0, 2]) for c in self.cameras]

    def backbone(self, record: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, V, K, 4) record -> (N, K, 3) world m from the first view, (N, K) tube radius m."""
        cam, s = self.cameras[0], self.size
        x0, y0, w, h = cam.crop
        f = cam.input_focal_px(s)
        z = self.z_base[0] * (1.0 + record[:, 0, :, 3] / f)
        u = (record[:, 0, :, 0] + 0.5) * w / s - 0.5 + x0
        v = (record[:, 0, :, 1] + 0.5) * h / s - 0.5 + y0
        pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], -1)
        return pc @ cam.R.T + cam.position, record[:, 0, :, 2] * z / f

    def record(self, points: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """(N, K, 3) world m + (K,) radius m -> (N, V, K, 4) keypoints as the shape record's."""
        return np.stack([cam.input_keypoints(points, radius, zb, self.size)
                         for cam, zb in zip(self.cameras, self.z_base)], 1).astype(np.float32)


def _faces_in(scene: Scene, sym: RigSymmetry) -> bool:
    """Whether a prism's x (the way it leans) points towards the robot's axis."""
    return scene.object == 'prism' and \
        math.cos(scene.rpy_rad[2] - sym.azimuth(scene.position_m)) < 0


def facing_out(scene: Scene, sym: RigSymmetry) -> Scene:
    """
    Describe a prism with its x (the way it leans) pointing away from the robot's axis.

    A prism and its twin (half a turn on, lean negated) are one object, but the features
    see yaw only up to a half turn, so they would read as the prism leaning the other way.
    Placements are drawn facing out (``sim/generate.random_scene``), so the head learns that
    description; a fit or a person may give the other (docs/model.md).
    """
    return twin(scene) if _faces_in(scene, sym) else scene


def read_facing_out(reading: Scene, sym: RigSymmetry) -> Scene:
    """
    Turn a reader's prism half a turn if it faces in, its lean kept.

    A reader learns the lean on placements drawn facing out but gives yaw only up to a
    half turn (``model.data.scene_from_vector``): its lean belongs to the yaw facing out.
    """
    if not _faces_in(reading, sym):
        return reading
    r, p, y = reading.rpy_rad
    return replace(reading, rpy_rad=(r, p, math.remainder(y + math.pi, 2 * math.pi)))


def folded_inputs(sym: RigSymmetry, scenes, pressures_pa, max_pressure_pa):
    """Placements + (N, 6) Pa -> (N, 17 + 6) head inputs in the fold, and each row's Fold."""
    pmax = np.asarray(max_pressure_pa, dtype=float)
    scenes = [facing_out(sc, sym) for sc in scenes]
    folds = [sym.fold_of(sc.position_m) for sc in scenes]
    x = [scene_vector(f.scene(sc)) + list(f.pressures(p) / pmax)
         for f, sc, p in zip(folds, scenes, np.asarray(pressures_pa, dtype=float))]
    return torch.tensor(x, dtype=torch.float32), folds


class PlacementHead(nn.Module):
    """MLP: folded placement features + pressures (23) -> folded backbone (K x 3, mm from base)."""

    def __init__(self, inputs: int = 23, keypoints: int = 16, width: int = 512):
        super().__init__()
        self.keypoints = keypoints
        self.net = nn.Sequential(nn.Linear(inputs, width), nn.SiLU(), nn.Linear(width, width),
                                 nn.SiLU(), nn.Linear(width, width), nn.SiLU(),
                                 nn.Linear(width, 3 * keypoints))
        for name, n in (('x_mean', inputs), ('x_std', inputs), ('y_mean', 3 * keypoints),
                        ('y_std', 3 * keypoints)):
            self.register_buffer(name, torch.zeros(n) if 'mean' in name else torch.ones(n))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """B x 23 -> B x K x 3 (mm, folded frame, from the base)."""
        y = self.net((x - self.x_mean) / self.x_std) * self.y_std + self.y_mean
        return y.view(len(x), self.keypoints, 3)


@dataclass
class ShapePredictor:
    """A trained head with what turns its output into the drawn keypoints."""

    head: PlacementHead
    sym: RigSymmetry
    projection: ShapeProjection
    radius_m: np.ndarray              # (K,) the tube's radius at each keypoint
    offset_px: np.ndarray             # (V, K, 4) added to the record: how the drawer draws
    max_pressure_pa: np.ndarray
    chambers: tuple = ()              # the chambers' names, in the pressures' order
    reach_m: dict = field(default_factory=dict)     # kind -> farthest training placement
    #                 from the rest robot's surface (m); beyond it the head extrapolates

    @torch.inference_mode()
    def keypoints(self, scenes, pressures_pa) -> torch.Tensor:
        """N placements + N x 6 Pa -> N x V x K x 4 keypoints for the tube model to draw."""
        x, folds = folded_inputs(self.sym, scenes, pressures_pa, self.max_pressure_pa)
        pts = self.head.eval()(x).double().numpy() * 1e-3
        world = np.stack([f.unfold_points(p + f.base) for f, p in zip(folds, pts)])
        rec = self.projection.record(world, self.radius_m) + self.offset_px
        return torch.from_numpy(rec.astype(np.float32))

    def save(self, path) -> Path:
        d = Path(path)
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / (WEIGHTS + '.tmp')
        tmp.write_bytes(save({k: v.contiguous() for k, v in self.head.state_dict().items()},
                             metadata={'format': FORMAT}))
        os.replace(tmp, d / WEIGHTS)
        cfg = {'format': FORMAT, 'views': self.projection.views, 'size': self.projection.size,
               'keypoints': self.head.keypoints, 'radius_m': self.radius_m.tolist(),
               'offset_px': self.offset_px.tolist(),
               'max_pressure_pa': self.max_pressure_pa.tolist(),
               'cameras': {v: cam_signature(c) for v, c in zip(self.projection.views,
                                                               self.projection.cameras)},
               'chambers': list(self.chambers), 'reach_m': self.reach_m}
        tmp = d / (CONFIG + '.tmp')
        tmp.write_text(json.dumps(cfg, indent=1))
        os.replace(tmp, d / CONFIG)
        return d

    @classmethod
    def load(cls, path, cfg: RigConfig) -> 'ShapePredictor':
        """Load a saved head for rig ``cfg``; PlacementHeadError names what does not match."""
        d = Path(path)
        try:
            meta = json.loads((d / CONFIG).read_text())
            state = load_file(d / WEIGHTS)
        except (OSError, ValueError, SafetensorError) as e:
            raise PlacementHeadError(f'{d}: cannot read the placement head: {e}') from e
        if not isinstance(meta, dict) or meta.get('format') != FORMAT:
            raise PlacementHeadError(f'{d / CONFIG}: not a placement head')
        try:
            out = cls.build(cfg, meta['views'], meta['size'], np.asarray(meta['radius_m']),
                            np.asarray(meta['offset_px'], np.float32),
                            np.asarray(meta['max_pressure_pa']), meta['keypoints'])
            cameras, chambers = dict(meta['cameras']), list(meta['chambers'])
            reach = meta.get('reach_m', {})     # heads saved before stop 54 do not say
            out.reach_m = {str(k): float(v) for k, v in reach.items()}
            if not all(v > 0 for v in out.reach_m.values()):
                raise ValueError(f'reach_m {reach!r}: not positive distances')
        except (KeyError, TypeError, ValueError) as e:
            raise PlacementHeadError(f'{d / CONFIG}: incomplete or malformed ({e!r})') from e
        for v, c in zip(out.projection.views, out.projection.cameras):
            if cameras.get(v) != cam_signature(c):
                raise PlacementHeadError(f'{d}: trained for another camera {v!r} than the rig\'s')
        if chambers != [c.name for c in cfg.chambers]:
            raise PlacementHeadError(f'{d}: trained for chambers {chambers}')
        try:
            out.head.load_state_dict(state)
        except RuntimeError as e:
            raise PlacementHeadError(f'{d / WEIGHTS}: weights do not fit the head: {e}') from e
        return out

    @classmethod
    def build(cls, cfg, views, size, radius_m, offset_px, max_pressure_pa, keypoints=16):
        return cls(PlacementHead(keypoints=keypoints), RigSymmetry.from_config(cfg),
                   ShapeProjection(cfg, views, size), np.asarray(radius_m, dtype=float),
                   np.asarray(offset_px, np.float32), np.asarray(max_pressure_pa, dtype=float),
                   tuple(c.name for c in cfg.chambers))


def cam_signature(cam: PinholeCamera) -> list:
    """Return the numbers a projection depends on (rounded: JSON round trips)."""
    return [round(float(v), 9) for v in (cam.fx, cam.fy, cam.cx, cam.cy, *cam.position,
                                         *cam.R.ravel(), *cam.crop)]


@dataclass
class HeadReport:
    steps: int
    seconds: float
    final_l1_mm: float
    rows: int
    placements: int


def train_shape_predictor(ds, cfg: RigConfig, views, steps: int = 20000, batch: int = 512,
                          lr: float = 2e-3, seed: int = 0, offset_px=None, rows=None,
                          progress: bool = True) -> tuple[ShapePredictor, HeadReport]:
    """
    Train a placement head on a simulated dataset's placements and shape record.

    ``ds``: a dataset with placements in its meta and a shape record (``softshape
    simulate``); ``views``: the cameras whose keypoints the head will draw; ``offset_px``
    (V, K, 4): added to every prediction, e.g. :func:`drawing_offset`; ``rows``: the rows
    to learn from (default: all). Returns the predictor and a :class:`HeadReport`.
    """
    idx = np.sort(np.asarray(np.arange(len(ds)) if rows is None else rows, dtype=np.int64))
    table = placements(ds, idx)
    record, _ = shape_tensors(ds, idx)
    if table is None or record is None:
        raise PlacementHeadError('the placement head learns from a simulated dataset: it needs '
                                 'the placements and the shape record')
    ids = np.asarray(ds.scene)[idx]
    scenes: list[Scene] = [table[int(s)] for s in ids]
    k = record.shape[2]
    v_all = list(ds.meta.get('cameras', views))
    record = record.numpy()[:, [v_all.index(v) for v in views]]
    pmax = np.asarray(ds.meta.get('max_pressure_pa'), dtype=float)
    out = ShapePredictor.build(cfg, views, ds.meta.get('image_size', 64), np.zeros(k),
                               np.zeros((len(views), k, 4)) if offset_px is None else offset_px,
                               pmax, k)
    pts, rad = out.projection.backbone(record)
    out.radius_m = rad.mean(0)
    x, folds = folded_inputs(out.sym, scenes, np.asarray(ds.pressure)[idx], pmax)
    y = torch.from_numpy(np.stack([f.points(p) - f.base for f, p in zip(folds, pts)]) * 1e3)
    y = y.float().reshape(len(y), -1)                                   # N x 3K, mm
    head = out.head
    head.x_mean.copy_(x.mean(0))
    # A feature the training never varies (a cylinder's roll and pitch, 0 in every simulated
    # placement) teaches nothing: weighed 1e-6, a fitted tilt of 0.01 rad leaves the input
    # where training saw it instead of 50 standard deviations off.
    std = x.std(0)
    head.x_std.copy_(torch.where(std < 1e-3, torch.full_like(std, 1e6), std))
    head.y_mean.copy_(y.mean(0))
    head.y_std.copy_(y.std(0).clamp_min(1e-3))
    torch.manual_seed(seed)
    for m in head.net:
        if isinstance(m, nn.Linear):
            m.reset_parameters()
    opt = torch.optim.Adam(head.net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps)
    g = torch.Generator().manual_seed(seed)
    t0 = time.monotonic()
    loss = torch.tensor(math.nan)
    head.train()
    for _ in tqdm(range(steps), desc='placement head', disable=not progress, leave=False):
        b = torch.randint(0, len(x), (batch,), generator=g)
        loss = (head(x[b]).reshape(len(b), -1) - y[b]).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    head.eval()
    out.reach_m = training_reach(cfg, views, [table[int(s)] for s in set(ids.tolist())])
    return out, HeadReport(steps, time.monotonic() - t0, float(loss.detach()), len(x),
                           len(set(ids.tolist())))


def training_reach(cfg: RigConfig, views, scenes) -> dict:
    """Return each kind's largest clearance from the rest robot among ``scenes`` (m)."""
    from softshape_ros.sim.placement_fit import UPRIGHT, PlacementFit
    fit = PlacementFit(cfg, views)
    reach: dict = {}
    for sc in scenes:
        if sc.object in UPRIGHT:
            reach[sc.object] = max(reach.get(sc.object, 0.0), fit.clearance(sc))
    return reach


@torch.inference_mode()
def drawing_offset(model, ds, idx, max_pressure_pa, batch: int = 250) -> np.ndarray:
    """
    (V, K, 4): how a tube model draws free robots beside the shape record (mean own - record).

    The shipped model draws the ends about 0.1 px longer than the record puts them; a head
    whose keypoints it draws scores best with that offset added (docs/model.md).
    """
    from softshape_ros.model.data import to_tensors
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    record, free = shape_tensors(ds, idx)
    if free is None or not bool(free.any()):
        raise PlacementHeadError('the drawing offset needs free rows with a shape record')
    own = []
    for i in range(0, len(idx), batch):
        ini, _, p = to_tensors(ds, idx[i:i + batch], max_pressure_pa)
        own.append(model(ini, p, parts='keypoints')[0])
    return (torch.cat(own) - record)[free].mean(0).numpy()
