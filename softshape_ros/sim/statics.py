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
from everything distal). A solve that does not converge raises :class:`SolverError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softshape_ros.sim.lie import cross, skew
from softshape_ros.sim.rod import Kinematics, Rod

_EX = np.array([1.0, 0.0, 0.0])
TRUST_START_M = 0.008     # first step with an object in the scene moves the backbone <= 8 mm
TRUST_MAX_M = 0.05
TRUST_MIN_M = 5e-4
ENERGY_MERIT_TOL = 1e-5   # below this relative residual the merit is the residual norm
STALL_TOL = 1e-7          # relative residual accepted when round-off stops further descent


def _project(dq, L, A, lo, max_active: int = 6):
    """
    Return the Newton step with the linearised constraints ``A dq >= lo`` (``lo < 0``) kept.

    A small primal active-set QP on the Newton model (``L L^T``, its Hessian): the most
    violated constraint joins the active set and the step is solved again on it. A step
    along an object then slides along the surface instead of being cut short. Should the
    active set run out, the step is scaled back until every constraint holds.
    """
    if len(lo) == 0:
        return dq
    act, dq0 = [], dq
    for _ in range(max_active):
        viol = A @ dq - lo
        viol[act] = np.inf
        i = int(np.argmin(viol))
        # Round-off (~1e-17 m) on a row that duplicates an active one is not a violation.
        if viol[i] >= -1e-13:
            return dq
        act.append(i)
        while act:
            Aw = A[act]
            Y = np.linalg.solve(L.T, np.linalg.solve(L, Aw.T))        # H^-1 A_W^T
            try:
                lam = np.linalg.solve(Aw @ Y, lo[act] - Aw @ dq0)
            except np.linalg.LinAlgError:
                act.pop()
                continue
            if (lam >= 0.0).all():
                dq = dq0 + Y @ lam
                break
            # A constraint that would pull (negative multiplier) leaves the set.
            act = [a for a, m in zip(act, lam) if m >= 0.0]
        else:
            dq = dq0
    rate = A @ dq
    bad = rate < lo
    if bad.any():
        dq = dq * float((lo[bad] / rate[bad]).min())
    return dq


class SolverError(RuntimeError):
    """The statics solve did not converge: no shape is returned rather than a wrong one."""


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
class LoadTerm:
    """Point forces at the backbone for residual and tangent assembly (arrays over loads)."""

    X: np.ndarray        # (P,) arc lengths
    g: np.ndarray        # (P, 4, 4) poses
    J: np.ndarray        # (P, 6, n) body Jacobians
    f: np.ndarray        # (P, 3) world forces
    m: np.ndarray        # (P, 3) world moments
    dfdp: np.ndarray | None = None   # (P, 3, 3) force derivative w.r.t. the point position
    stiffness: np.ndarray | None = None   # (n, n) added to the tangent as is


@dataclass
class Assembly:
    residual: np.ndarray
    partial_tangent: np.ndarray
    scale: float
    kin: Kinematics
    extra: dict = field(default_factory=dict)
    energy: float | None = None      # total potential (None: a load is not conservative)
    energy_scale: float = 0.0
    pending: object = None           # callable: the tangent part still to subtract

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
        self.gravity_on = gravity_on and rod.spec.density > 0 and np.any(rod.gravity != 0)
        ch = [i for i, a in enumerate(self.actuators) if a.kind == 'chamber']
        td = [i for i, a in enumerate(self.actuators) if a.kind == 'tendon']
        self.chamber_idx, self.tendon_idx = np.array(ch, int), np.array(td, int)
        # Chambers: a constant internal wrench p A [d x e1; e1] on their own segment.
        self.B_ch = np.zeros((rod.n, len(ch)))
        for j, i in enumerate(ch):
            a = self.actuators[i]
            lam = a.area_m2 * np.concatenate([cross(a.d, _EX), _EX])
            on = rod.gauss_seg == a.segment
            self.B_ch[:, j] = np.einsum('k,kin,i->n', rod.gauss_w[on], rod.phi_g[on], lam)
        # Tendons run from the base to the tip of their segment (distal ones through the
        # proximal segments): active at Gauss node k if its segment <= the tendon's.
        self.td_d = np.array([self.actuators[i].d for i in td]).reshape(-1, 3)
        self.td_on = np.array([[rod.gauss_seg[k] <= self.actuators[i].segment for i in td]
                               for k in range(len(rod.gauss_seg))], dtype=float).reshape(
                                   len(rod.gauss_seg), len(td))
        # sum_k w_k Phi_k^T X_k as one product: Phi of the Gauss nodes, weighted, (n, 6K).
        self._phiw = (rod.phi_g * rod.gauss_w[:, None, None]).reshape(-1, rod.n).T.copy()
        # Gravity: lumped weights at the Gauss nodes (world force).
        self.grav_f = (rod.spec.density * rod.area[rod.gauss_seg] * rod.gauss_w)[:, None] \
            * rod.gravity[None, :]

    # -- loads -------------------------------------------------------------------------
    def tendon_terms(self, kin: Kinematics, tension: np.ndarray):
        """Return (Q, dQ/dq) of the tendons; slack (negative) tensions pull nothing."""
        rod = self.rod
        T = np.maximum(tension, 0.0)
        xi = kin.xi_gauss                                   # (K, 6)
        k, nu = xi[:, :3], xi[:, 3:]
        d = self.td_d                                       # (t, 3)
        v = nu[:, None, :] + cross(k[:, None, :], d[None, :, :])   # (K, t, 3)
        nv = np.linalg.norm(v, axis=-1)
        t = v / nv[..., None]
        Tk = self.td_on * T[None, :]                        # (K, t)
        lam = -Tk[..., None] * np.concatenate([cross(d[None], t), t], axis=-1)
        Q = self._phiw @ lam.sum(axis=1).ravel()
        # d lam / d xi = -T [d^; I] (I - t t^T) / |v| [-d^, I]
        dh = skew(d)                                        # (t, 3, 3)
        P = (np.eye(3) - t[..., :, None] * t[..., None, :]) / nv[..., None, None]
        top = np.concatenate([dh[None].repeat(len(xi), 0), np.broadcast_to(
            np.eye(3), P.shape)], axis=-2)                  # (K, t, 6, 3)
        right = np.concatenate([-dh[None].repeat(len(xi), 0), np.broadcast_to(
            np.eye(3), P.shape)], axis=-1)                  # (K, t, 3, 6)
        dlam = -(Tk[..., None, None] * (top @ P @ right)).sum(axis=1)   # (K, 6, 6)
        dQ = self._phiw @ (dlam @ rod.phi_g).reshape(-1, rod.n)
        energy = float(np.einsum('k,kt,kt->', rod.gauss_w, Tk, nv))   # T x tendon length
        return Q, dQ, energy

    def gravity_term(self, kin: Kinematics) -> LoadTerm:
        rod = self.rod
        idx = rod.gauss_node
        zero = np.zeros_like(self.grav_f)
        return LoadTerm(rod.gauss_X, kin.g[idx], kin.J[idx], self.grav_f, zero)

    def point_term(self, kin: Kinematics, loads: list[PointLoad], factor: float) -> LoadTerm:
        X = np.array([ld.s_m for ld in loads], dtype=float)
        if np.any((X < 0) | (X > self.rod.length + 1e-12)):
            raise ValueError(f'point loads must act on 0 <= s <= {self.rod.length} m, got {X}')
        g, J = self.rod.at(kin, X)
        f = factor * np.array([ld.force_n for ld in loads], dtype=float).reshape(-1, 3)
        m = factor * np.array([ld.moment_nm for ld in loads], dtype=float).reshape(-1, 3)
        return LoadTerm(X, g, J, f, m)

    def _apply(self, term: LoadTerm, R: np.ndarray, Kt: np.ndarray, residual: bool) -> float:
        """Subtract J^T W from R (if ``residual``) and the material stiffness from Kt."""
        Q = np.zeros(0)
        if residual:
            Rt = np.swapaxes(term.g[:, :3, :3], 1, 2)
            W = np.concatenate([np.einsum('pij,pj->pi', Rt, term.m),
                                np.einsum('pij,pj->pi', Rt, term.f)], axis=1)
            Q = term.J.reshape(-1, term.J.shape[-1]).T @ W.ravel()
            R -= Q
        if term.dfdp is not None:
            D = term.g[:, :3, :3] @ term.J[:, 3:, :]          # (P, 3, n) world dp/dq
            n = D.shape[-1]
            Kt -= D.reshape(-1, n).T @ (term.dfdp @ D).reshape(-1, n)
        if term.stiffness is not None:
            Kt += term.stiffness
        return float(np.abs(Q).max(initial=0.0))

    def _dlam(self, g, J, F, M, dM):
        """Return d(internal wrench)/dq (K, 6, n) at frames g, J for distal dead loads."""
        Rk, pk = g[:, :3, :3], g[:, :3, 3]
        Rt = np.swapaxes(Rk, 1, 2)
        Dk = Rk @ J[:, 3:, :]
        a = M - cross(pk, F)
        ang = skew(np.einsum('kij,kj->ki', Rt, a)) @ J[:, :3, :] + Rt @ (dM + skew(F) @ Dk)
        lin = skew(np.einsum('kij,kj->ki', Rt, F)) @ J[:, :3, :]
        return np.concatenate([ang, lin], axis=1)

    @staticmethod
    def _lam(g, F, M):
        """Return the body internal wrench (K, 6) at frames g from distal loads F, M."""
        Rt = np.swapaxes(g[:, :3, :3], 1, 2)
        return np.concatenate([np.einsum('kij,kj->ki', Rt, M - cross(g[:, :3, 3], F)),
                               np.einsum('kij,kj->ki', Rt, F)], axis=1)

    def _geometric(self, kin: Kinematics, terms: list[LoadTerm], point_terms, quad):
        """
        Return (Q, dQ/dq): point loads in quadrature form, and the geometric stiffness.

        Q covers the loads flagged in ``quad``; dQ/dq all of them.

        The internal wrench at X from everything distal is smooth between load points, so
        each point load's own segment is integrated by a Gauss rule on [segment start, X_c]
        and the segments before it on the regular nodes: Q = int_0^Xc Phi^T Lambda dX is the
        continuum virtual work, exact for a constant internal wrench (pure moment, tendon)
        whatever the basis order. Gravity (lumped on the regular nodes) adds to the
        tangent only; its residual is J^T W at those nodes.
        """
        rod = self.rod
        ng, n = len(rod.gauss_X), rod.n
        Fb = np.zeros((ng + 1, 3))
        Mb = np.zeros((ng + 1, 3))
        dMb = np.zeros((ng + 1, 3, n))
        Fp = np.zeros((ng + 1, 3))
        Mp = np.zeros((ng + 1, 3))
        extra = np.zeros((n, n))
        Qp = np.zeros(n)
        for t, is_point, in_q in zip(terms, point_terms, quad):
            # The full rule also where only the tangent comes from this form: with 4 points
            # its error (~1e-2) made Newton converge linearly (two more iterations per solve).
            xg, wg = rod.leg_x, rod.leg_w
            if len(t.X) == 0:
                continue
            p = t.g[:, :3, 3]
            D = t.g[:, :3, :3] @ t.J[:, 3:, :]
            fm = t.m + cross(p, t.f)
            dfm = -skew(t.f) @ D
            if is_point:
                seg, x = rod.locate(t.X)
                start = rod.offsets[seg]
                # Regular nodes of the proximal segments only.
                b = np.searchsorted(rod.gauss_X, start - 1e-15, side='right')
                # All points' own-segment rules in one batch (numpy call overhead dominates).
                i = np.nonzero(x > 0.0)[0]
                if len(i):
                    G = len(xg)
                    Xq = (start[i, None] + x[i, None] * (xg + 1) / 2).ravel()
                    wq = (x[i, None] * wg / 2).ravel()
                    gq, Jq = rod.at(kin, Xq)
                    phq = rod.phi(np.repeat(seg[i], G), Xq - np.repeat(start[i], G))
                    Fq = np.repeat(t.f[i], G, axis=0)
                    Mq = np.repeat(fm[i], G, axis=0)
                    dl = self._dlam(gq, Jq, Fq, Mq, np.repeat(dfm[i], G, axis=0))
                    # Sums over quadrature points as one matrix product (sum_k w_k Phi_k^T X_k).
                    phw = (phq * wq[:, None, None]).reshape(-1, n).T
                    extra += phw @ dl.reshape(-1, n)
                    if in_q:
                        Qp += phw @ self._lam(gq, Fq, Mq).ravel()
                if in_q:
                    np.add.at(Fp, b, t.f)
                    np.add.at(Mp, b, fm)
            else:
                b = np.searchsorted(rod.gauss_X, t.X + 1e-15, side='right')
            np.add.at(Fb, b, t.f)
            np.add.at(Mb, b, fm)
            np.add.at(dMb, b, dfm)
        # Node k collects every load in bins > k (strictly distal).
        F = np.cumsum(Fb[::-1], axis=0)[::-1][1:]
        M = np.cumsum(Mb[::-1], axis=0)[::-1][1:]
        dM = np.cumsum(dMb[::-1], axis=0)[::-1][1:]
        gk = kin.g[rod.gauss_node]
        dl = self._dlam(gk, kin.J[rod.gauss_node], F, M, dM)
        Kg = self._phiw @ dl.reshape(-1, n) + extra
        lam = self._lam(gk, np.cumsum(Fp[::-1], axis=0)[::-1][1:],
                        np.cumsum(Mp[::-1], axis=0)[::-1][1:])
        Qp += self._phiw @ lam.ravel()
        return Qp, Kg

    def assemble(self, q, u, loads, factor: float = 1.0, contact=None) -> Assembly:
        """Residual ``K q - Q`` and its tangent at ``q`` (``factor`` scales u and loads)."""
        rod = self.rod
        kin = rod.forward(q)
        Kq = rod.K @ q
        R = Kq.copy()
        Kt = rod.K.copy()
        scale = float(np.abs(Kq).max())
        energies = [0.5 * float(q @ Kq)]
        u = np.asarray(u, dtype=float) * factor
        if len(self.chamber_idx):
            Qc = self.B_ch @ u[self.chamber_idx]
            R -= Qc
            energies.append(-float(Qc @ q))
            scale = max(scale, float(np.abs(Qc).max()))
        if len(self.tendon_idx):
            Qt, dQt, et = self.tendon_terms(kin, u[self.tendon_idx])
            R -= Qt
            Kt -= dQt
            energies.append(et)
            scale = max(scale, float(np.abs(Qt).max()))
        terms, is_point = [], []
        if self.gravity_on:
            terms.append(self.gravity_term(kin))
            terms[-1].f = terms[-1].f * factor
            is_point.append(False)
        if loads:
            terms.append(self.point_term(kin, loads, factor))
            is_point.append(True)
        conservative = True
        for t in terms:
            # Dead forces have potential -f.p; world moments in 3-D do not (path dependent).
            energies.append(-float(np.einsum('pi,pi->', t.f, t.g[:, :3, 3])))
            conservative = conservative and not np.any(t.m)
        extra = {}
        if contact is not None:
            cterm, extra = contact(rod, kin)      # its potential comes in extra['energy']
            if cterm is not None:
                terms.append(cterm)
                is_point.append(True)
        # Residual of point loads: J^T W (the exact gradient of the potential, so energy and
        # residual agree) for forces; the quadrature (virtual-work) form where moments act,
        # which keeps a constant internal wrench exact at any basis order.
        quad = [point and bool(np.any(t.m)) for t, point in zip(terms, is_point)]
        for t, qd in zip(terms, quad):
            scale = max(scale, self._apply(t, R, Kt, residual=not qd))
        deferred = None
        if terms and any(quad):
            Qp, Kg = self._geometric(kin, terms, is_point, quad)
            R -= Qp
            Kt -= Kg
            scale = max(scale, float(np.abs(Qp).max()))
        elif terms:
            # Tangent only: deferred until the Newton step asks for it.
            deferred = lambda: self._geometric(kin, terms, is_point, quad)[1]  # noqa: E731
        energies.append(float(extra.get('energy', 0.0)))
        energy = float(sum(energies)) if conservative else None
        return Assembly(R, Kt, scale, kin, extra, energy, float(sum(abs(e) for e in energies)),
                        deferred)

    def solve(self, u, loads=(), q0=None, contact=None, tol: float = 1e-10,
              max_iter: int = 40, max_depth: int = 8):
        """
        Solve for the equilibrium; return (q, assembly, iterations).

        Newton with a backtracking line search; when a step fails the load is applied in
        smaller increments (bisection of the load factor, up to ``max_depth`` times).
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
        lam_done, step, depth = 0.0, 1.0, 0
        last = None
        while lam_done < 1.0:
            lam = min(1.0, lam_done + step)
            ok, q_new, asm, it = self._newton(q, u, loads, lam, contact, tol, max_iter)
            total_iter += it
            if ok:
                q, last, lam_done = q_new, asm, lam
                if depth > 0:
                    step *= 2.0
                    depth -= 1
            else:
                if depth >= max_depth:
                    res = float(np.abs(asm.residual).max()) if asm is not None else float('nan')
                    raise SolverError(
                        f'statics did not converge: load factor {lam:.4f} failed after '
                        f'{total_iter} Newton iterations (residual {res:.3e}, '
                        f'{depth} load bisections)')
                step /= 2.0
                depth += 1
        return q, last, total_iter

    def _newton(self, q, u, loads, lam, contact, tol, max_iter):
        """
        Damped Newton on the total potential when all loads are conservative.

        The step solves (H + mu diag K) dq = -R with mu > 0 only where the tangent H is not
        positive definite, and the line search asks the energy to drop (Armijo): so the
        solver walks to stable equilibria and never settles on a saddle (e.g. the tip
        balanced on a cylinder it would slide off). Without an energy (world moments) the
        merit is the K-weighted residual norm.
        """
        rod = self.rod
        kd = np.diag(rod.K)
        asm = self.assemble(q, u, loads, lam, contact)
        max_dq = 4.0 * np.pi / rod.lengths.min()
        # Trust radius on the predicted motion of the backbone (m): with an object near,
        # a full Newton step from a free shape would dive deep into it.
        radius = TRUST_START_M if contact is not None else np.inf
        mu = 0.0

        def wnorm(a):
            return float(np.sqrt(np.sum(a.residual ** 2 / kd)))

        for it in range(1, max_iter + 1):
            r = asm.residual
            rn = float(np.abs(r).max())
            if not np.isfinite(rn):
                return False, q, asm, it
            if rn <= tol * asm.scale + 1e-15:
                return True, q, asm, it - 1
            H = 0.5 * (asm.tangent + asm.tangent.T)
            # Plain Newton where the tangent is positive definite; otherwise the smallest
            # diag(K) shift (from a tenth of the last one) that makes it so.
            shift, mu_next = 0.0, max(mu * 0.1, 1e-4)
            for _ in range(30):
                try:
                    L = np.linalg.cholesky(H + shift * np.diag(kd))
                    break
                except np.linalg.LinAlgError:
                    shift, mu_next = mu_next, mu_next * 10.0
            else:
                return False, q, asm, it
            mu = shift
            dq = -np.linalg.solve(L.T, np.linalg.solve(L, r))
            if hasattr(contact, 'step_constraints'):
                dq = _project(dq, L, *contact.step_constraints(rod, asm.kin, asm.extra))
            big = float(np.abs(dq).max())
            if not np.isfinite(big):
                return False, q, asm, it
            if big > max_dq:
                dq *= max_dq / big
            if np.isfinite(radius):
                kin = asm.kin
                move = (kin.g[:, :3, :3] @ kin.J[:, 3:, :]) @ dq
                mv = float(np.sqrt((move ** 2).sum(axis=1)).max())
                if mv > radius:
                    dq *= radius / mv
                    mv = radius
            slope = float(r @ dq)
            w0 = wnorm(asm)
            alpha, accepted = 1.0, False
            for _ in range(12):
                trial = self.assemble(q + alpha * dq, u, loads, lam, contact)
                tn = float(np.abs(trial.residual).max())
                if np.isfinite(tn):
                    wt = wnorm(trial)
                    # A positive-definite Newton step that shrinks the residual is taken
                    # (near the solution energy differences drown in round-off).
                    ok = mu == 0.0 and alpha == 1.0 and wt < 0.7 * w0
                    # Energy as merit away from the solution only: the point-load residual
                    # is its quadrature form, within ~1e-7 of the energy's gradient.
                    use_energy = (asm.energy is not None and trial.energy is not None
                                  and rn > ENERGY_MERIT_TOL * asm.scale)
                    if not ok and use_energy:
                        eps = 1e-12 * max(asm.energy_scale, trial.energy_scale)
                        ok = (trial.energy <= asm.energy + 1e-4 * alpha * slope
                              or (trial.energy <= asm.energy + eps and wt < w0))
                    elif not ok:
                        ok = wt < (1.0 - 1e-4 * alpha) * w0
                    if ok:
                        accepted = True
                        break
                alpha *= 0.5
            if not accepted:
                # Stalled at round-off level: accept a nearly converged state.
                ok = rn <= STALL_TOL * asm.scale + 1e-15
                return ok, q, asm, it
            if np.isfinite(radius):
                radius = (min(4.0 * radius, TRUST_MAX_M) if alpha == 1.0
                          else max(alpha * mv, TRUST_MIN_M))
            q, asm = q + alpha * dq, trial
        r = asm.residual
        ok = float(np.abs(r).max()) <= tol * asm.scale + 1e-15
        return ok, q, asm, max_iter
