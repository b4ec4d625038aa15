"""ament_python build of ppe_ros (colcon) and editable install for development (make venv).

Dependency versions are pinned in requirements.txt only.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'ppe_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml') + glob('config/*.xml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
        (f'share/{PACKAGE}/rviz', glob('rviz/*.rviz')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='ppe_ros developers',
    maintainer_email='dev@ppe-ros.invalid',
    description='Probabilistic Plane Extraction (PPE) for organized 3-D scans, with a ROS 2 node.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'extractor = ppe_ros.entry:extractor',
            'process_bag = ppe_ros.entry:process_bag',
            'ppe = ppe_ros.cli:main',
        ],
    },
)
