"""
A scene: one object placement (paper IV-B), the unit that rest images belong to.

The collector reads scenes from a session YAML, publishes each as JSON on ``/rig/scene``;
the mock hardware hands it to the simulator, and the dataset builder stores its id.
One class, one JSON form, so the physical and simulated rigs describe scenes alike.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import yaml

#: Object kinds and the dimensions each needs (metres / radians).
OBJECT_DIMS = {
    'none': (),
    'cylinder': ('radius_m', 'height_m'),
    'ring': ('major_radius_m', 'minor_radius_m'),
    'prism': ('width_m', 'depth_m', 'height_m', 'skew_rad'),
    'sphere': ('radius_m',),
    'plane': (),
}


class SceneError(ValueError):
    """A scene description is malformed; the message says which field."""


@dataclass(frozen=True)
class Scene:
    """One object placement; ``pose`` is in the world frame of config/rig.yaml."""

    id: int
    object: str = 'none'
    position_m: tuple = (0.0, 0.0, 0.0)
    rpy_rad: tuple = (0.0, 0.0, 0.0)
    dims: dict = field(default_factory=dict)
    actuations: int = 0
    label: str = ''

    def __post_init__(self):
        if self.object not in OBJECT_DIMS:
            raise SceneError(f'scene {self.id}: unknown object {self.object!r} '
                             f'(one of {", ".join(OBJECT_DIMS)})')
        for name, vec in (('position_m', self.position_m), ('rpy_rad', self.rpy_rad)):
            if len(vec) != 3 or not all(_finite(v) for v in vec):
                raise SceneError(f'scene {self.id}: {name} must be 3 finite numbers, got {vec!r}')
            object.__setattr__(self, name, tuple(float(v) for v in vec))
        if not isinstance(self.dims, dict):
            raise SceneError(f'scene {self.id}: dims must be a mapping, got {self.dims!r}')
        need = set(OBJECT_DIMS[self.object])
        have = set(self.dims)
        if have != need:
            raise SceneError(f'scene {self.id}: {self.object} needs dims {sorted(need)}, '
                             f'got {sorted(have)}')
        for k, v in self.dims.items():
            if not _finite(v) or (k != 'skew_rad' and v <= 0):
                raise SceneError(f'scene {self.id}: dims.{k} must be a positive number, got {v!r}')
        object.__setattr__(self, 'dims', {k: float(v) for k, v in sorted(self.dims.items())})
        if not isinstance(self.actuations, int) or self.actuations < 0:
            raise SceneError(f'scene {self.id}: actuations must be an integer >= 0')

    def to_json(self) -> str:
        d = asdict(self)
        d['position_m'], d['rpy_rad'] = list(self.position_m), list(self.rpy_rad)
        return json.dumps(d, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> 'Scene':
        if not isinstance(d, dict):
            raise SceneError(f'a scene must be a mapping, got {d!r}')
        known = {'id', 'object', 'position_m', 'rpy_rad', 'dims', 'actuations', 'label'}
        unknown = sorted(set(d) - known)
        if unknown:
            raise SceneError(f'scene {d.get("id", "?")}: unknown key {unknown[0]!r}')
        if 'id' not in d or isinstance(d['id'], bool) or not isinstance(d['id'], int):
            raise SceneError(f'scene: integer id required, got {d.get("id")!r}')
        return cls(**d)

    @classmethod
    def from_json(cls, text: str) -> 'Scene':
        try:
            return cls.from_dict(json.loads(text))
        except (ValueError, TypeError, RecursionError) as exc:
            if isinstance(exc, SceneError):
                raise
            raise SceneError(f'scene JSON is malformed: {exc}') from None


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def load_session(path) -> list[Scene]:
    """Read a collection session YAML: ``scenes: [ {id, object, position_m, ...}, ... ]``."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise SceneError(f'{p}: cannot read session: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise SceneError(f'{p}: not valid YAML: {exc}') from None
    if not isinstance(data, dict) or not isinstance(data.get('scenes'), list):
        raise SceneError(f'{p}: expected a mapping with a list under "scenes"')
    try:
        scenes = [Scene.from_dict(s) for s in data['scenes']]
    except (SceneError, TypeError) as exc:
        raise SceneError(f'{p}: {exc}') from None
    ids = [s.id for s in scenes]
    if len(set(ids)) != len(ids):
        raise SceneError(f'{p}: scene ids must be unique, got {ids}')
    return scenes
