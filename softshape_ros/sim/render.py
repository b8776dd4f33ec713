"""
Z-buffered rasteriser compiled with numba: the robot a tube of its real radius, objects solids.

Every surface is a closed triangle mesh made for the view: the robot a ring of vertices
around each backbone point (framed by parallel transport) closed by hemispherical caps; the
objects (cylinder, ring, oblique prism, sphere, plane) from their dimensions and pose.
Curved surfaces get as many chords as keep their outline within a tenth of a pixel, with an
area-preserving radius so the outline is unbiased. Front faces only, depth from 1/z,
normals interpolated perspective-correctly; each pixel keeps the nearest surface, so
occlusion is right whichever is in front. Lambertian shading with a head light; the robot is
dark, objects mid-light and the background light, so the three stay apart in gray (the
model learns from them). Everything runs in the camera frame, compiled, writing the uint8
image (RGB or gray) directly; the objects are drawn once per scene and view (their layer), so
a frame is a copy of that and the robot drawn over it.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numba
import numpy as np

from softshape_ros.sim.camera import PinholeCamera

BACKGROUND_RGB = np.array([0.94, 0.94, 0.94])
ROBOT_RGB = np.array([0.62, 0.30, 0.22])       # gray ~0.37 when lit
OBJECT_RGB = np.array([0.62, 0.80, 0.95])      # gray ~0.77 when lit
ROBOT_AMBIENT, OBJECT_AMBIENT = 0.45, 0.72
OUTLINE_TOLERANCE_PX = 0.1  # every mesh's chords stay this close to the true surface's outline
NEAR_M = 1e-3              # geometry nearer the camera than this is cut away
PLANE_EXTENT_M = 2000.0    # the plane object's mesh: a square this wide

# Object kinds in the packed parameter rows.
SPHERE, PLANE, CYLINDER, RING, PRISM = 0, 1, 2, 3, 4
_KINDS = {'sphere': SPHERE, 'plane': PLANE, 'cylinder': CYLINDER, 'ring': RING, 'prism': PRISM}
_OBJ_COLS = 24              # see pack_objects

# fastmath without 'nnan' / 'ninf' (the finiteness checks must stay) or 'afn': reciprocals,
# fused multiply-adds and reassociation (render_view 5-15 % less CPU in back-to-back runs
# on the reference scenes; their frames the same but for one pixel in 4.3 M, by one level).
_JIT = dict(cache=True, nogil=True, error_model='numpy',
            fastmath={'nsz', 'arcp', 'contract', 'reassoc'})
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
    f = area_scale(n_theta)
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
            r, px, py, pz = radii[k] * f, p[k, 0], p[k, 1], p[k, 2]
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
        verts[pole0, c] = p[0, c] - f * radii[0] * T[0, c]
        verts[pole1, c] = p[N - 1, c] + f * radii[N - 1] * T[N - 1, c]
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
    _wind_outward(verts, norms, tris)
    return verts, norms, tris


@numba.njit(**_JIT)
def segments(radius, tol):
    """Return the chords per turn that keep a circle of ``radius`` within ``tol`` (8..1024)."""
    if tol >= radius:
        return 8
    return min(max(int(np.ceil(np.pi / np.arccos(1.0 - tol / radius))), 8), 1024)


@numba.njit(**_JIT)
def area_scale(n):
    """
    Return the radius factor that gives a regular n-gon the area of its circle.

    Vertices a little outside, chord middles a little inside: the mesh's outline is then
    unbiased, which the area-averaged network inputs would otherwise show as a thinner
    robot (about 0.5 gray level at 64x64 with 0.4-pixel chords).
    """
    return np.sqrt(2.0 * np.pi / (n * np.sin(2.0 * np.pi / n)))


@numba.njit(**_JIT)
def _wind_outward(verts, norms, tris):
    """Flip the triangles whose winding disagrees with their vertices' normals."""
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


@numba.njit(**_JIT)
def _band(tris, n, r0, r1, m, closed):
    """Add the 2m triangles between rings r0 and r1 of m vertices (first indices); return n."""
    for j in range(m if closed else m - 1):
        a, b = r0 + j, r0 + (j + 1) % m
        c, d = r1 + j, r1 + (j + 1) % m
        tris[n, 0], tris[n, 1], tris[n, 2] = a, b, c
        tris[n + 1, 0], tris[n + 1, 1], tris[n + 1, 2] = b, d, c
        n += 2
    return n


@numba.njit(**_JIT)
def object_mesh(o, tol):
    """
    Return (vertices, unit normals, triangles) of object row ``o`` in its own frame.

    Curved surfaces get as many chords as keep them within ``tol`` metres; flat faces
    carry their face normal (prism, cylinder caps). The plane is a square of
    :data:`PLANE_EXTENT_M` a side (at 1 km, its edge is within a pixel of the horizon).
    """
    kind = int(o[0])
    if kind == SPHERE:
        r = o[17]
        n = segments(r, tol)
        return tube_mesh(np.zeros((1, 3)), np.array([r]), n, max(2, n // 4))
    if kind == CYLINDER:
        verts, norms, tris = _cylinder_mesh(o[17], o[18], tol)
    elif kind == RING:
        verts, norms, tris = _ring_mesh(o[17], o[18], tol)
    elif kind == PRISM:
        verts, norms, tris = _prism_mesh(o[17], o[18], o[19], o[20])
    else:                                         # PLANE: z = 0, solid below
        L = PLANE_EXTENT_M / 2
        verts = np.array([[-L, -L, 0.0], [L, -L, 0.0], [L, L, 0.0], [-L, L, 0.0]])
        norms = np.zeros((4, 3))
        norms[:, 2] = 1.0
        tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    _wind_outward(verts, norms, tris)
    return verts, norms, tris


@numba.njit(**_JIT)
def _cylinder_mesh(radius, half_height, tol):
    """Mesh a cylinder: its side band, then both caps as fans (rims with the flat normal)."""
    m = segments(radius, tol)
    r, hh = radius * area_scale(m), half_height
    verts = np.zeros((4 * m + 2, 3))
    norms = np.zeros((4 * m + 2, 3))
    for j in range(m):
        c, s_ = np.cos(2.0 * np.pi * j / m), np.sin(2.0 * np.pi * j / m)
        for g, (z, flat) in enumerate(((-hh, False), (hh, False), (-hh, True), (hh, True))):
            q = g * m + j
            verts[q, 0], verts[q, 1], verts[q, 2] = r * c, r * s_, z
            if flat:
                norms[q, 2] = 1.0 if z > 0 else -1.0
            else:
                norms[q, 0], norms[q, 1] = c, s_
    verts[4 * m, 2], verts[4 * m + 1, 2] = -hh, hh
    norms[4 * m, 2], norms[4 * m + 1, 2] = -1.0, 1.0
    tris = np.empty((4 * m, 3), np.int32)
    n = _band(tris, 0, 0, m, m, True)
    for j in range(m):
        tris[n, 0], tris[n, 1], tris[n, 2] = 4 * m, 2 * m + j, 2 * m + (j + 1) % m
        tris[n + 1, 0], tris[n + 1, 1], tris[n + 1, 2] = 4 * m + 1, 3 * m + j, \
            3 * m + (j + 1) % m
        n += 2
    return verts, norms, tris


@numba.njit(**_JIT)
def _ring_mesh(major_radius, minor_radius, tol):
    """Mesh a torus: M bands around the axis, m chords around the tube."""
    M, m = segments(major_radius + minor_radius, tol), segments(minor_radius, tol)
    R0, r = major_radius * area_scale(M), minor_radius * area_scale(m)
    verts = np.empty((M * m, 3))
    norms = np.empty((M * m, 3))
    for i in range(M):
        ca, sa = np.cos(2.0 * np.pi * i / M), np.sin(2.0 * np.pi * i / M)
        for j in range(m):
            cb, sb = np.cos(2.0 * np.pi * j / m), np.sin(2.0 * np.pi * j / m)
            q = i * m + j
            norms[q, 0], norms[q, 1], norms[q, 2] = cb * ca, cb * sa, sb
            verts[q, 0] = (R0 + r * cb) * ca
            verts[q, 1] = (R0 + r * cb) * sa
            verts[q, 2] = r * sb
    tris = np.empty((2 * M * m, 3), np.int32)
    n = 0
    for i in range(M):
        n = _band(tris, n, i * m, ((i + 1) % M) * m, m, True)
    return verts, norms, tris


@numba.njit(**_JIT)
def _prism_mesh(width, depth, height, skew):
    """Mesh a prism: six quads (four vertices each, face normal outward), top shifted by skew."""
    ts = np.tan(skew)
    corner = np.empty((8, 3))
    for b in range(8):
        sx, sy, sz = (b >> 2 & 1) * 2 - 1, (b >> 1 & 1) * 2 - 1, (b & 1) * 2 - 1
        corner[b, 0] = sx * width / 2 + sz * height / 2 * ts
        corner[b, 1], corner[b, 2] = sy * depth / 2, sz * height / 2
    verts = np.empty((24, 3))
    norms = np.empty((24, 3))
    tris = np.empty((12, 3), np.int32)
    f = 0
    for bit in (4, 2, 1):
        o1, o2 = (2, 1) if bit == 4 else ((4, 1) if bit == 2 else (4, 2))
        for side in (0, bit):
            quad = (side, side | o1, side | o1 | o2, side | o2)
            e1 = corner[quad[1]] - corner[quad[0]]
            e2 = corner[quad[3]] - corner[quad[0]]
            nrm = np.array([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                            e1[0] * e2[1] - e1[1] * e2[0]])
            nrm /= np.sqrt(nrm @ nrm)
            if nrm @ corner[quad[0]] < 0.0:
                nrm = -nrm                    # outward: the prism is centred
            for v in range(4):
                verts[4 * f + v] = corner[quad[v]]
                norms[4 * f + v] = nrm
            tris[2 * f, 0], tris[2 * f, 1], tris[2 * f, 2] = 4 * f, 4 * f + 1, 4 * f + 2
            tris[2 * f + 1, 0], tris[2 * f + 1, 1], tris[2 * f + 1, 2] = \
                4 * f, 4 * f + 2, 4 * f + 3
            f += 1
    return verts, norms, tris


# -- rasterisation -------------------------------------------------------------------------------
@numba.njit(**_INLINE)
def _shade(out, i, j, nx, ny, nz, shade, light):
    """
    Write pixel (i, j): Lambertian head light on the (unnormalised) normal.

    ``shade`` = (R, G, B on 0-255, ambient share) of the surface's material. A one-channel
    ``out`` gets the RGB pixel's gray (:func:`_gray`).
    """
    lambert = (nx * light[0] + ny * light[1] + nz * light[2]) / np.sqrt(nx * nx + ny * ny
                                                                        + nz * nz)
    lambert = min(max(lambert, 0.0), 1.0)
    s = shade[3] + (1.0 - shade[3]) * lambert
    # Rounded to the nearest level (values are >= 0 and < 255.5).
    r, g, b = np.uint8(shade[0] * s + 0.5), np.uint8(shade[1] * s + 0.5), \
        np.uint8(shade[2] * s + 0.5)
    if out.shape[2] == 1:
        out[i, j, 0] = _gray(r, g, b)
    else:
        out[i, j, 0], out[i, j, 1], out[i, j, 2] = r, g, b


@numba.njit(**_INLINE)
def _gray(r, g, b):
    """
    Return the gray level of an RGB uint8 pixel, as OpenCV's COLOR_RGB2GRAY computes it.

    BT.601 weights in 15-bit fixed point, rounded: bit-exact with cv2.cvtColor of OpenCV
    5.0 over all 2^24 colours (a version with other rounding differs by at most one level).
    """
    return np.uint8((np.int32(r) * 9798 + np.int32(g) * 19235 + np.int32(b) * 3735 + 16384)
                    >> 15)


@numba.njit(**_INLINE)
def _span(w, d, tol, lo, hi):
    """Narrow [lo, hi] to the steps n where the edge function w + d n is <= tol (inside)."""
    if d > 0.0:
        x = (tol - w) / d
        if x < hi:
            hi = math.floor(x) if x >= lo else lo - 1
    elif d < 0.0:
        x = (tol - w) / d
        if x > lo:
            lo = math.ceil(x) if x <= hi else hi + 1
    elif not w <= tol:
        hi = lo - 1
    return lo, hi


@numba.njit(**_INLINE)
def _triangle(ax, ay, az, bx, by, bz, qx, qy, qz, na0, na1, na2, nb0, nb1, nb2, nc0, nc1, nc2,
              shade, light, depth, out):
    """
    Z-buffer and shade one triangle given in grid coordinates (j, i), 1/z and normals per vertex.

    Front faces only (negative area with x right, y down). ``depth`` holds 1/z (larger is
    nearer), interpolated linearly in the image (exact on the triangle's plane); normals
    are interpolated perspective-correctly. Each pixel the triangle wins is shaded at once
    (:func:`_shade`): with closed meshes few pixels are drawn twice, and no normal or id
    buffer has to be written and read back (the frame's memory traffic was most of its time).
    """
    H, W = depth.shape
    area = (bx - ax) * (qy - ay) - (by - ay) * (qx - ax)
    if not area < 0.0:
        return                                    # a back face, edge-on, or not finite
    # Pixel centres inside the box (clamped to the frame first: a huge box is cheap).
    j0 = max(math.ceil(max(min(ax, bx, qx), -1.0) - 1e-9), 0)
    j1 = min(math.floor(min(max(ax, bx, qx), W + 1.0) + 1e-9), W - 1)
    i0 = max(math.ceil(max(min(ay, by, qy), -1.0) - 1e-9), 0)
    i1 = min(math.floor(min(max(ay, by, qy), H + 1.0) + 1e-9), H - 1)
    if j0 > j1 or i0 > i1:
        return
    inv = 1.0 / area
    za, zb, zc = az * inv, bz * inv, qz * inv
    nax, nay, naz = na0 * za, na1 * za, na2 * za
    nbx, nby, nbz = nb0 * zb, nb1 * zb, nb2 * zb
    ncx, ncy, ncz = nc0 * zc, nc1 * zc, nc2 * zc
    tol = 1e-9 * -area                            # shared edges: no pixel falls between
    da, db, dc = -(qy - by), -(ay - qy), -(by - ay)
    for i in range(i0, i1 + 1):
        # Edge functions (area x barycentric weight, <= 0 inside), linear along the row:
        # the row's covered pixels are one span, found from the three edges at once.
        wa = (qx - bx) * (i - by) - (qy - by) * (j0 - bx)
        wb = (ax - qx) * (i - qy) - (ay - qy) * (j0 - qx)
        wc = (bx - ax) * (i - ay) - (by - ay) * (j0 - ax)
        lo, hi = _span(wa, da, tol, 0, j1 - j0)
        lo, hi = _span(wb, db, tol, lo, hi)
        lo, hi = _span(wc, dc, tol, lo, hi)
        if lo > hi:
            continue
        wa += da * lo
        wb += db * lo
        wc += dc * lo
        for j in range(j0 + lo, j0 + hi + 1):
            iz = wa * za + wb * zb + wc * zc
            if iz > depth[i, j]:
                depth[i, j] = iz                  # nearer (the buffer holds 1/z)
                _shade(out, i, j, wa * nax + wb * nbx + wc * ncx,
                       wa * nay + wb * nby + wc * ncy, wa * naz + wb * nbz + wc * ncz,
                       shade, light)
            wa += da
            wb += db
            wc += dc


@numba.njit(**_JIT)
def _raster_mesh(verts, norms, tris, shade, light, grid, depth, out):
    """
    Z-buffer and shade the front faces of a camera-frame mesh, cut at :data:`NEAR_M` in front.

    ``grid`` = (fx, fy, cx, cy, u0, du, v0, dv): pixel (i, j) is the ray through image point
    (u0 + du j, v0 + dv i). ``out`` gets the material ``shade`` (:func:`_shade`) where the
    mesh is nearest.
    """
    fx, fy, cx, cy, u0, du, v0, dv = grid
    V = verts.shape[0]
    scr = np.empty((V, 3))
    for q in range(V):
        iz = 1.0 / verts[q, 2]
        scr[q, 0] = (verts[q, 0] * iz * fx + cx - u0) / du
        scr[q, 1] = (verts[q, 1] * iz * fy + cy - v0) / dv
        scr[q, 2] = iz
    poly = np.empty((4, 3))
    pnrm = np.empty((4, 3))
    pscr = np.empty((4, 3))
    for n in range(tris.shape[0]):
        a, b, c = tris[n, 0], tris[n, 1], tris[n, 2]
        inside = (verts[a, 2] > NEAR_M) + (verts[b, 2] > NEAR_M) + (verts[c, 2] > NEAR_M)
        if inside == 3:
            _triangle(scr[a, 0], scr[a, 1], scr[a, 2], scr[b, 0], scr[b, 1], scr[b, 2],
                      scr[c, 0], scr[c, 1], scr[c, 2], norms[a, 0], norms[a, 1], norms[a, 2],
                      norms[b, 0], norms[b, 1], norms[b, 2], norms[c, 0], norms[c, 1],
                      norms[c, 2], shade, light, depth, out)
            continue
        if inside == 0:
            continue
        # Cut the triangle at z = NEAR_M (Sutherland-Hodgman): 1 or 2 triangles remain.
        k = 0
        idx = (a, b, c)
        for e in range(3):
            p0, p1 = idx[e], idx[(e + 1) % 3]
            z0, z1 = verts[p0, 2], verts[p1, 2]
            if z0 > NEAR_M:
                poly[k] = verts[p0]
                pnrm[k] = norms[p0]
                k += 1
            if (z0 > NEAR_M) != (z1 > NEAR_M):
                s = (NEAR_M - z0) / (z1 - z0)
                poly[k] = verts[p0] + s * (verts[p1] - verts[p0])
                pnrm[k] = norms[p0] + s * (norms[p1] - norms[p0])
                k += 1
        for q in range(k):
            iz = 1.0 / poly[q, 2]
            pscr[q, 0] = (poly[q, 0] * iz * fx + cx - u0) / du
            pscr[q, 1] = (poly[q, 1] * iz * fy + cy - v0) / dv
            pscr[q, 2] = iz
        for q in range(1, k - 1):
            _triangle(pscr[0, 0], pscr[0, 1], pscr[0, 2], pscr[q, 0], pscr[q, 1], pscr[q, 2],
                      pscr[q + 1, 0], pscr[q + 1, 1], pscr[q + 1, 2], pnrm[0, 0], pnrm[0, 1],
                      pnrm[0, 2], pnrm[q, 0], pnrm[q, 1], pnrm[q, 2], pnrm[q + 1, 0],
                      pnrm[q + 1, 1], pnrm[q + 1, 2], shade, light, depth, out)


# -- the frame ---------------------------------------------------------------------------------
@numba.njit(**_JIT)
def _objects_mesh(objs, grid, tol_px):
    """
    Return (vertices, unit normals, triangles) of all the objects, in the camera frame.

    Each object row (:func:`pack_objects`) gets as many chords as keep its outline within
    ``tol_px`` pixels of ``grid`` at its least depth. The objects do not move within a
    scene, so a rig makes this once per scene and grid (:class:`ObjectMesh`).
    """
    px = grid[5] / grid[0]                        # metres per pixel at unit depth
    nv, nt = 0, 0
    parts = []
    for m in range(objs.shape[0]):
        o = objs[m]
        lv, ln, tris = object_mesh(o, tol_px * px * max(o[23], NEAR_M))
        parts.append((lv, ln, tris))
        nv += lv.shape[0]
        nt += tris.shape[0]
    verts = np.empty((nv, 3))
    norms = np.empty((nv, 3))
    out = np.empty((nt, 3), np.int32)
    v0, t0 = 0, 0
    for m in range(len(parts)):
        o = objs[m]
        lv, ln, tris = parts[m]
        # Object frame -> camera frame: x_c = centre + M^T x_l.
        for q in range(lv.shape[0]):
            for c in range(3):
                verts[v0 + q, c] = o[13 + c] + (o[1 + c] * lv[q, 0] + o[4 + c] * lv[q, 1]
                                                + o[7 + c] * lv[q, 2])
                norms[v0 + q, c] = o[1 + c] * ln[q, 0] + o[4 + c] * ln[q, 1] \
                    + o[7 + c] * ln[q, 2]
        for t in range(tris.shape[0]):
            for c in range(3):
                out[t0 + t, c] = tris[t, c] + v0
        v0 += lv.shape[0]
        t0 += tris.shape[0]
    return verts, norms, out


@numba.njit(**_INLINE)
def _copy(dst, src):
    """Copy flat ``src`` into ``dst`` (a plain loop: numba's slice assignment is slower)."""
    for k in range(dst.shape[0]):
        dst[k] = src[k]


@numba.njit(**_JIT)
def _objects_kernel(out, depth, grid, overts, onorms, otris, light, obj_shade, bg):
    """
    Z-buffer and shade the objects' mesh alone on the background: a scene's fixed layer.

    ``depth`` gets 1/z (0 where nothing is), ``out`` the H x W x C uint8 image (C = 3 for
    RGB, 1 for gray).
    """
    depth[:, :] = 0.0                             # 1/z: nothing is at z = inf
    H, W = depth.shape
    if out.shape[2] == 1:
        out[:, :, 0] = _gray(bg[0], bg[1], bg[2])
    else:
        for i in range(H):
            for j in range(W):
                out[i, j, 0], out[i, j, 1], out[i, j, 2] = bg[0], bg[1], bg[2]
    _raster_mesh(overts, onorms, otris, obj_shade, light, grid, depth, out)


@numba.njit(**_JIT)
def _render_kernel(out, depth, grid, pc, radii, layer_depth, layer_out, tol_px, light,
                   robot_shade):
    """
    Mesh the robot (camera-frame backbone ``pc``), then z-buffer and shade it over the objects.

    ``layer_depth`` and ``layer_out`` are the objects' layer (:func:`_objects_kernel`),
    copied into the work buffer ``depth`` and the image ``out`` before the robot is drawn.
    Returns 0, or the code of what is wrong with the backbone (``_ERRORS``) before drawing
    anything.
    """
    # The robot's ring size: chords within tol_px where the tube is largest in the image.
    scale = max(grid[0] / grid[5], grid[1] / grid[7])
    r_px = 0.0
    for k in range(pc.shape[0]):
        if not (np.isfinite(pc[k, 0]) and np.isfinite(pc[k, 1]) and np.isfinite(pc[k, 2])
                and np.isfinite(radii[k])):
            return 1
        if not radii[k] > 0.0:
            return 2
        if not pc[k, 2] - radii[k] > NEAR_M:
            return 3
        r_px = max(r_px, radii[k] * scale / (pc[k, 2] - radii[k]))
    n_theta = segments(r_px, tol_px)
    _copy(depth.reshape(-1), layer_depth.reshape(-1))
    _copy(out.reshape(-1), layer_out.reshape(-1))
    verts, norms, tris = tube_mesh(pc, radii, n_theta, max(2, n_theta // 4))
    _raster_mesh(verts, norms, tris, robot_shade, light, grid, depth, out)
    return 0


# -- Python side --------------------------------------------------------------------------------
def pack_objects(camera: PinholeCamera, obstacles) -> np.ndarray:
    """
    Return the obstacles as kernel rows in ``camera``'s frame; RenderError if one holds it.

    Row: [kind, M (9, camera -> object rotation), -, -, -, centre (3, camera frame), -,
    shape (4), -, -, least depth]. A camera inside an object would see nothing of it (its
    inside faces are culled), a silent wrong image: refused instead.
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
        M = obj.R.T @ Rc
        row = rows[k]
        row[0] = kind
        row[1:10] = M.ravel()
        row[13:16] = Rc.T @ (obj.t - pos)
        half = None
        if kind == SPHERE:
            row[17] = obj.r
        elif kind == CYLINDER:
            row[17:19] = obj.r, obj.hh
            half = (obj.r, obj.r, obj.hh)
        elif kind == RING:
            row[17:19] = obj.R0, obj.r
            half = (obj.R0 + obj.r, obj.R0 + obj.r, obj.r)
        elif kind == PRISM:
            w, dp, h, sk = obj.size
            row[17:21] = w, dp, h, sk
            half = (w / 2 + h / 2 * abs(np.tan(sk)), dp / 2, h / 2)
        if not np.all(np.isfinite(row)) or not np.all(row[17:20] >= 0.0):
            raise RenderError(f'object {obj.kind}: pose or size is not finite and >= 0')
        # Least depth (sets how finely the object is meshed): its box's nearest corner.
        if kind == PLANE:
            row[23] = NEAR_M
        elif kind == SPHERE:
            row[23] = row[15] - obj.r
        else:
            signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
            row[23] = float((row[13:16] + (signs * half) @ M).min(axis=0)[2])
    return rows


_workspace = threading.local()


def _depth_buffer(H, W):
    """Return a reusable H x W depth buffer (one per thread)."""
    depth = getattr(_workspace, 'depth', None)
    if depth is None or depth.shape != (H, W):
        _workspace.depth = depth = np.empty((H, W), np.float32)
    return depth


@dataclass(frozen=True)
class ObjectMesh:
    """
    The objects of a scene meshed for one camera and pixel grid (camera frame).

    The objects do not move within a scene, so their drawing on the background is made once
    per colour format (:meth:`layer`) and every frame starts from a copy of it.
    """

    grid: tuple
    tol_px: float
    verts: np.ndarray       # (V, 3)
    norms: np.ndarray       # (V, 3)
    tris: np.ndarray        # (T, 3) int32
    grid8: np.ndarray       # the camera's intrinsics and the grid (see _raster_mesh)
    light: np.ndarray       # the camera's head light
    layers: dict = field(default_factory=dict, compare=False, repr=False)

    def layer(self, channels: int):
        """Return (1/z (H, W) float32, image (H, W, channels) uint8) of the objects alone."""
        made = self.layers.get(channels)
        if made is None:
            W, H = self.grid[4], self.grid[5]
            made = (np.empty((H, W), np.float32), np.empty((H, W, channels), np.uint8))
            _objects_kernel(made[1], made[0], self.grid8, self.verts, self.norms, self.tris,
                            self.light, _OBJECT_SHADE, _BG)
            self.layers[channels] = made
        return made


def object_mesh_for(camera: PinholeCamera, objects: np.ndarray, grid=None,
                    tol_px: float = OUTLINE_TOLERANCE_PX) -> ObjectMesh:
    """Return the objects (:func:`pack_objects` rows) meshed for ``camera`` and ``grid``."""
    grid = tuple(grid if grid is not None else camera.grid())
    grid8 = _grid8(camera, grid)
    verts, norms, tris = _objects_mesh(np.ascontiguousarray(objects, dtype=float), grid8,
                                       float(tol_px))
    return ObjectMesh(grid, float(tol_px), verts, norms, tris, grid8, camera.head_light)


def _grid8(camera: PinholeCamera, grid) -> np.ndarray:
    u0, du, v0, dv = grid[:4]
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, u0, du, v0, dv], dtype=float)


def render_view(camera: PinholeCamera, centres: np.ndarray, radii: np.ndarray, obstacles,
                grid=None, objects=None, tol_px: float = OUTLINE_TOLERANCE_PX,
                gray: bool = False) -> np.ndarray:
    """
    Return an H x W x 3 uint8 RGB image of the tube through ``centres`` and the obstacles.

    With ``gray``, the H x W gray image instead: each pixel what ``cv2.cvtColor`` makes of
    the RGB one, without the colour frame being written and converted.

    ``grid`` comes from :meth:`PinholeCamera.grid` (default: the full frame); ``objects``
    is :func:`pack_objects` of ``obstacles`` for this camera, or their
    :func:`object_mesh_for` this grid and tolerance, when already made; ``tol_px`` is how
    far (grid pixels) a mesh's outline may stray from the true one. Raises
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
    if not isinstance(objects, ObjectMesh):
        objects = object_mesh_for(camera, pack_objects(camera, obstacles)
                                  if objects is None else objects, grid, tol_px)
    elif objects.grid != tuple(grid) or objects.tol_px != float(tol_px):
        raise ValueError('render_view: the object mesh was made for another grid or tolerance')
    pc = (c - camera.position) @ camera.R          # camera frame
    depth = _depth_buffer(H, W)
    channels = 1 if gray else 3
    out = np.empty((H, W, channels), np.uint8)
    layer_depth, layer_out = objects.layer(channels)
    err = _render_kernel(out, depth, _grid8(camera, grid), pc, np.ascontiguousarray(r),
                         layer_depth, layer_out, float(tol_px), camera.head_light,
                         _ROBOT_SHADE)
    if err:
        raise RenderError(f'camera {camera.name}: {_ERRORS[err]}')
    return out[:, :, 0] if gray else out


_BG = np.clip(np.rint(BACKGROUND_RGB * 255.0), 0, 255).astype(np.uint8)
_ROBOT_SHADE = np.append(ROBOT_RGB * 255.0, ROBOT_AMBIENT)     # see _shade
_OBJECT_SHADE = np.append(OBJECT_RGB * 255.0, OBJECT_AMBIENT)
_ERRORS = {1: 'backbone points and radii must be finite', 2: 'tube radii must be > 0',
           3: 'the robot reaches the camera plane'}


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Convert a [0, 1] float image to uint8 (rounded)."""
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
