"""
The rig configuration: one YAML file, one loader, strict validation.

Every part of the suite (simulator, bridge, cameras, dataset, model, nodes) reads
geometry, limits and topic names from here so the physical rig and the simulated
rig cannot disagree. Errors name the file and the dotted key, because a typo in a
pressure limit is a safety problem, not a style problem.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

__all__ = [
    'ConfigError', 'RigConfig', 'RobotConfig', 'SegmentConfig', 'ChamberConfig',
    'CameraConfig', 'TopicsConfig', 'CollectionConfig', 'DatasetConfig',
    'load_rig_config', 'default_config_path', 'config_from_dict',
]


class ConfigError(ValueError):
    """A configuration file is wrong; the message names the file and the key."""


def _num(lo=None, hi=None, lo_open=False, length=None):
    return {'min': lo, 'max': hi, 'min_open': lo_open, 'length': length}


@dataclass(frozen=True)
class SegmentConfig:
    length_m: float = field(metadata=_num(0.0, 10.0, lo_open=True))
    radius_m: float = field(metadata=_num(0.0, 1.0, lo_open=True))


@dataclass(frozen=True)
class RobotConfig:
    segments: list[SegmentConfig]
    youngs_modulus_pa: float = field(metadata=_num(0.0, 1e12, lo_open=True))
    poisson_ratio: float = field(metadata=_num(-1.0, 0.5, lo_open=True))
    density_kg_m3: float = field(metadata=_num(0.0, 1e5))
    gravity_m_s2: list[float] = field(metadata=_num(length=3))
    basis_order: int = field(metadata=_num(0, 12))
    shear: bool
    stretch: bool
    base_position_m: list[float] = field(metadata=_num(length=3))
    base_rpy_rad: list[float] = field(metadata=_num(length=3))

    @property
    def total_length_m(self) -> float:
        return sum(s.length_m for s in self.segments)


@dataclass(frozen=True)
class ChamberConfig:
    name: str
    segment: int = field(metadata=_num(0, None))
    angle_deg: float = field(metadata=_num(-360.0, 360.0))
    offset_m: float = field(metadata=_num(0.0, 1.0))
    area_m2: float = field(metadata=_num(0.0, 1.0))
    max_pressure_pa: float = field(metadata=_num(0.0, 1e6, lo_open=True))


@dataclass(frozen=True)
class CameraConfig:
    frame_id: str
    width: int = field(metadata=_num(1, 16384))
    height: int = field(metadata=_num(1, 16384))
    fx: float = field(metadata=_num(0.0, None, lo_open=True))
    fy: float = field(metadata=_num(0.0, None, lo_open=True))
    cx: float
    cy: float
    position_m: list[float] = field(metadata=_num(length=3))
    look_at_m: list[float] = field(metadata=_num(length=3))
    up: list[float] = field(metadata=_num(length=3))
    crop_px: list[int] = field(metadata=_num(0, None, length=4))


@dataclass(frozen=True)
class TopicsConfig:
    pressure_command: str
    pressure_measured: str
    trigger: str
    sample: str
    capture_time: str
    scene: str
    camera_image: str
    camera_info: str
    query: str
    predicted_image: str
    predicted_overlay: str
    diagnostics: str
    goal_image: str = '/softshape/goal/{camera}/image_raw'
    goal_silhouette: str = '/softshape/goal/{camera}/silhouette'
    goal_tip: str = '/softshape/goal/tip'
    goal_result: str = '/softshape/goal/result'

    def camera(self, template: str, camera: str) -> str:
        """Expand a per-camera template such as ``camera_image`` for ``main``."""
        return getattr(self, template).format(camera=camera)


@dataclass(frozen=True)
class CollectionConfig:
    rate_hz: float = field(metadata=_num(0.0, 1000.0, lo_open=True))
    settle_tolerance_pa: float = field(metadata=_num(0.0, None))
    settle_timeout_s: float = field(metadata=_num(0.0, None))
    max_capture_skew_s: float = field(metadata=_num(0.0, None))
    pressure_match_s: float = field(metadata=_num(0.0, None))


@dataclass(frozen=True)
class DatasetConfig:
    image_size: int = field(metadata=_num(8, 1024))
    gray: bool


@dataclass(frozen=True)
class RigConfig:
    robot: RobotConfig
    chambers: list[ChamberConfig]
    cameras: dict[str, CameraConfig]
    topics: TopicsConfig
    collection: CollectionConfig
    dataset: DatasetConfig
    source: str = field(default='<dict>', compare=False)

    @property
    def chamber_names(self) -> list[str]:
        return [c.name for c in self.chambers]

    @property
    def max_pressures_pa(self) -> list[float]:
        return [c.max_pressure_pa for c in self.chambers]

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)


def _type_name(tp) -> str:
    return getattr(tp, '__name__', str(tp))


def _convert(value, tp, key: str, meta: dict):
    """Check and convert one value against a type hint; raise ConfigError naming key."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key)
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(f'{key}: expected a list, got {value!r}')
        n = meta.get('length')
        if n is not None and len(value) != n:
            raise ConfigError(f'{key}: expected {n} items, got {len(value)}')
        item_meta = {k: v for k, v in meta.items() if k != 'length'}
        return [_convert(v, item_tp, f'{key}[{i}]', item_meta) for i, v in enumerate(value)]
    if origin is dict:
        _, val_tp = typing.get_args(tp)
        if not isinstance(value, dict) or not value:
            raise ConfigError(f'{key}: expected a non-empty mapping, got {value!r}')
        return {str(k): _convert(v, val_tp, f'{key}.{k}', meta) for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f'{key}: expected true or false, got {value!r}')
        return value
    if tp is str:
        if not isinstance(value, str) or not value:
            raise ConfigError(f'{key}: expected a non-empty string, got {value!r}')
        return value
    if tp in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            hint = ''
            if isinstance(value, str) and re.fullmatch(r'[-+]?[0-9.]+e[0-9]+', value):
                hint = ' (YAML reads 6.0e4 as text: write 6.0e+4)'
            raise ConfigError(f'{key}: expected {_type_name(tp)}, got {value!r}{hint}')
        if tp is int and not isinstance(value, int):
            raise ConfigError(f'{key}: expected an integer, got {value!r}')
        if not math.isfinite(value):
            raise ConfigError(f'{key}: must be finite, got {value!r}')
        lo, hi = meta.get('min'), meta.get('max')
        if lo is not None and (value < lo or (meta.get('min_open') and value == lo)):
            rel = '>' if meta.get('min_open') else '>='
            raise ConfigError(f'{key}: must be {rel} {lo}, got {value!r}')
        if hi is not None and value > hi:
            raise ConfigError(f'{key}: must be <= {hi}, got {value!r}')
        return tp(value)
    raise ConfigError(f'{key}: unsupported type {tp!r}')  # pragma: no cover


def _build(cls, data, key: str):
    if not isinstance(data, dict):
        raise ConfigError(f'{key or "<top>"}: expected a mapping, got {data!r}')
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name != 'source'}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = f'{key}.' if key else ''
        raise ConfigError(f'{where}{unknown[0]}: unknown key (known: {", ".join(fields)})')
    kwargs = {}
    for name, f in fields.items():
        sub = f'{key}.{name}' if key else name
        if name not in data:
            if f.default is not dataclasses.MISSING:
                continue
            raise ConfigError(f'{sub}: missing')
        kwargs[name] = _convert(data[name], hints[name], sub, dict(f.metadata))
    return cls(**kwargs)


def _check_consistency(cfg: RigConfig) -> None:
    nseg = len(cfg.robot.segments)
    if nseg < 1:
        raise ConfigError('robot.segments: at least one segment is required')
    if len(cfg.chambers) != 6:
        raise ConfigError(f'chambers: the rig has 6 chambers, got {len(cfg.chambers)}')
    names = cfg.chamber_names
    if len(set(names)) != len(names):
        raise ConfigError(f'chambers: names must be unique, got {names}')
    for i, ch in enumerate(cfg.chambers):
        if ch.segment >= nseg:
            raise ConfigError(
                f'chambers[{i}].segment: {ch.segment} but the robot has {nseg} segments')
        radius = cfg.robot.segments[ch.segment].radius_m
        if ch.offset_m >= radius:
            raise ConfigError(
                f'chambers[{i}].offset_m: {ch.offset_m} must be inside the radius {radius}')
    for name, cam in cfg.cameras.items():
        x, y, w, h = cam.crop_px
        if w < 1 or h < 1 or x + w > cam.width or y + h > cam.height:
            raise ConfigError(
                f'cameras.{name}.crop_px: {cam.crop_px} does not fit in {cam.width}x{cam.height}')
        d = [a - b for a, b in zip(cam.look_at_m, cam.position_m)]
        if math.sqrt(sum(v * v for v in d)) == 0.0:
            raise ConfigError(f'cameras.{name}.look_at_m: equals position_m')
    for tname in ('camera_image', 'camera_info', 'capture_time', 'predicted_image',
                  'predicted_overlay', 'goal_image', 'goal_silhouette'):
        if '{camera}' not in getattr(cfg.topics, tname):
            raise ConfigError(f'topics.{tname}: must contain the placeholder {{camera}}')


def config_from_dict(data: dict, source: str = '<dict>') -> RigConfig:
    """Validate a parsed config mapping; errors are prefixed with ``source``."""
    try:
        cfg = _build(RigConfig, data, '')
        cfg = dataclasses.replace(cfg, source=source)
        _check_consistency(cfg)
    except ConfigError as exc:
        raise ConfigError(f'{source}: {exc}') from None
    return cfg


def default_config_path() -> Path:
    """Where rig.yaml lives: $SOFTSHAPE_CONFIG, the source tree, or the ament share dir."""
    env = os.environ.get('SOFTSHAPE_CONFIG')
    if env:
        return Path(env)
    src = Path(__file__).resolve().parent.parent / 'config' / 'rig.yaml'
    if src.is_file():
        return src
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('softshape_ros')) / 'config' / 'rig.yaml'
    except Exception:  # not installed through colcon: report the source path
        return src


def load_rig_config(path: str | os.PathLike | None = None) -> RigConfig:
    """Load and validate the rig configuration (default: :func:`default_config_path`)."""
    p = Path(path) if path is not None else default_config_path()
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f'{p}: cannot read rig config: {exc.strerror or exc}') from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f'{p}: not valid YAML: {exc}') from None
    return config_from_dict(data, str(p))
