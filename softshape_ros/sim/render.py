"""
Z-buffered ray-cast renderer: the robot as a tube of its real radius, objects as solids.

Each pixel keeps the nearest hit along its ray (robot spheres swept along the backbone
at sub-millimetre spacing, analytic object intersections), so occlusion is right whichever
is in front. Lambertian shading with a head light; the robot is dark, objects mid-light
and the background light, so the three stay apart in gray (the model learns from them).
"""

from __future__ import annotations

import numpy as np

from softshape_ros.sim.camera import PinholeCamera

BACKGROUND_RGB = np.array([0.94, 0.94, 0.94])
ROBOT_RGB = np.array([0.62, 0.30, 0.22])       # gray ~0.37 when lit
OBJECT_RGB = np.array([0.62, 0.80, 0.95])      # gray ~0.77 when lit
ROBOT_AMBIENT, OBJECT_AMBIENT = 0.45, 0.72


def _shade(rgb, ambient, normals, light):
    lam = np.clip(normals @ light, 0.0, 1.0)
    return rgb[None, :] * (ambient + (1.0 - ambient) * lam)[:, None]


def render_view(camera: PinholeCamera, centres: np.ndarray, radii: np.ndarray, obstacles,
                grid=None) -> np.ndarray:
    """
    Return an H x W x 3 float image in [0, 1] of spheres (the robot) and obstacles.

    ``grid`` comes from :meth:`PinholeCamera.grid` (default: the full frame).
    """
    grid = grid if grid is not None else camera.grid()
    u0, du, v0, dv, W, H = grid
    dirs = camera.rays(grid)
    o = camera.position
    depth = np.full((H, W), np.inf)
    normal = np.zeros((H, W, 3))
    mat = np.zeros((H, W), dtype=np.int8)
    # Robot: one sphere at a time over its projected bounding box.
    proj = camera.project(centres)
    for (u, v, z), c, r in zip(proj, centres, radii):
        if z <= r:
            continue
        rp = r / np.sqrt(max(z * z - r * r, 1e-30)) * 1.3
        j0 = int(np.floor((u - camera.fx * rp - u0) / du))
        j1 = int(np.ceil((u + camera.fx * rp - u0) / du)) + 1
        i0 = int(np.floor((v - camera.fy * rp - v0) / dv))
        i1 = int(np.ceil((v + camera.fy * rp - v0) / dv)) + 1
        j0, i0, j1, i1 = max(j0, 0), max(i0, 0), min(j1, W), min(i1, H)
        if j0 >= j1 or i0 >= i1:
            continue
        d = dirs[i0:i1, j0:j1]
        oc = c - o
        b = np.einsum('hwi,i->hw', d, oc)
        disc = b * b - (oc @ oc - r * r)
        t = b - np.sqrt(np.maximum(disc, 0.0))
        sub = depth[i0:i1, j0:j1]
        win = (disc > 0) & (t > 0) & (t < sub)
        if not win.any():
            continue
        sub[win] = t[win]
        hit = o + t[win][:, None] * d[win]
        normal[i0:i1, j0:j1][win] = (hit - c) / r
        mat[i0:i1, j0:j1][win] = 1
    flat_dirs = dirs.reshape(-1, 3)
    flat_depth = depth.reshape(-1)
    flat_normal = normal.reshape(-1, 3)
    flat_mat = mat.reshape(-1)
    for obj in obstacles:
        rb = obj.bounding_radius()
        if np.isfinite(rb):
            # Only rays that pass through the object's bounding sphere can hit it.
            oc = obj.t - o
            b = np.einsum('pi,i->p', flat_dirs, oc)
            sel = np.nonzero(b * b - (oc @ oc - rb * rb) > 0)[0]
        else:
            sel = np.arange(len(flat_dirs))
        t, n = obj.raycast(o, flat_dirs[sel])
        win = t < flat_depth[sel]
        idx = sel[win]
        flat_depth[idx] = t[win]
        flat_normal[idx] = n[win]
        flat_mat[idx] = 2
    light = -camera.R[:, 2] + np.array([0.0, 0.0, 0.6])
    light /= np.linalg.norm(light)
    img = np.empty((H, W, 3))
    img[:] = BACKGROUND_RGB
    for m, rgb, amb in ((1, ROBOT_RGB, ROBOT_AMBIENT), (2, OBJECT_RGB, OBJECT_AMBIENT)):
        sel = mat == m
        if sel.any():
            nn = normal[sel]
            # Face the viewer (a normal pointing away means we see the inside of a shell).
            flip = np.einsum('pi,pi->p', nn, dirs[sel]) > 0
            nn[flip] *= -1
            img[sel] = _shade(rgb, amb, nn, light)
    return img


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Convert a [0, 1] float image to uint8 (rounded)."""
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
