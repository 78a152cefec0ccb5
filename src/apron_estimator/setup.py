from glob import glob

from setuptools import find_packages, setup

package_name = 'apron_estimator'

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
    description='Apron state estimator: IR beacon pixels to relative position/velocity (eqs. 27-35) and deck vertical state.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'apron_estimator_node = apron_estimator.node:main',
        ],
    },
)
