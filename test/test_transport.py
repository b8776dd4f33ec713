"""
The DDS transport: which Fast DDS profile a process runs with, and frames that cross processes.

The package profile (config/fastdds.xml) is used unless the user chose (their own profile,
an opt-out, another RMW); a profile the user names but that cannot be used stops the node
at start with the reason. Over real DDS, a plain best-effort subscriber in another process
than camera_trigger gets every frame of its 640x480 free run at 30 Hz (with Fast DDS's
defaults it lost most of them: benchmarks/bench_transport.py).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from softshape_ros.transport import (PROFILE_ENV, TransportProfileError, configure_transport,
                                     package_profile)


def test_the_package_profile_is_used_by_default_and_names_the_file():
    env = {}
    choice = configure_transport(env)
    assert choice.profile == package_profile() and env[PROFILE_ENV] == str(package_profile())
    assert choice.reason == 'the package profile'
    text = package_profile().read_text()
    assert '<segment_size>' in text and 'is_default_profile="true"' in text


def test_the_users_choice_is_kept(tmp_path, monkeypatch):
    mine = tmp_path / 'mine.xml'
    mine.write_text('<dds><profiles/></dds>')
    env = {PROFILE_ENV: str(mine)}
    assert configure_transport(env).profile == mine and env[PROFILE_ENV] == str(mine)
    env = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}
    assert configure_transport(env).profile is None and PROFILE_ENV not in env
    env = {'SOFTSHAPE_TRANSPORT_PROFILE': 'none'}
    assert configure_transport(env).profile is None and PROFILE_ENV not in env
    env = {'SKIP_DEFAULT_XML_FILE': '1'}
    assert configure_transport(env).profile is None and PROFILE_ENV not in env
    monkeypatch.chdir(tmp_path)                   # Fast DDS's own default file name
    (tmp_path / 'DEFAULT_FASTRTPS_PROFILES.xml').write_text('<profiles/>')
    env = {}
    choice = configure_transport(env)
    assert choice.profile == tmp_path / 'DEFAULT_FASTRTPS_PROFILES.xml'
    assert PROFILE_ENV not in env                 # Fast DDS finds it by itself


@pytest.mark.parametrize('content, reason', [
    (None, 'cannot read'), ('<dds><profiles>', 'not valid XML'),
    ('<launch/>', 'not a Fast DDS profile')])
def test_an_unusable_profile_is_an_error_naming_it(tmp_path, content, reason):
    path = tmp_path / 'bad.xml'
    if content is not None:
        path.write_text(content)
    with pytest.raises(TransportProfileError, match=reason) as err:
        configure_transport({PROFILE_ENV: str(path)})
    assert str(path) in str(err.value) and PROFILE_ENV in str(err.value)
    with pytest.raises(TransportProfileError, match=reason):
        configure_transport({'SOFTSHAPE_TRANSPORT_PROFILE': str(path)})


@pytest.mark.ros
def test_a_node_refuses_to_start_on_a_broken_user_profile(tmp_path):
    bad = tmp_path / 'typo.xml'
    bad.write_text('<dds><profiles><participant>')
    env = dict(os.environ, **{PROFILE_ENV: str(bad)})
    proc = subprocess.run(
        [sys.executable, '-c', 'from softshape_ros.nodes.camera_trigger import main; main()'],
        env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert f'{PROFILE_ENV}={bad}: not valid XML' in proc.stderr


@pytest.mark.ros
def test_best_effort_subscriber_in_another_process_gets_every_free_run_frame(tmp_path):
    """
    camera_trigger free-runs 640x480 RGB at 30 Hz in its own process (as ``ros2 run`` starts it).

    A plain viewer in a third process (test/plain_image_subscriber.py: single-threaded spin,
    sensor-data QoS, Fast DDS's defaults, not this package's profile) must receive every frame
    the camera captured: 60 in a row from its first image. The publisher's profile is the fix
    (its shared-memory segment holds a whole frame); with SOFTSHAPE_TRANSPORT_PROFILE=none
    this fails. Not in this test process: its multi-threaded executor, hosting many nodes
    across the suite, is a slower reader than a viewer and would measure itself.
    """
    from softshape_ros.config import load_rig_config
    from softshape_ros.vision.patterns import write_folder
    t = load_rig_config().topics
    folder = write_folder(tmp_path / 'frames', 12, width=640, height=480)
    plain = {k: v for k, v in os.environ.items() if k != PROFILE_ENV}
    viewer = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name('plain_image_subscriber.py')),
         t.camera('camera_image', 'main'), t.camera('capture_time', 'main'), '60', '60'],
        env=plain, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    cam = subprocess.Popen(
        [sys.executable, '-c', 'from softshape_ros.nodes.camera_trigger import main; main()',
         '--ros-args', '-p', 'camera_name:=main', '-p', f'source:={folder}',
         '-p', 'fps:=30.0', '-p', 'free_run:=true'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen, err = viewer.communicate(timeout=120)
    finally:
        viewer.kill()
        cam.terminate()
        out, _ = cam.communicate(timeout=30)
    assert viewer.returncode == 0, err
    report = json.loads(seen.strip().splitlines()[-1])
    assert len(report['window']) == 60, report         # 60 captured frames seen
    assert report['missing'] == [], (f"{len(report['missing'])} of 60 captured frames never "
                                     f"reached the viewer: {report}")
    assert len(set(report['window'])) == 60             # distinct frames, none repeated
    assert cam.returncode == 0, out
