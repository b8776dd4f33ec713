"""
Pinhole cameras from ``config/rig.yaml`` (OpenCV optical frame: x right, y down, z forward).

Pixel centres sit at integer coordinates (``u = fx X / Z + cx``), as in OpenCV, so a
render at the configured resolution and ``preprocess`` of it agree with the projection.
"""

from __future__ import annotations

import numpy as np


class PinholeCamera:
    """A camera's pose and intrinsics; projects points and makes pixel rays."""

    def __init__(self, name, width, height, fx, fy, cx, cy, position, look_at, up, crop=None):
        self.name = name
        if int(width) != width or int(height) != height or width < 1 or height < 1:
            raise ValueError(f'camera {name}: resolution must be at least 1x1 pixels, got '
                             f'{width}x{height}')
        self.width, self.height = int(width), int(height)
        self.fx, self.fy, self.cx, self.cy = float(fx), float(fy), float(cx), float(cy)
        if not (self.fx > 0 and self.fy > 0 and np.isfinite([self.fx, self.fy, self.cx,
                                                             self.cy]).all()):
            raise ValueError(f'camera {name}: fx, fy must be finite and > 0, cx, cy finite')
        self.position = np.asarray(position, dtype=float)
        z = np.asarray(look_at, dtype=float) - self.position
        if not (np.isfinite(self.position).all() and np.isfinite(z).all()
                and np.linalg.norm(z) > 0):
            raise ValueError(f'camera {name}: position and look_at must be finite and apart')
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(up, dtype=float))
        if np.linalg.norm(x) < 1e-9:
            raise ValueError(f'camera {name}: up is parallel to the viewing direction')
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        self.R = np.column_stack([x, y, z])        # camera axes in world (world <- camera)
        self.crop = list(crop) if crop is not None else [0, 0, self.width, self.height]
        # The renderer's light in the camera frame: from the camera, a little from above.
        light = -self.R[:, 2] + np.array([0.0, 0.0, 0.6])
        self.head_light = self.R.T @ (light / np.linalg.norm(light))

    @classmethod
    def from_config(cls, name, cam) -> 'PinholeCamera':
        return cls(name, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                   cam.position_m, cam.look_at_m, cam.up, cam.crop_px)

    def project(self, points) -> np.ndarray:
        """Return (P, 3): pixel u, v and depth z of world points."""
        pc = (np.atleast_2d(points) - self.position) @ self.R
        z = pc[:, 2]
        return np.column_stack([self.fx * pc[:, 0] / z + self.cx,
                                self.fy * pc[:, 1] / z + self.cy, z])

    def input_keypoints(self, points, radius, z_base: float, size: int) -> np.ndarray:
        """
        Return world points (..., 3) as the shape record's keypoints (..., 4) in this view.

        x, y in the ``size`` x ``size`` input image of the crop (pixel centres at integer
        coordinates), the tube's apparent ``radius`` (m, broadcast to the points) and the
        depth past ``z_base`` (:meth:`input_depth_px`): ``generate.measure_shape`` records
        these, and the placement head turns its 3D backbone into them.
        """
        x0, y0, w, h = self.crop
        pts = np.asarray(points, dtype=float)
        uvz = self.project(pts.reshape(-1, 3)).reshape(pts.shape)
        return np.stack([(uvz[..., 0] - x0 + 0.5) * size / w - 0.5,
                         (uvz[..., 1] - y0 + 0.5) * size / h - 0.5,
                         self.input_focal_px(size) * radius / uvz[..., 2],
                         self.input_depth_px(uvz[..., 2], z_base, size)], -1)

    def input_depth_px(self, z, z_base, size: int) -> np.ndarray:
        """
        Return camera depths ``z`` (m) as the shape record's depth: px further than ``z_base``.

        The unit is a pixel of the ``size`` x ``size`` input image (its crop resampled) at
        the base's depth, focal length x (z / z_base - 1), so depths compare with the
        keypoints' x, y and radius (``generate.measure_shape``, ``object_depth``).
        """
        return self.input_focal_px(size) * (np.asarray(z, dtype=float) / z_base - 1.0)

    def input_focal_px(self, size: int) -> float:
        """Return the focal length (px) of the ``size`` x ``size`` input image of the crop."""
        _, _, w, h = self.crop
        return 0.5 * (self.fx * size / w + self.fy * size / h)

    def grid(self, region=None, out_size=None):
        """
        Return (u0, du, v0, dv, W, H): a pixel grid over ``region`` = [x, y, w, h].

        ``out_size`` = (W, H) samples the region at another resolution, each sample at the
        centre of the source-pixel area it stands for (what an area resize averages).
        """
        x, y, w, h = region if region is not None else [0, 0, self.width, self.height]
        W, H = out_size if out_size is not None else (w, h)
        if not (W >= 1 and H >= 1 and w > 0 and h > 0):
            raise ValueError(f'camera {self.name}: cannot sample {list(region or [])} at '
                             f'{W}x{H} pixels')
        du, dv = w / W, h / H
        return x + 0.5 * du - 0.5, du, y + 0.5 * dv - 0.5, dv, int(W), int(H)

    def rays(self, grid) -> np.ndarray:
        """Return unit world ray directions (H, W, 3) for a pixel grid."""
        u0, du, v0, dv, W, H = grid
        u = u0 + du * np.arange(W)
        v = v0 + dv * np.arange(H)
        xc = (u - self.cx) / self.fx
        yc = (v - self.cy) / self.fy
        d = np.empty((H, W, 3))
        d[..., 0] = xc[None, :]
        d[..., 1] = yc[:, None]
        d[..., 2] = 1.0
        d /= np.sqrt(np.einsum('hwi,hwi->hw', d, d))[..., None]
        return np.einsum('hwi,ji->hwj', d, self.R)
