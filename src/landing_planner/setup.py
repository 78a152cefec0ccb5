from glob import glob

from setuptools import find_packages, setup

package_name = 'landing_planner'

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
    description='Landing state machine (paper section 3.3), smooth reference generator and horizontal position controller.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'landing_planner_node = landing_planner.node:main',
        ],
    },
)
