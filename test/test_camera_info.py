"""Calibration URLs as camera_info_manager reads them, and calibrations written back."""

import pytest

from softshape_ros.vision.camera_info import (CalibrationError, default_calibration_path,
                                              load_calibration, resolve_url, save_calibration)


@pytest.fixture
def package_share(tmp_path, monkeypatch):
    """Make a package ``rig_calib`` in an ament index of its own, with ``calib/main.yaml``."""
    prefix = tmp_path / 'prefix'
    index = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'rig_calib').write_text('')
    share = prefix / 'share' / 'rig_calib'
    (share / 'calib').mkdir(parents=True)
    (share / 'calib' / 'main.yaml').write_text(default_calibration_path('main').read_text())
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    return share


def test_urls_resolve_like_camera_info_manager(package_share, tmp_path, monkeypatch):
    assert resolve_url('', 'side') == default_calibration_path('side')
    path = resolve_url('package://rig_calib/calib/${NAME}.yaml', 'main')
    assert path == package_share / 'calib' / 'main.yaml'
    assert load_calibration(path).width == 640
    url = f'file://{tmp_path}/${{NAME}}_cam.yaml'
    assert resolve_url(url, 'side') == tmp_path / 'side_cam.yaml'
    monkeypatch.setenv('ROS_HOME', str(tmp_path / 'ros_home'))
    assert resolve_url('file://${ROS_HOME}/camera_info/${NAME}.yaml', 'main') == (
        tmp_path / 'ros_home' / 'camera_info' / 'main.yaml')
    assert resolve_url(str(tmp_path / 'plain.yaml'), 'main') == tmp_path / 'plain.yaml'


@pytest.mark.parametrize('url, match', [
    ('package://no_such_package/x.yaml', "package 'no_such_package' not found"),
    ('package://rig_calib', 'expected package://<package>/<path>'),
    ('file://relative/x.yaml', 'needs an absolute path'),
    ('http://example.invalid/cal.yaml', 'unsupported URL'),
    ('file:///tmp/${CAMERA}.yaml', r'unknown variable \$\{CAMERA\}'),
])
def test_bad_urls_say_what_is_wrong(package_share, url, match):
    with pytest.raises(CalibrationError, match=match):
        resolve_url(url, 'main')


def test_save_writes_a_file_load_reads_back_and_bad_ones_are_refused(tmp_path):
    import dataclasses
    cal = load_calibration(default_calibration_path('main'))
    new = dataclasses.replace(cal, k=(1000.0, 0.0, 300.0, 0.0, 1001.0, 200.0, 0.0, 0.0, 1.0))
    out = save_calibration(new, tmp_path / 'sub' / 'main.yaml')
    assert load_calibration(out) == new
    assert [p.name for p in out.parent.iterdir()] == ['main.yaml']   # no temporary left
    for bad, match in [(dataclasses.replace(new, k=(0.0,) * 9), 'focal lengths'),
                       (dataclasses.replace(new, p=(1.0,) * 5), 'P needs 12'),
                       (dataclasses.replace(new, d=(float('nan'),)), 'non-finite'),
                       (dataclasses.replace(new, width=0), 'not positive')]:
        with pytest.raises(CalibrationError, match=match):
            save_calibration(bad, out)
    assert load_calibration(out) == new
