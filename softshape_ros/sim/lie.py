"""
SE(3) helpers for the Cosserat rod, batched over a leading axis.

Twists and wrenches are 6-vectors with the angular part first (SoRoSim order):
``xi = [k, nu]``. Closed forms (Rodrigues, and the Cayley-Hamilton form of the tangent
operator) keep the kinematics exact for constant strain, which the exact-answer tests need.
"""

from __future__ import annotations

import numpy as np

_SMALL = 1e-2


def _skew_rows(v):
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


# skew and ad as one product with a constant 0/+-1 matrix (exact): a single numpy call
# instead of a dozen, which is what these small arrays cost.
_SKEW = _skew_rows(np.eye(3)).reshape(3, 9)


def _ad_rows(x):
    out = np.zeros(x.shape[:-1] + (6, 6))
    w, v = _skew_rows(x[..., :3]), _skew_rows(x[..., 3:])
    out[..., :3, :3] = w
    out[..., 3:, 3:] = w
    out[..., 3:, :3] = v
    return out


_AD = _ad_rows(np.eye(6)).reshape(6, 36)


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 cross-product matrix(es) of ``v`` (..., 3)."""
    v = np.asarray(v, dtype=float)
    return (v @ _SKEW).reshape(v.shape[:-1] + (3, 3))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return a x b over the last axis (broadcasting; faster than np.cross for small arrays)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return np.einsum('...ij,...j->...i', skew(a), b)


def ad(x: np.ndarray) -> np.ndarray:
    """Return the 6x6 adjoint matrix(es) of twists ``x`` (..., 6): ``ad_x y = [x, y]``."""
    x = np.asarray(x, dtype=float)
    return (x @ _AD).reshape(x.shape[:-1] + (6, 6))


def ad_inv_pose(g: np.ndarray) -> np.ndarray:
    """Return ``Ad_{g^-1}`` (..., 6, 6) for poses ``g`` (..., 4, 4): maps twists into g's frame."""
    R = g[..., :3, :3]
    p = g[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros(g.shape[:-2] + (6, 6))
    out[..., :3, :3] = Rt
    out[..., 3:, 3:] = Rt
    out[..., 3:, :3] = -Rt @ skew(p)
    return out


def _coefficients(th2, tangent: bool):
    """
    Return the exp coefficients (a, b, c) and, if ``tangent``, dexp's (f1..f4) of angles^2.

    Closed forms; the series below ``_SMALL`` are evaluated only when such angles occur.
    """
    small = th2 < _SMALL * _SMALL
    all_small = bool(small.all())
    any_small = all_small or bool(small.any())
    if not all_small:
        t = np.sqrt(np.where(small, 1.0, th2) if any_small else th2)
        s, c = np.sin(t), np.cos(t)
        t2 = t * t
        t3 = t2 * t
        out = [s / t, (1 - c) / t2, (t - s) / t3]
        if tangent:
            ts, tc = t * s, t * c
            out += [-(4 - 4 * c - ts) / (2 * t2), (4 * t - 5 * s + tc) / (2 * t3),
                    -(2 - 2 * c - ts) / (2 * t2 * t2), (2 * t - 3 * s + tc) / (2 * t3 * t2)]
        if not any_small:
            return out
    th4 = th2 * th2
    series = [1 - th2 / 6 + th4 / 120, 0.5 - th2 / 24 + th4 / 720,
              1 / 6 - th2 / 120 + th4 / 5040]
    if tangent:
        series += [-(0.5 - th4 / 720), 1 / 6 - th4 / 5040,
                   -(1 / 24 - th2 / 360 + th4 / 13440),
                   1 / 120 - th2 / 2520 + th4 / 120960]
    if all_small:
        return series
    return [np.where(small, a, b) for a, b in zip(series, out)]


def _exp(x, coef):
    """Return exp(x) (..., 4, 4) from its coefficients (Rodrigues)."""
    a, b, c = (k[..., None, None] for k in coef[:3])
    W = skew(x[..., :3])
    W2 = W @ W
    out = np.zeros(x.shape[:-1] + (4, 4))
    out[..., :3, :3] = a * W + b * W2
    out[..., :3, 3] = x[..., 3:]
    out[..., :3, 3] += np.einsum('...ij,...j->...i', b * W + c * W2, x[..., 3:])
    out[..., 0, 0] += 1.0
    out[..., 1, 1] += 1.0
    out[..., 2, 2] += 1.0
    out[..., 3, 3] = 1.0
    return out


def _dexp(x, coef):
    A = ad(x)
    A2 = A @ A
    A3 = A2 @ A
    A4 = A2 @ A2
    e = (Ellipsis, None, None)
    f1, f2, f3, f4 = coef[3:]
    return np.eye(6) + f1[e] * A + f2[e] * A2 + f3[e] * A3 + f4[e] * A4


def exp_se3(x: np.ndarray) -> np.ndarray:
    """Return the SE(3) exponential(s) (..., 4, 4) of twists ``x`` (..., 6), closed form."""
    x = np.asarray(x, dtype=float)
    return _exp(x, _coefficients(np.sum(x[..., :3] ** 2, axis=-1), False))


def dexp_se3(x: np.ndarray) -> np.ndarray:
    """
    Return the tangent operator T(x) (..., 6, 6) with ``d exp(x) = exp(x) (T(x) dx)^``.

    T(x) = sum_k (-ad_x)^k / (k+1)!, written with Cayley-Hamilton
    (ad^5 = -2 th^2 ad^3 - th^4 ad) as I + f1 ad + f2 ad^2 + f3 ad^3 + f4 ad^4.
    """
    x = np.asarray(x, dtype=float)
    return _dexp(x, _coefficients(np.sum(x[..., :3] ** 2, axis=-1), True))


def exp_dexp_se3(x: np.ndarray, adinv: bool = True):
    """Return exp(x), Ad_{exp(-x)} (None unless ``adinv``) and T(x), sharing coefficients."""
    x = np.asarray(x, dtype=float)
    coef = _coefficients(np.sum(x[..., :3] ** 2, axis=-1), True)
    E = _exp(x, coef)
    return E, (ad_inv_pose(E) if adinv else None), _dexp(x, coef)


def rpy_matrix(rpy) -> np.ndarray:
    """Return R = Rz(yaw) Ry(pitch) Rx(roll), the ROS convention for fixed-axis rpy."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def pose(position, rpy) -> np.ndarray:
    """Return the 4x4 pose from a position and roll-pitch-yaw."""
    g = np.eye(4)
    g[:3, :3] = rpy_matrix(rpy)
    g[:3, 3] = np.asarray(position, dtype=float)
    return g
