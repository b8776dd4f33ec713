"""
The DDS transport: which Fast DDS profile a process runs with, and frames that cross processes.

The package profile (config/fastdds.xml) is used unless the user chose (their own profile,
an opt-out, another RMW); a profile the user names but that cannot be used stops the node
at start with the reason. Over real DDS, a plain best-effort subscriber in another process
than camera_trigger gets every frame of its 640x480 free run at 30 Hz (with Fast DDS's
defaults it lost most of them: benchmarks/bench_transport.py).
"""

import os
import subprocess
import sys
import threading

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
def test_best_effort_subscriber_in_another_process_gets_every_free_run_frame(ros, tmp_path):
    """
    camera_trigger free-runs 640x480 RGB at 30 Hz in its own process (as ``ros2 run`` starts it).

    Every frame it captured (its capture_time messages, reliable and small) must reach a
    best-effort image subscription here: 60 in a row from the first frame received (before
    that, discovery may not have matched the image writer with this reader yet).
    """
    from sensor_msgs.msg import Image, TimeReference

    from softshape_ros.config import load_rig_config
    from softshape_ros.nodes.common import RELIABLE_QOS, SENSOR_QOS, stamp_to_ns
    from softshape_ros.vision.patterns import write_folder
    t = load_rig_config().topics
    folder = write_folder(tmp_path / 'frames', 12, width=640, height=480)
    node = ros.node('free_run_viewer')
    lock = threading.Lock()
    frames, captured = set(), []

    def on_image(msg):
        with lock:
            frames.add(stamp_to_ns(msg.header.stamp))

    def on_time(msg):
        with lock:
            captured.append(stamp_to_ns(msg.header.stamp))
    node.create_subscription(Image, t.camera('camera_image', 'main'), on_image, SENSOR_QOS)
    node.create_subscription(TimeReference, t.camera('capture_time', 'main'), on_time,
                             RELIABLE_QOS)
    cam = subprocess.Popen(
        [sys.executable, '-c', 'from softshape_ros.nodes.camera_trigger import main; main()',
         '--ros-args', '-p', 'camera_name:=main', '-p', f'source:={folder}',
         '-p', 'fps:=30.0', '-p', 'free_run:=true'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        def window():
            with lock:
                return [s for s in captured if frames and s >= min(frames)][:60], set(frames)

        def sixty_in_a_row_received():
            stamps, got = window()
            return len(stamps) == 60 and set(stamps) <= got

        def state():
            stamps, got = window()
            return (f'60 captured frames in a row at the best-effort subscriber (captured '
                    f'{len(captured)}, received {len(got)}, missing in the window '
                    f'{len(set(stamps) - got)})')
        ros.wait_for(sixty_in_a_row_received, 30, what=state)
    finally:
        cam.terminate()
        out, _ = cam.communicate(timeout=30)
    assert cam.returncode == 0, out
    stamps, _ = window()
    assert len(set(stamps)) == 60                   # 60 distinct frames, none repeated
