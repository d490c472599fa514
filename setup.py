# Copyright 2026 piezo_stage_ros maintainers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""Build script for ament_python (colcon) and for a plain pip install into a virtualenv."""

from glob import glob
import os
import xml.etree.ElementTree as ElementTree

from setuptools import find_packages, setup

package_name = 'piezo_stage_ros'
here = os.path.dirname(os.path.abspath(__file__))
# The one version string lives in package.xml.
version = ElementTree.parse(os.path.join(here, 'package.xml')).getroot().findtext('version')

setup(
    name=package_name,
    version=version,
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', sorted(glob('config/*.yaml'))),
        ('share/' + package_name + '/launch', sorted(glob('launch/*.launch.py'))),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='piezo_stage_ros maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-3e7679ff.example',
    description='Modelling and robust adaptive control of piezoelectric nanopositioning stages',
    license='Apache-2.0',
    python_requires='>=3.11',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'simulate = piezo_stage_ros.simulate:main',
            'analyze = piezo_stage_ros.analyze:main',
            'identify = piezo_stage_ros.identify:main',
            'benchmark = piezo_stage_ros.benchmark:main',
            'soak = piezo_stage_ros.soak:main',
            'tune = piezo_stage_ros.tune:main',
            'commission = piezo_stage_ros.commission:main',
            'robustness = piezo_stage_ros.robustness:main',
            'check = piezo_stage_ros.check:main',
            'simulate_axes = piezo_stage_ros.simulate_axes:main',
            'identify_axes = piezo_stage_ros.identify_axes:main',
            'plant_node = piezo_stage_ros.nodes.plant_node:main',
            'controller_node = piezo_stage_ros.nodes.controller_node:main',
            'trajectory_node = piezo_stage_ros.nodes.trajectory_node:main',
            'stage_servo = piezo_stage_ros.nodes.stage_servo:main',
            'stage_emulator = piezo_stage_ros.hardware.emulator:main',
        ],
    },
)
