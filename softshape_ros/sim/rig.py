"""
SimRig: the simulated rig. Six chamber pressures + a scene -> equilibrium -> camera images.

Backs the mock hardware node and ``softshape simulate``. Everything comes from the
``RigConfig`` (robot, chambers, cameras), so the simulated and the physical rig agree on
geometry, limits and image format. Deterministic for a seed: noise draws come from one
``numpy`` generator, and solves warm-start from the previous equilibrium of the same scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softshape_ros.config import RigConfig
from softshape_ros.pressure import check_command
from softshape_ros.scene import Scene, SceneError
from softshape_ros.sim import kernels
from softshape_ros.sim.camera import PinholeCamera
from softshape_ros.sim.contact import (DEFAULT_SMOOTHING_M, DEFAULT_STIFFNESS_N_M,
                                       PenaltyContact)
from softshape_ros.sim.objects import ObstacleSet, obstacle_from_scene
from softshape_ros.sim.render import (OUTLINE_TOLERANCE_PX, RenderError, object_mesh_for,
                                      pack_objects, render_view)
from softshape_ros.sim.rod import Rod, RodSpec
from softshape_ros.sim.statics import Actuator, SolverError, Statics

SPHERE_SPACING_M = 0.0015
PREDICTED_DEPTH_M = 1e-3    # skip the free solve when its prediction is this deep inside
TOUCH_TOL_M = 1e-4          # the touching start ends this close outside (regula falsi)
TOUCH_PATH_TOL = 1e-6       # ... or when its bracket on the path is this short
TOUCH_STEPS = 20
# The contact solve's fallbacks: (start, penalty stiffness stages); None starts straight.
STIFFENING_STAGES = (('touching', (1.0,)), ('touching', (0.1, 1.0)),
                     (None, (0.01, 0.1, 1.0)))
STAGE_TOL = 1e-6            # relative residual of the softened stages (only starts)
# A contact solve that fails at the rig's quadrature is redone with this many times the Gauss
# nodes (shorter Magnus steps): where the robot lies flat along a face, the gap profile is
# flat to a tenth of a micron over a centimetre, and the single Magnus step from a node puts
# the points' positions off the strain's tangent by up to 3e-5 in slope, enough to move a
# critical point by 0.3 mm and keep the forces from being the potential's gradient there.
FINE_QUADRATURE = 2
# The passes over STIFFENING_STAGES, in order: (at FINE_QUADRATURE, with the crease test).
# Strict first at both quadratures; the crease test only after every strict attempt failed,
# last at the finer nodes (row 75309 of the 100 000-sample plan converges only there).
CONTACT_PASSES = ((False, False), (True, False), (False, True), (True, True))


@dataclass
class SimState:
    """An equilibrium: strain coordinates, backbone, contacts and how the solve went."""

    q: np.ndarray
    pressures_pa: np.ndarray
    s_m: np.ndarray                 # (N,) backbone arc lengths
    backbone_m: np.ndarray          # (N, 3) world points
    radii_m: np.ndarray             # (N,) tube radius at each point
    tip_pose: np.ndarray            # (4, 4) world pose of the tip section
    residual: float
    iterations: int
    contacts: list = field(default_factory=list)
    max_penetration_m: float = 0.0
    crease: bool = False            # converged by the crease test (statics.CREASE_MOTION_M)

    @property
    def backbone(self) -> np.ndarray:
        """Alias of ``backbone_m`` (world points, m)."""
        return self.backbone_m

    def to_dict(self) -> dict:
        return {'q': self.q.tolist(), 'pressures_pa': self.pressures_pa.tolist(),
                'tip_position_m': self.tip_pose[:3, 3].tolist(),
                'tip_rotation': self.tip_pose[:3, :3].tolist(),
                's_m': self.s_m.tolist(), 'backbone_m': self.backbone_m.tolist(),
                'residual': self.residual, 'iterations': self.iterations,
                'contacts': [c.to_dict() for c in self.contacts],
                'max_penetration_m': self.max_penetration_m, 'crease': self.crease}


def chamber_actuators(cfg: RigConfig) -> list[Actuator]:
    """Return the six chambers of the config as simulator actuators (angle 0 = body +y)."""
    return [Actuator('chamber', c.segment, np.deg2rad(c.angle_deg), c.offset_m, c.area_m2)
            for c in cfg.chambers]


class SimRig:
    """Pressures (Pa) + scene -> equilibrium -> {'main': RGB, 'side': RGB} images."""

    def __init__(self, cfg: RigConfig, seed: int = 0, image_noise_std: float = 0.0,
                 pressure_noise_pa: float = 0.0, contact: bool = True,
                 contact_stiffness: float = DEFAULT_STIFFNESS_N_M,
                 contact_smoothing: float = DEFAULT_SMOOTHING_M, **rod_overrides):
        if image_noise_std < 0 or pressure_noise_pa < 0:
            raise ValueError('noise levels must be >= 0')
        self.cfg = cfg
        self.rod = Rod(RodSpec.from_config(cfg.robot, **rod_overrides))
        self.statics = Statics(self.rod, chamber_actuators(cfg), gravity_on=True)
        self.cameras = {n: PinholeCamera.from_config(n, c) for n, c in cfg.cameras.items()}
        self.rng = np.random.default_rng(seed)
        self.image_noise_std = float(image_noise_std)
        self.pressure_noise_pa = float(pressure_noise_pa)
        self.contact_on = contact
        self._rod_overrides = dict(rod_overrides)
        self._fine = None           # (rod, statics) at FINE_QUADRATURE, made on first need
        self.contact_args = (contact_stiffness, contact_smoothing)
        self.limits = np.asarray(cfg.max_pressures_pa, dtype=float)
        self.scene = None
        self.obstacles = []
        self._render_objects = {n: pack_objects(cam, []) for n, cam in self.cameras.items()}
        self._object_meshes = {}    # (camera, grid, tolerance) -> ObjectMesh of this scene
        self.obstacle_set = ObstacleSet.of([])
        self.contact = None
        self._q = None
        self._free = None           # (q, assembly, pressures) of the last free equilibrium
        sample_n = int(np.ceil(self.rod.length / SPHERE_SPACING_M)) + 1
        self.sample_s = np.linspace(0.0, self.rod.length, sample_n)
        self._sample_radii = self.rod.radii[self.rod.locate(self.sample_s)[0]]
        self._node_radii = self.rod.radii[self.rod.locate(self.rod.node_X)[0]]

    def set_scene(self, scene: Scene | None) -> None:
        """
        Place the scene's object (None or object 'none': the robot alone).

        Raises :class:`~softshape_ros.scene.SceneError` (a ValueError) for an object that
        cannot be placed: one overlapping the robot at rest, or a shape without a body.
        """
        if scene is not None and not isinstance(scene, Scene):
            raise TypeError(f'set_scene expects a Scene or None, got {type(scene).__name__}')
        obj = obstacle_from_scene(scene)
        obstacles = [obj] if obj is not None else []
        obstacle_set = ObstacleSet.of(obstacles)
        if obstacles:
            rest = self.rod.forward(np.zeros(self.rod.n), jac=False)
            pts = np.vstack([rest.g[:, :3, 3], self.rod.positions(rest, self.sample_s)])
            rad = np.concatenate([self._node_radii, self._sample_radii])
            gap = obstacle_set.least_gap(pts, rad)
            if gap < 0.0:
                raise SceneError(f'scene {scene.id}: the {scene.object} overlaps the robot at '
                                 f'rest by {-gap * 1e3:.2f} mm; it cannot be placed there')
        render_objects = {}
        for name, cam in self.cameras.items():
            try:
                render_objects[name] = pack_objects(cam, obstacles)
            except RenderError as exc:    # e.g. a camera inside the object: solving still works
                render_objects[name] = exc
        self.scene = scene
        self.obstacles = obstacles
        self.obstacle_set = obstacle_set
        self._render_objects = render_objects
        self._object_meshes = {}
        self.contact = (PenaltyContact.of(self.obstacles, *self.contact_args)
                        if self.obstacles and self.contact_on else None)
        self._q = None
        self._free = None

    def solve(self, pressures_pa) -> SimState:
        """Return the equilibrium for 6 chamber pressures (Pa; clamped to the limits)."""
        p = check_command(pressures_pa, self.limits).pressures_pa
        if self.pressure_noise_pa > 0:
            p = np.clip(p + self.rng.normal(0.0, self.pressure_noise_pa, p.shape), 0.0,
                        self.limits)
        # The free shape first (cheap); it is the answer when it does not touch the object.
        q0 = None
        if self._free is not None:
            # The Newton step from the last free equilibrium, without assembling there again:
            # the chamber load is linear in the pressures.
            q0, last, p_last = self._free
            st = self.statics
            dQ = st.B_ch @ (p - p_last)[st.chamber_idx]
            step, ok = kernels.lu_solve(last.tangent, dQ)
            if ok:
                q0 = q0 + step
        g0 = self._node_gap(q0) if self.contact is not None and q0 is not None else np.inf
        if g0 < -PREDICTED_DEPTH_M:
            # The predicted free shape is deep in the object: the free equilibrium would
            # only serve as the end of the touching-start path, and the prediction does
            # that as well (the contact solve ends where it ends either way).
            q, asm, it, rod = self._solve_contact(p, self._touching_start(q0, g0))
            if not asm.contact.any and rod is self.rod:
                self._free = (q, asm, p)      # it was free after all: a fresh base
            self._q = q
            return self._state(q, p, asm, it, rod)
        q, asm, it = self.statics.solve(p, q0=q0)
        self._free = (q, asm, p)
        if self.contact is not None:
            # A node inside an object settles it; otherwise the contact model decides (a
            # contact between nodes, or one within the penalty's reach): with no candidate
            # it adds nothing to asm.
            g_free = self._node_gap(q, asm.kin)
            near = None if g_free < 0.0 else self.contact.evaluate(self.rod, asm.kin)
            if near is None or near.any:
                q, asm, it2, rod = self._solve_contact(p, self._touching_start(q, g_free))
                self._q = q
                return self._state(q, p, asm, it + it2, rod)
            asm.contact = near
        self._q = q
        return self._state(q, p, asm, it)

    def _solve_contact(self, p, q0):
        """
        Solve with contact from ``q0``; on failure retry with the penalty stiffened in stages.

        Attempts (``STIFFENING_STAGES``): direct from ``q0``; from ``q0`` with the penalty at
        1/10 first; from the straight rod with 1/100, 1/10, 1; then all of them again with
        ``FINE_QUADRATURE`` times the Gauss nodes; only then the same stages with the crease
        test (``statics.CREASE_MOTION_M``), at the rig's quadrature and last at the finer one
        (``CONTACT_PASSES``). Returns (q, assembly, iterations, the rod solved on); the last
        failure raises :class:`SolverError`.
        """
        its, error = 0, None
        for fine, crease in CONTACT_PASSES:
            rod, statics = self._fine_model() if fine else (self.rod, self.statics)
            for start, stages in STIFFENING_STAGES:
                q = q0 if start == 'touching' else None
                try:
                    for f in stages:
                        q, asm, it = statics.solve(p, q0=q, contact=self.contact.scaled(f),
                                                   tol=STAGE_TOL if f < 1 else 1e-10,
                                                   crease=crease)
                        its += it
                    return q, asm, its, rod
                except SolverError as exc:
                    error = exc
        raise error

    def _fine_model(self):
        """Return (rod, statics) of the same robot with FINE_QUADRATURE times the nodes."""
        if self._fine is None:
            spec = self.rod.spec
            nodes = FINE_QUADRATURE * (spec.n_gauss or spec.order + 4)
            rod = Rod(RodSpec.from_config(self.cfg.robot, **dict(self._rod_overrides,
                                                                 n_gauss=nodes)))
            self._fine = (rod, Statics(rod, chamber_actuators(self.cfg), gravity_on=True))
        return self._fine

    def _node_gap(self, q, kin=None) -> float:
        """Return the least gap (m) between the tube at the nodes and the objects."""
        kin = kin if kin is not None else self.rod.forward(q, jac=False)
        return self.obstacle_set.least_gap(kin.g[:, :3, 3], self._node_radii)

    def _touching_start(self, q_free, gap_free=None):
        """
        Return the shape on the way from the last one to ``q_free`` that just touches.

        Regula falsi (Illinois) on the least gap along the straight path in q: a start
        with the tip already deep in the object costs many damped Newton steps.
        """
        q_prev = self._q if self._q is not None else np.zeros_like(q_free)

        def gap(t):
            # At the nodes (<= 4.2 mm apart, the tip included): no interpolation needed.
            return self._node_gap(q_prev + t * (q_free - q_prev))

        a, b = 0.0, 1.0
        ga, gb = gap(a), (gap(b) if gap_free is None else gap_free)
        if ga <= 0.0 and self._q is not None:
            # The last shape touches: walk from the rest shape instead.
            q_prev = np.zeros_like(q_free)
            ga = gap(a)
        if ga <= 0.0 or gb >= 0.0:
            return q_prev if ga <= 0.0 else q_free
        side = 0
        for _ in range(TOUCH_STEPS):
            t = (a * gb - b * ga) / (gb - ga)
            gt = gap(t)
            if gt >= 0.0:
                a, ga = t, gt
                if side == 1:
                    gb *= 0.5
                side = 1
            else:
                b, gb = t, gt
                if side == -1:
                    ga *= 0.5
                side = -1
            if 0.0 <= gt < TOUCH_TOL_M or b - a < TOUCH_PATH_TOL:
                break
        return q_prev + a * (q_free - q_prev)

    def _state(self, q, p, asm, it, rod=None) -> SimState:
        rod = rod if rod is not None else self.rod
        kin = asm.kin
        g, _ = rod.at(kin, self.sample_s, jac=False)
        contact = asm.contact
        return SimState(q=q, pressures_pa=np.asarray(p, dtype=float), s_m=self.sample_s.copy(),
                        backbone_m=g[:, :3, 3], radii_m=self._sample_radii.copy(),
                        tip_pose=kin.g[-1].copy(), residual=asm.residual_norm,
                        iterations=int(it),
                        contacts=contact.contacts if contact is not None else [],
                        max_penetration_m=(contact.max_penetration_m
                                           if contact is not None else 0.0),
                        crease=asm.crease)

    def _noisy(self, img: np.ndarray) -> np.ndarray:
        if self.image_noise_std > 0:
            noisy = img + self.rng.normal(0.0, self.image_noise_std, img.shape)
            img = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        return img

    def check_views(self, cameras=None) -> None:
        """Raise the RenderError that keeps a camera from seeing this scene (e.g. inside it)."""
        for name in cameras if cameras is not None else self.cameras:
            if isinstance(self._render_objects.get(name), RenderError):
                raise self._render_objects[name]

    def _objects_for(self, name: str, grid, tol_px: float):
        """Return the scene's objects meshed for camera ``name`` and ``grid`` (made once)."""
        key = (name, tuple(grid), float(tol_px))
        mesh = self._object_meshes.get(key)
        if mesh is None:
            mesh = object_mesh_for(self.cameras[name], self._render_objects[name], grid, tol_px)
            self._object_meshes[key] = mesh
        return mesh

    def render(self, state: SimState) -> dict:
        """Return {camera: H x W x 3 uint8 RGB} at each camera's configured resolution."""
        self.check_views()
        out = {}
        for name, cam in self.cameras.items():
            grid = cam.grid()
            out[name] = self._noisy(render_view(
                cam, state.backbone_m, state.radii_m, self.obstacles, grid,
                objects=self._objects_for(name, grid, OUTLINE_TOLERANCE_PX)))
        return out

    def render_inputs(self, state: SimState, size: int = 64, gray: bool = True,
                      supersample: int = 4, cameras=None) -> dict:
        """
        Return {camera: C x size x size uint8}, the network input of each camera.

        Only the crop region is rendered, at ``size * supersample`` pixels (each at the
        centre of the source-pixel area it stands for), then passed through
        :func:`~softshape_ros.vision.preprocess.preprocess` (gray, area resize): the same
        result as preprocessing a full-resolution frame, far faster (test_sim_render).
        ``supersample`` 0 renders the crop at the camera's own pixels: that result to the
        gray level, edges included (docs/simulator.md).
        """
        from softshape_ros.vision.preprocess import preprocess
        if int(size) != size or size < 1 or int(supersample) != supersample or supersample < 0:
            raise RenderError(f'size must be an integer >= 1 and supersample >= 0, got '
                              f'{size!r} and {supersample!r}')
        size, supersample = int(size), int(supersample)
        names = list(cameras) if cameras is not None else list(self.cameras)
        unknown = [n for n in names if n not in self.cameras]
        if unknown:
            raise RenderError(f'unknown camera(s) {unknown}; the rig has {list(self.cameras)}')
        self.check_views(names)
        out = {}
        # Noise is the sensor's, on the colour frame; without it a gray input is rendered
        # gray (the same pixels as converting the colour crop, a fifth less work).
        render_gray = gray and not self.image_noise_std > 0
        for name in names:
            cam = self.cameras[name]
            # 0: the crop's own camera pixels, each sampled at its centre (what render()
            # and the camera node's preprocess make of a frame, to the pixel).
            grid = cam.grid(cam.crop, None if supersample == 0 else (size * supersample,) * 2)
            img = self._noisy(render_view(cam, state.backbone_m, state.radii_m, self.obstacles,
                                          grid, objects=self._objects_for(
                                              name, grid, OUTLINE_TOLERANCE_PX),
                                          gray=render_gray))
            width, height = grid[4:]
            out[name] = preprocess(img, [0, 0, width, height], size, gray)
        return out

    def snap(self, pressures_pa) -> dict:
        """Solve and render: {camera: RGB uint8} (deterministic for a seed)."""
        return self.render(self.solve(pressures_pa))
