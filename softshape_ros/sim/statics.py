"""
Static equilibrium of the rod: ``B(q) u + Q_ext(q) + Q_grav(q) - K q = 0`` by damped Newton.

Sign convention (one for the whole simulator): a positive tendon tension *pulls* and bends
its segment towards the tendon; a positive chamber pressure *inflates* and bends the
segment away from the chamber (and stretches it when stretch is on). Actuator offsets
``d`` are in the section's body frame ``(0, d_y, d_z)``: angle 0 is the body +y axis.

Residual: point loads (tip, user, contact) enter exactly as ``J(X)^T W`` at their arc
length; gravity and actuation by Gauss quadrature. Tangent: the constant K, the analytic
actuation and contact-material terms, plus the geometric (dead-load) stiffness from the
derivative of the quadrature form of the same loads (internal wrench at each Gauss node
from everything distal; ``kernels.geometric_stiffness``). A solve that does not converge
raises :class:`SolverError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from softshape_ros.sim import kernels
from softshape_ros.sim.contact import ContactLaw, ContactResult
from softshape_ros.sim.rod import Kinematics, Rod

_EX = np.array([1.0, 0.0, 0.0])
TRUST_START_M = 0.008     # first step with an object in the scene moves the backbone <= 8 mm
TRUST_MAX_M = 0.05
TRUST_MIN_M = 5e-4
TRUST_GROWTH = 4.0        # a full step lets the next move this much farther
ENERGY_MERIT_TOL = 1e-5   # below this relative residual the merit is the residual norm
STALL_TOL = 1e-7          # relative residual accepted when round-off stops further descent
RESIDUAL_FLOOR = 1e-15    # absolute residual always accepted (a rod with no load at all)
MAX_TURN_RAD = 4 * np.pi  # a step bends a segment by at most this much
SHIFT_TRIES = 30          # tangent shifts tried (x10 each) before a step is given up
LINE_SEARCH_HALVINGS = 12
ARMIJO = 1e-4             # sufficient decrease of the merit, per unit of predicted decrease
NEWTON_SHRINK = 0.7       # a plain Newton step that shrinks the residual norm this much is taken
ENERGY_ROUNDOFF = 1e-12   # energies within this (relative) are equal
MAX_ACTIVE = 6            # constraints the step QP may hold at once
LOAD_TOL_M = 1e-12        # point loads may act this far past the tip (round-off)
# Where the robot lies along an object the gap profile is flat, and a pair of gap extrema (a
# contact and a ridge) is born or dies within a step: the pair's forces grow with the square
# root of the shape's motion, so the residual has no Lipschitz bound there. Newton's step from
# one side lands in the other with the residual tens of times larger, and the merit falls
# along no step at all, microns from the equilibrium. Where no strict solve converges, a
# state where the line search finds no acceptable step (or only tiny ones, TINY_STEPS),
# whose Newton correction moves no backbone point more than the contact's smoothing length
# (the penalty does not resolve the surface finer) and whose residual is within CREASE_TOL
# (where the contact jumps between the tip and a point before it, the force's jump is up to
# 4e-3 of the largest load), is taken (``Assembly.crease`` says so; the states report their
# residual).
CREASE_MOTION_M = 2e-5
CREASE_TOL = 1e-2
# Steps this short, this many times in a row, are a stall: the attempt ends there (its load
# bisection or the next stage follows) instead of spending its iterations, each a full line
# search, on steps that do not move it.
TINY_STEP = 1.0 / 256
TINY_STEPS = 3


class SolverError(RuntimeError):
    """The statics solve did not converge: no shape is returned rather than a wrong one."""


def project_step(dq, L, A, lo, max_active: int = MAX_ACTIVE) -> np.ndarray:
    """Return the Newton step with ``A dq >= lo`` kept (``kernels.project_step``)."""
    if len(lo) == 0:
        return dq
    return kernels.project_step(np.ascontiguousarray(dq, dtype=float), L,
                                np.ascontiguousarray(A, dtype=float),
                                np.ascontiguousarray(lo, dtype=float), int(max_active))


@dataclass(frozen=True)
class Actuator:
    """A chamber (``kind='chamber'``) or tendon (``kind='tendon'``) of one segment."""

    kind: str
    segment: int
    angle_rad: float
    offset_m: float
    area_m2: float = 1.0

    @property
    def d(self) -> np.ndarray:
        return self.offset_m * np.array([0.0, np.cos(self.angle_rad), np.sin(self.angle_rad)])


@dataclass(frozen=True)
class PointLoad:
    """A dead (world-fixed) force and moment applied at backbone arc length ``s_m``."""

    s_m: float
    force_n: tuple = (0.0, 0.0, 0.0)
    moment_nm: tuple = (0.0, 0.0, 0.0)


@dataclass
class PointLoads:
    """Point forces and moments on the backbone as the kernels read them (arrays over loads)."""

    X: np.ndarray        # (P,) arc lengths
    g: np.ndarray        # (P, 4, 4) poses
    J: np.ndarray        # (P, 6, n) body Jacobians
    f: np.ndarray        # (P, 3) world forces
    m: np.ndarray        # (P, 3) world moments
    quad: np.ndarray     # (P,) bool: residual in quadrature form (where moments act)

    @staticmethod
    def none(n: int) -> 'PointLoads':
        return PointLoads(np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 6, n)),
                          np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool))

    @staticmethod
    def join(parts: list['PointLoads'], n: int) -> 'PointLoads':
        if not parts:
            return PointLoads.none(n)
        if len(parts) == 1:
            return parts[0]
        return PointLoads(*(np.concatenate([getattr(p, k) for p in parts])
                            for k in ('X', 'g', 'J', 'f', 'm', 'quad')))


@dataclass
class Assembly:
    """Residual, tangent and potential of one shape; the tangent's costly part on demand."""

    residual: np.ndarray
    residual_norm: float             # max |residual| (NaN if any is NaN)
    scale: float                     # the largest generalised force: tolerances are relative
    kin: Kinematics
    energy: float | None             # total potential (None: a load is not conservative)
    energy_scale: float
    contact: ContactResult | None
    partial_tangent: np.ndarray
    pending: Callable | None = None  # the geometric stiffness, still to subtract
    crease: bool = False             # converged by the crease test (CREASE_MOTION_M)

    @property
    def tangent(self) -> np.ndarray:
        """
        Return the tangent; its geometric stiffness is computed on first use.

        Rejected line-search trials and the converged state never need it.
        """
        if self.pending is not None:
            self.partial_tangent = self.partial_tangent - self.pending()
            self.pending = None
        return self.partial_tangent


@dataclass
class NewtonResult:
    ok: bool
    q: np.ndarray
    assembly: Assembly
    iterations: int


class Statics:
    """Residual/tangent assembly and the Newton solver for one rod and its actuators."""

    def __init__(self, rod: Rod, actuators: list[Actuator], gravity_on: bool = True):
        self.rod = rod
        self.actuators = list(actuators)
        for a in self.actuators:
            if a.kind not in ('chamber', 'tendon'):
                raise ValueError(f'actuator kind must be chamber or tendon, got {a.kind!r}')
            if not 0 <= a.segment < rod.nseg:
                raise ValueError(f'actuator segment {a.segment} out of range')
        self.gravity_on = bool(gravity_on and rod.spec.density > 0 and np.any(rod.gravity != 0))
        ch = [i for i, a in enumerate(self.actuators) if a.kind == 'chamber']
        td = [i for i, a in enumerate(self.actuators) if a.kind == 'tendon']
        self.chamber_idx, self.tendon_idx = np.array(ch, int), np.array(td, int)
        # Chambers: a constant internal wrench p A [d x e1; e1] on their own segment.
        self.B_ch = np.zeros((rod.n, len(ch)))
        for j, i in enumerate(ch):
            a = self.actuators[i]
            wrench = a.area_m2 * np.concatenate([np.cross(a.d, _EX), _EX])
            on = rod.gauss_seg == a.segment
            self.B_ch[:, j] = np.einsum('k,kin,i->n', rod.gauss_w[on], rod.phi_g[on], wrench)
        # Tendons run from the base to the tip of their segment (distal ones through the
        # proximal segments): active at Gauss node k if its segment <= the tendon's.
        self.td_d = np.array([self.actuators[i].d for i in td]).reshape(-1, 3)
        self.td_on = np.array([[rod.gauss_seg[k] <= self.actuators[i].segment for i in td]
                               for k in range(len(rod.gauss_seg))], dtype=float).reshape(
                                   len(rod.gauss_seg), len(td))
        # Gravity: lumped weights at the Gauss nodes (world force).
        self.grav_f = (rod.spec.density * rod.area[rod.gauss_seg] * rod.gauss_w)[:, None] \
            * rod.gravity[None, :]
        self._no_moment = np.zeros_like(self.grav_f)
        self._no_force = np.zeros((0, 3))
        self._no_points = PointLoads.none(rod.n)

    # -- loads -------------------------------------------------------------------------
    def tendon_terms(self, kin: Kinematics, tension: np.ndarray):
        """Return (Q, dQ/dq, energy) of the tendons; slack (negative) tensions pull nothing."""
        return kernels.tendon_terms(*self.rod.tables, kin.xi_gauss, self.td_d, self.td_on,
                                    np.ascontiguousarray(tension, dtype=float))

    def point_loads(self, kin: Kinematics, loads: list[PointLoad], factor: float) -> PointLoads:
        """Return the user's point loads at their frames (scaled by the load factor)."""
        X = np.array([ld.s_m for ld in loads], dtype=float)
        if np.any(~np.isfinite(X) | (X < 0) | (X > self.rod.length + LOAD_TOL_M)):
            raise ValueError(f'point loads must act on 0 <= s <= {self.rod.length} m, got {X}')
        f = factor * np.array([ld.force_n for ld in loads], dtype=float).reshape(-1, 3)
        m = factor * np.array([ld.moment_nm for ld in loads], dtype=float).reshape(-1, 3)
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(m))):
            raise ValueError('point loads must be finite')
        g, J = self.rod.at(kin, X)
        # Where moments act, the residual takes the quadrature (virtual-work) form, which
        # keeps a constant internal wrench exact at any basis order.
        quad = np.full(len(X), bool(np.any(m)))
        return PointLoads(X, g, J, f, m, quad)

    def assemble(self, q, u, loads=(), factor: float = 1.0,
                 contact: ContactLaw | None = None) -> Assembly:
        """Residual ``K q - Q`` and its tangent at ``q`` (``factor`` scales u and loads)."""
        rod, tab = self.rod, self.rod.tables
        amax = kernels.abs_max
        kin = rod.forward(q)
        Kq = rod.kdiag * kin.q
        R = Kq
        Kt = rod.K
        scale = amax(Kq)
        energies = [0.5 * float(kin.q @ Kq)]
        u = np.asarray(u, dtype=float) * factor
        if len(self.chamber_idx):
            Qc = self.B_ch @ u[self.chamber_idx]
            R = R - Qc
            energies.append(-float(Qc @ kin.q))
            scale = max(scale, amax(Qc))
        if len(self.tendon_idx):
            Qt, dQt, et = self.tendon_terms(kin, u[self.tendon_idx])
            R = R - Qt
            Kt = Kt - dQt
            energies.append(et)
            scale = max(scale, amax(Qt))
        grav = self.grav_f * factor if self.gravity_on else self._no_force
        conservative = True
        if self.gravity_on:
            # Dead forces have potential -f.p; world moments in 3-D do not (path dependent).
            Qg, work = kernels.wrench_residual(kin.g, kin.J, rod.gauss_node, grav,
                                               self._no_moment)
            R = R - Qg
            energies.append(-work)
            scale = max(scale, amax(Qg))
        points = []
        if loads:
            pl = self.point_loads(kin, list(loads), factor)
            Qu, work = kernels.wrench_residual(pl.g, pl.J, np.arange(len(pl.X)), pl.f, pl.m)
            energies.append(-work)
            conservative = not np.any(pl.m)
            if not pl.quad.any():
                R = R - Qu
                scale = max(scale, amax(Qu))
            points.append(pl)
        result = contact.evaluate(rod, kin) if contact is not None else None
        if result is not None and result.any:
            R = R - result.generalised_force
            Kt = Kt + result.stiffness
            scale = max(scale, amax(result.generalised_force))
            points.append(PointLoads(result.s_m, result.poses, result.jacobians,
                                     result.force_n, np.zeros_like(result.force_n),
                                     np.zeros(len(result.s_m), dtype=bool)))
        pts = PointLoads.join(points, rod.n) if points else self._no_points

        def geometric():
            return kernels.geometric_stiffness(*tab, kin.q, kin.g, kin.J, grav, pts.X, pts.g,
                                               pts.J, pts.f, pts.m, pts.quad)

        pending = None
        if pts.quad.any():
            Qp, Kg = geometric()
            R = R - Qp
            Kt = Kt - Kg
            scale = max(scale, amax(Qp))
        elif self.gravity_on or len(pts.X):
            pending = lambda: geometric()[1]  # noqa: E731  (tangent only, on demand)
        energies.append(result.energy if result is not None else 0.0)
        energy = float(sum(energies)) if conservative else None
        return Assembly(R, amax(R), scale, kin, energy, float(sum(map(abs, energies))), result,
                        Kt, pending)

    # -- solver ------------------------------------------------------------------------
    def solve(self, u, loads=(), q0=None, contact: ContactLaw | None = None,
              tol: float = 1e-10, max_iter: int = 40, max_depth: int = 8,
              crease: bool = False):
        """
        Solve for the equilibrium; return (q, assembly, iterations).

        Newton with a backtracking line search; when a step fails the load is applied in
        smaller increments (bisection of the load factor, up to ``max_depth`` times).
        ``crease``: also accept a state by the crease test (``CREASE_MOTION_M``), a last
        resort where strict convergence failed.
        """
        rod = self.rod
        q = np.zeros(rod.n) if q0 is None else np.array(q0, dtype=float)
        if q.shape != (rod.n,) or not np.all(np.isfinite(q)):
            q = np.zeros(rod.n)
        u = np.asarray(u, dtype=float)
        if not np.all(np.isfinite(u)):
            raise ValueError(f'actuation must be finite, got {u}')
        loads = list(loads)
        total_iter = 0
        done, step, depth = 0.0, 1.0, 0
        last = None
        while done < 1.0:
            # A step past the full load is cut to it, so a halved step is a new load factor.
            step = min(step, 1.0 - done)
            load_factor = min(1.0, done + step)
            res = self._newton(q, u, loads, load_factor, contact, tol, max_iter, crease)
            total_iter += res.iterations
            if res.ok:
                q, last, done = res.q, res.assembly, load_factor
                if depth > 0:
                    step *= 2.0
                    depth -= 1
                continue
            if depth >= max_depth:
                r = res.assembly.residual_norm
                raise SolverError(
                    f'statics did not converge: load factor {load_factor:.4f} failed after '
                    f'{total_iter} Newton iterations (residual {r:.3e}, '
                    f'{depth} load bisections)')
            step /= 2.0
            depth += 1
        return q, last, total_iter

    def _converged(self, asm: Assembly, tol: float) -> bool:
        return asm.residual_norm <= tol * asm.scale + RESIDUAL_FLOOR

    def _newton(self, q, u, loads, load_factor, contact, tol, max_iter,
                crease: bool = False) -> NewtonResult:
        """
        Damped Newton on the total potential when all loads are conservative.

        The step solves (H + mu diag K) dq = -R with mu > 0 only where the tangent H is not
        positive definite, and the line search asks the energy to drop (Armijo): so the
        solver walks to stable equilibria and never settles on a saddle (e.g. the tip
        balanced on a cylinder it would slide off). Without an energy (world moments) the
        merit is the K-weighted residual norm.
        """
        def trial_at(qt):
            return self.assemble(qt, u, loads, load_factor, contact)

        asm = trial_at(q)
        # Trust radius on the predicted motion of the backbone (m): with an object near,
        # a full Newton step from a free shape would dive deep into it.
        radius = TRUST_START_M if contact is not None else np.inf
        mu, tiny = 0.0, 0
        for it in range(1, max_iter + 1):
            rn = asm.residual_norm
            if not np.isfinite(rn):
                return NewtonResult(False, q, asm, it)
            if self._converged(asm, tol):
                return NewtonResult(True, q, asm, it - 1)
            step = self._direction(asm, mu, radius)
            if step is None:
                return NewtonResult(False, q, asm, it)
            dq, mu, move = step
            alpha, trial = self._line_search(q, dq, asm, mu, trial_at)
            tiny = tiny + 1 if alpha < TINY_STEP else 0
            if trial is None or tiny >= TINY_STEPS:
                # Stalled at round-off level, or on a crease: accept a nearly converged state.
                ok = rn <= STALL_TOL * asm.scale + RESIDUAL_FLOOR
                if not ok and crease and move <= CREASE_MOTION_M \
                        and rn <= CREASE_TOL * asm.scale + RESIDUAL_FLOOR:
                    ok = asm.crease = True
                return NewtonResult(ok, q, asm, it)
            if np.isfinite(radius):
                radius = (min(TRUST_GROWTH * radius, TRUST_MAX_M) if alpha == 1.0
                          else max(alpha * move, TRUST_MIN_M))
            q, asm = q + alpha * dq, trial
        return NewtonResult(self._converged(asm, tol), q, asm, max_iter)

    def _direction(self, asm: Assembly, mu: float, radius: float):
        """
        Return (dq, shift, backbone motion) of the next step, or None if there is none.

        Plain Newton where the tangent is positive definite; otherwise the smallest diag(K)
        shift (from a tenth of the last one) that makes it so. With contact, the step keeps
        the linearised gaps (a small QP), then it is capped in bending and in motion.
        """
        rod = self.rod
        H = 0.5 * (asm.tangent + asm.tangent.T)
        L, shift, ok = kernels.shifted_cholesky(H, rod.kdiag, mu, SHIFT_TRIES)
        if not ok:
            return None
        dq = -kernels.cho_solve(L, asm.residual)
        if asm.contact is not None:
            dq = project_step(dq, L, asm.contact.step_rows, asm.contact.step_lower)
        big = kernels.abs_max(dq)
        if not np.isfinite(big):
            return None
        max_dq = MAX_TURN_RAD / rod.lengths.min()
        if big > max_dq:
            dq *= max_dq / big
        move = np.inf
        if np.isfinite(radius):
            move = kernels.largest_motion(asm.kin.J, dq)
            if move > radius:
                dq *= radius / move
                move = radius
        return dq, shift, move

    def _line_search(self, q, dq, asm: Assembly, mu: float, trial_at):
        """
        Return (alpha, trial) for the first acceptable step length, or (alpha, None).

        The merit is the total potential (Armijo) away from the solution and the K-weighted
        residual norm near it, where energy differences drown in round-off; a plain Newton
        step that shrinks that norm is always taken.
        """
        kd = self.rod.kdiag

        def wnorm(a):
            return kernels.weighted_norm(a.residual, kd)

        rn = asm.residual_norm
        slope = float(asm.residual @ dq)
        w0 = wnorm(asm)
        # Energy as merit away from the solution only: the point-load residual is its
        # quadrature form, within ~1e-7 of the energy's gradient.
        energy_merit = asm.energy is not None and rn > ENERGY_MERIT_TOL * asm.scale
        alpha = 1.0
        for _ in range(LINE_SEARCH_HALVINGS):
            trial = trial_at(q + alpha * dq)
            if np.isfinite(trial.residual_norm):
                wt = wnorm(trial)
                ok = mu == 0.0 and alpha == 1.0 and wt < NEWTON_SHRINK * w0
                if not ok and energy_merit and trial.energy is not None:
                    eps = ENERGY_ROUNDOFF * max(asm.energy_scale, trial.energy_scale)
                    ok = (trial.energy <= asm.energy + ARMIJO * alpha * slope
                          or (trial.energy <= asm.energy + eps and wt < w0))
                elif not ok:
                    ok = wt < (1.0 - ARMIJO * alpha) * w0
                if ok:
                    return alpha, trial
            alpha *= 0.5
        return alpha, None
