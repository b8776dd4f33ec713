"""The rig config loader: the shipped file loads, and every kind of mistake names file and key."""

import copy
from pathlib import Path

import pytest
import yaml

from softshape_ros.config import ConfigError, config_from_dict, load_rig_config

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / 'config' / 'rig.yaml'


@pytest.fixture
def raw():
    return yaml.safe_load(RIG.read_text())


def test_shipped_config_loads():
    cfg = load_rig_config(RIG)
    assert len(cfg.chambers) == 6
    assert cfg.camera_names == ['main', 'side']
    assert cfg.robot.total_length_m == pytest.approx(0.046)
    assert cfg.topics.camera('camera_image', 'side') == '/rig/camera_side/image_raw'
    assert all(p > 0 for p in cfg.max_pressures_pa)


def test_every_params_file_is_ros_parameters_format():
    for f in sorted((ROOT / 'config' / 'params').glob('*.yaml')):
        data = yaml.safe_load(f.read_text())
        assert isinstance(data, dict) and len(data) == 1, f
        (node,) = data
        assert f.stem == node or node == '/**', f'{f}: top key {node!r} should be the node name'
        assert set(data[node]) == {'ros__parameters'}, f


def _bad(raw, mutate):
    data = copy.deepcopy(raw)
    mutate(data)
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, 'rig-under-test.yaml')
    msg = str(info.value)
    assert msg.startswith('rig-under-test.yaml: '), msg
    return msg


def test_unknown_key(raw):
    msg = _bad(raw, lambda d: d['robot'].update(youngs_modulus=1.0))
    assert 'robot.youngs_modulus: unknown key' in msg


def test_unknown_top_level_key(raw):
    assert 'camerass: unknown key' in _bad(raw, lambda d: d.update(camerass={}))


def test_missing_field(raw):
    msg = _bad(raw, lambda d: d['chambers'][2].pop('max_pressure_pa'))
    assert 'chambers[2].max_pressure_pa: missing' in msg


def test_wrong_type(raw):
    msg = _bad(raw, lambda d: d['cameras']['side'].update(width='640'))
    assert 'cameras.side.width: expected int' in msg


def test_float_written_as_yaml_text_gets_a_hint(raw):
    msg = _bad(raw, lambda d: d['robot'].update(youngs_modulus_pa='6.0e4'))
    assert 'robot.youngs_modulus_pa' in msg and '6.0e+4' in msg


def test_bool_is_not_a_number(raw):
    assert 'robot.basis_order' in _bad(raw, lambda d: d['robot'].update(basis_order=True))


def test_out_of_range(raw):
    msg = _bad(raw, lambda d: d['chambers'][0].update(max_pressure_pa=-5.0))
    assert 'chambers[0].max_pressure_pa: must be > 0' in msg


def test_wrong_list_length(raw):
    msg = _bad(raw, lambda d: d['robot'].update(gravity_m_s2=[0, 0]))
    assert 'robot.gravity_m_s2: expected 3 items' in msg


def test_non_finite(raw):
    assert 'must be finite' in _bad(raw, lambda d: d['robot'].update(density_kg_m3=float('nan')))


def test_inconsistent_chamber_segment(raw):
    msg = _bad(raw, lambda d: d['chambers'][5].update(segment=7))
    assert 'chambers[5].segment' in msg


def test_crop_outside_frame(raw):
    msg = _bad(raw, lambda d: d['cameras']['main'].update(crop_px=[600, 0, 100, 100]))
    assert 'cameras.main.crop_px' in msg


def test_topic_template_needs_placeholder(raw):
    msg = _bad(raw, lambda d: d['topics'].update(camera_image='/rig/image_raw'))
    assert 'topics.camera_image' in msg


def test_wrong_chamber_count(raw):
    assert 'chambers: the rig has 6' in _bad(raw, lambda d: d['chambers'].pop())


def test_unreadable_and_invalid_yaml(tmp_path):
    with pytest.raises(ConfigError, match='cannot read'):
        load_rig_config(tmp_path / 'nope.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('robot: [unclosed\n')
    with pytest.raises(ConfigError, match='bad.yaml: not valid YAML'):
        load_rig_config(bad)


def test_environment_variable_selects_file(tmp_path, monkeypatch, raw):
    raw['collection']['rate_hz'] = 5.0
    f = tmp_path / 'other.yaml'
    f.write_text(yaml.safe_dump(raw))
    monkeypatch.setenv('SOFTSHAPE_CONFIG', str(f))
    assert load_rig_config().collection.rate_hz == 5.0
