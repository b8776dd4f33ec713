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

Style, for compile time and speed alike: plain loops over small arrays (no fancy indexing,
no ``@``, no whole-array arithmetic: each numpy feature used here costs seconds of
compilation), and hot helpers that take scalars and few arrays (every array passed to a
function that is not inlined costs a reference-count pair, ~10 ns). Twists and wrenches are
6-vectors with the angular part first (SoRoSim order), poses 4x4. The strain basis is sparse
(a point of segment ``s`` touches only that segment's columns of ``q``), so the kernels loop
over (component, mode) pairs instead of multiplying dense ``Phi`` matrices.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from numba import njit
import numpy as np


def _jit(fn, **kw):
    """
    Compile ``fn`` on first use with numpy's float semantics, its machine code cached on disk.

    The cache goes beside this file (``__pycache__``), else to numba's user cache
    (``NUMBA_CACHE_DIR`` or ``~/.cache``); with no writable place at all numba refuses to
    cache and each process compiles for itself (~30 s of CPU for all kernels).
    """
    try:
        return njit(cache=True, error_model='numpy', **kw)(fn)
    except RuntimeError:        # "cannot cache function ...: no locator available"
        return njit(cache=False, error_model='numpy', **kw)(fn)


def _kernel(fn):
    return _jit(fn)


def _inline(fn):
    """Compile ``fn`` into each caller (the hot Magnus step: no call overhead)."""
    return _jit(fn, inline='always')


SMALL_ANGLE2 = 1e-4     # exp/dexp coefficients from their series below 0.01 rad (error < 1e-17)
Z1 = 0.5 - math.sqrt(3.0) / 6.0      # Zanna points of the 4th-order Magnus step
Z2 = 0.5 + math.sqrt(3.0) / 6.0
C4 = math.sqrt(3.0) / 12.0
PIVOT_FLOOR = 0.0       # a Cholesky pivot at or below this: not positive definite
SHIFT_START = 1e-4      # the first tangent shift tried (x diag K) where it is not PD ...
SHIFT_RELAX = 0.1       # ... or a tenth of the last one used ...
SHIFT_GROWTH = 10.0     # ... growing tenfold until the Cholesky succeeds
SOFTPLUS_LINEAR = 30.0  # softplus(z) = z beyond this (to 1e-13)
QP_ROUNDOFF = -1e-13    # a step QP violation above this is round-off (a row duplicating another)
CURVE_FLOOR = 1e-12     # |d2 gap / dX2| below this: no Newton step on the contact abscissa
SLIDE_FLOOR = 1e-9      # ... below this: the contact point's sliding term is left out
ABSCISSA_STEP_M = 1e-10  # a Newton step on the contact abscissa this short has converged
BRACKET_M = 1e-13       # a bracket this narrow has converged
REFINE_STEPS = 60       # steps on a contact abscissa at most (60 halvings: 1e-18 m)
TIP_GUARD_M = 1e-12     # a contact this close to the tip is the tip (it does not slide)
# An interval is sampled unless the cubic through its nodes' gaps and gap slopes stays this
# far beyond ``near``: on smooth profiles that cubic is within microns of the gap, and the
# margin covers a prism's edges (where the gap is only once differentiable).
CULL_MARGIN_M = 1e-3
DIST_FLOOR = 1e-12      # distances below this in a curvature denominator (m)
NORM_FLOOR = 1e-300     # vectors shorter than this normalise to zero
LOCATE_EPS_M = 1e-15    # a point load this close past a segment start belongs to it

# Obstacle kinds and the layout of their parameter rows (objects.py packs them).
PLANE, SPHERE, CYLINDER, RING, PRISM = 0, 1, 2, 3, 4
PRISM_NORMALS, PRISM_OFFSETS, PRISM_EA, PRISM_EAB = 0, 18, 24, 60
PRISM_EAB2, PRISM_EA_EAB, PRISM_EA2, PRISM_FPROJ = 96, 108, 120, 132
PRISM_FA_AB, PRISM_FN, PRISM_FN_A, PRISM_PARAMS = 168, 180, 198, 204
# Columns of penalty_contacts' per-contact rows.
C_X, C_OBJ, C_SIGN, C_GAP, C_P, C_N, C_F, C_RAD, C_COLS = 0, 1, 2, 3, 4, 7, 10, 13, 14


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


# Kernels take the tables packed into one float and one int array (:func:`pack_tables`) and
# unpack them into a tuple of views read by these indices: numba types array arguments in C
# but a tuple or NamedTuple of arrays element by element in Python at every call (~10 us
# per call on numba 0.58, Ubuntu 24.04's).
(T_SEG_LEN, T_OFFSETS, T_RADII, T_COMPS, T_N_MODES, T_BASE, T_NODE_X, T_NODE_SEG, T_INT_SEG,
 T_INT_A, T_INT_H, T_GAUSS_X, T_GAUSS_NODE, T_GAUSS_SEG, T_GAUSS_W, T_RULE_X,
 T_RULE_W) = range(17)
assert RodTables._fields[T_RULE_W] == 'rule_w' and RodTables._fields[T_NODE_X] == 'node_X'
_FLOATS = ('seg_len', 'offsets', 'radii', 'base', 'node_X', 'int_a', 'int_h', 'gauss_X',
           'gauss_w', 'rule_x', 'rule_w')
_INTS = ('comps', 'node_seg', 'int_seg', 'gauss_node', 'gauss_seg')


def pack_tables(t: RodTables) -> tuple:
    """Return (tf, ti): the tables as one float64 and one int64 array (see _unpack)."""
    S, C, N, K, G = len(t.seg_len), len(t.comps), len(t.node_X), len(t.gauss_X), len(t.rule_x)
    ints = [np.asarray(getattr(t, k)).ravel() for k in _INTS]
    ti = np.concatenate([[S, t.n_modes, C, N, K, G]] + ints).astype(np.int64)
    tf = np.concatenate([np.asarray(getattr(t, k), dtype=float).ravel() for k in _FLOATS])
    return tf, ti


@_kernel
def _unpack(tf, ti):
    """Return the tables as the tuple the kernels index with T_* (views into tf and ti)."""
    S, nm, C, N, K, G = ti[0], ti[1], ti[2], ti[3], ti[4], ti[5]
    M = N - 1
    i = 6
    comps = ti[i:i + C]
    i += C
    node_seg = ti[i:i + N]
    i += N
    int_seg = ti[i:i + M]
    i += M
    gauss_node = ti[i:i + K]
    i += K
    gauss_seg = ti[i:i + K]
    f = 0
    seg_len = tf[f:f + S]
    f += S
    offsets = tf[f:f + S + 1]
    f += S + 1
    radii = tf[f:f + S]
    f += S
    base = tf[f:f + 16].reshape((4, 4))
    f += 16
    node_X = tf[f:f + N]
    f += N
    int_a = tf[f:f + M]
    f += M
    int_h = tf[f:f + M]
    f += M
    gauss_X = tf[f:f + K]
    f += K
    gauss_w = tf[f:f + K]
    f += K
    rule_x = tf[f:f + G]
    f += G
    rule_w = tf[f:f + G]
    return (seg_len, offsets, radii, comps, nm, base, node_X, node_seg, int_seg, int_a, int_h,
            gauss_X, gauss_node, gauss_seg, gauss_w, rule_x, rule_w)


# -- small dense algebra -------------------------------------------------------------------
@_kernel
def abs_max(a):
    """Return max |a_i| (0 for an empty array, NaN if any is NaN)."""
    m = 0.0
    for i in range(a.shape[0]):
        v = abs(a[i])
        if v != v:
            return v
        m = max(m, v)
    return m


@_kernel
def weighted_norm(r, kdiag):
    """Return sqrt(sum r_i^2 / k_i): the residual norm in the stiffness metric."""
    s = 0.0
    for i in range(r.shape[0]):
        s += r[i] * r[i] / kdiag[i]
    return math.sqrt(s)


@_kernel
def largest_motion(J, dq):
    """Return the largest backbone displacement |J_v dq| over the nodes (to first order)."""
    best = 0.0
    for k in range(J.shape[0]):
        s = 0.0
        for r in range(3, 6):
            v = 0.0
            for c in range(dq.shape[0]):
                v += J[k, r, c] * dq[c]
            s += v * v
        best = max(best, math.sqrt(s))
    return best


@_kernel
def _dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@_kernel
def _bisect_right(a, x):
    """Return the number of entries of the sorted array a that are <= x."""
    lo, hi = 0, a.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if x < a[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


@_kernel
def _bisect_left(a, x):
    """Return the number of entries of the sorted array a that are < x."""
    lo, hi = 0, a.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_kernel
def cholesky(H, L):
    """Write the lower Cholesky factor of ``H`` into ``L``; return False if H is not PD."""
    n = H.shape[0]
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
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
    """Return ``x`` with ``L L^T x = b``."""
    x = np.empty(L.shape[0])
    _cho_solve_into(L, b, x)
    return x


@_kernel
def _cho_solve_into(L, b, x):
    """Write ``x`` with ``L L^T x = b`` (x may not alias b)."""
    n = L.shape[0]
    for i in range(n):                      # L y = b
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):          # L^T x = y
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


@_kernel
def lu_solve(A, b):
    """Return (x, ok) with ``A x = b`` (LU, partial pivoting); ok False if A is singular."""
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
    1e-4) * 10^i`` that makes it so (``tries`` of them; SHIFT_* below).
    """
    n = H.shape[0]
    L = np.empty((n, n))
    Hs = H.copy()
    shift, mu_next = 0.0, max(mu_last * SHIFT_RELAX, SHIFT_START)
    for _ in range(tries):
        for i in range(n):
            Hs[i, i] = H[i, i] + shift * kdiag[i]
        if cholesky(Hs, L):
            return L, shift, True
        shift, mu_next = mu_next, mu_next * SHIFT_GROWTH
    return L, shift, False


@_kernel
def _most_violated(A, lo, dq, act, n_act):
    """Return (violation, row) of the most violated constraint not in act[:n_act]."""
    best, i_best = np.inf, -1
    for r in range(lo.shape[0]):
        skip = False
        for a in range(n_act):
            skip = skip or act[a] == r
        if not skip:
            v = _dot(A[r], dq) - lo[r]
            if v < best:
                best, i_best = v, r
    return best, i_best


@_kernel
def _active_set_step(dq0, L, A, lo, act, n_act, Y, dq):
    """
    Solve the step with the constraints act[:n_act] held as equalities; return the set size.

    ``dq = dq0 + H^-1 A_W^T m`` with ``(A_W H^-1 A_W^T) m = lo_W - A_W dq0``; a constraint
    that would pull (m < 0) leaves and the step is solved again, one that makes the system
    singular (the last added) too. Returns 0 (dq untouched) if the set runs out.
    """
    n = dq0.shape[0]
    while n_act > 0:
        for a in range(n_act):
            _cho_solve_into(L, A[act[a]], Y[a])             # rows of H^-1 A_W^T
        G = np.empty((n_act, n_act))
        rhs = np.empty(n_act)
        for a in range(n_act):
            rhs[a] = lo[act[a]] - _dot(A[act[a]], dq0)
            for b in range(n_act):
                G[a, b] = _dot(A[act[a]], Y[b])
        multipliers, ok = lu_solve(G, rhs)
        if not ok:
            n_act -= 1
            continue
        pulling = False
        for a in range(n_act):
            pulling = pulling or multipliers[a] < 0.0
        if not pulling:
            for i in range(n):
                s = dq0[i]
                for a in range(n_act):
                    s += Y[a, i] * multipliers[a]
                dq[i] = s
            return n_act
        keep = 0
        for a in range(n_act):
            if multipliers[a] >= 0.0:
                act[keep] = act[a]
                keep += 1
        n_act = keep
    return 0


@_kernel
def project_step(dq, L, A, lo, max_active):
    """
    Return the Newton step with the linearised constraints ``A dq >= lo`` (``lo < 0``) kept.

    A small primal active-set QP on the Newton model (``L L^T``, its Hessian): the most
    violated constraint joins the active set and the step is solved again on it; one that
    would pull (negative multiplier) leaves it. Should the active set run out, the step is
    scaled back until every constraint holds.
    """
    n = dq.shape[0]
    dq0 = dq.copy()
    dq = dq.copy()
    act = np.empty(max_active, dtype=np.int64)
    Y = np.empty((max_active, n))
    n_act = 0
    for _ in range(max_active):
        worst, i = _most_violated(A, lo, dq, act, n_act)
        if i < 0 or worst >= QP_ROUNDOFF:
            return dq
        act[n_act] = i
        n_act = _active_set_step(dq0, L, A, lo, act, n_act + 1, Y, dq)
        if n_act == 0:
            for k in range(n):
                dq[k] = dq0[k]
    scale = 1.0
    for r in range(lo.shape[0]):
        rate = _dot(A[r], dq)
        if rate < lo[r]:
            scale = min(scale, lo[r] / rate)
    if scale < 1.0:
        for k in range(n):
            dq[k] *= scale
    return dq


# -- SE(3) and the strain basis -----------------------------------------------------------
@_kernel
def _coefficients(th2):
    """Return exp's (a, b, c) and dexp's (f1..f4) coefficients of angle^2 ``th2``."""
    if th2 < SMALL_ANGLE2:
        th4 = th2 * th2
        return (1 - th2 / 6 + th4 / 120, 0.5 - th2 / 24 + th4 / 720,
                1 / 6 - th2 / 120 + th4 / 5040, -(0.5 - th4 / 720), 1 / 6 - th4 / 5040,
                -(1 / 24 - th2 / 360 + th4 / 13440), 1 / 120 - th2 / 2520 + th4 / 120960)
    t = math.sqrt(th2)
    s, co = math.sin(t), math.cos(t)
    t2 = t * t
    t3 = t2 * t
    ts, tc = t * s, t * co
    return (s / t, (1 - co) / t2, (t - s) / t3, -(4 - 4 * co - ts) / (2 * t2),
            (4 * t - 5 * s + tc) / (2 * t3), -(2 - 2 * co - ts) / (2 * t2 * t2),
            (2 * t - 3 * s + tc) / (2 * t3 * t2))


@_kernel
def _exp_into(om, E):
    """
    Write exp(om) (4x4, Rodrigues) into E; return (th2, f1, f2, f3, f4) for its tangent.

    ``W^2 = w w^T - th^2 I``, so ``R = I + a W + b W^2``, ``p = v + b w x v + c W^2 v``.
    """
    w0, w1, w2, v0, v1, v2 = om[0], om[1], om[2], om[3], om[4], om[5]
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    a, b, c, f1, f2, f3, f4 = _coefficients(th2)
    E[0, 0] = 1.0 + b * (w0 * w0 - th2)
    E[0, 1] = -a * w2 + b * (w0 * w1)
    E[0, 2] = a * w1 + b * (w0 * w2)
    E[1, 0] = a * w2 + b * (w1 * w0)
    E[1, 1] = 1.0 + b * (w1 * w1 - th2)
    E[1, 2] = -a * w0 + b * (w1 * w2)
    E[2, 0] = -a * w1 + b * (w2 * w0)
    E[2, 1] = a * w0 + b * (w2 * w1)
    E[2, 2] = 1.0 + b * (w2 * w2 - th2)
    wv = w0 * v0 + w1 * v1 + w2 * v2
    E[0, 3] = v0 + b * (w1 * v2 - w2 * v1) + c * (w0 * wv - th2 * v0)
    E[1, 3] = v1 + b * (w2 * v0 - w0 * v2) + c * (w1 * wv - th2 * v1)
    E[2, 3] = v2 + b * (w0 * v1 - w1 * v0) + c * (w2 * wv - th2 * v2)
    E[3, 0], E[3, 1], E[3, 2], E[3, 3] = 0.0, 0.0, 0.0, 1.0
    return th2, f1, f2, f3, f4


@_kernel
def _skew_into(a, b, c, S):
    """Write the cross-product matrix of (a, b, c) into S."""
    S[0, 0], S[0, 1], S[0, 2] = 0.0, -c, b
    S[1, 0], S[1, 1], S[1, 2] = c, 0.0, -a
    S[2, 0], S[2, 1], S[2, 2] = -b, a, 0.0


@_kernel
def _dexp_blocks(om, th2, f1, f2, f3, f4, M):
    """
    Write the blocks of T(om) = [[TR, 0], [TV, TR]] into M[6], M[7].

    T = I + f1 ad + f2 ad^2 + f3 ad^3 + f4 ad^4 with ad^k = [[W^k, 0], [B_k, W^k]],
    B_1 = V, B_{k+1} = V W^k + W B_k (W, V the cross-product matrices of the angular and
    linear parts) and W^3 = -th^2 W. M: (8, 3, 3), M[0:6] scratch.
    """
    W, V, W2, B2, B3, B4 = M[0], M[1], M[2], M[3], M[4], M[5]
    TR, TV = M[6], M[7]
    _skew_into(om[0], om[1], om[2], W)
    _skew_into(om[3], om[4], om[5], V)
    for i in range(3):
        for j in range(3):
            s = 0.0
            t = 0.0
            for k in range(3):
                s += W[i, k] * W[k, j]
                t += V[i, k] * W[k, j] + W[i, k] * V[k, j]
            W2[i, j] = s
            B2[i, j] = t
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += V[i, k] * W2[k, j] + W[i, k] * B2[k, j]
            B3[i, j] = s
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += -th2 * (V[i, k] * W[k, j]) + W[i, k] * B3[k, j]
            B4[i, j] = s
    g1, g2 = f1 - th2 * f3, f2 - th2 * f4
    for i in range(3):
        for j in range(3):
            TR[i, j] = (1.0 if i == j else 0.0) + g1 * W[i, j] + g2 * W2[i, j]
            TV[i, j] = f1 * V[i, j] + f2 * B2[i, j] + f3 * B3[i, j] + f4 * B4[i, j]


@_kernel
def _pose_mul(g, E, out):
    """Write the pose product ``g @ E`` into ``out`` (out must not alias E)."""
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
    p0, p1, p2 = E[0, 3], E[1, 3], E[2, 3]
    for col in range(n_cols):
        w0, w1, w2 = J[0, col], J[1, col], J[2, col]
        v0 = J[3, col] - (p1 * w2 - p2 * w1)
        v1 = J[4, col] - (p2 * w0 - p0 * w2)
        v2 = J[5, col] - (p0 * w1 - p1 * w0)
        for i in range(3):
            out[i, col] = E[0, i] * w0 + E[1, i] * w1 + E[2, i] * w2
            out[3 + i, col] = E[0, i] * v0 + E[1, i] * v1 + E[2, i] * v2


@_kernel
def _legendre(y, P):
    """Fill P with the Legendre polynomials P_0..P_{nm-1} at y."""
    nm = P.shape[0]
    P[0] = 1.0
    if nm > 1:
        P[1] = y
    for j in range(2, nm):
        P[j] = ((2 * j - 1) * y * P[j - 1] - (j - 1) * P[j - 2]) / j


@_kernel
def _strain_at(P, q, col0, comps, xi):
    """Fill xi with the strain from the basis values P (segment columns from col0)."""
    nm = P.shape[0]
    xi[0], xi[1], xi[2], xi[3], xi[4], xi[5] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for ci in range(comps.shape[0]):
        s = 0.0
        for j in range(nm):
            s += P[j] * q[col0 + ci * nm + j]
        xi[comps[ci]] = s
    xi[3] += 1.0


@_kernel
def _ad_column(x, c, out):
    """Write column c of ad_x = [[w^, 0], [v^, w^]] into out[0:6] (w^ e_k = w x e_k)."""
    k = c if c < 3 else c - 3
    o = 3 if c < 3 else 0          # where the column's second block reads from
    w0, w1, w2 = x[0], x[1], x[2]
    u0, u1, u2 = x[o], x[o + 1], x[o + 2]
    if k == 0:
        a0, a1, a2, b0, b1, b2 = 0.0, w2, -w1, 0.0, u2, -u1
    elif k == 1:
        a0, a1, a2, b0, b1, b2 = -w2, 0.0, w0, -u2, 0.0, u0
    else:
        a0, a1, a2, b0, b1, b2 = w1, -w0, 0.0, u1, -u0, 0.0
    if c < 3:
        out[0], out[1], out[2], out[3], out[4], out[5] = a0, a1, a2, b0, b1, b2
    else:
        out[0], out[1], out[2], out[3], out[4], out[5] = 0.0, 0.0, 0.0, a0, a1, a2


@_kernel
def _t_apply(M, y, out):
    """Write T y = [TR y_w; TV y_w + TR y_v] into out (TR, TV in M[6], M[7])."""
    for i in range(3):
        out[i] = M[6, i, 0] * y[0] + M[6, i, 1] * y[1] + M[6, i, 2] * y[2]
        out[3 + i] = (M[7, i, 0] * y[0] + M[7, i, 1] * y[1] + M[7, i, 2] * y[2]) \
            + (M[6, i, 0] * y[3] + M[6, i, 1] * y[4] + M[6, i, 2] * y[5])


class Scratch(NamedTuple):
    """Work arrays of the Magnus step, allocated once per kernel call."""

    P: np.ndarray        # (2, nm) basis at the two Zanna points
    X: np.ndarray        # (4, 6) strains there, the twist, a spare row
    E: np.ndarray        # (4, 4) the step's pose
    M: np.ndarray        # (8, 3, 3) dexp blocks (M[6] = TR, M[7] = TV) and their scratch
    U: np.ndarray        # (4, 6) columns of T, T ad_x1, T ad_x2; a spare
    TS: np.ndarray       # (6, D) T(om) d om / dq on one segment's columns


@_kernel
def scratch(nm, D):
    return Scratch(np.empty((2, nm)), np.empty((4, 6)), np.empty((4, 4)), np.empty((8, 3, 3)),
                   np.empty((4, 6)), np.empty((6, D)))


@_inline
def _magnus(q, L, comps, col0, a, h, jac, P, X, E, M, U, TS):
    """
    Take one Magnus step over [a, a + h] (local abscissae) of a segment of length L.

    The segment's columns of q start at col0. The step's pose goes into E and, with
    ``jac``, ``T(om) d om / dq`` on the segment's columns into TS (6, D):
    ``d om = h/2 (dx1 + dx2) + C4 h^2 (ad_x1 dx2 - ad_x2 dx1)``.
    """
    x1, x2, om = X[0], X[1], X[2]
    P1, P2 = P[0], P[1]
    _legendre(2.0 * (a + Z1 * h) / L - 1.0, P1)
    _legendre(2.0 * (a + Z2 * h) / L - 1.0, P2)
    _strain_at(P1, q, col0, comps, x1)
    _strain_at(P2, q, col0, comps, x2)
    c2 = C4 * h ** 2
    b0 = x1[1] * x2[2] - x1[2] * x2[1]                      # [x1, x2] = ad_x1 x2
    b1 = x1[2] * x2[0] - x1[0] * x2[2]
    b2 = x1[0] * x2[1] - x1[1] * x2[0]
    b3 = (x1[1] * x2[5] - x1[2] * x2[4]) + (x1[4] * x2[2] - x1[5] * x2[1])
    b4 = (x1[2] * x2[3] - x1[0] * x2[5]) + (x1[5] * x2[0] - x1[3] * x2[2])
    b5 = (x1[0] * x2[4] - x1[1] * x2[3]) + (x1[3] * x2[1] - x1[4] * x2[0])
    om[0] = h / 2 * (x1[0] + x2[0]) + c2 * b0
    om[1] = h / 2 * (x1[1] + x2[1]) + c2 * b1
    om[2] = h / 2 * (x1[2] + x2[2]) + c2 * b2
    om[3] = h / 2 * (x1[3] + x2[3]) + c2 * b3
    om[4] = h / 2 * (x1[4] + x2[4]) + c2 * b4
    om[5] = h / 2 * (x1[5] + x2[5]) + c2 * b5
    th2, f1, f2, f3, f4 = _exp_into(om, E)
    if jac:
        _dexp_blocks(om, th2, f1, f2, f3, f4, M)
        nm = P.shape[1]
        for ci in range(comps.shape[0]):
            c = comps[ci]
            # T e_c, T ad_x1 e_c and T ad_x2 e_c; each column of TS combines them.
            for r in range(6):
                U[3, r] = 1.0 if r == c else 0.0
            _t_apply(M, U[3], U[0])
            _ad_column(x1, c, U[3])
            _t_apply(M, U[3], U[1])
            _ad_column(x2, c, U[3])
            _t_apply(M, U[3], U[2])
            for j in range(nm):
                hp = h / 2 * (P1[j] + P2[j])
                for r in range(6):
                    TS[r, ci * nm + j] = hp * U[0, r] + c2 * (P2[j] * U[1, r] - P1[j] * U[2, r])


@_kernel
def _locate(offsets, X):
    """Return (segment, local abscissa) of arc length X (clipped to the rod)."""
    X = min(max(X, 0.0), offsets[offsets.shape[0] - 1])
    seg = min(max(_bisect_right(offsets, X) - 1, 0), offsets.shape[0] - 2)
    return seg, X - offsets[seg]


@_kernel
def forward(tf, ti, q, jac):
    """
    Return node poses g (N, 4, 4), Jacobians J (N, 6, n) and Gauss-point strains (K, 6).

    J is empty unless ``jac``. The poses chain the Magnus steps from the base; the Jacobian
    follows in the same pass, ``J_{k+1} = Ad_{exp(-om_k)} J_k + T(om_k) d om_k / dq``.
    """
    tab = _unpack(tf, ti)
    seg_len, comps, int_seg = tab[T_SEG_LEN], tab[T_COMPS], tab[T_INT_SEG]
    int_a, int_h = tab[T_INT_A], tab[T_INT_H]
    nm = tab[T_N_MODES]
    M = int_h.shape[0]
    n = q.shape[0]
    D = nm * comps.shape[0]
    P, X, E, Ms, U, TS = scratch(nm, D)
    g = np.empty((M + 1, 4, 4))
    for i in range(4):
        for j in range(4):
            g[0, i, j] = tab[T_BASE][i, j]
    J = np.zeros((M + 1 if jac else 0, 6, n))
    for k in range(M):
        seg = int_seg[k]
        _magnus(q, seg_len[seg], comps, seg * D, int_a[k], int_h[k], jac, P, X, E, Ms, U, TS)
        _pose_mul(g[k], E, g[k + 1])
        if jac:
            _adinv_apply(E, J[k], J[k + 1], (seg + 1) * D)
            for r in range(6):
                for c in range(D):
                    J[k + 1, r, seg * D + c] += TS[r, c]
    gauss_X, gauss_seg, offsets = tab[T_GAUSS_X], tab[T_GAUSS_SEG], tab[T_OFFSETS]
    xi = np.empty((gauss_X.shape[0], 6))
    for i in range(gauss_X.shape[0]):
        s = gauss_seg[i]
        _legendre(2.0 * (gauss_X[i] - offsets[s]) / seg_len[s] - 1.0, P[0])
        _strain_at(P[0], q, s * D, comps, xi[i])
    return g, J, xi


@_kernel
def _at_node(node_X, X):
    """Return the node index at X, or -1 if X is not a node; X is clipped to the rod."""
    k = _bisect_left(node_X, X)
    return k if k < node_X.shape[0] and node_X[k] == X else -1


@_inline
def _point_frame(q, tab, g_nodes, J_nodes, X, w, g_out, J_out):
    """Write the pose and the body Jacobian at X: a Magnus step from the node before it."""
    P, Xw, E, Ms, U, TS = w
    node_X, comps = tab[T_NODE_X], tab[T_COMPS]
    N = node_X.shape[0]
    X = min(max(X, 0.0), node_X[N - 1])
    k = _at_node(node_X, X)
    if k >= 0:
        for i in range(4):
            for j in range(4):
                g_out[i, j] = g_nodes[k, i, j]
        for i in range(6):
            for j in range(J_out.shape[1]):
                J_out[i, j] = J_nodes[k, i, j]
        return
    m = min(max(_bisect_right(node_X, X) - 1, 0), N - 2)
    seg = tab[T_INT_SEG][m]
    D = P.shape[1] * comps.shape[0]
    _magnus(q, tab[T_SEG_LEN][seg], comps, seg * D, tab[T_INT_A][m], X - node_X[m], True, P, Xw, E,
            Ms, U, TS)
    _pose_mul(g_nodes[m], E, g_out)
    _adinv_apply(E, J_nodes[m], J_out, J_out.shape[1])
    for r in range(6):
        for c in range(D):
            J_out[r, seg * D + c] += TS[r, c]


@_inline
def _point_pose(q, tab, g_nodes, X, w, g_out):
    """Write the pose at X (no Jacobian)."""
    P, Xw, E, Ms, U, TS = w
    node_X, comps = tab[T_NODE_X], tab[T_COMPS]
    N = node_X.shape[0]
    X = min(max(X, 0.0), node_X[N - 1])
    k = _at_node(node_X, X)
    if k >= 0:
        for i in range(4):
            for j in range(4):
                g_out[i, j] = g_nodes[k, i, j]
        return
    m = min(max(_bisect_right(node_X, X) - 1, 0), N - 2)
    seg = tab[T_INT_SEG][m]
    D = P.shape[1] * comps.shape[0]
    _magnus(q, tab[T_SEG_LEN][seg], comps, seg * D, tab[T_INT_A][m], X - node_X[m], False, P, Xw,
            E, Ms, U, TS)
    _pose_mul(g_nodes[m], E, g_out)


@_kernel
def point_frames(tf, ti, q, g_nodes, J_nodes, X, jac):
    """Return poses (P, 4, 4) and body Jacobians (P, 6, n) (empty unless ``jac``) at X."""
    tab = _unpack(tf, ti)
    n = q.shape[0]
    w = scratch(tab[T_N_MODES], tab[T_N_MODES] * tab[T_COMPS].shape[0])
    g = np.empty((X.shape[0], 4, 4))
    J = np.zeros((X.shape[0] if jac else 0, 6, n))
    for i in range(X.shape[0]):
        if jac:
            _point_frame(q, tab, g_nodes, J_nodes, X[i], w, g[i], J[i])
        else:
            _point_pose(q, tab, g_nodes, X[i], w, g[i])
    return g, J


@_kernel
def strains(tf, ti, q, X):
    """Return the strain (P, 6) at arc lengths X (segment ends read the next segment)."""
    tab = _unpack(tf, ti)
    D = tab[T_N_MODES] * tab[T_COMPS].shape[0]
    P = np.empty((1, tab[T_N_MODES]))
    xi = np.empty((X.shape[0], 6))
    for i in range(X.shape[0]):
        seg, x = _locate(tab[T_OFFSETS], X[i])
        _legendre(2.0 * x / tab[T_SEG_LEN][seg] - 1.0, P[0])
        _strain_at(P[0], q, seg * D, tab[T_COMPS], xi[i])
    return xi


@_kernel
def basis_matrices(tf, ti, seg, x, n):
    """Return Phi (P, 6, n) at local abscissae x of segments seg (the dense form)."""
    tab = _unpack(tf, ti)
    nm, nc = tab[T_N_MODES], tab[T_COMPS].shape[0]
    P = np.empty((1, nm))
    out = np.zeros((x.shape[0], 6, n))
    for i in range(x.shape[0]):
        _legendre(2.0 * x[i] / tab[T_SEG_LEN][seg[i]] - 1.0, P[0])
        for ci in range(nc):
            for j in range(nm):
                out[i, tab[T_COMPS][ci], seg[i] * nm * nc + ci * nm + j] = P[0, j]
    return out


@_kernel
def _add_phi_t(comps, col0, P, weight, rows, out):
    """Add ``weight Phi^T rows`` to out (n, k): Phi's nonzeros are P[0, j] at (c, col)."""
    nm = P.shape[1]
    for ci in range(comps.shape[0]):
        c = comps[ci]
        for j in range(nm):
            f = weight * P[0, j]
            col = col0 + ci * nm + j
            for k in range(rows.shape[1]):
                out[col, k] += f * rows[c, k]


@_kernel
def _add_phi_t_vec(comps, col0, P, weight, v, out):
    """Add ``weight Phi^T v`` to out (n,) for a 6-vector v."""
    nm = P.shape[1]
    for ci in range(comps.shape[0]):
        c = comps[ci]
        for j in range(nm):
            out[col0 + ci * nm + j] += weight * P[0, j] * v[c]


# -- obstacles: signed distance, unit gradient and Hessian ---------------------------------
# Each kind takes a point of its own frame as scalars, returns (d, nx, ny, nz) and writes
# the distance's Hessian into H (always: a flag would compile each kind twice).
@_kernel
def _unit(x, y, z):
    r = max(math.sqrt(x * x + y * y + z * z), NORM_FLOOR)
    return x / r, y / r, z / r


@_kernel
def _circle_hessian(x, y, n0, n1, n2, dist, R0, H):
    """H = [(I - n n^T) - (R0 / rho) t t^T] / dist: distance to a circle of radius R0 about z."""
    rho = max(math.hypot(x, y), DIST_FLOOR)
    t0, t1 = -y / rho, x / rho
    c = R0 / rho
    den = max(dist, DIST_FLOOR)
    H[0, 0] = ((1.0 - n0 * n0) - c * (t0 * t0)) / den
    H[0, 1] = ((0.0 - n0 * n1) - c * (t0 * t1)) / den
    H[0, 2] = ((0.0 - n0 * n2) - c * (t0 * 0.0)) / den
    H[1, 0] = ((0.0 - n1 * n0) - c * (t1 * t0)) / den
    H[1, 1] = ((1.0 - n1 * n1) - c * (t1 * t1)) / den
    H[1, 2] = ((0.0 - n1 * n2) - c * (t1 * 0.0)) / den
    H[2, 0] = ((0.0 - n2 * n0) - c * (0.0 * t0)) / den
    H[2, 1] = ((0.0 - n2 * n1) - c * (0.0 * t1)) / den
    H[2, 2] = ((1.0 - n2 * n2) - c * 0.0) / den


@_kernel
def _zero3(H):
    for i in range(3):
        for j in range(3):
            H[i, j] = 0.0


@_kernel
def _sphere(prm, x, y, z, H):
    nrm = math.sqrt(x * x + y * y + z * z)
    d = nrm - prm[0]
    n0, n1, n2 = _unit(x, y, z)
    _circle_hessian(x, y, n0, n1, n2, d + prm[0], 0.0, H)
    return d, n0, n1, n2


@_kernel
def _plane(prm, x, y, z, H):
    _zero3(H)
    return z, 0.0, 0.0, 1.0


@_kernel
def _cylinder(prm, x, y, z, H):
    """Axis z, centred: radius prm[0], half height prm[1]; the rim is a circle."""
    r, hh = prm[0], prm[1]
    rho = math.sqrt(x * x + y * y)
    dr, dz = rho - r, abs(z) - hh
    out_r, out_z = max(dr, 0.0), max(dz, 0.0)
    outside = math.hypot(out_r, out_z)
    d = outside + min(max(dr, dz), 0.0)
    u0, u1, _ = _unit(x, y, 0.0)                        # radial unit vector
    axial = (1.0 if z > 0 else (-1.0 if z < 0 else 0.0)) + (1.0 if z == 0 else 0.0)
    if outside > 0:
        n0, n1, n2 = _unit(out_r * u0, out_r * u1, out_z * axial)
    elif dr > dz:
        n0, n1, n2 = u0, u1, 0.0
    else:
        n0, n1, n2 = 0.0, 0.0, axial
    rho = max(math.hypot(x, y), DIST_FLOOR)
    dr = rho - r
    if dr > 0 and dz > 0:                                # rim: distance to a circle
        _circle_hessian(x, y, n0, n1, n2, d, r, H)
        return d, n0, n1, n2
    side = (dr > 0 and dz <= 0) or (d <= 0 and dr > dz)
    t0, t1 = -y / rho, x / rho
    f = (1.0 if side else 0.0) / rho
    _zero3(H)
    H[0, 0], H[0, 1], H[1, 0], H[1, 1] = f * (t0 * t0), f * (t0 * t1), f * (t1 * t0), f * (t1 * t1)
    return d, n0, n1, n2


@_kernel
def _ring(prm, x, y, z, H):
    """Torus around z in the x-y plane: major radius prm[0], minor prm[1]."""
    R0, r = prm[0], prm[1]
    u0, u1, _ = _unit(x, y, 0.0)
    v0, v1, v2 = x - R0 * u0, y - R0 * u1, z
    d = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2) - r
    n0, n1, n2 = _unit(v0, v1, v2)
    _circle_hessian(x, y, n0, n1, n2, d + r, R0, H)
    return d, n0, n1, n2


@_kernel
def _prism(prm, x, y, z, H):
    """
    Return the distance to an oblique prism (exact).

    Outside the nearest face interior or edge, inside the largest face distance; edges are
    lines with a Hessian, faces are flat.
    """
    pp = x * x + y * y + z * z
    inside_d, j_in = -np.inf, 0
    for j in range(6):
        o = PRISM_NORMALS + 3 * j
        e = (x * prm[o] + y * prm[o + 1] + z * prm[o + 2]) - prm[PRISM_OFFSETS + j]
        if e > inside_d:
            inside_d, j_in = e, j
    best, k_best, t_best = np.inf, 0, 0.0
    for k in range(12):
        ea, eab = PRISM_EA + 3 * k, PRISM_EAB + 3 * k
        dot = (x * prm[eab] + y * prm[eab + 1] + z * prm[eab + 2]) - prm[PRISM_EA_EAB + k]
        l2 = prm[PRISM_EAB2 + k]
        t = min(max(dot / l2, 0.0), 1.0)
        rel2 = pp - 2.0 * (x * prm[ea] + y * prm[ea + 1] + z * prm[ea + 2]) + prm[PRISM_EA2 + k]
        de = math.sqrt(max(rel2 - t * (2.0 * dot - t * l2), 0.0))
        if de < best:
            best, k_best, t_best = de, k, t
    h_best = 0.0
    for f in range(6):
        a0 = PRISM_FPROJ + 6 * f
        u = (x * prm[a0] + y * prm[a0 + 1] + z * prm[a0 + 2]) - prm[PRISM_FA_AB + 2 * f]
        v = (x * prm[a0 + 3] + y * prm[a0 + 4] + z * prm[a0 + 5]) - prm[PRISM_FA_AB + 2 * f + 1]
        if 0.0 <= u <= 1.0 and 0.0 <= v <= 1.0:
            fn = PRISM_FN + 3 * f
            h = (x * prm[fn] + y * prm[fn + 1] + z * prm[fn + 2]) - prm[PRISM_FN_A + f]
            if abs(h) < best:
                best, k_best, h_best = abs(h), 12 + f, h
    if inside_d > 0:
        if k_best < 12:
            ea, eab = PRISM_EA + 3 * k_best, PRISM_EAB + 3 * k_best
            n0, n1, n2 = _unit(x - (prm[ea] + t_best * prm[eab]),
                               y - (prm[ea + 1] + t_best * prm[eab + 1]),
                               z - (prm[ea + 2] + t_best * prm[eab + 2]))
        else:
            fn = PRISM_FN + 3 * (k_best - 12)            # p - (p - h fn)
            n0, n1, n2 = _unit(h_best * prm[fn], h_best * prm[fn + 1], h_best * prm[fn + 2])
        d = best
    else:
        o = PRISM_NORMALS + 3 * j_in
        n0, n1, n2 = prm[o], prm[o + 1], prm[o + 2]
        d = inside_d
        k_best = 12
    _zero3(H)
    if k_best < 12:
        eab = PRISM_EAB + 3 * k_best
        a0, a1, a2 = _unit(prm[eab], prm[eab + 1], prm[eab + 2])
        line = 1.0 if 0.0 < t_best < 1.0 else 0.0
        den = max(d, DIST_FLOOR)
        nv = (n0, n1, n2)
        av = (a0, a1, a2)
        for i in range(3):
            for j in range(3):
                H[i, j] = (((1.0 if i == j else 0.0) - nv[i] * nv[j]) - line * (av[i] * av[j])) \
                    / den
    return d, n0, n1, n2


@_kernel
def _sdf_world(kind, prm, pose, px, py, pz, H):
    """Return (d, nx, ny, nz) at a world point and write its world Hessian into H."""
    x = ((px - pose[0, 3]) * pose[0, 0] + (py - pose[1, 3]) * pose[1, 0]) \
        + (pz - pose[2, 3]) * pose[2, 0]
    y = ((px - pose[0, 3]) * pose[0, 1] + (py - pose[1, 3]) * pose[1, 1]) \
        + (pz - pose[2, 3]) * pose[2, 1]
    z = ((px - pose[0, 3]) * pose[0, 2] + (py - pose[1, 3]) * pose[1, 2]) \
        + (pz - pose[2, 3]) * pose[2, 2]
    if kind == CYLINDER:
        d, a, b, c = _cylinder(prm, x, y, z, H)
    elif kind == RING:
        d, a, b, c = _ring(prm, x, y, z, H)
    elif kind == PRISM:
        d, a, b, c = _prism(prm, x, y, z, H)
    elif kind == SPHERE:
        d, a, b, c = _sphere(prm, x, y, z, H)
    else:
        d, a, b, c = _plane(prm, x, y, z, H)
    n0 = (a * pose[0, 0] + b * pose[0, 1]) + c * pose[0, 2]
    n1 = (a * pose[1, 0] + b * pose[1, 1]) + c * pose[1, 2]
    n2 = (a * pose[2, 0] + b * pose[2, 1]) + c * pose[2, 2]
    # H <- R H R^T, through R H first (9 temporaries).
    h00 = H[0, 0] * pose[0, 0] + H[1, 0] * pose[0, 1] + H[2, 0] * pose[0, 2]
    h01 = H[0, 1] * pose[0, 0] + H[1, 1] * pose[0, 1] + H[2, 1] * pose[0, 2]
    h02 = H[0, 2] * pose[0, 0] + H[1, 2] * pose[0, 1] + H[2, 2] * pose[0, 2]
    h10 = H[0, 0] * pose[1, 0] + H[1, 0] * pose[1, 1] + H[2, 0] * pose[1, 2]
    h11 = H[0, 1] * pose[1, 0] + H[1, 1] * pose[1, 1] + H[2, 1] * pose[1, 2]
    h12 = H[0, 2] * pose[1, 0] + H[1, 2] * pose[1, 1] + H[2, 2] * pose[1, 2]
    h20 = H[0, 0] * pose[2, 0] + H[1, 0] * pose[2, 1] + H[2, 0] * pose[2, 2]
    h21 = H[0, 1] * pose[2, 0] + H[1, 1] * pose[2, 1] + H[2, 1] * pose[2, 2]
    h22 = H[0, 2] * pose[2, 0] + H[1, 2] * pose[2, 1] + H[2, 2] * pose[2, 2]
    for j in range(3):
        H[0, j] = h00 * pose[j, 0] + h01 * pose[j, 1] + h02 * pose[j, 2]
        H[1, j] = h10 * pose[j, 0] + h11 * pose[j, 1] + h12 * pose[j, 2]
        H[2, j] = h20 * pose[j, 0] + h21 * pose[j, 1] + h22 * pose[j, 2]
    return d, n0, n1, n2


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
    for i in range(P):
        d[i], n[i, 0], n[i, 1], n[i, 2] = _sdf_world(kind, prm, pose, pts[i, 0], pts[i, 1],
                                                     pts[i, 2], Hd)
        if hess:
            for r in range(3):
                for c in range(3):
                    H[i, r, c] = Hd[r, c]
    return d, n, H


@_kernel
def least_gap(kinds, prms, poses, pts, radii):
    """Return the least ``distance - radius`` of points (P, 3) over all obstacles."""
    H = np.empty((3, 3))
    best = np.inf
    for o in range(kinds.shape[0]):
        for i in range(pts.shape[0]):
            d = _sdf_world(kinds[o], prms[o], poses[o], pts[i, 0], pts[i, 1], pts[i, 2], H)[0]
            best = min(best, d - radii[i])
    return best


# -- the contact record of an equilibrium ----------------------------------------------------
@_kernel
def _least_gap_at(kinds, prms, poses, x, y, z, H):
    """Return the least signed distance of a world point to the obstacles."""
    best = np.inf
    for o in range(kinds.shape[0]):
        best = min(best, _sdf_world(kinds[o], prms[o], poses[o], x, y, z, H)[0])
    return best


@_kernel
def _arc_knots(s, P, radii, cs, cp, cg, kinds, prms, poses, band, H):
    """Merge backbone samples and contact points by arc length; return knots and their count."""
    N, C = s.shape[0], cs.shape[0]
    order = np.argsort(cs, kind='mergesort')
    K = N + C
    kn = np.empty(K)
    kp = np.empty((K, 3))
    kr = np.empty(K)
    kg = np.empty(K)
    i = j = k = 0
    while i < N or j < C:
        if i < N:
            far = True
            for c in range(C):
                if abs(s[i] - cs[c]) <= 1e-5:
                    far = False
            if not far:
                i += 1
                continue
        # Ties go to the sample (the order a stable sort of samples, then contacts, gives).
        if j >= C or (i < N and s[i] <= cs[order[j]]):
            kn[k], kr[k] = s[i], radii[i]
            for r in range(3):
                kp[k, r] = P[i, r]
            kg[k] = _least_gap_at(kinds, prms, poses, P[i, 0], P[i, 1], P[i, 2], H) \
                - radii[i] - band
            i += 1
        else:
            c = order[j]
            kn[k] = cs[c]
            for r in range(3):
                kp[k, r] = cp[c, r]
            # The tube radius there, linear between the samples (as np.interp).
            m = min(max(_bisect_right(s, cs[c]) - 1, 0), N - 2)
            t = (cs[c] - s[m]) / (s[m + 1] - s[m]) if N > 1 else 0.0
            t = min(max(t, 0.0), 1.0)
            kr[k] = radii[m] + t * (radii[min(m + 1, N - 1)] - radii[m])
            kg[k] = cg[c] - band
            j += 1
        k += 1
    return kn, kp, kr, kg, k


@_kernel
def _knot_tangents(kn, kp, k):
    """Return the Hermite tangents at the first ``k`` knots (three-point differences)."""
    T = np.empty((k, 3))
    for r in range(3):
        for a in range(k):
            if k == 2:
                T[a, r] = (kp[1, r] - kp[0, r]) / (kn[1] - kn[0])
            elif a == 0 or a == k - 1:
                b0 = 0 if a == 0 else k - 3
                h0, h1 = kn[b0 + 1] - kn[b0], kn[b0 + 2] - kn[b0 + 1]
                d0 = (kp[b0 + 1, r] - kp[b0, r]) / h0
                d1 = (kp[b0 + 2, r] - kp[b0 + 1, r]) / h1
                if a == 0:
                    T[a, r] = d0 - h0 * (d1 - d0) / (h0 + h1)
                else:
                    T[a, r] = d1 + h1 * (d1 - d0) / (h1 + h0)
            else:
                h0, h1 = kn[a] - kn[a - 1], kn[a + 1] - kn[a]
                d0 = (kp[a, r] - kp[a - 1, r]) / h0
                d1 = (kp[a + 1, r] - kp[a, r]) / h1
                T[a, r] = (h1 * d0 + h0 * d1) / (h0 + h1)
    return T


@_kernel
def contact_arc(s, P, radii, cs, cp, cg, kinds, prms, poses, step, band, near):
    """
    Return the backbone length (m) whose tube surface lies within ``band`` of the obstacles.

    Knots: the backbone samples (s, P, radii; those within 10 um of a contact point left
    out) and the contact points (cs, cp, exact gaps cg), in arc-length order. Each knot
    interval whose ends come within ``near`` of the band is sampled every ``step`` on the
    cubic Hermite through its knots (tangents: three-point differences, exact for
    quadratics); inside each interval the crossings are linear in the gap.
    """
    H = np.empty((3, 3))
    kn, kp, kr, kg, k = _arc_knots(s, P, radii, cs, cp, cg, kinds, prms, poses, band, H)
    if k < 2:
        return 0.0
    T = _knot_tangents(kn, kp, k)
    arc = 0.0
    for a in range(k - 1):
        ga, gb = kg[a], kg[a + 1]
        if min(ga, gb) > near:
            continue
        h = kn[a + 1] - kn[a]
        m = max(1, int(math.ceil(h / step)))
        lo = ga
        for q in range(1, m + 1):
            if q == m:
                hi = gb
            else:
                t = q / m
                h00, h10 = ((2 * t - 3) * t * t + 1), ((t - 2) * t + 1) * t * h
                h01, h11 = (3 - 2 * t) * t * t, (t - 1) * t * t * h
                x = h00 * kp[a, 0] + h10 * T[a, 0] + h01 * kp[a + 1, 0] + h11 * T[a + 1, 0]
                y = h00 * kp[a, 1] + h10 * T[a, 1] + h01 * kp[a + 1, 1] + h11 * T[a + 1, 1]
                z = h00 * kp[a, 2] + h10 * T[a, 2] + h01 * kp[a + 1, 2] + h11 * T[a + 1, 2]
                hi = _least_gap_at(kinds, prms, poses, x, y, z, H) \
                    - (kr[a] + t * (kr[a + 1] - kr[a])) - band
            w = h / m
            if lo <= 0 and hi <= 0:
                arc += w
            elif (lo <= 0) != (hi <= 0):
                dn = (lo if lo <= 0 else hi) - 1e-15
                up = hi if lo <= 0 else lo
                arc += w * dn / (dn - up)
            lo = hi
    return arc


# -- contact -------------------------------------------------------------------------------
class PenaltyParams(NamedTuple):
    """Numbers of the penalty contact law (contact.py documents each); a float array to kernels."""

    stiffness: float         # k (N/m)
    smoothing: float         # delta (m)
    stiffening: float        # p0 (m)
    cutoff: float            # force-free beyond this gap (m)
    near: float              # refine critical points of gaps below this (m)
    samples: int             # gap samples per node interval
    step_depth: float        # a Newton step may press a node this deep (m)


L_STIFFNESS, L_SMOOTHING, L_STIFFENING, L_CUTOFF, L_NEAR, L_SAMPLES, L_STEP_DEPTH = range(7)
assert PenaltyParams._fields[L_STEP_DEPTH] == 'step_depth'


@_kernel
def _cubic_min(g0, g1, m0, m1):
    """Return the least value on [0, 1] of the cubic with values g0, g1 and slopes m0, m1."""
    c1 = m0
    c2 = 3.0 * (g1 - g0) - 2.0 * m0 - m1
    c3 = 2.0 * (g0 - g1) + m0 + m1
    best = min(g0, g1)
    a, b, c = 3.0 * c3, 2.0 * c2, c1                    # g'(t) = c + b t + a t^2
    r0, r1 = -1.0, -1.0
    if a == 0.0:
        if b != 0.0:
            r0 = -c / b
    else:
        disc = b * b - 4.0 * a * c
        if disc >= 0.0:
            s = math.sqrt(disc)
            r0, r1 = (-b - s) / (2.0 * a), (-b + s) / (2.0 * a)
    if 0.0 < r0 < 1.0:
        best = min(best, g0 + r0 * (c1 + r0 * (c2 + r0 * c3)))
    if 0.0 < r1 < 1.0:
        best = min(best, g0 + r1 * (c1 + r1 * (c2 + r1 * c3)))
    return best


@_kernel
def _slope(G, xi, n0, n1, n2):
    """Return d gap / dX = n . (R nu) at frame G with strain xi."""
    s = 0.0
    nv = (n0, n1, n2)
    for r in range(3):
        s += nv[r] * (G[r, 0] * xi[3] + G[r, 1] * xi[4] + G[r, 2] * xi[5])
    return s


@_kernel
def _sample_gaps(tab, q, g_nodes, kind, prm, pose, near, sub, node_gap, node_slope, w):
    """
    Return the sample abscissae, gaps and gap slopes along the backbone for one obstacle.

    Samples are the nodes and ``sub - 1`` points inside each node interval, on the exact rod
    (a Magnus step from the interval's first node). An interval whose nodes' cubic stays far
    from the obstacle is not sampled (gap +inf, slope +1).
    """
    node_X, int_seg, int_a, seg_len, comps = tab[T_NODE_X], tab[T_INT_SEG], tab[T_INT_A], \
        tab[T_SEG_LEN], tab[T_COMPS]
    offsets, radii = tab[T_OFFSETS], tab[T_RADII]
    P, Xw, E, Ms, U, TS = w
    D = P.shape[1] * comps.shape[0]
    N = node_X.shape[0]
    S = (N - 1) * sub + 1
    Xs = np.empty(S)
    gap = np.empty(S)
    slope = np.empty(S)
    H = np.empty((3, 3))
    G = np.empty((4, 4))
    xi = Xw[3]
    spread = 0.0
    for s in range(radii.shape[0]):
        spread = max(spread, radii[s] - radii[0], radii[0] - radii[s])
    for i in range(N):
        Xs[i * sub] = node_X[i]
        gap[i * sub] = node_gap[i]
        slope[i * sub] = node_slope[i]
    for i in range(N - 1):
        h = node_X[i + 1] - node_X[i]
        far = _cubic_min(node_gap[i], node_gap[i + 1], h * node_slope[i],
                         h * node_slope[i + 1]) - 2.0 * spread > near + CULL_MARGIN_M
        seg = int_seg[i]
        for s in range(1, sub):
            k = i * sub + s
            Xs[k] = node_X[i] + h * (s / sub)
            if far:
                gap[k], slope[k] = np.inf, 1.0
                continue
            hk = Xs[k] - node_X[i]
            _magnus(q, seg_len[seg], comps, seg * D, int_a[i], hk, False, P, Xw, E, Ms, U, TS)
            _pose_mul(g_nodes[i], E, G)
            _legendre(2.0 * (int_a[i] + hk) / seg_len[seg] - 1.0, P[0])
            _strain_at(P[0], q, seg * D, comps, xi)
            d, n0, n1, n2 = _sdf_world(kind, prm, pose, G[0, 3], G[1, 3], G[2, 3], H)
            gap[k] = d - radii[_locate(offsets, Xs[k])[0]]
            slope[k] = _slope(G, xi, n0, n1, n2)
    return Xs, gap, slope


@_inline
def _gap_derivatives(tab, q, g_nodes, iv, X, kind, prm, pose, w, H, G):
    """Return (d gap/dX, d2 gap/dX2) at X in node interval iv (strain-based p'')."""
    P, Xw, E, Ms, U, TS = w
    xi = Xw[3]
    seg = tab[T_INT_SEG][iv]
    L = tab[T_SEG_LEN][seg]
    a = tab[T_INT_A][iv]
    comps = tab[T_COMPS]
    D = P.shape[1] * comps.shape[0]
    h = X - tab[T_NODE_X][iv]
    _magnus(q, L, comps, seg * D, a, h, False, P, Xw, E, Ms, U, TS)
    _pose_mul(g_nodes[iv], E, G)
    _legendre(2.0 * (a + h) / L - 1.0, P[0])
    _strain_at(P[0], q, seg * D, comps, xi)
    d, n0, n1, n2 = _sdf_world(kind, prm, pose, G[0, 3], G[1, 3], G[2, 3], H)
    k0 = xi[1] * xi[5] - xi[2] * xi[4]                  # k x nu
    k1 = xi[2] * xi[3] - xi[0] * xi[5]
    k2 = xi[0] * xi[4] - xi[1] * xi[3]
    nv = (n0, n1, n2)
    t = (G[0, 0] * xi[3] + G[0, 1] * xi[4] + G[0, 2] * xi[5],
         G[1, 0] * xi[3] + G[1, 1] * xi[4] + G[1, 2] * xi[5],
         G[2, 0] * xi[3] + G[2, 1] * xi[4] + G[2, 2] * xi[5])
    d1, d2n, tHt = 0.0, 0.0, 0.0
    for r in range(3):
        d1 += nv[r] * t[r]
        d2n += nv[r] * (G[r, 0] * k0 + G[r, 1] * k1 + G[r, 2] * k2)
        for c in range(3):
            tHt += t[r] * H[r, c] * t[c]
    return d1, tHt + d2n


@_kernel
def _refine(tab, q, g_nodes, iv, lo, hi, sa, sb, sign, kind, prm, pose, w):
    """
    Return the critical point of the gap in [lo, hi] (a sign change of its slope).

    Safeguarded Newton on the exact rod, bisection where a step would leave the bracket.
    """
    H = np.empty((3, 3))
    G = np.empty((4, 4))
    frac = sa / (sa - sb) if sa != sb else 0.5
    x = min(max(lo + (hi - lo) * frac, lo), hi)
    for _ in range(REFINE_STEPS):
        d1, d2 = _gap_derivatives(tab, q, g_nodes, iv, x, kind, prm, pose, w, H, G)
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
def _find(tab, q, g_nodes, kinds, prms, poses, law, node_gap, node_normal, w):
    """
    Return the gap's critical points near the obstacles: rows (X, obstacle, sign).

    sign +1: a minimum (or the tip when the gap falls towards it), -1: an interior
    maximum. Brackets come from sign changes of the exact gap slope at the samples, so the
    result depends on q only. Fills the node gaps and normals on the way.
    """
    node_X, node_seg, offsets, radii, seg_len, comps = tab[T_NODE_X], tab[T_NODE_SEG], \
        tab[T_OFFSETS], tab[T_RADII], tab[T_SEG_LEN], tab[T_COMPS]
    P, Xw = w.P, w.X
    xi = Xw[3]
    N = node_X.shape[0]
    n_obj = kinds.shape[0]
    sub = int(law[L_SAMPLES])
    near = law[L_NEAR]
    S = (N - 1) * sub + 1
    L = offsets[offsets.shape[0] - 1]
    D = tab[T_N_MODES] * comps.shape[0]
    cand = np.empty((n_obj * (S + 1), 3))
    nc = 0
    H = np.empty((3, 3))
    slope_n = np.empty(N)
    for o in range(n_obj):
        kind, prm, pose = kinds[o], prms[o], poses[o]
        for i in range(N):
            d, n0, n1, n2 = _sdf_world(kind, prm, pose, g_nodes[i, 0, 3], g_nodes[i, 1, 3],
                                       g_nodes[i, 2, 3], H)
            node_normal[o, i, 0], node_normal[o, i, 1], node_normal[o, i, 2] = n0, n1, n2
            node_gap[o, i] = d - radii[_locate(offsets, node_X[i])[0]]
            seg = node_seg[i]
            _legendre(2.0 * (node_X[i] - offsets[seg]) / seg_len[seg] - 1.0, P[0])
            _strain_at(P[0], q, seg * D, comps, xi)
            slope_n[i] = _slope(g_nodes[i], xi, n0, n1, n2)
        Xs, gap, slope = _sample_gaps(tab, q, g_nodes, kind, prm, pose, near, sub, node_gap[o],
                                      slope_n, w)
        for k in range(S - 1):
            if min(gap[k], gap[k + 1]) >= near:
                continue
            up_a, up_b = slope[k] >= 0, slope[k + 1] >= 0
            if up_a == up_b:
                continue
            sign = 1.0 if up_b else -1.0
            cand[nc, 0] = _refine(tab, q, g_nodes, k // sub, Xs[k], Xs[k + 1], slope[k],
                                  slope[k + 1], sign, kind, prm, pose, w)
            cand[nc, 1], cand[nc, 2] = o, sign
            nc += 1
        if slope[S - 1] < 0 and gap[S - 1] < near:
            cand[nc, 0], cand[nc, 1], cand[nc, 2] = L, o, 1.0
            nc += 1
    return cand[:nc]


@_kernel
def _softplus(x):
    return x if x > SOFTPLUS_LINEAR else math.log1p(math.exp(min(x, SOFTPLUS_LINEAR)))


@_kernel
def _add_sliding(tab, seg, P, xi, g, J, D, Htv, nv, coef, tmp, gxq, Kc):
    """
    Add the contact point's sliding to Kc: ``coef gXq^T gXq``, coef = sign lambda / gXX.

    The point is a critical point of the gap over X, so it moves with q; ``gXq = (H p')^T D
    + n^T d p'/dq`` with ``d p'/dq = R (-nu^ J_w + Phi_nu)`` (p' = R nu the tangent).
    """
    comps = tab[T_COMPS]
    nm, ncomp = tab[T_N_MODES], comps.shape[0]
    n = J.shape[1]
    for col in range(n):
        w0, w1, w2 = J[0, col], J[1, col], J[2, col]
        tmp[0, col] = -(xi[4] * w2 - xi[5] * w1)
        tmp[1, col] = -(xi[5] * w0 - xi[3] * w2)
        tmp[2, col] = -(xi[3] * w1 - xi[4] * w0)
    for ci in range(ncomp):
        comp = comps[ci]
        if comp >= 3:
            for j in range(nm):
                tmp[comp - 3, seg * nm * ncomp + ci * nm + j] += P[0, j]
    nb = (g[0, 0] * nv[0] + g[1, 0] * nv[1] + g[2, 0] * nv[2],      # R^T n
          g[0, 1] * nv[0] + g[1, 1] * nv[1] + g[2, 1] * nv[2],
          g[0, 2] * nv[0] + g[1, 2] * nv[1] + g[2, 2] * nv[2])
    for col in range(n):
        s = 0.0
        for r in range(3):
            s += Htv[r] * D[r, col] + nb[r] * tmp[r, col]
        gxq[col] = s
    for a in range(n):
        u = coef * gxq[a]
        for b in range(n):
            Kc[a, b] += u * gxq[b]


@_kernel
def _contact_point(tab, q, g_nodes, J_nodes, X, sign, kind, prm, pose, law, w, g, J, row,
                   Q, Kc, grad, D, tmp, gxq, H):
    """
    Evaluate one contact point at X: fill g, J, its row of numbers and the loads.

    Returns False (nothing added) when the gap is beyond the cutoff. Adds the generalised
    force ``D^T f`` to Q and to Kc the material term ``-D^T df/dp D`` and the sliding of the
    contact point (:func:`_add_sliding`).
    """
    comps, seg_len = tab[T_COMPS], tab[T_SEG_LEN]
    nm, ncomp = tab[T_N_MODES], comps.shape[0]
    n = q.shape[0]
    P, Xw = w.P, w.X
    xi = Xw[3]
    _point_frame(q, tab, g_nodes, J_nodes, X, w, g, J)
    seg, xloc = _locate(tab[T_OFFSETS], X)
    _legendre(2.0 * xloc / seg_len[seg] - 1.0, P[0])
    _strain_at(P[0], q, seg * nm * ncomp, comps, xi)
    d, n0, n1, n2 = _sdf_world(kind, prm, pose, g[0, 3], g[1, 3], g[2, 3], H)
    rad = tab[T_RADII][seg]
    gap = d - rad
    if gap > law[L_CUTOFF]:
        return False
    nv = (n0, n1, n2)
    kv = (xi[1] * xi[5] - xi[2] * xi[4], xi[2] * xi[3] - xi[0] * xi[5],
          xi[0] * xi[4] - xi[1] * xi[3])
    tv = np.empty(3)
    Htv = np.empty(3)
    for r in range(3):
        tv[r] = g[r, 0] * xi[3] + g[r, 1] * xi[4] + g[r, 2] * xi[5]
    gxx = 0.0
    for r in range(3):
        Htv[r] = H[r, 0] * tv[0] + H[r, 1] * tv[1] + H[r, 2] * tv[2]
        gxx += tv[r] * Htv[r] + nv[r] * (g[r, 0] * kv[0] + g[r, 1] * kv[1] + g[r, 2] * kv[2])
    z = -gap / law[L_SMOOTHING]
    pen = law[L_SMOOTHING] * _softplus(z)
    force = law[L_STIFFNESS] * pen * (1.0 + pen / law[L_STIFFENING])
    dforce = -law[L_STIFFNESS] * 0.5 * (1.0 + math.tanh(0.5 * z)) \
        * (1.0 + 2.0 * pen / law[L_STIFFENING])
    row[C_X], row[C_SIGN], row[C_GAP], row[C_RAD] = X, sign, gap, rad
    for r in range(3):
        row[C_P + r] = g[r, 3]
        row[C_N + r] = nv[r]
        row[C_F + r] = sign * force * nv[r]
    # D = R J_v: the world motion of the backbone point per dq.
    for r in range(3):
        for col in range(n):
            D[r, col] = g[r, 0] * J[3, col] + g[r, 1] * J[4, col] + g[r, 2] * J[5, col]
    for col in range(n):
        grad[col] = nv[0] * D[0, col] + nv[1] * D[1, col] + nv[2] * D[2, col]
        Q[col] += row[C_F] * D[0, col] + row[C_F + 1] * D[1, col] + row[C_F + 2] * D[2, col]
    # -D^T df/dp D, df/dp = sign (lambda' n n^T + lambda H).
    for a in range(n):
        for r in range(3):
            u = 0.0
            for s in range(3):
                u += D[s, a] * (sign * dforce * nv[s] * nv[r] + sign * force * H[s, r])
            if u != 0.0:
                for b in range(n):
                    Kc[a, b] -= u * D[r, b]
    if X < tab[T_OFFSETS][tab[T_OFFSETS].shape[0] - 1] - TIP_GUARD_M and sign * gxx > SLIDE_FLOOR:
        _add_sliding(tab, seg, P, xi, g, J, D, Htv, nv, sign * force / gxx, tmp, gxq, Kc)
    return True


@_kernel
def _step_rows(rows, grad, node_gap, node_normal, g_nodes, J_nodes, depth):
    """
    Return (A, lo): the linearised gaps a Newton step must keep, ``A dq >= lo``.

    Each contact (ridges aside) may press to ``depth`` or twice its depth: where it lifts
    off, its penalty is nearly flat and the Newton model alone would send it millimetres
    deep. Each node now outside may press at most ``depth`` in.
    """
    n = grad.shape[1]
    n_rows = 0
    for c in range(rows.shape[0]):
        n_rows += rows[c, C_SIGN] > 0
    for o in range(node_gap.shape[0]):
        for i in range(node_gap.shape[1]):
            n_rows += node_gap[o, i] > 0
    A = np.empty((n_rows, n))
    lo = np.empty(n_rows)
    r = 0
    for c in range(rows.shape[0]):
        if rows[c, C_SIGN] > 0:
            gap = rows[c, C_GAP]
            for col in range(n):
                A[r, col] = grad[c, col]
            lo[r] = min(2.0 * gap, -depth) - gap
            r += 1
    for o in range(node_gap.shape[0]):
        for i in range(node_gap.shape[1]):
            if node_gap[o, i] > 0:
                for col in range(n):
                    s = 0.0
                    for a in range(3):
                        s += node_normal[o, i, a] * (g_nodes[i, a, 0] * J_nodes[i, 3, col]
                                                     + g_nodes[i, a, 1] * J_nodes[i, 4, col]
                                                     + g_nodes[i, a, 2] * J_nodes[i, 5, col])
                    A[r, col] = s
                lo[r] = -depth - node_gap[o, i]
                r += 1
    return A, lo


@_kernel
def penalty_contacts(tf, ti, q, g_nodes, J_nodes, kinds, prms, poses, law):
    """
    Return the contact points of a shape and their loads.

    Returns (rows (C, C_COLS): X, obstacle, sign, gap, backbone point, normal, force,
    radius; poses (C, 4, 4); Jacobians (C, 6, n); generalised force Q (n,); tangent part Kc
    (n, n); step rows A (R, n) and lower bounds lo (R,); node gaps (O, N)). Kc holds the
    material and sliding terms; the geometric (dead-load) part comes with the other point
    loads in :func:`geometric_stiffness`; the step rows are :func:`_step_rows`.
    """
    tab = _unpack(tf, ti)
    N = tab[T_NODE_X].shape[0]
    n_obj = kinds.shape[0]
    n = q.shape[0]
    w = scratch(tab[T_N_MODES], tab[T_N_MODES] * tab[T_COMPS].shape[0])
    node_gap = np.empty((n_obj, N))
    node_normal = np.empty((n_obj, N, 3))
    cand = _find(tab, q, g_nodes, kinds, prms, poses, law, node_gap, node_normal, w)
    C = cand.shape[0]
    rows = np.empty((C, C_COLS))
    g = np.empty((C, 4, 4))
    J = np.zeros((C, 6, n))
    grad = np.empty((C, n))
    Q = np.zeros(n)
    Kc = np.zeros((n, n))
    H = np.empty((3, 3))
    D = np.empty((3, n))
    tmp = np.empty((3, n))
    gxq = np.empty(n)
    kept = 0
    for c in range(C):
        o = int(cand[c, 1])
        if _contact_point(tab, q, g_nodes, J_nodes, cand[c, 0], cand[c, 2], kinds[o], prms[o],
                          poses[o], law, w, g[kept], J[kept], rows[kept], Q, Kc, grad[kept], D,
                          tmp, gxq, H):
            rows[kept, C_OBJ] = o
            kept += 1
    A, lo = _step_rows(rows[:kept], grad, node_gap, node_normal, g_nodes, J_nodes,
                       law[L_STEP_DEPTH])
    return rows[:kept], g[:kept], J[:kept], Q, Kc, A, lo, node_gap


# Spence's integral by Cephes' rational approximation (S. L. Moshier), the one
# scipy.special.spence uses, so the penalty potential matches scipy to rounding.
_SPENCE_A = (4.65128586073990045278E-5, 7.31589045238094711071E-3, 1.33847639578309018650E-1,
             8.79691311754530315341E-1, 2.71149851196553469920E0, 4.25697156008121755724E0,
             3.29771340985225106936E0, 1.00000000000000000126E0)
_SPENCE_B = (6.90990488912553276999E-4, 2.54043763932544379113E-2, 2.82974860602568089943E-1,
             1.41172597751831069617E0, 3.63800533345137075418E0, 5.03278880143316990390E0,
             3.54771340985225096217E0, 9.99999999999999998740E-1)


@_kernel
def spence(x):
    """Return Spence's integral -int_1^x log t / (t - 1) dt for x >= 0 (NaN below)."""
    if x < 0.0:
        return np.nan
    if x == 1.0:
        return 0.0
    if x == 0.0:
        return math.pi * math.pi / 6.0
    flag = 0
    if x > 2.0:
        x = 1.0 / x
        flag |= 2
    if x > 1.5:
        w = (1.0 / x) - 1.0
        flag |= 2
    elif x < 0.5:
        w = -x
        flag |= 1
    else:
        w = x - 1.0
    pa, pb = _SPENCE_A[0], _SPENCE_B[0]
    for i in range(1, 8):
        pa = pa * w + _SPENCE_A[i]
        pb = pb * w + _SPENCE_B[i]
    y = -w * pa / pb
    if flag & 1:
        y = (math.pi * math.pi) / 6.0 - math.log(x) * math.log(1.0 - x) - y
    if flag & 2:
        z = math.log(x)
        y = -0.5 * z * z - y
    return y


@_kernel
def penalty_energy(rows, stiffness, smoothing, stiffening):
    """
    Return the penalty potential of the contacts: sum of sign x (smooth part + stiffening).

    Smooth part ``int_gap^inf k pen = k delta^2 (-Li2(-e^z))``, z = -gap / delta,
    ``-Li2(-e^z) = -spence(1 + e^z)`` (its asymptote beyond z = SOFTPLUS_LINEAR); the
    stiffening part ``k pen^3 / (3 p0)`` taken unsmoothed (it only serves as a merit).
    """
    e = 0.0
    for c in range(rows.shape[0]):
        gap = rows[c, C_GAP]
        z = -gap / smoothing
        if z > SOFTPLUS_LINEAR:
            smooth = z ** 2 / 2 + math.pi ** 2 / 6 - math.exp(-z)
        else:
            smooth = -spence(1.0 + math.exp(z))
        e += rows[c, C_SIGN] * (stiffness * smoothing ** 2 * smooth
                                + stiffness * max(0.0, -gap) ** 3 / (3 * stiffening))
    return e


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
def _moment_and_rate(g, J, f, m, fm, dfm):
    """Write fm = m + p x f (moment about the origin) and d(p x f)/dq = -f^ R J_v (3, n)."""
    p0, p1, p2 = g[0, 3], g[1, 3], g[2, 3]
    fm[0] = m[0] + (p1 * f[2] - p2 * f[1])
    fm[1] = m[1] + (p2 * f[0] - p0 * f[2])
    fm[2] = m[2] + (p0 * f[1] - p1 * f[0])
    for col in range(J.shape[1]):
        D0 = g[0, 0] * J[3, col] + g[0, 1] * J[4, col] + g[0, 2] * J[5, col]
        D1 = g[1, 0] * J[3, col] + g[1, 1] * J[4, col] + g[1, 2] * J[5, col]
        D2 = g[2, 0] * J[3, col] + g[2, 1] * J[4, col] + g[2, 2] * J[5, col]
        dfm[0, col] = f[2] * D1 - f[1] * D2
        dfm[1, col] = f[0] * D2 - f[2] * D0
        dfm[2, col] = f[1] * D0 - f[0] * D1


@_kernel
def _bin_add(Fb, Mb, dMb, b, f, fm, dfm):
    """Add a load (force f, moment fm about the origin, its rate dfm) to bin b."""
    for r in range(3):
        Fb[b, r] += f[r]
        Mb[b, r] += fm[r]
        for col in range(dfm.shape[1]):
            dMb[b, r, col] += dfm[r, col]


@_kernel
def _own_segment_rule(tab, q, g_nodes, J_nodes, seg, x, f, fm, dfm, quad, w, Kg, Qp):
    """
    Integrate one point load over its own segment, [segment start, X]: Kg, and Qp if quad.

    The load's internal wrench there is constant in the world (f, moment fm about the
    origin), so a Gauss rule on that stretch integrates ``Phi^T Lambda`` exactly enough
    whatever the basis order.
    """
    comps, seg_len = tab[T_COMPS], tab[T_SEG_LEN]
    rule_x, rule_w = tab[T_RULE_X], tab[T_RULE_W]
    start = tab[T_OFFSETS][seg]
    n = q.shape[0]
    D = tab[T_N_MODES] * comps.shape[0]
    P = np.empty((1, tab[T_N_MODES]))
    dl = np.empty((6, n))
    wrench = np.empty(6)
    gq = np.empty((4, 4))
    Jq = np.empty((6, n))
    for k in range(rule_x.shape[0]):
        Xq = start + x * (rule_x[k] + 1) / 2
        wq = x * rule_w[k] / 2
        _point_frame(q, tab, g_nodes, J_nodes, Xq, w, gq, Jq)
        _legendre(2.0 * (Xq - start) / seg_len[seg] - 1.0, P[0])
        _wrench_rate(gq, Jq, f, fm, dfm, dl)
        _add_phi_t(comps, seg * D, P, wq, dl, Kg)
        if quad:
            _wrench(gq, f, fm, wrench)
            _add_phi_t_vec(comps, seg * D, P, wq, wrench, Qp)


@_kernel
def geometric_stiffness(tf, ti, q, g_nodes, J_nodes, grav_f, pt_X, pt_g, pt_J, pt_f, pt_m,
                        pt_quad):
    """
    Return (Qp, Kg): point loads in quadrature form, and the geometric stiffness of all loads.

    ``Kg = d/dq sum_k w_k Phi_k^T Lambda_k``, Lambda the internal wrench at each Gauss point
    from everything distal (dead loads: gravity ``grav_f`` (K, 3) at the Gauss points, and
    the point forces/moments ``pt_*``). Lambda is smooth between load points, so each point
    load's own segment is integrated by a Gauss rule on [segment start, X] and the segments
    before it on the regular points: ``Qp = int_0^X Phi^T Lambda dX``, the continuum virtual
    work, exact for a constant internal wrench (pure moment, tendon) at any basis order.
    Qp covers the points flagged in ``pt_quad``; Kg all loads. Loads go into bins: bin b is
    distal to Gauss points 0..b-1.
    """
    tab = _unpack(tf, ti)
    comps, offsets, seg_len = tab[T_COMPS], tab[T_OFFSETS], tab[T_SEG_LEN]
    gauss_X, gauss_node = tab[T_GAUSS_X], tab[T_GAUSS_NODE]
    gauss_seg, gauss_w = tab[T_GAUSS_SEG], tab[T_GAUSS_W]
    nm = tab[T_N_MODES]
    D = nm * comps.shape[0]
    n = q.shape[0]
    K = gauss_X.shape[0]
    Fb = np.zeros((K + 1, 3))
    Mb = np.zeros((K + 1, 3))
    dMb = np.zeros((K + 1, 3, n))
    Fp = np.zeros((K + 1, 3))              # the loads whose residual is in quadrature form
    Mp = np.zeros((K + 1, 3))
    Kg = np.zeros((n, n))
    Qp = np.zeros(n)
    w = scratch(nm, D)
    P = np.empty((1, nm))
    fm = np.empty(3)
    dfm = np.empty((3, n))
    dl = np.empty((6, n))
    wrench = np.empty(6)
    zero = np.zeros(3)
    for j in range(grav_f.shape[0]):
        node = gauss_node[j]
        _moment_and_rate(g_nodes[node], J_nodes[node], grav_f[j], zero, fm, dfm)
        _bin_add(Fb, Mb, dMb, j + 1, grav_f[j], fm, dfm)
    for i in range(pt_X.shape[0]):
        _moment_and_rate(pt_g[i], pt_J[i], pt_f[i], pt_m[i], fm, dfm)
        seg, x = _locate(offsets, pt_X[i])
        b = _bisect_right(gauss_X, offsets[seg] - LOCATE_EPS_M)
        if x > 0.0:
            _own_segment_rule(tab, q, g_nodes, J_nodes, seg, x, pt_f[i], fm, dfm, pt_quad[i],
                              w, Kg, Qp)
        _bin_add(Fb, Mb, dMb, b, pt_f[i], fm, dfm)
        if pt_quad[i]:
            for r in range(3):
                Fp[b, r] += pt_f[i, r]
                Mp[b, r] += fm[r]
    # Gauss point k collects every load in bins > k (strictly distal).
    F = np.zeros(3)
    M = np.zeros(3)
    dM = np.zeros((3, n))
    Fq = np.zeros(3)
    Mq = np.zeros(3)
    for k in range(K - 1, -1, -1):
        for r in range(3):
            F[r] += Fb[k + 1, r]
            M[r] += Mb[k + 1, r]
            Fq[r] += Fp[k + 1, r]
            Mq[r] += Mp[k + 1, r]
            for col in range(n):
                dM[r, col] += dMb[k + 1, r, col]
        node, seg = gauss_node[k], gauss_seg[k]
        _legendre(2.0 * (gauss_X[k] - offsets[seg]) / seg_len[seg] - 1.0, P[0])
        _wrench_rate(g_nodes[node], J_nodes[node], F, M, dM, dl)
        _add_phi_t(comps, seg * D, P, gauss_w[k], dl, Kg)
        _wrench(g_nodes[node], Fq, Mq, wrench)
        _add_phi_t_vec(comps, seg * D, P, gauss_w[k], wrench, Qp)
    return Qp, Kg


@_kernel
def _add_tendon(xi, d0, d1, d2, T, wrench, dwrench, B):
    """
    Add one tendon's wrench on the section and its strain derivative; return its length rate.

    The tendon at body offset d runs along ``v = nu + k x d``; its wrench is
    ``-T [d x t; t]``, t = v / |v|, and ``d wrench / d xi = -T [d^; I] (I - t t^T) / |v|
    [-d^, I]``. B: (6, 3) scratch.
    """
    v0 = (xi[1] * d2 - xi[2] * d1) + xi[3]
    v1 = (xi[2] * d0 - xi[0] * d2) + xi[4]
    v2 = (xi[0] * d1 - xi[1] * d0) + xi[5]
    nv = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    t = (v0 / nv, v1 / nv, v2 / nv)
    wrench[0] -= T * (d1 * t[2] - d2 * t[1])
    wrench[1] -= T * (d2 * t[0] - d0 * t[2])
    wrench[2] -= T * (d0 * t[1] - d1 * t[0])
    wrench[3] -= T * t[0]
    wrench[4] -= T * t[1]
    wrench[5] -= T * t[2]
    dh = ((0.0, -d2, d1), (d2, 0.0, -d0), (-d1, d0, 0.0))
    for i in range(3):
        for j in range(3):
            B[3 + i, j] = ((1.0 if i == j else 0.0) - t[i] * t[j]) / nv
    for i in range(3):
        for j in range(3):
            B[i, j] = dh[i][0] * B[3, j] + dh[i][1] * B[4, j] + dh[i][2] * B[5, j]
    for i in range(6):
        for j in range(3):
            dwrench[i, j] -= T * -(B[i, 0] * dh[0][j] + B[i, 1] * dh[1][j] + B[i, 2] * dh[2][j])
            dwrench[i, 3 + j] -= T * B[i, j]
    return nv


@_kernel
def tendon_terms(tf, ti, xi_gauss, td_d, td_on, tension):
    """
    Return (Q, dQ/dq, energy) of thread-like tendons; slack (negative) tensions pull nothing.

    Each tendon's wrench (:func:`_add_tendon`) integrated by the Gauss rule; its potential
    is T times its length.
    """
    tab = _unpack(tf, ti)
    comps, offsets, seg_len = tab[T_COMPS], tab[T_OFFSETS], tab[T_SEG_LEN]
    gauss_X, gauss_seg, gauss_w = tab[T_GAUSS_X], tab[T_GAUSS_SEG], tab[T_GAUSS_W]
    nm, nc = tab[T_N_MODES], comps.shape[0]
    D = nm * nc
    n = D * seg_len.shape[0]
    Q = np.zeros(n)
    dQ = np.zeros((n, n))
    energy = 0.0
    P = np.empty((1, nm))
    wrench = np.empty(6)
    dwrench = np.empty((6, 6))
    B = np.empty((6, 3))
    tmp = np.empty((6, n))
    for k in range(xi_gauss.shape[0]):
        seg = gauss_seg[k]
        for i in range(6):
            wrench[i] = 0.0
            for j in range(6):
                dwrench[i, j] = 0.0
        for a in range(td_d.shape[0]):
            T = max(tension[a], 0.0) * td_on[k, a]
            nv = _add_tendon(xi_gauss[k], td_d[a, 0], td_d[a, 1], td_d[a, 2], T, wrench,
                             dwrench, B)
            energy += gauss_w[k] * T * nv
        _legendre(2.0 * (gauss_X[k] - offsets[seg]) / seg_len[seg] - 1.0, P[0])
        _add_phi_t_vec(comps, seg * D, P, gauss_w[k], wrench, Q)
        # dQ += w Phi^T dwrench Phi: dwrench Phi first (6, n), then Phi^T.
        for r in range(6):
            for col in range(n):
                tmp[r, col] = 0.0
        for ci in range(nc):
            c = comps[ci]
            for j in range(nm):
                col = seg * D + ci * nm + j
                for r in range(6):
                    tmp[r, col] = dwrench[r, c] * P[0, j]
        _add_phi_t(comps, seg * D, P, gauss_w[k], tmp, dQ)
    return Q, dQ, energy
