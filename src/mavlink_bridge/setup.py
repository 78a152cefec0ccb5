from glob import glob

from setuptools import find_packages, setup

package_name = 'mavlink_bridge'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    package_data={package_name: ['data/*.yaml']},
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='deckland developers',
    maintainer_email='dev@deckland.invalid',
    description='MAVLink bridge between the deckland graph and a PX4/ArduPilot autopilot (pymavlink).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'mavlink_bridge_node = mavlink_bridge.node:main',
            'ship_telemetry_node = mavlink_bridge.ship_node:main',
        ],
    },
)
