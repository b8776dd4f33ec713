"""Scene descriptions: one JSON form, strict validation with field names."""

import pytest

from softshape_ros.scene import Scene, SceneError, load_session


def test_round_trip_json():
    s = Scene(id=3, object='cylinder', position_m=[0.02, 0, 0.01], rpy_rad=[0, 0, 0.1],
              dims={'radius_m': 0.01, 'height_m': 0.05}, actuations=5, label='near')
    assert Scene.from_json(s.to_json()) == s


@pytest.mark.parametrize('bad, match', [
    ('{"id": 1, "object": "cube"}', 'unknown object'),
    ('{"id": 1, "object": "sphere"}', 'needs dims'),
    ('{"id": 1, "object": "sphere", "dims": {"radius_m": -1}}', 'dims.radius_m'),
    ('{"id": 1, "position_m": [0, 0]}', 'position_m'),
    ('{"id": 1, "position_m": [0, 0, NaN]}', 'position_m'),
    ('{"object": "none"}', 'integer id'),
    ('{"id": 1, "colour": "red"}', "unknown key 'colour'"),
    ('not json', 'malformed'),
    ('[1, 2]', 'must be a mapping'),
    ('{"id": 1, "object": "cylinder", "dims": ["radius_m", "height_m"]}',
     'dims must be a mapping'),
    ('[' * 100000 + ']' * 100000, 'malformed'),
])
def test_bad_scenes_are_named(bad, match):
    with pytest.raises(SceneError, match=match):
        Scene.from_json(bad)


def test_shipped_session_loads():
    from pathlib import Path
    scenes = load_session(Path(__file__).parent.parent / 'config' / 'session_sim.yaml')
    assert [s.object for s in scenes] == ['cylinder', 'cylinder', 'ring', 'prism']
    assert all(s.actuations > 0 for s in scenes)


def test_duplicate_ids_rejected(tmp_path):
    f = tmp_path / 's.yaml'
    f.write_text('scenes: [{id: 1}, {id: 1}]\n')
    with pytest.raises(SceneError, match='unique'):
        load_session(f)
