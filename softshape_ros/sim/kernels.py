"""
Compiled kernels of the simulator (numba).

SE(3), strain basis, kinematics, distances, contact search, load assembly and the small
dense solves of a Newton step.

Every compiled function lives in this one file on purpose: numba's on-disk cache
(``cache=True``; a new process loads machine code instead of compiling it again) checks only
the source file of the function it caches, so a kernel calling a helper kept in another file
would go on running the helper's old code after an edit. The Python modules beside it
(``rod``, ``objects``, ``contact``, ``statics``) build the tables read here and hold the logic
a reader follows; these functions are the arithmetic.

Conventions: twists and wrenches are 6-vectors with the angular part first (SoRoSim order),
poses 4x4. The strain basis is sparse (a point of segment ``s`` touches only that segment's
columns of ``q``), so the kernels loop over (component, mode) pairs instead of multiplying
dense ``Phi`` matrices. No kernel allocates inside its per-point loops.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from numba import njit
import numpy as np


def _kernel(fn):
    """Compile ``fn`` on first use, cached on disk, with numpy's float semantics (no checks)."""
    return njit(cache=True, error_model='numpy')(fn)


SMALL_ANGLE2 = 1e-4     # exp/dexp coefficients from their series below 0.01 rad (error < 1e-17)
Z1 = 0.5 - math.sqrt(3.0) / 6.0      # Zanna points of the 4th-order Magnus step
Z2 = 0.5 + math.sqrt(3.0) / 6.0
C4 = math.sqrt(3.0) / 12.0
PIVOT_FLOOR = 0.0       # a Cholesky pivot at or below this: not positive definite
QP_ROUNDOFF = -1e-13    # a step QP violation above this is round-off (a row duplicating another)
CURVE_FLOOR = 1e-12     # |d2 gap / dX2| below this: no Newton step on the contact abscissa
SLIDE_FLOOR = 1e-9      # ... below this: the contact point's sliding term is left out
ABSCISSA_STEP_M = 1e-10  # a Newton step on the contact abscissa this short has converged
BRACKET_M = 1e-13       # a bracket this narrow has converged
TIP_GUARD_M = 1e-12     # a contact this close to the tip is the tip (it does not slide)
FAR_CUT_SLACK = 1.0     # sample an interval only if its nodes' gap minus this x its length is near
DIST_FLOOR = 1e-12      # distances below this in a curvature denominator (m)

# Obstacle kinds and the layout of their parameter rows (objects.py packs them).
PLANE, SPHERE, CYLINDER, RING, PRISM = 0, 1, 2, 3, 4
PRISM_NORMALS, PRISM_OFFSETS, PRISM_EA, PRISM_EAB = 0, 18, 24, 60
PRISM_EAB2, PRISM_EA_EAB, PRISM_EA2, PRISM_FPROJ = 96, 108, 120, 132
PRISM_FA_AB, PRISM_FN, PRISM_FN_A, PRISM_PARAMS = 168, 180, 198, 204


class RodTables(NamedTuple):
    """The layout of one rod that every kernel reads (built once by ``rod.Rod``)."""

    seg_len: np.ndarray      # (S,) segment lengths
    offsets: np.ndarray      # (S + 1,) arc length at each segment start, then the total
    radii: np.ndarray        # (S,) tube radii
    comps: np.ndarray        # (C,) int: strain components carried by modes
    n_modes: int             # Legendre modes per component and segment
    base: np.ndarray         # (4, 4) base pose
    node_X: np.ndarray       # (N,) node arc lengths: 0, the interval ends (N = M + 1)
    node_seg: np.ndarray     # (N,) int: segment whose strain a node reads (its interval's)
    int_seg: np.ndarray      # (M,) int: segment of each Magnus interval
    int_a: np.ndarray        # (M,) local abscissa where the interval starts
    int_h: np.ndarray        # (M,) interval length
    gauss_X: np.ndarray      # (K,) Gauss points (arc length); each is a node
    gauss_node: np.ndarray   # (K,) int: node index of each Gauss point
    gauss_seg: np.ndarray    # (K,) int
    gauss_w: np.ndarray      # (K,) weights (m)
    rule_x: np.ndarray       # (G,) Gauss rule on [-1, 1] (a point load's own-segment rule)
    rule_w: np.ndarray       # (G,)


# -- small dense algebra -------------------------------------------------------------------
@_kernel
def _matmul(A, B, out):
    """Write ``A @ B`` into ``out`` (small matrices)."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[k, j]
            out[i, j] = s


@_kernel
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@_kernel
def _skew(w, out):
    out[0, 0], out[0, 1], out[0, 2] = 0.0, -w[2], w[1]
    out[1, 0], out[1, 1], out[1, 2] = w[2], 0.0, -w[0]
    out[2, 0], out[2, 1], out[2, 2] = -w[1], w[0], 0.0


@_kernel
def _ad(x, out):
    """Write the 6x6 adjoint ``ad_x`` (``ad_x y = [x, y]``) into ``out``."""
    out[:, :] = 0.0
    _skew(x[:3], out[:3, :3])
    _skew(x[:3], out[3:, 3:])
    _skew(x[3:], out[3:, :3])


@_kernel
def cholesky(H, L):
    """Write the lower Cholesky factor of ``H`` into ``L``; return False if H is not PD."""
    n = H.shape[0]
    L[:, :] = 0.0
    for j in range(n):
        s = H[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > PIVOT_FLOOR:          # also NaN
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    return True


@_kernel
def cho_solve(L, b):
    """Return ``x`` with ``L L^T x = b`` (b: (n,) or (n, m))."""
    x = b.copy()
    n = L.shape[0]
    for i in range(n):                      # L y = b
        for k in range(i):
            x[i] -= L[i, k] * x[k]
        x[i] /= L[i, i]
    for i in range(n - 1, -1, -1):          # L^T x = y
        for k in range(i + 1, n):
            x[i] -= L[k, i] * x[k]
        x[i] /= L[i, i]
    return x


@_kernel
def _lu_solve(A, b):
    """Return (x, ok) with ``A x = b`` by LU with partial pivoting; ok False if singular."""
    n = A.shape[0]
    M = A.copy()
    x = b.copy()
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if M[p, c] == 0.0:
            return x, False
        if p != c:
            for k in range(n):
                M[c, k], M[p, k] = M[p, k], M[c, k]
            x[c], x[p] = x[p], x[c]
        for r in range(c + 1, n):
            f = M[r, c] / M[c, c]
            for k in range(c, n):
                M[r, k] -= f * M[c, k]
            x[r] -= f * x[c]
    for r in range(n - 1, -1, -1):
        for k in range(r + 1, n):
            x[r] -= M[r, k] * x[k]
        x[r] /= M[r, r]
    return x, True


@_kernel
def shifted_cholesky(H, kdiag, mu_last, tries):
    """
    Return (L, shift, ok): the Cholesky factor of ``H + shift diag(kdiag)``.

    ``shift`` is 0 where H is positive definite, else the smallest of ``max(mu_last / 10,
    1e-4) * 10^i`` that makes it so (``tries`` of them).
    """
    n = H.shape[0]
    L = np.empty((n, n))
    Hs = H.copy()
    shift, mu_next = 0.0, max(mu_last * 0.1, 1e-4)
    for _ in range(tries):
        for i in range(n):
            Hs[i, i] = H[i, i] + shift * kdiag[i]
        if cholesky(Hs, L):
            return L, shift, True
        shift, mu_next = mu_next, mu_next * 10.0
    return L, shift, False


@_kernel
def project_step(dq, L, A, lo, max_active):
    """
    Return the Newton step with the linearised constraints ``A dq >= lo`` (``lo < 0``) kept.

    A small primal active-set QP on the Newton model (``L L^T``, its Hessian): the most
    violated constraint joins the active set and the step is solved again on it; one that
    would pull (negative multiplier) leaves it. Should the active set run out, the step is
    scaled back until every constraint holds.
    """
    m = lo.shape[0]
    if m == 0:
        return dq
    dq0 = dq
    act = np.empty(max_active, dtype=np.int64)
    n_act = 0
    for _ in range(max_active):
        viol = A @ dq - lo
        for a in range(n_act):
            viol[act[a]] = np.inf
        i = int(np.argmin(viol))
        if viol[i] >= QP_ROUNDOFF:
            return dq
        act[n_act] = i
        n_act += 1
        solved = False
        while n_act > 0:
            Aw = np.empty((n_act, A.shape[1]))
            rhs = np.empty(n_act)
            for a in range(n_act):
                Aw[a] = A[act[a]]
            Y = cho_solve(L, Aw.T.copy())                       # H^-1 A_W^T
            rhs = lo[act[:n_act]] - Aw @ dq0
            multipliers, ok = _lu_solve(Aw @ Y, rhs)
            if not ok:
                n_act -= 1
                continue
            if np.all(multipliers >= 0.0):
                dq = dq0 + Y @ multipliers
                solved = True
                break
            keep = 0
            for a in range(n_act):
                if multipliers[a] >= 0.0:
                    act[keep] = act[a]
                    keep += 1
            n_act = keep
        if not solved:
            dq = dq0
    rate = A @ dq
    scale = 1.0
    for r in range(m):
        if rate[r] < lo[r]:
            scale = min(scale, lo[r] / rate[r])
    if scale < 1.0:
        dq = dq * scale
    return dq


# -- SE(3) ---------------------------------------------------------------------------------
@_kernel
def _coefficients(th2, c):
    """Fill c[0:3] with exp's (a, b, c) and c[3:7] with dexp's (f1..f4) of angle^2 ``th2``."""
    if th2 < SMALL_ANGLE2:
        th4 = th2 * th2
        c[0] = 1 - th2 / 6 + th4 / 120
        c[1] = 0.5 - th2 / 24 + th4 / 720
        c[2] = 1 / 6 - th2 / 120 + th4 / 5040
        c[3] = -(0.5 - th4 / 720)
        c[4] = 1 / 6 - th4 / 5040
        c[5] = -(1 / 24 - th2 / 360 + th4 / 13440)
        c[6] = 1 / 120 - th2 / 2520 + th4 / 120960
        return
    t = math.sqrt(th2)
    s, co = math.sin(t), math.cos(t)
    t2 = t * t
    t3 = t2 * t
    c[0] = s / t
    c[1] = (1 - co) / t2
    c[2] = (t - s) / t3
    ts, tc = t * s, t * co
    c[3] = -(4 - 4 * co - ts) / (2 * t2)
    c[4] = (4 * t - 5 * s + tc) / (2 * t3)
    c[5] = -(2 - 2 * co - ts) / (2 * t2 * t2)
    c[6] = (2 * t - 3 * s + tc) / (2 * t3 * t2)


class _Work(NamedTuple):
    """Scratch arrays of one Magnus step (allocated once per kernel call)."""

    P1: np.ndarray       # (nm,) basis values at the Zanna points
    P2: np.ndarray
    x1: np.ndarray       # (6,) strains there
    x2: np.ndarray
    om: np.ndarray       # (6,) Magnus twist
    coef: np.ndarray     # (7,) exp/dexp coefficients
    W: np.ndarray        # (3, 3)
    W2: np.ndarray
    E: np.ndarray        # (4, 4) the step's pose
    A: np.ndarray        # (6, 6) powers of ad(om), then T = dexp(om)
    A2: np.ndarray
    A3: np.ndarray
    A4: np.ndarray
    T: np.ndarray
    S: np.ndarray        # (6, D) d om / dq on the segment's columns
    TS: np.ndarray       # (6, D)
    ad1: np.ndarray      # (6, 6)
    ad2: np.ndarray
    br: np.ndarray       # (6,) the Lie bracket [x1, x2]
    G: np.ndarray        # (4, 4) a node pose times E
    t: np.ndarray        # (3,) tangent, curvature x nu
    kv: np.ndarray


@_kernel
def _work(n_modes, n_cols):
    return _Work(np.empty(n_modes), np.empty(n_modes), np.empty(6), np.empty(6), np.empty(6),
                 np.empty(7), np.empty((3, 3)), np.empty((3, 3)), np.empty((4, 4)),
                 np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)),
                 np.empty((6, 6)), np.empty((6, n_cols)), np.empty((6, n_cols)),
                 np.empty((6, 6)), np.empty((6, 6)), np.empty(6), np.empty((4, 4)),
                 np.empty(3), np.empty(3))


@_kernel
def _exp(x, w):
    """Write exp(x) into w.E (Rodrigues) and leave the coefficients in w.coef."""
    _coefficients(x[0] * x[0] + x[1] * x[1] + x[2] * x[2], w.coef)
    a, b, c = w.coef[0], w.coef[1], w.coef[2]
    _skew(x[:3], w.W)
    _matmul(w.W, w.W, w.W2)
    E = w.E
    for i in range(3):
        for j in range(3):
            E[i, j] = a * w.W[i, j] + b * w.W2[i, j]
        E[i, i] += 1.0
        s = 0.0
        for j in range(3):
            s += (b * w.W[i, j] + c * w.W2[i, j]) * x[3 + j]
        E[i, 3] = x[3 + i] + s
    E[3, 0], E[3, 1], E[3, 2], E[3, 3] = 0.0, 0.0, 0.0, 1.0


@_kernel
def _dexp(x, w):
    """Write the tangent operator T(x) = I + f1 ad + f2 ad^2 + f3 ad^3 + f4 ad^4 into w.T."""
    _ad(x, w.A)
    _matmul(w.A, w.A, w.A2)
    _matmul(w.A2, w.A, w.A3)
    _matmul(w.A2, w.A2, w.A4)
    f1, f2, f3, f4 = w.coef[3], w.coef[4], w.coef[5], w.coef[6]
    for i in range(6):
        for j in range(6):
            w.T[i, j] = ((((1.0 if i == j else 0.0) + f1 * w.A[i, j]) + f2 * w.A2[i, j])
                         + f3 * w.A3[i, j]) + f4 * w.A4[i, j]


@_kernel
def _pose_mul(g, E, out):
    """Write the pose product ``g @ E`` into ``out``."""
    for i in range(3):
        for j in range(4):
            s = g[i, 3] if j == 3 else 0.0
            for k in range(3):
                s += g[i, k] * E[k, j]
            out[i, j] = s
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@_kernel
def _adinv_apply(E, J, out, n_cols):
    """Write ``Ad_{E^-1} J`` (first ``n_cols`` columns) into ``out``: twists into E's frame."""
    for col in range(n_cols):
        w0, w1, w2 = J[0, col], J[1, col], J[2, col]
        p0, p1, p2 = E[0, 3], E[1, 3], E[2, 3]
        v0 = J[3, col] - (p1 * w2 - p2 * w1)
        v1 = J[4, col] - (p2 * w0 - p0 * w2)
        v2 = J[5, col] - (p0 * w1 - p1 * w0)
        for i in range(3):
            out[i, col] = E[0, i] * w0 + E[1, i] * w1 + E[2, i] * w2
            out[3 + i, col] = E[0, i] * v0 + E[1, i] * v1 + E[2, i] * v2


# -- strain basis and kinematics -----------------------------------------------------------
@_kernel
def _legendre(y, out):
    """Fill ``out`` with the Legendre polynomials P_0..P_{len-1} at y."""
    out[0] = 1.0
    if out.shape[0] > 1:
        out[1] = y
    for j in range(2, out.shape[0]):
        out[j] = ((2 * j - 1) * y * out[j - 1] - (j - 1) * out[j - 2]) / j


@_kernel
def _strain(tab, q, seg, x, P, xi):
    """Fill P with the basis at local abscissa x of segment ``seg`` and xi with the strain."""
    _legendre(2.0 * x / tab.seg_len[seg] - 1.0, P)
    nm = tab.n_modes
    col = seg * nm * tab.comps.shape[0]
    xi[:] = 0.0
    for ci in range(tab.comps.shape[0]):
        s = 0.0
        for j in range(nm):
            s += P[j] * q[col + ci * nm + j]
        xi[tab.comps[ci]] = s
    xi[3] += 1.0


@_kernel
def _locate(tab, X):
    """Return (segment, local abscissa) of arc length X (clipped to the rod)."""
    X = min(max(X, 0.0), tab.offsets[-1])
    seg = np.searchsorted(tab.offsets, X, side='right') - 1
    seg = min(max(seg, 0), tab.seg_len.shape[0] - 1)
    return seg, X - tab.offsets[seg]


@_kernel
def _magnus(tab, q, seg, a, h, jac, w):
    """
    Take one Magnus step over [a, a + h] of segment ``seg``.

    Its pose goes into w.E and, with ``jac``, ``T(om) d om / dq`` on the segment's
    columns into w.TS.
    """
    _strain(tab, q, seg, a + Z1 * h, w.P1, w.x1)
    _strain(tab, q, seg, a + Z2 * h, w.P2, w.x2)
    x1, x2 = w.x1, w.x2
    bracket = w.br
    bracket[0] = x1[1] * x2[2] - x1[2] * x2[1]
    bracket[1] = x1[2] * x2[0] - x1[0] * x2[2]
    bracket[2] = x1[0] * x2[1] - x1[1] * x2[0]
    bracket[3] = (x1[1] * x2[5] - x1[2] * x2[4]) + (x1[4] * x2[2] - x1[5] * x2[1])
    bracket[4] = (x1[2] * x2[3] - x1[0] * x2[5]) + (x1[5] * x2[0] - x1[3] * x2[2])
    bracket[5] = (x1[0] * x2[4] - x1[1] * x2[3]) + (x1[3] * x2[1] - x1[4] * x2[0])
    c2 = C4 * h ** 2
    for i in range(6):
        w.om[i] = h / 2 * (x1[i] + x2[i]) + c2 * bracket[i]
    _exp(w.om, w)
    if not jac:
        return
    _dexp(w.om, w)
    _ad(x1, w.ad1)
    _ad(x2, w.ad2)
    nm = tab.n_modes
    for ci in range(tab.comps.shape[0]):
        c = tab.comps[ci]
        for j in range(nm):
            col = ci * nm + j
            for r in range(6):
                w.S[r, col] = c2 * (w.P2[j] * w.ad1[r, c] - w.P1[j] * w.ad2[r, c])
            w.S[c, col] += h / 2 * (w.P1[j] + w.P2[j])
    _matmul(w.T, w.S, w.TS)


@_kernel
def forward(tab, q, jac):
    """
    Return node poses g (N, 4, 4), Jacobians J (N, 6, n) and Gauss-point strains (K, 6).

    J is empty unless ``jac``. The poses chain the Magnus steps from the base; the Jacobian
    follows in the same pass, ``J_{k+1} = Ad_{exp(-om_k)} J_k + T(om_k) d om_k / dq``.
    """
    M = tab.int_h.shape[0]
    n = q.shape[0]
    D = tab.n_modes * tab.comps.shape[0]
    w = _work(tab.n_modes, D)
    g = np.empty((M + 1, 4, 4))
    g[0] = tab.base
    J = np.zeros((M + 1 if jac else 0, 6, n))
    for k in range(M):
        seg = tab.int_seg[k]
        _magnus(tab, q, seg, tab.int_a[k], tab.int_h[k], jac, w)
        _pose_mul(g[k], w.E, g[k + 1])
        if jac:
            _adinv_apply(w.E, J[k], J[k + 1], (seg + 1) * D)
            J[k + 1, :, seg * D:(seg + 1) * D] += w.TS
    xi = np.empty((tab.gauss_X.shape[0], 6))
    for i in range(tab.gauss_X.shape[0]):
        s = tab.gauss_seg[i]
        _strain(tab, q, s, tab.gauss_X[i] - tab.offsets[s], w.P1, xi[i])
    return g, J, xi


@_kernel
def _point_frame(tab, q, g_nodes, J_nodes, X, jac, w, g_out, J_out):
    """Write the pose (and with ``jac`` the Jacobian) at X: a Magnus step from the node before."""
    X = min(max(X, 0.0), tab.offsets[-1])
    N = tab.node_X.shape[0]
    k = np.searchsorted(tab.node_X, X)
    if k < N and tab.node_X[k] == X:
        g_out[:, :] = g_nodes[k]
        if jac:
            J_out[:, :] = J_nodes[k]
        return
    m = min(max(np.searchsorted(tab.node_X, X, side='right') - 1, 0), N - 2)
    seg = tab.int_seg[m]
    _magnus(tab, q, seg, tab.int_a[m], X - tab.node_X[m], jac, w)
    _pose_mul(g_nodes[m], w.E, g_out)
    if jac:
        D = tab.n_modes * tab.comps.shape[0]
        _adinv_apply(w.E, J_nodes[m], J_out, J_out.shape[1])
        J_out[:, seg * D:(seg + 1) * D] += w.TS


@_kernel
def point_frames(tab, q, g_nodes, J_nodes, X, jac):
    """Return poses (P, 4, 4) and body Jacobians (P, 6, n) (empty unless ``jac``) at X."""
    n = q.shape[0]
    w = _work(tab.n_modes, tab.n_modes * tab.comps.shape[0])
    g = np.empty((X.shape[0], 4, 4))
    J = np.zeros((X.shape[0] if jac else 0, 6, n))
    dummy = np.empty((6, n))
    for i in range(X.shape[0]):
        _point_frame(tab, q, g_nodes, J_nodes, X[i], jac, w, g[i], J[i] if jac else dummy)
    return g, J


@_kernel
def strains(tab, q, X):
    """Return the strain (P, 6) at arc lengths X (segment ends read the next segment)."""
    P = np.empty(tab.n_modes)
    xi = np.empty((X.shape[0], 6))
    for i in range(X.shape[0]):
        seg, x = _locate(tab, X[i])
        _strain(tab, q, seg, x, P, xi[i])
    return xi


@_kernel
def basis_matrices(tab, seg, x, n):
    """Return Phi (P, 6, n) at local abscissae x of segments seg (the dense form)."""
    nm, nc = tab.n_modes, tab.comps.shape[0]
    P = np.empty(nm)
    out = np.zeros((x.shape[0], 6, n))
    for i in range(x.shape[0]):
        _legendre(2.0 * x[i] / tab.seg_len[seg[i]] - 1.0, P)
        for ci in range(nc):
            for j in range(nm):
                out[i, tab.comps[ci], seg[i] * nm * nc + ci * nm + j] = P[j]
    return out


@_kernel
def _add_phi_t(tab, seg, P, weight, rows, out):
    """Add ``weight Phi^T rows`` to ``out`` (n, k): Phi's nonzeros are P_j at (c, col)."""
    nm, nc = tab.n_modes, tab.comps.shape[0]
    for ci in range(nc):
        c = tab.comps[ci]
        for j in range(nm):
            col = seg * nm * nc + ci * nm + j
            f = weight * P[j]
            for k in range(rows.shape[1]):
                out[col, k] += f * rows[c, k]


@_kernel
def _add_phi_t_vec(tab, seg, P, weight, v, out):
    """Add ``weight Phi^T v`` to ``out`` (n,) for a 6-vector v."""
    nm, nc = tab.n_modes, tab.comps.shape[0]
    for ci in range(nc):
        c = tab.comps[ci]
        for j in range(nm):
            out[seg * nm * nc + ci * nm + j] += weight * P[j] * v[c]


# -- obstacles: signed distance, unit gradient and Hessian ---------------------------------
@_kernel
def _normalise(v):
    r = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    r = max(r, 1e-300)
    v[0] /= r
    v[1] /= r
    v[2] /= r


@_kernel
def _circle_hessian(p, n, dist, R0, H):
    """H = [(I - n n^T) - (R0 / rho) t t^T] / dist: distance to a circle of radius R0 about z."""
    rho = max(math.hypot(p[0], p[1]), DIST_FLOOR)
    t0, t1 = -p[1] / rho, p[0] / rho
    c = R0 / rho
    den = max(dist, DIST_FLOOR)
    tt = (t0, t1, 0.0)
    for i in range(3):
        for j in range(3):
            H[i, j] = (((1.0 if i == j else 0.0) - n[i] * n[j]) - c * (tt[i] * tt[j])) / den


@_kernel
def _sphere(prm, p, hess, n, H):
    nrm = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
    d = nrm - prm[0]
    n[:] = p
    _normalise(n)
    if hess:
        _circle_hessian(p, n, d + prm[0], 0.0, H)
    return d


@_kernel
def _plane(prm, p, hess, n, H):
    n[0], n[1], n[2] = 0.0, 0.0, 1.0
    if hess:
        H[:, :] = 0.0
    return p[2]


@_kernel
def _cylinder(prm, p, hess, n, H):
    """Axis z, centred: radius prm[0], half height prm[1]; the rim is a circle."""
    r, hh = prm[0], prm[1]
    rho = math.sqrt(p[0] * p[0] + p[1] * p[1])
    dr, dz = rho - r, abs(p[2]) - hh
    out_r, out_z = max(dr, 0.0), max(dz, 0.0)
    outside = math.hypot(out_r, out_z)
    d = outside + min(max(dr, dz), 0.0)
    rn = max(math.sqrt(p[0] * p[0] + p[1] * p[1]), 1e-300)
    u0, u1 = p[0] / rn, p[1] / rn                        # radial unit vector
    axial = (1.0 if p[2] > 0 else (-1.0 if p[2] < 0 else 0.0)) + (1.0 if p[2] == 0 else 0.0)
    if outside > 0:
        n[0], n[1], n[2] = out_r * u0, out_r * u1, out_z * axial
        _normalise(n)
    elif dr > dz:
        n[0], n[1], n[2] = u0, u1, 0.0
    else:
        n[0], n[1], n[2] = 0.0, 0.0, axial
    if not hess:
        return d
    rho = max(math.hypot(p[0], p[1]), DIST_FLOOR)
    dr = rho - r
    if dr > 0 and dz > 0:                                # rim: distance to a circle
        _circle_hessian(p, n, d, r, H)                   # (its z does not enter)
        return d
    side = (dr > 0 and dz <= 0) or (d <= 0 and dr > dz)
    t0, t1 = -p[1] / rho, p[0] / rho
    f = (1.0 if side else 0.0) / rho
    H[:, :] = 0.0
    H[0, 0], H[0, 1], H[1, 0], H[1, 1] = f * (t0 * t0), f * (t0 * t1), f * (t1 * t0), f * (t1 * t1)
    return d


@_kernel
def _ring(prm, p, hess, n, H):
    """Torus around z in the x-y plane: major radius prm[0], minor prm[1]."""
    R0, r = prm[0], prm[1]
    rn = max(math.sqrt(p[0] * p[0] + p[1] * p[1]), 1e-300)
    n[0], n[1], n[2] = p[0] - R0 * (p[0] / rn), p[1] - R0 * (p[1] / rn), p[2]
    d = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) - r
    _normalise(n)
    if hess:
        _circle_hessian(p, n, d + r, R0, H)
    return d


@_kernel
def _prism(prm, p, hess, n, H):
    """
    Return the distance to an oblique prism (exact).

    Outside the nearest face interior or edge, inside the largest face distance; edges are
    lines with a Hessian, faces are flat.
    """
    pp = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    inside_d, j_in = -np.inf, 0
    for j in range(6):
        e = (p[0] * prm[PRISM_NORMALS + 3 * j] + p[1] * prm[PRISM_NORMALS + 3 * j + 1]
             + p[2] * prm[PRISM_NORMALS + 3 * j + 2]) - prm[PRISM_OFFSETS + j]
        if e > inside_d:
            inside_d, j_in = e, j
    best, k_best, t_best = np.inf, 0, 0.0
    for k in range(12):
        ea, eab = PRISM_EA + 3 * k, PRISM_EAB + 3 * k
        dot = (p[0] * prm[eab] + p[1] * prm[eab + 1] + p[2] * prm[eab + 2]) \
            - prm[PRISM_EA_EAB + k]
        l2 = prm[PRISM_EAB2 + k]
        t = min(max(dot / l2, 0.0), 1.0)
        rel2 = pp - 2.0 * (p[0] * prm[ea] + p[1] * prm[ea + 1] + p[2] * prm[ea + 2]) \
            + prm[PRISM_EA2 + k]
        de = math.sqrt(max(rel2 - t * (2.0 * dot - t * l2), 0.0))
        if de < best:
            best, k_best, t_best = de, k, t
    h_best = 0.0
    for f in range(6):
        a0 = PRISM_FPROJ + 6 * f
        u = (p[0] * prm[a0] + p[1] * prm[a0 + 1] + p[2] * prm[a0 + 2]) \
            - prm[PRISM_FA_AB + 2 * f]
        v = (p[0] * prm[a0 + 3] + p[1] * prm[a0 + 4] + p[2] * prm[a0 + 5]) \
            - prm[PRISM_FA_AB + 2 * f + 1]
        if 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0:
            fn = PRISM_FN + 3 * f
            h = (p[0] * prm[fn] + p[1] * prm[fn + 1] + p[2] * prm[fn + 2]) - prm[PRISM_FN_A + f]
            if abs(h) < best:
                best, k_best, h_best = abs(h), 12 + f, h
    if inside_d > 0:
        if k_best < 12:
            ea, eab = PRISM_EA + 3 * k_best, PRISM_EAB + 3 * k_best
            for i in range(3):
                n[i] = p[i] - (prm[ea + i] + t_best * prm[eab + i])
        else:
            fn = PRISM_FN + 3 * (k_best - 12)
            for i in range(3):
                n[i] = h_best * prm[fn + i]      # p - (p - h fn)
        _normalise(n)
        d = best
    else:
        for i in range(3):
            n[i] = prm[PRISM_NORMALS + 3 * j_in + i]
        d = inside_d
        k_best = 12
    if not hess:
        return d
    H[:, :] = 0.0
    if k_best < 12:
        eab = PRISM_EAB + 3 * k_best
        la = max(math.sqrt(prm[eab] ** 2 + prm[eab + 1] ** 2 + prm[eab + 2] ** 2), 1e-300)
        line = 1.0 if 0.0 < t_best < 1.0 else 0.0
        den = max(d, DIST_FLOOR)
        for i in range(3):
            for j in range(3):
                H[i, j] = (((1.0 if i == j else 0.0) - n[i] * n[j])
                           - line * ((prm[eab + i] / la) * (prm[eab + j] / la))) / den
    return d


@_kernel
def _sdf_local(kind, prm, p, hess, n, H):
    if kind == CYLINDER:
        return _cylinder(prm, p, hess, n, H)
    if kind == RING:
        return _ring(prm, p, hess, n, H)
    if kind == PRISM:
        return _prism(prm, p, hess, n, H)
    if kind == SPHERE:
        return _sphere(prm, p, hess, n, H)
    return _plane(prm, p, hess, n, H)


@_kernel
def _sdf_world(kind, prm, pose, p, hess, n, H, scratch):
    """Return the distance at world point p; world gradient into n, Hessian into H."""
    pl, nl, Hl = scratch[0], scratch[1], scratch[2:5]
    for j in range(3):
        pl[j] = ((p[0] - pose[0, 3]) * pose[0, j] + (p[1] - pose[1, 3]) * pose[1, j]) \
            + (p[2] - pose[2, 3]) * pose[2, j]
    d = _sdf_local(kind, prm, pl, hess, nl, Hl)
    for i in range(3):
        n[i] = (nl[0] * pose[i, 0] + nl[1] * pose[i, 1]) + nl[2] * pose[i, 2]
    if hess:
        for i in range(3):
            for j in range(3):
                s = 0.0
                for a in range(3):
                    for b in range(3):
                        s += pose[i, a] * Hl[a, b] * pose[j, b]
                H[i, j] = s
    return d


@_kernel
def sdf_points(kind, prm, pose, pts, hess):
    """
    Return distances (P,), unit gradients (P, 3) and Hessians (P, 3, 3) at world points.

    One obstacle; the Hessians are empty unless ``hess``.
    """
    P = pts.shape[0]
    d = np.empty(P)
    n = np.empty((P, 3))
    H = np.zeros((P if hess else 0, 3, 3))
    Hd = np.empty((3, 3))
    scratch = np.empty((5, 3))
    for i in range(P):
        d[i] = _sdf_world(kind, prm, pose, pts[i], hess, n[i], H[i] if hess else Hd, scratch)
    return d, n, H


@_kernel
def least_gap(kinds, prms, poses, pts, radii):
    """Return the least ``distance - radius`` of points (P, 3) over all obstacles."""
    n = np.empty(3)
    H = np.empty((3, 3))
    scratch = np.empty((5, 3))
    best = np.inf
    for o in range(kinds.shape[0]):
        for i in range(pts.shape[0]):
            best = min(best, _sdf_world(kinds[o], prms[o], poses[o], pts[i], False, n, H,
                                        scratch) - radii[i])
    return best


# -- contact -------------------------------------------------------------------------------
class PenaltyParams(NamedTuple):
    """Numbers of the penalty contact law (contact.py documents each)."""

    stiffness: float         # k (N/m)
    smoothing: float         # delta (m)
    stiffening: float        # p0 (m)
    cutoff: float            # force-free beyond this gap (m)
    near: float              # refine critical points of gaps below this (m)
    samples: int             # gap samples per node interval
    step_depth: float        # a Newton step may press a node this deep (m)


@_kernel
def _tube_radius(tab, X):
    return tab.radii[_locate(tab, X)[0]]


@_kernel
def _sample_gaps(tab, q, g_nodes, kind, prm, pose, law, node_gap, node_slope, w):
    """
    Return the sample abscissae, gaps and gap slopes along the backbone for one obstacle.

    Samples are the nodes and ``law.samples - 1`` points inside each node interval, on the
    exact rod (a Magnus step from the interval's first node). An interval whose nodes are
    so far that no point between can be near is not sampled (gap +inf, slope +1).
    """
    N = tab.node_X.shape[0]
    sub = law.samples
    S = (N - 1) * sub + 1
    Xs = np.empty(S)
    gap = np.empty(S)
    slope = np.empty(S)
    n = np.empty(3)
    H = np.empty((3, 3))
    scratch = np.empty((5, 3))
    xi = np.empty(6)
    p = np.empty(3)
    spread = tab.radii.max() - tab.radii.min()
    for i in range(N):
        Xs[min(i * sub, S - 1)] = tab.node_X[i]
        gap[min(i * sub, S - 1)] = node_gap[i]
        slope[min(i * sub, S - 1)] = node_slope[i]
    for i in range(N - 1):
        h = tab.node_X[i + 1] - tab.node_X[i]
        far = min(node_gap[i], node_gap[i + 1]) - FAR_CUT_SLACK * h - spread > law.near
        seg = tab.int_seg[i]
        for s in range(1, sub):
            k = i * sub + s
            Xs[k] = tab.node_X[i] + h * (s / sub)
            if far:
                gap[k], slope[k] = np.inf, 1.0
                continue
            hk = Xs[k] - tab.node_X[i]
            _magnus(tab, q, seg, tab.int_a[i], hk, False, w)
            _pose_mul(g_nodes[i], w.E, w.G)
            _strain(tab, q, seg, tab.int_a[i] + hk, w.P1, xi)
            for r in range(3):
                p[r] = w.G[r, 3]
            d = _sdf_world(kind, prm, pose, p, False, n, H, scratch)
            gap[k] = d - _tube_radius(tab, Xs[k])
            sl = 0.0
            for r in range(3):
                sl += n[r] * (w.G[r, 0] * xi[3] + w.G[r, 1] * xi[4] + w.G[r, 2] * xi[5])
            slope[k] = sl
    return Xs, gap, slope


@_kernel
def _gap_derivatives(tab, q, g_nodes, iv, X, kind, prm, pose, w, n, H, scratch):
    """Return (d gap/dX, d2 gap/dX2) at X in node interval iv (strain-based p'')."""
    xi = w.x2
    _magnus(tab, q, tab.int_seg[iv], tab.int_a[iv], X - tab.node_X[iv], False, w)
    _pose_mul(g_nodes[iv], w.E, w.G)
    _strain(tab, q, tab.int_seg[iv], tab.int_a[iv] + X - tab.node_X[iv], w.P1, xi)
    p = scratch[5]
    for r in range(3):
        p[r] = w.G[r, 3]
    _sdf_world(kind, prm, pose, p, True, n, H, scratch)
    t, kv = w.t, w.kv
    _cross(xi[:3], xi[3:], kv)
    d1, d2n = 0.0, 0.0
    for r in range(3):
        t[r] = w.G[r, 0] * xi[3] + w.G[r, 1] * xi[4] + w.G[r, 2] * xi[5]
        d1 += n[r] * t[r]
        d2n += n[r] * (w.G[r, 0] * kv[0] + w.G[r, 1] * kv[1] + w.G[r, 2] * kv[2])
    tHt = 0.0
    for r in range(3):
        for c in range(3):
            tHt += t[r] * H[r, c] * t[c]
    return d1, tHt + d2n


@_kernel
def _refine(tab, q, g_nodes, iv, lo, hi, sa, sb, sign, kind, prm, pose, w):
    """
    Return the critical point of the gap in [lo, hi] (a sign change of its slope).

    Safeguarded Newton on the exact rod, bisection where a step would leave the bracket.
    """
    n = np.empty(3)
    H = np.empty((3, 3))
    scratch = np.empty((6, 3))
    frac = sa / (sa - sb) if sa != sb else 0.5
    x = min(max(lo + (hi - lo) * frac, lo), hi)
    for _ in range(60):
        d1, d2 = _gap_derivatives(tab, q, g_nodes, iv, x, kind, prm, pose, w, n, H, scratch)
        if sign * d1 < 0:
            lo = x
        else:
            hi = x
        ok = sign * d2 > CURVE_FLOOR
        newton = x - d1 / d2 if ok else x
        ok = ok and lo <= newton <= hi
        xn = newton if ok else 0.5 * (lo + hi)
        done = (ok and abs(xn - x) < ABSCISSA_STEP_M) or hi - lo < BRACKET_M
        x = xn
        if done:
            break
    return x


@_kernel
def _find(tab, q, g_nodes, kinds, prms, poses, law, node_gap, node_normal):
    """
    Return the gap's critical points near the obstacles: arc lengths, obstacle, sign.

    sign +1: a minimum (or the tip when the gap falls towards it), -1: an interior
    maximum. Brackets come from sign changes of the exact gap slope at the samples, so the
    result depends on q only. Fills the node gaps and normals on the way.
    """
    N = tab.node_X.shape[0]
    n_obj = kinds.shape[0]
    sub = law.samples
    S = (N - 1) * sub + 1
    L = tab.offsets[-1]
    w = _work(tab.n_modes, tab.n_modes * tab.comps.shape[0])
    cand_X = np.empty(n_obj * (S + 1))
    cand_o = np.empty(n_obj * (S + 1), dtype=np.int64)
    cand_s = np.empty(n_obj * (S + 1))
    nc = 0
    H = np.empty((3, 3))
    scratch = np.empty((5, 3))
    xi = np.empty(6)
    P = np.empty(tab.n_modes)
    slope_n = np.empty(N)
    p = np.empty(3)
    for o in range(n_obj):
        for i in range(N):
            for r in range(3):
                p[r] = g_nodes[i, r, 3]
            d = _sdf_world(kinds[o], prms[o], poses[o], p, False, node_normal[o, i], H, scratch)
            node_gap[o, i] = d - _tube_radius(tab, tab.node_X[i])
            seg = tab.node_seg[i]
            _strain(tab, q, seg, tab.node_X[i] - tab.offsets[seg], P, xi)
            sl = 0.0
            for r in range(3):
                sl += node_normal[o, i, r] * (g_nodes[i, r, 0] * xi[3] + g_nodes[i, r, 1] * xi[4]
                                              + g_nodes[i, r, 2] * xi[5])
            slope_n[i] = sl
        Xs, gap, slope = _sample_gaps(tab, q, g_nodes, kinds[o], prms[o], poses[o], law,
                                      node_gap[o], slope_n, w)
        for k in range(S - 1):
            if min(gap[k], gap[k + 1]) >= law.near:
                continue
            up_a, up_b = slope[k] >= 0, slope[k + 1] >= 0
            if up_a == up_b:
                continue
            sign = 1.0 if up_b else -1.0
            cand_X[nc] = _refine(tab, q, g_nodes, k // sub, Xs[k], Xs[k + 1], slope[k],
                                 slope[k + 1], sign, kinds[o], prms[o], poses[o], w)
            cand_o[nc], cand_s[nc] = o, sign
            nc += 1
        if slope[S - 1] < 0 and gap[S - 1] < law.near:
            cand_X[nc], cand_o[nc], cand_s[nc] = L, o, 1.0
            nc += 1
    return cand_X[:nc], cand_o[:nc], cand_s[:nc]


@_kernel
def _softplus(x):
    return x if x > 30 else math.log1p(math.exp(min(x, 30.0)))


@_kernel
def penalty_contacts(tab, q, g_nodes, J_nodes, kinds, prms, poses, law):
    """
    Return the contact points and their loads for the kernel-side arrays of contact.py.

    Returns (X, obstacle, sign, gap, backbone point, normal, force, radius, pose, Jacobian,
    generalised force Q, tangent part Kc, step rows A, step lower bounds lo, node gaps).
    ``Kc`` holds the material term ``-D^T df/dp D`` and the sliding of each contact point
    (a critical point of the gap over X: ``lambda gXq^T gXq / gXX``); the geometric
    (dead-load) part comes with the other point loads in :func:`geometric_stiffness`.
    """
    N = tab.node_X.shape[0]
    n_obj = kinds.shape[0]
    n = q.shape[0]
    L = tab.offsets[-1]
    node_gap = np.empty((n_obj, N))
    node_normal = np.empty((n_obj, N, 3))
    cX, co, cs = _find(tab, q, g_nodes, kinds, prms, poses, law, node_gap, node_normal)
    C = cX.shape[0]
    keep = np.zeros(C, dtype=np.bool_)
    w = _work(tab.n_modes, tab.n_modes * tab.comps.shape[0])
    g = np.empty((C, 4, 4))
    J = np.zeros((C, 6, n))
    gap = np.empty(C)
    nrm = np.empty((C, 3))
    f = np.empty((C, 3))
    rad = np.empty(C)
    Q = np.zeros(n)
    Kc = np.zeros((n, n))
    grad = np.zeros((C, n))
    H = np.empty((3, 3))
    scratch = np.empty((5, 3))
    xi = np.empty(6)
    P = np.empty(tab.n_modes)
    D = np.empty((3, n))
    p = np.empty(3)
    tv, pp, Htv, kv, nb = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    dfdp = np.empty((3, 3))
    gxq = np.empty(n)
    tmp = np.empty((3, n))
    nm, ncomp = tab.n_modes, tab.comps.shape[0]
    for c in range(C):
        X = cX[c]
        _point_frame(tab, q, g_nodes, J_nodes, X, True, w, g[c], J[c])
        seg, xloc = _locate(tab, X)
        _strain(tab, q, seg, xloc, P, xi)
        for r in range(3):
            p[r] = g[c, r, 3]
        d = _sdf_world(kinds[co[c]], prms[co[c]], poses[co[c]], p, True, nrm[c], H, scratch)
        rad[c] = tab.radii[seg]
        gap[c] = d - rad[c]
        if gap[c] > law.cutoff:
            continue
        keep[c] = True
        sign = cs[c]
        R = g[c, :3, :3]
        _cross(xi[:3], xi[3:], kv)
        for r in range(3):
            tv[r] = R[r, 0] * xi[3] + R[r, 1] * xi[4] + R[r, 2] * xi[5]
            pp[r] = R[r, 0] * kv[0] + R[r, 1] * kv[1] + R[r, 2] * kv[2]
        gxx = 0.0
        for r in range(3):
            Htv[r] = H[r, 0] * tv[0] + H[r, 1] * tv[1] + H[r, 2] * tv[2]
        for r in range(3):
            gxx += tv[r] * Htv[r]
        for r in range(3):
            gxx += nrm[c, r] * pp[r]
        z = -gap[c] / law.smoothing
        pen = law.smoothing * _softplus(z)
        force = law.stiffness * pen * (1.0 + pen / law.stiffening)
        dforce = -law.stiffness * 0.5 * (1.0 + math.tanh(0.5 * z)) \
            * (1.0 + 2.0 * pen / law.stiffening)
        for r in range(3):
            f[c, r] = sign * force * nrm[c, r]
            for s in range(3):
                dfdp[r, s] = sign * dforce * nrm[c, r] * nrm[c, s] + sign * force * H[r, s]
        # D = R J_v: the world motion of the backbone point per dq.
        for r in range(3):
            for col in range(n):
                D[r, col] = R[r, 0] * J[c, 3, col] + R[r, 1] * J[c, 4, col] \
                    + R[r, 2] * J[c, 5, col]
        for col in range(n):
            s = 0.0
            for r in range(3):
                s += nrm[c, r] * D[r, col]
            grad[c, col] = s
            s = 0.0
            for r in range(3):
                s += f[c, r] * D[r, col]
            Q[col] += s
        for a in range(n):
            for r in range(3):
                u = 0.0
                for s in range(3):
                    u += D[s, a] * dfdp[s, r]
                if u != 0.0:
                    for b in range(n):
                        Kc[a, b] -= u * D[r, b]
        if X < L - TIP_GUARD_M and sign * gxx > SLIDE_FLOOR:
            # gXq = (H p')^T D + n^T d p'/dq, d p'/dq = R (-nu^ J_w + Phi_nu).
            for r in range(3):
                nb[r] = R[0, r] * nrm[c, 0] + R[1, r] * nrm[c, 1] + R[2, r] * nrm[c, 2]
            for col in range(n):
                w0, w1, w2 = J[c, 0, col], J[c, 1, col], J[c, 2, col]
                tmp[0, col] = -(xi[4] * w2 - xi[5] * w1)
                tmp[1, col] = -(xi[5] * w0 - xi[3] * w2)
                tmp[2, col] = -(xi[3] * w1 - xi[4] * w0)
            for ci in range(ncomp):
                comp = tab.comps[ci]
                if comp >= 3:
                    for j in range(nm):
                        tmp[comp - 3, seg * nm * ncomp + ci * nm + j] += P[j]
            for col in range(n):
                s = 0.0
                for r in range(3):
                    s += Htv[r] * D[r, col] + nb[r] * tmp[r, col]
                gxq[col] = s
            coef = sign * force / gxx
            for a in range(n):
                u = coef * gxq[a]
                for b in range(n):
                    Kc[a, b] += u * gxq[b]
    idx = np.nonzero(keep)[0]
    # Step rows: each contact (ridges aside) may press to step_depth or twice its depth,
    # each node now outside at most step_depth in (linearised gaps).
    rows = 0
    for c in idx:
        if cs[c] > 0:
            rows += 1
    for o in range(n_obj):
        for i in range(N):
            if node_gap[o, i] > 0:
                rows += 1
    A = np.empty((rows, n))
    lo = np.empty(rows)
    r = 0
    for c in idx:
        if cs[c] > 0:
            A[r] = grad[c]
            lo[r] = min(2.0 * gap[c], -law.step_depth) - gap[c]
            r += 1
    for o in range(n_obj):
        for i in range(N):
            if node_gap[o, i] > 0:
                for col in range(n):
                    s = 0.0
                    for a in range(3):
                        s += node_normal[o, i, a] * (g_nodes[i, a, 0] * J_nodes[i, 3, col]
                                                     + g_nodes[i, a, 1] * J_nodes[i, 4, col]
                                                     + g_nodes[i, a, 2] * J_nodes[i, 5, col])
                    A[r, col] = s
                lo[r] = -law.step_depth - node_gap[o, i]
                r += 1
    pts = np.empty((idx.shape[0], 3))
    for a in range(idx.shape[0]):
        pts[a] = g[idx[a], :3, 3]
    return (cX[idx], co[idx], cs[idx], gap[idx], pts, nrm[idx], f[idx], rad[idx], g[idx],
            J[idx], Q, Kc, A, lo, node_gap)


# -- loads ---------------------------------------------------------------------------------
@_kernel
def wrench_residual(g, J, idx, f, m):
    """
    Return (sum_i J_i^T [R_i^T m_i; R_i^T f_i], sum_i f_i . p_i) over the frames ``idx``.

    The generalised force of dead world forces and moments at points (and their work, the
    negative of their potential for forces).
    """
    n = J.shape[2]
    Q = np.zeros(n)
    work = 0.0
    W = np.empty(6)
    for a in range(idx.shape[0]):
        i = idx[a]
        for r in range(3):
            W[r] = g[i, 0, r] * m[a, 0] + g[i, 1, r] * m[a, 1] + g[i, 2, r] * m[a, 2]
            W[3 + r] = g[i, 0, r] * f[a, 0] + g[i, 1, r] * f[a, 1] + g[i, 2, r] * f[a, 2]
            work += f[a, r] * g[i, r, 3]
        for col in range(n):
            s = 0.0
            for r in range(6):
                s += J[i, r, col] * W[r]
            Q[col] += s
    return Q, work


@_kernel
def _wrench_rate(g, J, F, M, dM, out):
    """
    Write d(internal wrench)/dq (6, n) at frame g, J for distal dead loads F, M.

    F, M: world force and moment about the origin, dM the moment's derivative. The wrench
    [R^T (M - p x F); R^T F]: its angular part turns with R and moves with p.
    """
    p0, p1, p2 = g[0, 3], g[1, 3], g[2, 3]
    a0 = M[0] - (p1 * F[2] - p2 * F[1])
    a1 = M[1] - (p2 * F[0] - p0 * F[2])
    a2 = M[2] - (p0 * F[1] - p1 * F[0])
    ra0 = g[0, 0] * a0 + g[1, 0] * a1 + g[2, 0] * a2      # R^T a
    ra1 = g[0, 1] * a0 + g[1, 1] * a1 + g[2, 1] * a2
    ra2 = g[0, 2] * a0 + g[1, 2] * a1 + g[2, 2] * a2
    rf0 = g[0, 0] * F[0] + g[1, 0] * F[1] + g[2, 0] * F[2]  # R^T F
    rf1 = g[0, 1] * F[0] + g[1, 1] * F[1] + g[2, 1] * F[2]
    rf2 = g[0, 2] * F[0] + g[1, 2] * F[1] + g[2, 2] * F[2]
    for col in range(J.shape[1]):
        w0, w1, w2 = J[0, col], J[1, col], J[2, col]
        d0 = g[0, 0] * J[3, col] + g[0, 1] * J[4, col] + g[0, 2] * J[5, col]   # R J_v
        d1 = g[1, 0] * J[3, col] + g[1, 1] * J[4, col] + g[1, 2] * J[5, col]
        d2 = g[2, 0] * J[3, col] + g[2, 1] * J[4, col] + g[2, 2] * J[5, col]
        u0 = dM[0, col] + (F[1] * d2 - F[2] * d1)          # dM + F x D
        u1 = dM[1, col] + (F[2] * d0 - F[0] * d2)
        u2 = dM[2, col] + (F[0] * d1 - F[1] * d0)
        out[0, col] = (ra1 * w2 - ra2 * w1) + (g[0, 0] * u0 + g[1, 0] * u1 + g[2, 0] * u2)
        out[1, col] = (ra2 * w0 - ra0 * w2) + (g[0, 1] * u0 + g[1, 1] * u1 + g[2, 1] * u2)
        out[2, col] = (ra0 * w1 - ra1 * w0) + (g[0, 2] * u0 + g[1, 2] * u1 + g[2, 2] * u2)
        out[3, col] = rf1 * w2 - rf2 * w1
        out[4, col] = rf2 * w0 - rf0 * w2
        out[5, col] = rf0 * w1 - rf1 * w0


@_kernel
def _wrench(g, F, M, out):
    """Write the body internal wrench [R^T (M - p x F); R^T F] at frame g into out (6,)."""
    p0, p1, p2 = g[0, 3], g[1, 3], g[2, 3]
    a0 = M[0] - (p1 * F[2] - p2 * F[1])
    a1 = M[1] - (p2 * F[0] - p0 * F[2])
    a2 = M[2] - (p0 * F[1] - p1 * F[0])
    for i in range(3):
        out[i] = g[0, i] * a0 + g[1, i] * a1 + g[2, i] * a2
        out[3 + i] = g[0, i] * F[0] + g[1, i] * F[1] + g[2, i] * F[2]


@_kernel
def _moment_rate(g, J, f, out):
    """Write d(p x f)/dq = -f^ R J_v (3, n) for a dead force f at frame g into out."""
    for col in range(J.shape[1]):
        D0 = g[0, 0] * J[3, col] + g[0, 1] * J[4, col] + g[0, 2] * J[5, col]
        D1 = g[1, 0] * J[3, col] + g[1, 1] * J[4, col] + g[1, 2] * J[5, col]
        D2 = g[2, 0] * J[3, col] + g[2, 1] * J[4, col] + g[2, 2] * J[5, col]
        out[0, col] = -(-f[2] * D1 + f[1] * D2)
        out[1, col] = -(f[2] * D0 - f[0] * D2)
        out[2, col] = -(-f[1] * D0 + f[0] * D1)


@_kernel
def geometric_stiffness(tab, q, g_nodes, J_nodes, grav_f, pt_X, pt_g, pt_J, pt_f, pt_m,
                        pt_quad):
    """
    Return (Qp, Kg): point loads in quadrature form, and the geometric stiffness of all loads.

    ``Kg = d/dq sum_k w_k Phi_k^T Lambda_k``, Lambda the internal wrench at each Gauss point
    from everything distal (dead loads: gravity ``grav_f`` (K, 3) at the Gauss points, and
    the point forces/moments ``pt_*``). Lambda is smooth between load points, so each point
    load's own segment is integrated by a Gauss rule on [segment start, X] and the segments
    before it on the regular points: ``Qp = int_0^X Phi^T Lambda dX``, the continuum virtual
    work, exact for a constant internal wrench (pure moment, tendon) at any basis order.
    Qp covers the points flagged in ``pt_quad``; Kg all loads.
    """
    n = q.shape[0]
    K = tab.gauss_X.shape[0]
    G = tab.rule_x.shape[0]
    Fb = np.zeros((K + 1, 3))
    Mb = np.zeros((K + 1, 3))
    dMb = np.zeros((K + 1, 3, n))
    Fp = np.zeros((K + 1, 3))
    Mp = np.zeros((K + 1, 3))
    Kg = np.zeros((n, n))
    Qp = np.zeros(n)
    w = _work(tab.n_modes, tab.n_modes * tab.comps.shape[0])
    P = np.empty(tab.n_modes)
    fm = np.empty(3)
    dfm = np.empty((3, n))
    dl = np.empty((6, n))
    lam = np.empty(6)
    gq = np.empty((4, 4))
    Jq = np.empty((6, n))
    for j in range(grav_f.shape[0]):
        node = tab.gauss_node[j]
        _cross(g_nodes[node, :3, 3], grav_f[j], fm)
        _moment_rate(g_nodes[node], J_nodes[node], grav_f[j], dfm)
        Fb[j + 1] += grav_f[j]
        Mb[j + 1] += fm
        dMb[j + 1] += dfm
    for i in range(pt_X.shape[0]):
        _cross(pt_g[i, :3, 3], pt_f[i], fm)
        fm += pt_m[i]
        _moment_rate(pt_g[i], pt_J[i], pt_f[i], dfm)
        seg, x = _locate(tab, pt_X[i])
        start = tab.offsets[seg]
        b = np.searchsorted(tab.gauss_X, start - 1e-15, side='right')
        if x > 0.0:
            for k in range(G):
                Xq = start + x * (tab.rule_x[k] + 1) / 2
                wq = x * tab.rule_w[k] / 2
                _point_frame(tab, q, g_nodes, J_nodes, Xq, True, w, gq, Jq)
                _legendre(2.0 * (Xq - start) / tab.seg_len[seg] - 1.0, P)
                _wrench_rate(gq, Jq, pt_f[i], fm, dfm, dl)
                _add_phi_t(tab, seg, P, wq, dl, Kg)
                if pt_quad[i]:
                    _wrench(gq, pt_f[i], fm, lam)
                    _add_phi_t_vec(tab, seg, P, wq, lam, Qp)
        if pt_quad[i]:
            Fp[b] += pt_f[i]
            Mp[b] += fm
        Fb[b] += pt_f[i]
        Mb[b] += fm
        dMb[b] += dfm
    # Gauss point k collects every load in bins > k (strictly distal).
    F = np.zeros(3)
    M = np.zeros(3)
    dM = np.zeros((3, n))
    Fq = np.zeros(3)
    Mq = np.zeros(3)
    for k in range(K - 1, -1, -1):
        F += Fb[k + 1]
        M += Mb[k + 1]
        dM += dMb[k + 1]
        Fq += Fp[k + 1]
        Mq += Mp[k + 1]
        node, seg = tab.gauss_node[k], tab.gauss_seg[k]
        _legendre(2.0 * (tab.gauss_X[k] - tab.offsets[seg]) / tab.seg_len[seg] - 1.0, P)
        _wrench_rate(g_nodes[node], J_nodes[node], F, M, dM, dl)
        _add_phi_t(tab, seg, P, tab.gauss_w[k], dl, Kg)
        _wrench(g_nodes[node], Fq, Mq, lam)
        _add_phi_t_vec(tab, seg, P, tab.gauss_w[k], lam, Qp)
    return Qp, Kg


@_kernel
def tendon_terms(tab, xi_gauss, td_d, td_on, tension):
    """
    Return (Q, dQ/dq, energy) of thread-like tendons; slack (negative) tensions pull nothing.

    A tendon at body offset d runs along ``v = nu + k x d``; its wrench on the section is
    ``-T [d x t; t]``, t = v / |v|, and its potential T times its length.
    """
    n = tab.n_modes * tab.comps.shape[0] * tab.seg_len.shape[0]
    Q = np.zeros(n)
    dQ = np.zeros((n, n))
    energy = 0.0
    P = np.empty(tab.n_modes)
    v = np.empty(3)
    t = np.empty(3)
    lam = np.empty(6)
    dlam = np.empty((6, 6))
    Bm = np.empty((6, 3))
    Pm = np.empty((3, 3))
    Cm = np.empty((3, 6))
    BP = np.empty((6, 3))
    BPC = np.empty((6, 6))
    dh = np.empty((3, 3))
    tmp = np.empty((6, n))
    dxt = np.empty(3)
    nm, nc = tab.n_modes, tab.comps.shape[0]
    for k in range(xi_gauss.shape[0]):
        xi = xi_gauss[k]
        seg = tab.gauss_seg[k]
        lam[:] = 0.0
        dlam[:, :] = 0.0
        for a in range(td_d.shape[0]):
            T = max(tension[a], 0.0) * td_on[k, a]
            d = td_d[a]
            _cross(xi[:3], d, v)
            for i in range(3):
                v[i] += xi[3 + i]
            nv = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            for i in range(3):
                t[i] = v[i] / nv
            _cross(d, t, dxt)
            for i in range(3):
                lam[i] -= T * dxt[i]
                lam[3 + i] -= T * t[i]
            energy += tab.gauss_w[k] * T * nv
            # d lam / d xi = -T [d^; I] (I - t t^T) / |v| [-d^, I]
            _skew(d, dh)
            for i in range(3):
                for j in range(3):
                    Bm[i, j] = dh[i, j]
                    Bm[3 + i, j] = 1.0 if i == j else 0.0
                    Pm[i, j] = ((1.0 if i == j else 0.0) - t[i] * t[j]) / nv
                    Cm[i, j] = -dh[i, j]
                    Cm[i, 3 + j] = 1.0 if i == j else 0.0
            _matmul(Bm, Pm, BP)
            _matmul(BP, Cm, BPC)
            for i in range(6):
                for j in range(6):
                    dlam[i, j] -= T * BPC[i, j]
        _legendre(2.0 * (tab.gauss_X[k] - tab.offsets[seg]) / tab.seg_len[seg] - 1.0, P)
        _add_phi_t_vec(tab, seg, P, tab.gauss_w[k], lam, Q)
        # dQ += w Phi^T dlam Phi: dlam Phi first (6, n), then Phi^T.
        tmp[:, :] = 0.0
        for ci in range(nc):
            c = tab.comps[ci]
            for j in range(nm):
                col = seg * nm * nc + ci * nm + j
                for r in range(6):
                    tmp[r, col] = dlam[r, c] * P[j]
        _add_phi_t(tab, seg, P, tab.gauss_w[k], tmp, dQ)
    return Q, dQ, energy
