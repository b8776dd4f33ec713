"""
Camera calibration files in the camera_info_manager YAML format (what ROS tools write).

``config/camera_info/{main,side}.yaml`` hold the rig's calibrations; the camera_trigger
node publishes them as CameraInfo, and the mock hardware builds the same structure from
the simulated pinhole cameras in config/rig.yaml, so both rigs publish alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import yaml

__all__ = ['CalibrationError', 'Calibration', 'load_calibration', 'calibration_from_camera',
           'calibration_to_yaml', 'default_calibration_path']


class CalibrationError(ValueError):
    """A calibration file is malformed; the message names the file and the field."""


@dataclass(frozen=True)
class Calibration:
    camera_name: str
    width: int
    height: int
    k: tuple                     # 3x3 row-major
    d: tuple                     # distortion coefficients
    r: tuple                     # 3x3 rectification
    p: tuple                     # 3x4 projection
    distortion_model: str = 'plumb_bob'

    def scaled(self, width: int, height: int) -> 'Calibration':
        """Return the calibration for a frame of another resolution (pinhole scaling)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        k = list(self.k)
        k[0], k[2], k[4], k[5] = k[0] * sx, k[2] * sx, k[4] * sy, k[5] * sy
        p = list(self.p)
        p[0], p[2], p[3], p[5], p[6] = p[0] * sx, p[2] * sx, p[3] * sx, p[5] * sy, p[6] * sy
        return Calibration(self.camera_name, width, height, tuple(k), self.d, self.r,
                           tuple(p), self.distortion_model)


def _matrix(data: dict, key: str, rows: int, cols, src: str) -> tuple:
    m = data.get(key)
    if not isinstance(m, dict) or 'data' not in m:
        raise CalibrationError(f'{src}: {key}: expected a mapping with rows, cols and data')
    vals = m['data']
    if not isinstance(vals, list) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            for v in vals):
        raise CalibrationError(f'{src}: {key}.data: expected finite numbers, got {vals!r}')
    n = rows * cols if cols else len(vals)
    if m.get('rows') != rows or (cols and m.get('cols') != cols) or len(vals) != n:
        raise CalibrationError(f'{src}: {key}: expected {rows}x{cols or "n"} '
                               f'({n} values), got rows={m.get("rows")} cols={m.get("cols")} '
                               f'and {len(vals)} values')
    return tuple(float(v) for v in vals)


def load_calibration(path) -> Calibration:
    """Read a camera_info_manager YAML; raise CalibrationError naming the bad field."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise CalibrationError(f'{p}: cannot read calibration: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f'{p}: not valid YAML: {exc}') from None
    if not isinstance(data, dict):
        raise CalibrationError(f'{p}: expected a mapping')
    for key in ('image_width', 'image_height'):
        v = data.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise CalibrationError(f'{p}: {key}: expected a positive integer, got {v!r}')
    return Calibration(
        camera_name=str(data.get('camera_name', '')),
        width=data['image_width'], height=data['image_height'],
        k=_matrix(data, 'camera_matrix', 3, 3, p),
        d=_matrix(data, 'distortion_coefficients', 1, 0, p),
        r=_matrix(data, 'rectification_matrix', 3, 3, p),
        p=_matrix(data, 'projection_matrix', 3, 4, p),
        distortion_model=str(data.get('distortion_model', 'plumb_bob')))


def calibration_from_camera(name: str, cam) -> Calibration:
    """Build the ideal pinhole calibration of a ``config.CameraConfig`` (no distortion)."""
    k = (cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0)
    p = (cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0)
    return Calibration(name, cam.width, cam.height, tuple(float(v) for v in k),
                       (0.0,) * 5, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
                       tuple(float(v) for v in p))


def calibration_to_yaml(cal: Calibration) -> str:
    """Write a calibration in the camera_info_manager format."""
    def mat(rows, cols, vals):
        return {'rows': rows, 'cols': cols, 'data': [float(v) for v in vals]}
    data = {
        'image_width': cal.width, 'image_height': cal.height, 'camera_name': cal.camera_name,
        'camera_matrix': mat(3, 3, cal.k), 'distortion_model': cal.distortion_model,
        'distortion_coefficients': mat(1, len(cal.d), cal.d),
        'rectification_matrix': mat(3, 3, cal.r), 'projection_matrix': mat(3, 4, cal.p),
    }
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None)


def default_calibration_path(camera: str) -> Path:
    """``config/camera_info/<camera>.yaml`` in the source tree or the installed share dir."""
    src = Path(__file__).resolve().parent.parent.parent / 'config' / 'camera_info'
    if (src / f'{camera}.yaml').is_file():
        return src / f'{camera}.yaml'
    try:
        from ament_index_python.packages import get_package_share_directory
        share = Path(get_package_share_directory('softshape_ros'))
        return share / 'config' / 'camera_info' / f'{camera}.yaml'
    except Exception:  # not installed through colcon: report the source path
        return src / f'{camera}.yaml'
