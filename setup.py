"""Install the controlled_islanding ament_python package."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'controlled_islanding'
NODES = ['pmu_ingestion', 'coherency', 'partitioning', 'breaker_command', 'bag_player', 'recorder', 'pdc_client',
         'grid_sim', 'stability_monitor']

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*']),
    package_data={PACKAGE: ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
        (f'share/{PACKAGE}/msg_schemas/msg', glob('msg_schemas/msg/*.msg')),
        (f'share/{PACKAGE}/msg_schemas/srv', glob('msg_schemas/srv/*.srv')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='controlled_islanding maintainers',
    maintainer_email='maintainers@controlled-islanding.invalid',
    description='Online PMU-driven controlled islanding as ROS 2 nodes.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            f'{node} = {PACKAGE}.nodes.{node}:main' for node in NODES
        ] + [
            f'controlled-islanding = {PACKAGE}.cli:main',
        ],
        # The islanding_replay fixture for users' own bag tests, loaded by pytest once the package is installed.
        'pytest11': [f'{PACKAGE} = {PACKAGE}.harness.pytest_plugin'],
    },
)
