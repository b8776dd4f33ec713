"""
Camera calibration files in the camera_info_manager YAML format (what ROS tools write).

``config/camera_info/{main,side}.yaml`` hold the rig's calibrations; the camera_trigger
node publishes them as CameraInfo, and the mock hardware builds the same structure from
the simulated pinhole cameras in config/rig.yaml, so both rigs publish alike.
Calibration URLs follow camera_info_manager: ``file:///abs/path.yaml``,
``package://<pkg>/<path in its share directory>``, a plain path, with ``${NAME}`` (the
camera's name) and ``${ROS_HOME}`` substituted; :func:`save_calibration` writes what the
``set_camera_info`` service receives (the standard camera_calibration tool commits so).
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import yaml

__all__ = ['CalibrationError', 'Calibration', 'load_calibration', 'calibration_from_camera',
           'calibration_to_yaml', 'default_calibration_path', 'resolve_url',
           'check_calibration', 'save_calibration']


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


_VARIABLE = re.compile(r'\$\{([A-Za-z_][A-Za-z0-9_]*)\}')


def _substitute(url: str, camera: str) -> str:
    def value(m):
        name = m.group(1)
        if name == 'NAME':
            return camera
        if name == 'ROS_HOME':
            return os.environ.get('ROS_HOME') or str(Path.home() / '.ros')
        raise CalibrationError(f'{url}: unknown variable ${{{name}}} (known: ${{NAME}}, '
                               '${ROS_HOME})')
    return _VARIABLE.sub(value, url)


def resolve_url(url: str, camera: str) -> Path:
    """
    Turn a camera_info_manager URL into a file path.

    '' = the package's ``config/camera_info/<camera>.yaml``; ``file://`` takes an absolute
    path; ``package://pkg/rel`` a path in the package's share directory (from the ament
    index); a bare path is taken as it is. Raises CalibrationError for other schemes or an
    unknown package.
    """
    if not url:
        return default_calibration_path(camera)
    text = _substitute(url, camera)
    if text.startswith('file://'):
        path = text[len('file://'):]
        if not path.startswith('/'):
            raise CalibrationError(f'{url}: a file:// URL needs an absolute path '
                                   '(file:///path/to/camera.yaml)')
        return Path(path)
    if text.startswith('package://'):
        pkg, _, rel = text[len('package://'):].partition('/')
        if not pkg or not rel:
            raise CalibrationError(f'{url}: expected package://<package>/<path>')
        try:
            from ament_index_python.packages import get_package_share_directory
            share = get_package_share_directory(pkg)
        except Exception as exc:  # PackageNotFoundError, or no ament index at all
            raise CalibrationError(f'{url}: package {pkg!r} not found: {exc}') from None
        return Path(share) / rel
    if '://' in text:
        raise CalibrationError(f'{url}: unsupported URL (file://, package:// or a path)')
    return Path(text)


def check_calibration(cal: Calibration) -> None:
    """Raise CalibrationError if a calibration (e.g. received over a service) is unusable."""
    if cal.width <= 0 or cal.height <= 0:
        raise CalibrationError(f'image size {cal.width}x{cal.height} is not positive')
    for name, vals, n in (('K', cal.k, 9), ('R', cal.r, 9), ('P', cal.p, 12), ('D', cal.d, 0)):
        if n and len(vals) != n:
            raise CalibrationError(f'{name} needs {n} values, got {len(vals)}')
        if not all(math.isfinite(float(v)) for v in vals):
            raise CalibrationError(f'{name} has non-finite values: {list(vals)}')
    if cal.k[0] <= 0 or cal.k[4] <= 0:
        raise CalibrationError(f'focal lengths fx={cal.k[0]}, fy={cal.k[4]} must be positive')


def save_calibration(cal: Calibration, path) -> Path:
    """
    Write ``cal`` as camera_info_manager YAML at ``path``, atomically; return the path.

    A half-written calibration must never replace a good one: the text goes to a
    temporary file beside it, which is then renamed over the old file.
    """
    check_calibration(cal)
    p = Path(path)
    tmp = None
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f'.{p.name}.', dir=p.parent)
        with os.fdopen(fd, 'w') as f:
            f.write(calibration_to_yaml(cal))
        os.replace(tmp, p)
        tmp = None
    except OSError as exc:
        raise CalibrationError(f'{p}: cannot write calibration: {exc.strerror or exc}') from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
    return p
