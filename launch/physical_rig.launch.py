"""
The physical rig: Due bridge, both cameras and their static transforms, collector, recorder.

ros2 launch softshape_ros physical_rig.launch.py port:=/dev/ttyACM0 main_device:=/dev/video0 \
    side_device:=/dev/video2 session:=/path/to/session.yaml

pressure_bridge is a lifecycle node: this file configures it (opens the port, handshakes)
and, once it is inactive, activates it (commands accepted). If configure fails (no Due),
it stays unconfigured: ``ros2 lifecycle set /pressure_bridge configure`` once it is plugged
in, then ``activate``. The camera transforms are rig.yaml's camera poses
(``python -m softshape_ros.frames`` prints them; test_package_install checks them).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition


def params_file(node):
    """Return the installed default parameter file of ``node``."""
    share = get_package_share_directory('softshape_ros')
    return os.path.join(share, 'config', 'params', f'{node}.yaml')


def generate_launch_description():
    """Start the physical rig and drive the bridge to active."""
    share = get_package_share_directory('softshape_ros')
    bridge = LifecycleNode(
        package='softshape_ros', executable='pressure_bridge', name='pressure_bridge',
        namespace='', output='screen',
        parameters=[params_file('pressure_bridge'), {'port': LaunchConfiguration('port')}])
    configure = EmitEvent(event=ChangeState(
        lifecycle_node_matcher=matches_action(bridge),
        transition_id=Transition.TRANSITION_CONFIGURE))
    activate_when_configured = RegisterEventHandler(OnStateTransition(
        target_lifecycle_node=bridge, goal_state='inactive',
        entities=[EmitEvent(event=ChangeState(
            lifecycle_node_matcher=matches_action(bridge),
            transition_id=Transition.TRANSITION_ACTIVATE))]))
    return LaunchDescription([
        DeclareLaunchArgument('port', default_value='/dev/ttyACM0'),
        DeclareLaunchArgument('main_device', default_value='/dev/video0'),
        DeclareLaunchArgument('side_device', default_value='/dev/video2'),
        DeclareLaunchArgument('session',
                              default_value=os.path.join(share, 'config', 'session_sim.yaml')),
        DeclareLaunchArgument('bag', default_value='softshape_bag'),
        bridge,
        activate_when_configured,
        configure,
        Node(package='softshape_ros', executable='camera_trigger', name='camera_main',
             output='screen',
             parameters=[params_file('camera_trigger'),
                         {'camera_name': 'main', 'source': LaunchConfiguration('main_device')}]),
        Node(package='softshape_ros', executable='camera_trigger', name='camera_side',
             output='screen',
             parameters=[params_file('camera_trigger'),
                         {'camera_name': 'side', 'source': LaunchConfiguration('side_device')}]),
        Node(package='tf2_ros', executable='static_transform_publisher',
             name='camera_main_tf', output='log',
             arguments=['--x', '0.0', '--y', '-0.22', '--z', '0.035',
                        '--qx', '-0.707106781', '--qy', '0.0', '--qz', '0.0',
                        '--qw', '0.707106781',
                        '--frame-id', 'world', '--child-frame-id', 'camera_main_optical_frame']),
        Node(package='tf2_ros', executable='static_transform_publisher',
             name='camera_side_tf', output='log',
             arguments=['--x', '0.155563492', '--y', '-0.155563492', '--z', '0.035',
                        '--qx', '-0.653281482', '--qy', '-0.27059805', '--qz', '0.27059805',
                        '--qw', '0.653281482',
                        '--frame-id', 'world', '--child-frame-id', 'camera_side_optical_frame']),
        Node(package='softshape_ros', executable='recorder', name='recorder', output='screen',
             parameters=[params_file('recorder'), {'output': LaunchConfiguration('bag')}]),
        Node(package='softshape_ros', executable='collector', name='collector', output='screen',
             parameters=[params_file('collector'),
                         {'session': LaunchConfiguration('session'), 'simulated': False,
                          'recorder': 'recorder'}]),     # the first scene waits for it
    ])
