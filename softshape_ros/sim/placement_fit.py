"""
Read a placement from its rest images by rendering it and comparing (render-and-compare).

A learned reader reads the object's position to about 0.5 mm; the rest images hold it to
about 0.1 mm (docs/model.md, "The placement read by fitting the simulator's own
rendering"). This fit starts from a reading (the tube model's, or a person's) and moves
the placement until the simulator's rendering of the rest scene matches both rest images
best (Nelder-Mead on the mean squared gray-level error, supersampled as the dataset is).

An object that one view sees only behind the robot has no depth along the other view's
ray in the images: the fit lands somewhere on a ray some 10 mm long and says so
(:attr:`FitResult.hidden`, docs/model.md "Where the images do not hold the placement").

Simulation only as it stands: it reads images with the renderer that drew them. On the
real rig it needs a rendering matched to the cameras (docs/model.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.optimize import minimize

from softshape_ros.config import RigConfig
from softshape_ros.scene import OBJECT_DIMS, Scene, SceneError
from softshape_ros.sim.objects import obstacle_from_scene
from softshape_ros.sim.render import render_view
from softshape_ros.sim.rig import SimRig

GOOD_MSE = 0.05         # gray levels^2: the truth scores 0.02-0.03 against uint8 images
MIN_STARTS, MAX_STARTS = 2, 6
START_SPREAD = 1.0      # mm (and 0.1 rad) around the reading for the restarts
SCALES = (1.0, 0.5, 0.25, 0.1)      # Nelder-Mead simplex sizes, one run each
MAX_EVALS = 1500        # per run
SCREEN_EVALS = 300      # a short first run from each of several readings, best first
RETYPE_MSE = 1.0        # gray levels^2 beyond the images' own: may be a misread kind (misread)
CLEARANCE_COST = 100.0  # gray levels^2 per mm^2 short of the clearance: a wall to the images
# Roll and pitch of an object standing as the rig's objects stand: cylinders and prisms on
# end, rings on edge (the simulated placements' and the lab's).
UPRIGHT = {'cylinder': (0.0, 0.0), 'ring': (math.pi / 2, 0.0), 'prism': (0.0, 0.0)}
# A view the object changes fewer than HIDDEN_PX pixels of, by more than SHOWN_GRAY gray
# levels (the yellow mask's level), does not show it: it stands behind the robot there.
HIDDEN_PX = 5
SHOWN_GRAY = 10.0


class FitError(ValueError):
    """The fit cannot read this placement (no object, or an object it does not know)."""


def placement_params(scene: Scene, upright: bool = False) -> np.ndarray:
    """
    Return a placement as the fit moves it: position and sizes in mm, angles in 0.1 rad.

    Position, the kind's sizes, then roll and pitch (unless ``upright``: the object stands
    as :data:`UPRIGHT` says) and, for rings and prisms, whose yaw is seen, yaw. A reader
    reads the tilt a few hundredths of a radian off, and a ring tilted that much is a
    different image (test_placement): fit it, or know that the object stands upright.
    """
    if scene.object not in UPRIGHT:
        raise FitError(f'the placement fit reads cylinders, rings and prisms, not '
                       f'{scene.object!r}')
    p, d = np.asarray(scene.position_m) * 1e3, scene.dims
    roll, pitch, yaw = (10 * v for v in scene.rpy_rad)
    sizes = [d[k] * (10 if k == 'skew_rad' else 1e3) for k in OBJECT_DIMS[scene.object]]
    return np.r_[p, sizes, [] if upright else [roll, pitch],
                 [] if scene.object == 'cylinder' else [yaw]]


def placement_scene(template: Scene, params, upright: bool = False) -> Scene:
    """Undo :func:`placement_params` (kind, id, a cylinder's yaw from ``template``)."""
    t = np.asarray(params, dtype=float)
    pos = tuple(float(v) for v in t[:3] * 1e-3)
    yaw = template.rpy_rad[2]
    sizes = OBJECT_DIMS[template.object]
    dims = {k: float(v) * (0.1 if k == 'skew_rad' else 1e-3)
            for k, v in zip(sizes, t[3:3 + len(sizes)])}
    rest = t[3 + len(sizes):] / 10
    if upright:
        roll, pitch = UPRIGHT[template.object]
    else:
        (roll, pitch), rest = rest[:2], rest[2:]
    if template.object != 'cylinder':
        yaw = rest[0]
    return replace(template, position_m=pos, rpy_rad=(float(roll), float(pitch), float(yaw)),
                   dims=dims)


def twin(scene: Scene) -> Scene:
    """Describe the same prism the other way round (yaw + pi, skew negated)."""
    d = dict(scene.dims, skew_rad=-scene.dims['skew_rad'])
    r, p, y = scene.rpy_rad
    return replace(scene, rpy_rad=(r, p, math.remainder(y + math.pi, 2 * math.pi)), dims=d)


def quarter(scene: Scene) -> Scene:
    """Turn a prism a quarter and swap width and depth: the same box, skew aside."""
    d = dict(scene.dims, width_m=scene.dims['depth_m'], depth_m=scene.dims['width_m'])
    r, p, y = scene.rpy_rad
    return replace(scene, rpy_rad=(r, p, math.remainder(y + math.pi / 2, 2 * math.pi)), dims=d)


def flipped(scene: Scene) -> Scene:
    """Lean a prism the other way (skew negated, nothing else)."""
    return replace(scene, dims=dict(scene.dims, skew_rad=-scene.dims['skew_rad']))


def retyped(scene: Scene, kind: str) -> Scene:
    """
    Return ``scene``'s object as another kind of about its extent, at its place.

    The objects are centred on their position, so only the sizes change: a half width and
    a half height carried over (a ring on edge is as wide as it is tall, its tube a third
    of its radius). Yaw is kept where both kinds have one (a cylinder's is zero).
    """
    d = scene.dims
    half_w, half_h = {
        'cylinder': lambda: (d['radius_m'], d['height_m'] / 2),
        'prism': lambda: ((d['width_m'] + d['depth_m']) / 4, d['height_m'] / 2),
        'ring': lambda: (d['major_radius_m'] + d['minor_radius_m'],) * 2,
    }[scene.object]()
    if kind == 'cylinder':
        dims = {'radius_m': half_w, 'height_m': 2 * half_h}
    elif kind == 'prism':
        dims = {'width_m': 2 * half_w, 'depth_m': 2 * half_w, 'height_m': 2 * half_h,
                'skew_rad': 0.0}
    else:
        outer = max(half_w, half_h)
        dims = {'major_radius_m': 0.75 * outer, 'minor_radius_m': 0.25 * outer}
    yaw = 0.0 if 'cylinder' in (kind, scene.object) else scene.rpy_rad[2]
    return replace(scene, object=kind, dims=dims, rpy_rad=(*UPRIGHT[kind], yaw))


def turns(scene: Scene, n: int = 4) -> list[Scene]:
    """
    Return ``scene`` turned about the vertical in ``n`` steps over what tells turns apart.

    A square prism looks the same a quarter turn round, a ring on edge a half turn round,
    a cylinder any turn round (so it is returned alone): starts for a kind whose yaw
    nothing has read yet (:meth:`PlacementFit._retyped`).
    """
    span = {'prism': math.pi / 2, 'ring': math.pi}.get(scene.object)
    if span is None:
        return [scene]
    r, p, y = scene.rpy_rad
    return [replace(scene, rpy_rad=(r, p, math.remainder(y + k * span / n, 2 * math.pi)))
            for k in range(n)]


def readings(scene: Scene) -> list[Scene]:
    """
    Return a reading and the prisms a reader may have confused it with (eight).

    A reader sees yaw only up to a half turn, so the lean's sign it reads belongs to either
    yaw; and a box turned a quarter is the same box with width and depth swapped.
    """
    if scene.object != 'prism':
        return [scene]
    out = []
    for a in (scene, quarter(scene)):
        out += [a, flipped(a), twin(a), twin(flipped(a))]
    return out


@dataclass(frozen=True)
class FitResult:
    scene: Scene
    mse: float              # gray levels^2 against the rest images
    evaluations: int
    starts: int
    hidden: tuple = ()      # views that do not show the fitted object (PlacementFit.hidden_views)


class PlacementFit:
    """
    Renders rest scenes of one rig and fits placements to rest images.

    ``upright``: the objects stand as :data:`UPRIGHT` says (two numbers fewer to fit, and
    no tilt traded for position). ``min_clearance_m``: the object keeps at least this
    from the robot at rest; the rest images show the robot undisturbed, so it is not
    inside the object, whatever a view that cannot see the object's depth allows.
    ``max_starts``: restarts at most while the match is not good (GOOD_MSE).
    """

    def __init__(self, cfg: RigConfig, views, size: int = 64, supersample: int = 3,
                 upright: bool = True, min_clearance_m: float = 0.0,
                 max_starts: int = MAX_STARTS):
        self.rig = SimRig(cfg)
        self.views, self.size, self.ss = list(views), int(size), int(supersample)
        self.upright, self.min_clearance_m = bool(upright), float(min_clearance_m)
        self.max_starts = max(MIN_STARTS, int(max_starts))
        self.rig.set_scene(None)
        self.rest = self.rig.solve([0.0] * len(cfg.chambers))
        self.grids = []
        for v in self.views:
            cam = self.rig.cameras[v]
            self.grids.append((cam, cam.grid(cam.crop, (self.size * self.ss,) * 2)))
        self.robot_alone = self._render([])

    def render(self, scene: Scene) -> np.ndarray:
        """Render the rest scene as (V, S, S) float gray levels (supersampled, area-averaged)."""
        return self._render([obstacle_from_scene(scene)])

    def _render(self, obstacles) -> np.ndarray:
        s, k = self.size, self.ss
        return np.stack([render_view(cam, self.rest.backbone_m, self.rest.radii_m, obstacles,
                                     grid, gray=True).astype(np.float32)
                         .reshape(s, k, s, k).mean(axis=(1, 3)) for cam, grid in self.grids])

    def hidden_views(self, scene: Scene) -> tuple:
        """
        Return the views that do not show ``scene``'s object (it stands behind the robot).

        Seen in one view only, the object can slide along that view's ray, growing as it
        recedes, over as much as the robot hides it in the other: the same rest images
        for placements some 10 mm apart (docs/model.md).
        """
        return self._hidden(self.render(scene))

    def _hidden(self, rendered: np.ndarray) -> tuple:
        shown = (np.abs(rendered - self.robot_alone) > SHOWN_GRAY).sum(axis=(1, 2))
        return tuple(v for v, n in zip(self.views, shown) if n < HIDDEN_PX)

    def clearance(self, scene: Scene) -> float:
        """Return the object's least distance to the robot's surface at rest (m; < 0: inside)."""
        d, _ = obstacle_from_scene(scene).sdf(self.rest.backbone_m)
        return float(np.min(d - self.rest.radii_m))

    def mse(self, scene: Scene, images) -> float:
        """Mean squared gray-level error of ``scene``'s rendering against rest images."""
        return float(((self.render(scene) - self._images(images)) ** 2).mean())

    def _images(self, images) -> np.ndarray:
        """V x S x S or V x 1 x S x S gray levels -> V x S x S float32; ValueError if not."""
        img = np.asarray(images, dtype=np.float32)
        want = (len(self.views), self.size, self.size)
        if img.size != np.prod(want) or img.shape[0] != want[0] or img.shape[-2:] != want[1:]:
            raise ValueError(f'rest images must be {want} gray (or V x 1 x S x S), got '
                             f'{img.shape}')
        return img.reshape(want)

    def fit(self, images, reading: Scene, seed: int = 0) -> FitResult:
        """
        Fit the placement to rest images (V x S x S, or V x 1 x S x S, gray levels).

        ``reading``: where the object is thought to be (kind, and a first guess within
        a millimetre or two). Restarts around it until two are done and the match is
        good (GOOD_MSE), ``max_starts`` at most; a prism first from the best of its eight
        :func:`readings` after a short run from each (a reader may read its half turn,
        lean or width for depth wrong), and a prism still matched poorly once more from
        its fitted position in its other descriptions (:meth:`_redescribed`). A match
        poorer still (:meth:`misread`) may be a misread kind (:meth:`_retyped`): the
        result may be another kind than the reading's.
        """
        img = self._images(images)
        rng = np.random.default_rng(seed)
        evals = [0]
        x, f, starts = self._fit_kind(img, reading, rng, evals)
        template = reading
        if self.misread(img, placement_scene(reading, x, self.upright), f):
            template, x, f, more = self._retyped(img, reading, x, f, rng, evals)
            starts += more
        scene = placement_scene(template, x, self.upright)
        rendered = self.render(scene)
        return FitResult(scene, float(((rendered - img) ** 2).mean()), evals[0], starts,
                         self._hidden(rendered))

    def misread(self, images, scene: Scene, mse: float) -> bool:
        """
        Say whether ``scene``, matched to ``images`` at ``mse``, may be a misread kind.

        Its match must be poorer than RETYPE_MSE beyond what the images cost away from the
        object (more than 2 px from where it changes the rendering by a gray level): about
        nothing on the simulator's own images, but on a rig's camera frames every edge is
        off a little (9 gray levels squared on the mock rig's), and a good match there is
        no reason to try other kinds. Nor is a match held off by ``min_clearance_m``:
        another kind would only find a way round the wall.
        """
        if mse < RETYPE_MSE or (self.min_clearance_m > 0
                                and self.clearance(scene) < self.min_clearance_m + 5e-4):
            return False
        img, rendered = self._images(images), self.render(scene)
        near = ndimage.binary_dilation(np.abs(rendered - self.robot_alone) > 1.0,
                                       structure=np.ones((1, 5, 5), bool))
        away = ((rendered - img) ** 2)[~near]
        return mse - (float(away.mean()) if away.size else 0.0) >= RETYPE_MSE

    def _fit_kind(self, img, reading: Scene, rng, evals: list) -> tuple[np.ndarray, float, int]:
        """Fit ``reading``'s kind from it, as :meth:`fit` says: (best x, its cost, starts)."""
        up = self.upright
        x_read = placement_params(reading, up)
        cost = self.objective(img, reading, evals)
        firsts = [placement_params(r, up) for r in readings(reading)]
        if len(firsts) > 1:                 # screen them: a short run each, best first
            screened = [self._run(cost, x, SCALES[0], SCREEN_EVALS) for x in firsts]
            firsts = [x for x, _ in sorted(screened, key=lambda r: r[1])]
        best_x, best_f, starts = x_read, cost(x_read), 0
        while starts < self.max_starts and (starts < MIN_STARTS or best_f >= GOOD_MSE):
            x = firsts[starts] if starts < len(firsts) else \
                x_read + rng.normal(0.0, START_SPREAD, x_read.shape)
            fx = cost(x)
            for scale in SCALES:
                xs, fs = self._run(cost, x, scale, MAX_EVALS)
                if fs < fx:
                    x, fx = xs, fs
            starts += 1
            if fx < best_f:
                best_x, best_f = x, fx
        if best_f >= GOOD_MSE and reading.object == 'prism':
            best_x, best_f = self._redescribed(cost, reading, best_x, best_f)
        return best_x, best_f, starts

    def objective(self, images, template: Scene, evals: list | None = None):
        """
        Return the fit's cost of :func:`placement_params` (``template`` gives the kind).

        The mean squared gray-level error of the rendering against ``images``, plus a wall
        where the object comes closer to the robot than ``min_clearance_m``. ``evals``: a
        one-item list, counted up at every call.
        """
        img, up = self._images(images), self.upright

        def cost(t) -> float:
            if evals is not None:
                evals[0] += 1
            try:
                scene = placement_scene(template, t, up)
                err = float(((self.render(scene) - img) ** 2).mean())
                c = self.clearance(scene)
            except (SceneError, ValueError):
                return 1e9                      # impossible sizes: far from any match
            inside = max(0.0, self.min_clearance_m - c) * 1e3
            return err + CLEARANCE_COST * inside ** 2
        return cost

    def _redescribed(self, cost, reading: Scene, x, fx: float) -> tuple[np.ndarray, float]:
        """
        Try the fitted prism's other descriptions from where the fit stopped: (best x, cost).

        A prism fit can stall where the restarts about the reading do not reach (a turn
        round with the lower end traded for height, a lean the wrong way, width for depth):
        further runs from there stay there. From the fitted position each of the other seven
        descriptions gets a short run, and the best is run on at the finer steps.
        """
        up = self.upright
        here = placement_scene(reading, x, up)
        others = [placement_params(r, up) for r in readings(here)[1:]]
        y, fy = min((self._run(cost, o, SCALES[0], SCREEN_EVALS) for o in others),
                    key=lambda r: r[1])
        for scale in SCALES[1:]:
            ys, fs = self._run(cost, y, scale, MAX_EVALS)
            if fs < fy:
                y, fy = ys, fs
        return (y, fy) if fy < fx else (x, fx)

    def _retyped(self, img, reading: Scene, x, fx: float, rng,
                 evals: list) -> tuple[Scene, np.ndarray, float, int]:
        """
        Try the fitted object as each other kind: (template, best x, its cost, starts).

        A reader can take a prism for a cylinder and the other way round (2 of the 400
        seed-42 test placements); the fit then stays poor whatever it moves, but it has
        found the object's place and extent. Each other kind of that extent
        (:func:`retyped`, :func:`turns`) gets a short run from there; the best, if it
        matches better, gets the whole fit as if the reader had read it (seconds, only
        where the match is this poor).
        """
        up = self.upright
        here = placement_scene(reading, x, up)
        tries = []
        for kind in UPRIGHT:
            if kind == reading.object:
                continue
            template = retyped(here, kind)
            cost = self.objective(img, template, evals)
            for other in turns(template):
                y, fy = self._run(cost, placement_params(other, up), SCALES[0], SCREEN_EVALS)
                tries.append((fy, placement_scene(other, y, up)))
        fy, other = min(tries, key=lambda t: t[0])
        if fy >= fx:
            return reading, x, fx, 0
        y, fy, starts = self._fit_kind(img, other, rng, evals)
        return (other, y, fy, starts) if fy < fx else (reading, x, fx, starts)

    @staticmethod
    def _run(cost, x, scale: float, evals: int) -> tuple[np.ndarray, float]:
        """One Nelder-Mead run from ``x`` with a simplex of ``scale``: (best x, its cost)."""
        simplex = np.vstack([x, x + np.diag(np.full(len(x), scale))])
        r = minimize(cost, x, method='Nelder-Mead', options={
            'xatol': 1e-3, 'fatol': 1e-7, 'maxfev': evals, 'initial_simplex': simplex})
        return r.x, float(r.fun)
