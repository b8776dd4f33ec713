"""
Z-buffered renderer compiled with numba: the robot as a tube of its real radius, objects as solids.

The robot is a closed triangle mesh (a ring of vertices around each backbone point, framed
by parallel transport, and hemispherical caps) whose rings stay within a tenth of a pixel of
the tube's circle (their vertex count follows the tube's size in pixels), rasterised front
faces only, with depth from 1/z and normals interpolated perspective-correctly. Objects are
intersected exactly, per pixel of their projected bounding box: sphere, plane, cylinder and
oblique prism analytically, the ring by sphere tracing its exact distance. Each pixel keeps
the nearest surface, so occlusion is right whichever is in front. Lambertian shading with a
head light; the robot is dark, objects mid-light and the background light, so the three stay
apart in gray (the model learns from them). Everything runs in the camera frame, in one
compiled pass per view that writes the uint8 image directly.
"""

from __future__ import annotations

import threading

import numba
import numpy as np

from softshape_ros.sim.camera import PinholeCamera

BACKGROUND_RGB = np.array([0.94, 0.94, 0.94])
ROBOT_RGB = np.array([0.62, 0.30, 0.22])       # gray ~0.37 when lit
OBJECT_RGB = np.array([0.62, 0.80, 0.95])      # gray ~0.77 when lit
ROBOT_AMBIENT, OBJECT_AMBIENT = 0.45, 0.72
OUTLINE_TOLERANCE_PX = 0.1  # the mesh rings' chords stay this close to the tube's circle

# Object kinds in the packed parameter rows.
SPHERE, PLANE, CYLINDER, RING, PRISM = 0, 1, 2, 3, 4
_KINDS = {'sphere': SPHERE, 'plane': PLANE, 'cylinder': CYLINDER, 'ring': RING, 'prism': PRISM}
_OBJ_COLS = 48              # [kind, M (9), o (3), -, shape (24), x0 x1 y0 y1 zmin of the image]

_JIT = dict(cache=True, nogil=True, error_model='numpy')
_INLINE = dict(_JIT, inline='always')     # per-pixel helpers: a call costs more than the work


class RenderError(ValueError):
    """A view that cannot be rendered honestly (bad geometry, size or camera placement)."""


# -- the robot: a closed triangle mesh of the tube ---------------------------------------------
@numba.njit(**_JIT)
def _unit(x, y, z):
    n = np.sqrt(x * x + y * y + z * z)
    return x / n, y / n, z / n


@numba.njit(**_JIT)
def _frames(p):
    """Return unit tangents (N, 3) and parallel-transported unit normals (N, 3) along ``p``."""
    N = p.shape[0]
    T = np.empty((N, 3))
    for k in range(N):
        a, b = max(k - 1, 0), min(k + 1, N - 1)
        if a == b:
            T[k, 0], T[k, 1], T[k, 2] = 0.0, 0.0, 1.0
        else:
            T[k, 0], T[k, 1], T[k, 2] = _unit(p[b, 0] - p[a, 0], p[b, 1] - p[a, 1],
                                              p[b, 2] - p[a, 2])
    # A first normal: the axis least aligned with the tangent, made orthogonal to it.
    e = np.zeros(3)
    e[np.argmin(np.abs(T[0]))] = 1.0
    d = e @ T[0]
    U = np.empty((N, 3))
    U[0, 0], U[0, 1], U[0, 2] = _unit(e[0] - d * T[0, 0], e[1] - d * T[0, 1],
                                      e[2] - d * T[0, 2])
    for k in range(N - 1):
        # Double reflection (Wang et al. 2008): a rotation-minimising frame, no twist.
        v1 = p[k + 1] - p[k]
        c1 = v1 @ v1
        if c1 < 1e-30:
            U[k + 1] = U[k]
            continue
        rL = U[k] - (2.0 / c1) * (v1 @ U[k]) * v1
        tL = T[k] - (2.0 / c1) * (v1 @ T[k]) * v1
        v2 = T[k + 1] - tL
        c2 = v2 @ v2
        if c2 > 1e-30:
            rL = rL - (2.0 / c2) * (v2 @ rL) * v2
        d = rL @ T[k + 1]
        U[k + 1, 0], U[k + 1, 1], U[k + 1, 2] = _unit(rL[0] - d * T[k + 1, 0],
                                                      rL[1] - d * T[k + 1, 1],
                                                      rL[2] - d * T[k + 1, 2])
    return T, U


@numba.njit(**_JIT)
def tube_mesh(p, radii, n_theta, n_cap):
    """
    Return (vertices (V, 3), unit normals (V, 3), triangles (T, 3)) of the tube through ``p``.

    A ring of ``n_theta`` vertices of radius ``radii[k]`` around each backbone point, normal
    to the backbone there; hemispherical caps of ``n_cap`` latitude bands close the base and
    the tip, as the contact model has them. Triangles wind outward.
    """
    N = p.shape[0]
    T, U = _frames(p)
    ang = 2.0 * np.pi * np.arange(n_theta) / n_theta
    ct, st = np.cos(ang), np.sin(ang)
    rings = N + 2 * (n_cap - 1)
    V = rings * n_theta + 2
    verts = np.empty((V, 3))
    norms = np.empty((V, 3))
    # Rings in order: the base cap from its pole, the tube, the tip cap to its pole.
    ring = 0
    for side in range(3):
        count = N if side == 1 else n_cap - 1
        for m in range(count):
            if side == 0:
                k, lat = 0, -0.5 * np.pi * (n_cap - 1 - m) / n_cap
            elif side == 1:
                k, lat = m, 0.0
            else:
                k, lat = N - 1, 0.5 * np.pi * (m + 1) / n_cap
            tx, ty, tz = T[k, 0], T[k, 1], T[k, 2]
            ux, uy, uz = U[k, 0], U[k, 1], U[k, 2]
            wx, wy, wz = ty * uz - tz * uy, tz * ux - tx * uz, tx * uy - ty * ux
            cl, sl = np.cos(lat), np.sin(lat)
            r, px, py, pz = radii[k], p[k, 0], p[k, 1], p[k, 2]
            for j in range(n_theta):
                q = ring * n_theta + j
                nx = cl * (ct[j] * ux + st[j] * wx) + sl * tx
                ny = cl * (ct[j] * uy + st[j] * wy) + sl * ty
                nz = cl * (ct[j] * uz + st[j] * wz) + sl * tz
                norms[q, 0], norms[q, 1], norms[q, 2] = nx, ny, nz
                verts[q, 0], verts[q, 1], verts[q, 2] = px + r * nx, py + r * ny, pz + r * nz
            ring += 1
    pole0, pole1 = V - 2, V - 1
    for c in range(3):
        norms[pole0, c], norms[pole1, c] = -T[0, c], T[N - 1, c]
        verts[pole0, c] = p[0, c] - radii[0] * T[0, c]
        verts[pole1, c] = p[N - 1, c] + radii[N - 1] * T[N - 1, c]
    tris = np.empty((2 * rings * n_theta, 3), np.int32)
    n = 0
    for g in range(rings - 1):
        for j in range(n_theta):
            a, b = g * n_theta + j, g * n_theta + (j + 1) % n_theta
            tris[n, 0], tris[n, 1], tris[n, 2] = a, b, a + n_theta
            tris[n + 1, 0], tris[n + 1, 1], tris[n + 1, 2] = b, b + n_theta, a + n_theta
            n += 2
    last = (rings - 1) * n_theta
    for j in range(n_theta):
        jb = (j + 1) % n_theta
        tris[n, 0], tris[n, 1], tris[n, 2] = pole0, jb, j
        tris[n + 1, 0], tris[n + 1, 1], tris[n + 1, 2] = pole1, last + j, last + jb
        n += 2
    # Wind every triangle outward: its normal along its vertices' normals.
    for n in range(tris.shape[0]):
        a, b, c = tris[n, 0], tris[n, 1], tris[n, 2]
        e1x, e1y, e1z = verts[b, 0] - verts[a, 0], verts[b, 1] - verts[a, 1], \
            verts[b, 2] - verts[a, 2]
        e2x, e2y, e2z = verts[c, 0] - verts[a, 0], verts[c, 1] - verts[a, 1], \
            verts[c, 2] - verts[a, 2]
        g = ((e1y * e2z - e1z * e2y) * (norms[a, 0] + norms[b, 0] + norms[c, 0])
             + (e1z * e2x - e1x * e2z) * (norms[a, 1] + norms[b, 1] + norms[c, 1])
             + (e1x * e2y - e1y * e2x) * (norms[a, 2] + norms[b, 2] + norms[c, 2]))
        if g < 0.0:
            tris[n, 1], tris[n, 2] = c, b
    return verts, norms, tris


@numba.njit(**_JIT)
def _raster_mesh(verts, norms, tris, fx, fy, cx, cy, u0, du, v0, dv, depth, ident, normal,
                 scr):
    """
    Z-buffer the front faces of a closed camera-frame mesh with its interpolated normals.

    Pixel (i, j) is the ray through grid point (u0 + du j, v0 + dv i). Depth is z, from 1/z
    interpolated linearly in the image (exact on the triangle's plane); normals are
    interpolated perspective-correctly. ``scr`` is work space for (j, i, 1/z) per vertex.
    """
    H, W = depth.shape
    for q in range(verts.shape[0]):
        iz = 1.0 / verts[q, 2]
        scr[q, 0] = (verts[q, 0] * iz * fx + cx - u0) / du
        scr[q, 1] = (verts[q, 1] * iz * fy + cy - v0) / dv
        scr[q, 2] = iz
    for n in range(tris.shape[0]):
        a, b, c = tris[n, 0], tris[n, 1], tris[n, 2]
        ax, ay = scr[a, 0], scr[a, 1]
        bx, by = scr[b, 0], scr[b, 1]
        qx, qy = scr[c, 0], scr[c, 1]
        area = (bx - ax) * (qy - ay) - (by - ay) * (qx - ax)
        if area >= 0.0:
            continue                              # a back face (x right, y down) or edge-on
        j0 = max(int(np.ceil(min(ax, bx, qx) - 1e-9)), 0)
        j1 = min(int(np.floor(max(ax, bx, qx) + 1e-9)), W - 1)
        i0 = max(int(np.ceil(min(ay, by, qy) - 1e-9)), 0)
        i1 = min(int(np.floor(max(ay, by, qy) + 1e-9)), H - 1)
        if j0 > j1 or i0 > i1:
            continue
        inv = 1.0 / area
        za, zb, zc = scr[a, 2] * inv, scr[b, 2] * inv, scr[c, 2] * inv
        nax, nay, naz = norms[a, 0] * za, norms[a, 1] * za, norms[a, 2] * za
        nbx, nby, nbz = norms[b, 0] * zb, norms[b, 1] * zb, norms[b, 2] * zb
        ncx, ncy, ncz = norms[c, 0] * zc, norms[c, 1] * zc, norms[c, 2] * zc
        tol = 1e-9 * -area                        # shared edges: no pixel falls between
        for i in range(i0, i1 + 1):
            # The edge functions (area x barycentric weight; <= 0 inside a front face) are
            # linear along the row.
            wa = (qx - bx) * (i - by) - (qy - by) * (j0 - bx)
            wb = (ax - qx) * (i - qy) - (ay - qy) * (j0 - qx)
            wc = (bx - ax) * (i - ay) - (by - ay) * (j0 - ax)
            da, db, dc = -(qy - by), -(ay - qy), -(by - ay)
            for j in range(j0, j1 + 1):
                if wa <= tol and wb <= tol and wc <= tol:
                    iz = wa * za + wb * zb + wc * zc
                    z = 1.0 / iz
                    if z < depth[i, j]:
                        depth[i, j] = z
                        ident[i, j] = n
                        # (barycentric / z) weights; the sum over 1/z normalises, sign kept.
                        nx = wa * nax + wb * nbx + wc * ncx
                        ny = wa * nay + wb * nby + wc * ncy
                        nz = wa * naz + wb * nbz + wc * ncz
                        k = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
                        normal[i, j, 0], normal[i, j, 1], normal[i, j, 2] = \
                            nx * k, ny * k, nz * k
                wa += da
                wb += db
                wc += dc


# -- objects: exact ray intersections ------------------------------------------------------------
@numba.njit(**_JIT)
def _sphere_bounds(X, Y, Z, r):
    """Return the normalised image bounds (x0, x1, y0, y1) of a sphere's exact silhouette."""
    if Z - r <= 1e-9:
        return -np.inf, np.inf, -np.inf, np.inf   # touches the camera plane: unbounded
    den = Z * Z - r * r
    sx = r * np.sqrt(X * X + den)
    sy = r * np.sqrt(Y * Y + den)
    return (X * Z - sx) / den, (X * Z + sx) / den, (Y * Z - sy) / den, (Y * Z + sy) / den


@numba.njit(**_JIT)
def _pixel_box(x0, x1, y0, y1, fx, fy, cx, cy, u0, du, v0, dv, W, H, box):
    """Write the pixel box [i0, i1, j0, j1) covering normalised bounds, one pixel to spare."""
    box[0], box[1], box[2], box[3] = 0, H, 0, W
    if x0 > -np.inf:
        box[2] = max(int(np.floor((x0 * fx + cx - u0) / du)) - 1, 0)
    if x1 < np.inf:
        box[3] = min(int(np.ceil((x1 * fx + cx - u0) / du)) + 2, W)
    if y0 > -np.inf:
        box[0] = max(int(np.floor((y0 * fy + cy - v0) / dv)) - 1, 0)
    if y1 < np.inf:
        box[1] = min(int(np.ceil((y1 * fy + cy - v0) / dv)) + 2, H)


@numba.njit(**_INLINE)
def _torus_sdf(px, py, pz, R0, r):
    rho = np.sqrt(px * px + py * py)
    s = R0 / max(rho, 1e-300)
    vx, vy, vz = px - s * px, py - s * py, pz
    nv = np.sqrt(vx * vx + vy * vy + vz * vz)
    k = 1.0 / max(nv, 1e-300)
    return nv - r, vx * k, vy * k, vz * k


@numba.njit(**_INLINE)
def _hit_object(kind, o, x, y):
    """
    Return (depth, unit normal in the camera frame) of the ray (x, y, 1) and object row ``o``.

    The ray goes to the object's frame (origin ``o[10:13]``, direction ``M (x, y, 1)``, not
    normalised, so the ray parameter is the depth) and is intersected there exactly as the
    object's geometry says. ``kind`` is ``o[0]``, passed apart so that the branch is
    hoisted out of the pixel loop.
    """
    inf = np.inf
    dx = o[1] * x + o[2] * y + o[3]
    dy = o[4] * x + o[5] * y + o[6]
    dz = o[7] * x + o[8] * y + o[9]
    ox, oy, oz = o[10], o[11], o[12]
    t, nx, ny, nz = inf, 0.0, 0.0, 0.0
    if kind == SPHERE:
        ir = o[18]                                 # 1 / r; o[19] = |o|^2 - r^2
        a = dx * dx + dy * dy + dz * dz
        b = dx * ox + dy * oy + dz * oz
        disc = b * b - a * o[19]
        if disc >= 0.0:
            tt = (-b - np.sqrt(disc)) / a
            if tt > 0.0:
                t = tt
                nx, ny, nz = (ox + t * dx) * ir, (oy + t * dy) * ir, (oz + t * dz) * ir
    elif kind == PLANE:
        if oz > 0.0 and dz < 0.0:
            t = -oz / dz
            nz = 1.0
    elif kind == CYLINDER:
        r, hh, ir = o[17], o[18], o[19]            # o[20] = ox^2 + oy^2 - r^2
        a = dx * dx + dy * dy
        b = dx * ox + dy * oy
        disc = b * b - a * o[20]
        ts = inf
        if disc >= 0.0 and a > 1e-300:
            tt = (-b - np.sqrt(disc)) / a
            if tt > 0.0 and abs(oz + tt * dz) <= hh:
                ts = tt
        tc = inf
        if abs(oz) > hh and dz != 0.0:
            sgn = 1.0 if oz > 0.0 else -1.0
            tt = (sgn * hh - oz) / dz
            xc, yc = ox + tt * dx, oy + tt * dy
            if tt > 0.0 and xc * xc + yc * yc <= r * r:
                tc = tt
        if ts <= tc and ts < inf:
            t = ts
            nx, ny = (ox + t * dx) * ir, (oy + t * dy) * ir
        elif tc < inf:
            t = tc
            nz = 1.0 if oz > 0.0 else -1.0
    elif kind == RING:
        # Sphere tracing (the torus distance is exact) along the unit ray, from where it
        # enters the bounding sphere, as many steps as objects.py takes.
        R0, r, Rb = o[17], o[18], o[17] + o[18]
        dn = np.sqrt(dx * dx + dy * dy + dz * dz)
        k = 1.0 / dn
        ex, ey, ez = dx * k, dy * k, dz * k
        b = ex * ox + ey * oy + ez * oz
        disc = b * b - (ox * ox + oy * oy + oz * oz - Rb * Rb)
        if disc > 0.0:
            sq = np.sqrt(disc)
            tt, tmax = max(-b - sq, 0.0), -b + sq
            for _ in range(80):
                dist = _torus_sdf(ox + tt * ex, oy + tt * ey, oz + tt * ez, R0, r)[0]
                tt += dist
                if not (dist > 1e-7 and tt <= tmax):
                    break
            dist, gx, gy, gz = _torus_sdf(ox + tt * ex, oy + tt * ey, oz + tt * ez, R0, r)
            if abs(dist) < 1e-6 and tt <= tmax:
                t, nx, ny, nz = tt * k, gx, gy, gz
    elif kind == PRISM:
        t0, t1, best = -inf, inf, 0
        for f in range(6):
            kx, ky, kz = o[17 + 3 * f], o[18 + 3 * f], o[19 + 3 * f]
            den = kx * dx + ky * dy + kz * dz
            num = o[35 + f] - (kx * ox + ky * oy + kz * oz)
            if den < 0.0:
                tk = num / den
                if tk > t0:
                    t0, best = tk, f
            elif den > 0.0:
                t1 = min(t1, num / den)
            elif num < 0.0:
                t1 = -inf                        # parallel to a face, outside it
        if t0 <= t1 and t0 > 0.0:
            t = t0
            nx, ny, nz = o[17 + 3 * best], o[18 + 3 * best], o[19 + 3 * best]
    if t == inf:
        return inf, 0.0, 0.0, 0.0
    # Local normal -> camera frame (M^T n).
    return (t, o[1] * nx + o[4] * ny + o[7] * nz, o[2] * nx + o[5] * ny + o[8] * nz,
            o[3] * nx + o[6] * ny + o[9] * nz)


# -- the frame ---------------------------------------------------------------------------------
@numba.njit(**_JIT)
def _render_kernel(out, depth, ident, normal, u0, du, v0, dv, fx, fy, cx, cy, verts, norms,
                   tris, objs, light, robot_rgb, robot_amb, obj_rgb, obj_amb, bg):
    """
    Z-buffer the robot mesh and the packed objects, then shade every pixel into ``out``.

    ``depth``, ``ident`` (triangle, or triangle count + object) and ``normal`` are work
    buffers of the frame's size.
    """
    H, W = depth.shape
    depth[:, :] = np.inf
    ident[:, :] = -1
    scr = np.empty((verts.shape[0], 3))
    _raster_mesh(verts, norms, tris, fx, fy, cx, cy, u0, du, v0, dv, depth, ident, normal, scr)
    K = tris.shape[0]
    box = np.zeros(4, np.int64)
    for m in range(objs.shape[0]):
        o = objs[m]
        _pixel_box(o[41], o[42], o[43], o[44], fx, fy, cx, cy, u0, du, v0, dv, W, H, box)
        zmin = o[45]
        kind = int(o[0])
        for i in range(box[0], box[1]):
            y = (v0 + dv * i - cy) / fy
            for j in range(box[2], box[3]):
                if zmin >= depth[i, j]:
                    continue                      # the robot is in front of all of it
                x = (u0 + du * j - cx) / fx
                t, nx, ny, nz = _hit_object(kind, o, x, y)
                if t < depth[i, j]:
                    depth[i, j] = t
                    ident[i, j] = K + m
                    normal[i, j, 0], normal[i, j, 1], normal[i, j, 2] = nx, ny, nz
    lx, ly, lz = light[0], light[1], light[2]
    for i in range(H):
        y = (v0 + dv * i - cy) / fy
        for j in range(W):
            k = ident[i, j]
            if k < 0:
                out[i, j, 0], out[i, j, 1], out[i, j, 2] = bg[0], bg[1], bg[2]
                continue
            x = (u0 + du * j - cx) / fx
            nx, ny, nz = normal[i, j, 0], normal[i, j, 1], normal[i, j, 2]
            if k < K:
                rgb, amb = robot_rgb, robot_amb
            else:
                rgb, amb = obj_rgb, obj_amb
            if nx * x + ny * y + nz > 0.0:
                # Face the viewer (a normal pointing away means we see the inside of a shell).
                nx, ny, nz = -nx, -ny, -nz
            lam = min(max(nx * lx + ny * ly + nz * lz, 0.0), 1.0)
            s = amb + (1.0 - amb) * lam
            for c in range(3):
                out[i, j, c] = np.uint8(min(max(np.rint(rgb[c] * s * 255.0), 0.0), 255.0))


# -- Python side --------------------------------------------------------------------------------
def pack_objects(camera: PinholeCamera, obstacles) -> np.ndarray:
    """
    Return the obstacles as kernel rows in ``camera``'s frame; RenderError if one holds it.

    A camera inside an object would see nothing of it (every ray starts inside), a silent
    wrong image: refused instead.
    """
    rows = np.zeros((len(obstacles), _OBJ_COLS))
    Rc, pos = camera.R, camera.position
    for k, obj in enumerate(obstacles):
        kind = _KINDS.get(getattr(obj, 'kind', None))
        if kind is None:
            raise RenderError(f'cannot render object kind {getattr(obj, "kind", obj)!r}')
        gap = float(obj.sdf(pos[None])[0][0])
        if not gap > 0.0:
            raise RenderError(f'camera {camera.name} at {pos.tolist()} m is inside the {obj.kind} '
                              f'(signed distance {gap:.4g} m): the scene cannot be placed')
        M = obj.R.T @ Rc                           # camera -> object frame
        row = rows[k]
        row[0] = kind
        row[1:10] = M.ravel()
        row[10:13] = obj.R.T @ (pos - obj.t)
        centre = Rc.T @ (obj.t - pos)
        half = None
        o = row[10:13]
        if kind == SPHERE:
            row[17:20] = obj.r, 1.0 / obj.r, o @ o - obj.r ** 2
        elif kind == CYLINDER:
            row[17:21] = obj.r, obj.hh, 1.0 / obj.r, o[0] ** 2 + o[1] ** 2 - obj.r ** 2
            half = (obj.r, obj.r, obj.hh)
        elif kind == RING:
            row[17:19] = obj.R0, obj.r
            half = (obj.R0 + obj.r, obj.R0 + obj.r, obj.r)
        elif kind == PRISM:
            row[17:35] = np.asarray(obj.normals, dtype=float).ravel()
            row[35:41] = obj.offsets
            w, dp, h, sk = obj.size
            half = (w / 2 + h / 2 * abs(np.tan(sk)), dp / 2, h / 2)
        row[41:46] = _image_bounds(kind, centre, M.T, half, getattr(obj, 'r', 0.0))
        if not np.all(np.isfinite(row[:41])):
            raise RenderError(f'object {obj.kind}: pose or size is not finite')
    return rows


def _image_bounds(kind, centre, Rco, half, radius):
    """
    Return (x0, x1, y0, y1, zmin): normalised image bounds and least depth of an object.

    From the exact silhouette of a sphere, or the 8 corners of the object's local box
    (``Rco`` turns local vectors into the camera frame); unbounded where the object
    reaches the camera plane or is infinite (the plane).
    """
    inf = np.inf
    if kind == PLANE:
        return -inf, inf, -inf, inf, -inf
    if kind == SPHERE:
        return (*_sphere_bounds(*centre, radius), centre[2] - radius)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    corners = centre + (signs * half) @ Rco.T
    z = corners[:, 2]
    if z.min() <= 1e-9:
        return -inf, inf, -inf, inf, -inf
    x, y = corners[:, 0] / z, corners[:, 1] / z
    return x.min(), x.max(), y.min(), y.max(), z.min()


_workspace = threading.local()


def _buffers(H, W):
    """Return reusable depth, id and normal buffers for an H x W frame (one set per thread)."""
    cache = getattr(_workspace, 'cache', None)
    if cache is None or cache[0].shape != (H, W):
        _workspace.cache = cache = (np.empty((H, W), np.float32), np.empty((H, W), np.int32),
                                    np.empty((H, W, 3), np.float32))
    return cache


def render_view(camera: PinholeCamera, centres: np.ndarray, radii: np.ndarray, obstacles,
                grid=None, objects: np.ndarray | None = None) -> np.ndarray:
    """
    Return an H x W x 3 uint8 RGB image of the tube through ``centres`` and the obstacles.

    ``grid`` comes from :meth:`PinholeCamera.grid` (default: the full frame); ``objects``
    is :func:`pack_objects` of ``obstacles`` for this camera when already made. Raises
    :class:`RenderError` for a backbone that is not finite, radii that are not positive, an
    empty grid or a camera inside an object: never a silent image.
    """
    grid = grid if grid is not None else camera.grid()
    u0, du, v0, dv, W, H = grid
    if W < 1 or H < 1 or not (du > 0 and dv > 0):
        raise RenderError(f'camera {camera.name}: cannot render a {W}x{H} image')
    c = np.asarray(centres, dtype=float)
    r = np.asarray(radii, dtype=float)
    if c.ndim != 2 or c.shape[1] != 3 or len(c) < 1 or r.shape != (len(c),):
        raise RenderError(f'backbone must be (N, 3) points with N radii, got {c.shape} and '
                          f'{r.shape}')
    if not (np.isfinite(c).all() and np.isfinite(r).all() and (r > 0).all()):
        raise RenderError('backbone points and radii must be finite, radii > 0')
    pc = (c - camera.position) @ camera.R          # camera frame
    if ((pc[:, 2] - r) <= 0.0).any():
        raise RenderError(f'camera {camera.name}: the robot reaches the camera plane')
    if objects is None:
        objects = pack_objects(camera, obstacles)
    verts, norms, tris = tube_mesh(np.ascontiguousarray(pc), np.ascontiguousarray(r),
                                   *mesh_resolution(camera, pc, r, du, dv))
    light = -camera.R[:, 2] + np.array([0.0, 0.0, 0.6])
    light = camera.R.T @ (light / np.linalg.norm(light))
    depth, ident, normal = _buffers(H, W)
    out = np.empty((H, W, 3), np.uint8)
    _render_kernel(out, depth, ident, normal, float(u0), float(du), float(v0), float(dv),
                   camera.fx, camera.fy, camera.cx, camera.cy, verts, norms, tris, objects,
                   light,
                   ROBOT_RGB, ROBOT_AMBIENT, OBJECT_RGB, OBJECT_AMBIENT, _BG)
    return out


def mesh_resolution(camera: PinholeCamera, pc: np.ndarray, radii: np.ndarray, du: float,
                    dv: float) -> tuple[int, int]:
    """
    Return (vertices per ring, cap bands) for a tube at camera-frame points ``pc``.

    A ring of n chords sits r (1 - cos(pi / n)) inside its circle: n is the least for which
    that is :data:`OUTLINE_TOLERANCE_PX` where the tube is largest in the image.
    """
    scale = max(camera.fx / du, camera.fy / dv)
    r_px = float((radii * scale / (pc[:, 2] - radii)).max())
    if r_px <= OUTLINE_TOLERANCE_PX:
        n = 8
    else:
        n = int(np.ceil(np.pi / np.arccos(1.0 - OUTLINE_TOLERANCE_PX / r_px)))
    n = int(min(max(n, 8), 1024))
    return n, max(2, n // 4)


_BG = np.clip(np.rint(BACKGROUND_RGB * 255.0), 0, 255).astype(np.uint8)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Convert a [0, 1] float image to uint8 (rounded)."""
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
