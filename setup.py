"""ament_python package setup; each ``softshape_ros/nodes/<name>.py`` with ``main`` is a node."""

import re
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

package_name = 'softshape_ros'
HERE = Path(__file__).resolve().parent


def node_modules():
    """Node executables: modules in nodes/ that define ``main`` (``ros2 run`` names)."""
    names = []
    for f in sorted((HERE / package_name / 'nodes').glob('*.py')):
        if not f.name.startswith('_') and re.search(r'^(def main\(|main = )', f.read_text(), re.M):
            names.append(f.stem)
    return names


NODES = node_modules()

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'benchmarks']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + package_name + '/config/params', glob('config/params/*.yaml')),
        ('share/' + package_name + '/config/camera_info', glob('config/camera_info/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='softshape_ros maintainers',
    maintainer_email='softshape@example.com',
    description='ROS 2 suite for a soft continuum robot rig: pressure bridge, synchronised '
                'cameras, bag recorder, Cosserat-simulated mock hardware, and a deep visual '
                'forward model.',
    license='Apache-2.0',
    extras_require={'test': ['pytest', 'hypothesis']},
    entry_points={
        'console_scripts': [f'{n} = {package_name}.nodes.{n}:main' for n in NODES]
        + [f'softshape = {package_name}.cli:main'],
    },
)
